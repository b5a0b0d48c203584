//! A `--load-map` file's keyframes in the loop detector before the first live keyframe, so
//! that a new session can relocalise into the loaded maps ([`map_store`]).
use std::path::Path;
use std::time::Instant;

use slam_core::ids::KeyframeId;

use crate::Closer;

/// What [`load`] inserted.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoadedKeyframes {
    /// Keyframes inserted.
    pub keyframes: usize,
    /// Time to read, check, decode and insert them, ms.
    pub ms: f64,
}

/// Reads the map file at `path` (clients renamed as the mapper renames them,
/// [`map_store::remap`]) and inserts every keyframe's summary into `closer` without a loop
/// search ([`Closer::insert`]). The BoW vectors are computed again with the loop closer's
/// own vocabulary (always consistent with it, whatever vocabulary the file's vectors were
/// made with; BENCHMARKS.md "Saved maps" for the cost).
pub fn load(closer: &mut Closer, path: &Path) -> anyhow::Result<LoadedKeyframes> {
    let t0 = Instant::now();
    let loaded = map_store::load(path)?;
    let mut keyframes = 0;
    for saved in &loaded.file.maps {
        let m = &saved.map;
        for k in m.map.keyframes.keys() {
            if let Some(kf) = m.kept_summary(*k, KeyframeId::from_raw(*k).client_kf()) {
                closer.insert(kf);
                keyframes += 1;
            }
        }
    }
    Ok(LoadedKeyframes {
        keyframes,
        ms: t0.elapsed().as_secs_f64() * 1e3,
    })
}
