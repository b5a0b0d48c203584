//! A `--load-map` file's keyframes in the loop detector before the first live keyframe, so
//! that a new session can relocalise into the loaded maps ([`map_store`]).
use std::path::Path;
use std::time::Instant;

use slam_core::ids::KeyframeId;

use crate::{Closer, LoopCloserConfig};

/// What [`load`] inserted.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoadedKeyframes {
    /// Keyframes inserted.
    pub keyframes: usize,
    /// True when the file's BoW and feature vectors were used (same vocabulary and feature
    /// level as the loop closer's); false when they were computed again.
    pub vectors_from_file: bool,
    /// Time to read, check, decode and insert them, ms.
    pub ms: f64,
}

/// The identity of the loop closer's vocabulary ([`map_store::vocabulary_id`]): of the
/// configured file, else of the shipped one; `None` when the file cannot be read.
pub fn vocabulary_id(cfg: &LoopCloserConfig) -> Option<u32> {
    match &cfg.vocabulary {
        Some(p) => std::fs::read(p).ok().map(|b| map_store::vocabulary_id(&b)),
        None => Some(map_store::vocabulary_id(map_store::SHIPPED_VOCABULARY)),
    }
}

/// Reads the map file at `path` (clients renamed as the mapper renames them,
/// [`map_store::remap`]) and inserts every keyframe's summary into `closer` without a loop
/// search. The file's BoW and feature vectors are used when they were made with the
/// vocabulary of identity `vocabulary_id` at the closer's feature level; else they are
/// computed again ([`Closer::insert`]). With `freeze` (`--localize-only`) its maps are
/// frozen ([`Closer::freeze`]).
pub fn load(
    closer: &mut Closer,
    path: &Path,
    vocabulary_id: Option<u32>,
    freeze: bool,
) -> anyhow::Result<LoadedKeyframes> {
    let t0 = Instant::now();
    let loaded = map_store::load(path)?;
    let level = closer.feature_level().map_or(0, |l| l as u32);
    let vectors_from_file = Some(loaded.header.vocabulary_id) == vocabulary_id
        && loaded.file.feature_level == level
        && level > 0;
    let mut keyframes = 0;
    for saved in loaded.file.maps {
        let m = &saved.map;
        if freeze {
            closer.freeze(m.id);
        }
        let mut vectors: std::collections::HashMap<u64, _> = saved
            .bow
            .into_iter()
            .map(|(k, bow, fv)| (k, (bow, fv)))
            .collect();
        for k in m.map.keyframes.keys() {
            let Some(kf) = m.kept_summary(*k, KeyframeId::from_raw(*k).client_kf()) else {
                continue;
            };
            match vectors.remove(k).filter(|_| vectors_from_file) {
                Some((bow, fv)) => closer.insert_with_vectors(kf, bow, fv),
                None => closer.insert(kf),
            }
            keyframes += 1;
        }
    }
    Ok(LoadedKeyframes {
        keyframes,
        vectors_from_file,
        ms: t0.elapsed().as_secs_f64() * 1e3,
    })
}
