//! Saved maps: the maps of a `--load-map` file hosted at the start, all maps written to the
//! `--save-map` file at the end ([`map_store`]).
use std::path::Path;
use std::time::Instant;

use anyhow::Context;
use shoal_runtime::ErrorKind;
use slam_core::place::Vocabulary;
use slam_core::server::ServerMap;

use crate::core::Mapper;

/// Loads the map file at `path` (clients renamed, [`map_store::remap`]) and hosts its maps;
/// the status gets `map_loaded_{maps,keyframes,points}` and `map_load_ms`. A file refused
/// here (the launcher checked it before the start) is an error: the mapper does not start
/// half-loaded.
pub fn load(m: &mut Mapper, path: &Path) -> anyhow::Result<()> {
    let t0 = Instant::now();
    let loaded = map_store::load(path)?;
    let (maps, kfs, pts) = (
        loaded.file.maps.len(),
        loaded.file.keyframes(),
        loaded.file.points(),
    );
    let mut hosted: Vec<ServerMap> = loaded.file.maps.into_iter().map(|s| s.map).collect();
    if m.localize_only {
        for map in &mut hosted {
            map.freeze();
            m.frozen_digests.insert(map.id, map_store::map_digest(map));
        }
    }
    m.host_loaded(hosted)
        .with_context(|| format!("hosting the maps of {}", path.display()))?;
    let s = &mut m.status;
    s.set_value("map_loaded_maps", maps as f64);
    s.set_value("map_loaded_keyframes", kfs as f64);
    s.set_value("map_loaded_points", pts as f64);
    s.set_value("map_load_ms", t0.elapsed().as_secs_f64() * 1e3);
    eprintln!(
        "mapper: loaded {maps} maps, {kfs} keyframes, {pts} points from {}",
        path.display()
    );
    Ok(())
}

/// `--localize-only`, at the end (after the drain): compares each frozen map with what was
/// loaded ([`map_store::map_digest`]); the status gets `map_localize_only_unchanged` (1 when
/// every one is the same) and an error names a map that changed or is gone.
pub fn check_frozen(m: &mut Mapper) {
    let maps = m.take_final_maps();
    let mut unchanged = true;
    for (id, digest) in std::mem::take(&mut m.frozen_digests) {
        let now = maps.get(&id).map(map_store::map_digest);
        if now != Some(digest) {
            unchanged = false;
            let what = if now.is_none() { "is gone" } else { "changed" };
            let detail = format!("--localize-only: the loaded map {:#x} {what}", id.raw());
            m.status.error(ErrorKind::MapFile, detail);
        }
    }
    m.status.set_value(
        "map_localize_only_unchanged",
        f64::from(u8::from(unchanged)),
    );
}

/// The feature-vector level the file's keyframes get: the loop detector's default (a loop
/// closer configured otherwise computes its own when it loads the file).
pub fn feature_level() -> u32 {
    let p = slam_core::loop_closing::LoopDetectorParams::default();
    p.feature_level.map_or(0, |l| l as u32)
}

/// Writes every map the handler threads ended with to `path` (after the drain), with each
/// keyframe's BoW and feature vectors of the shipped vocabulary; the status gets `map_saved_bytes`,
/// `map_saved_{maps,keyframes,points}` and `map_save_ms`. A failure is a `map_file` error
/// of the status (the run's other outputs are written anyway).
pub fn save(m: &mut Mapper, path: &Path, all_joined: bool) {
    let t0 = Instant::now();
    if !all_joined {
        let detail = format!(
            "{}: a handler thread had not finished at the end: its maps are not saved",
            path.display()
        );
        m.status.error(ErrorKind::MapFile, detail);
    }
    let maps = m.take_final_maps();
    let vocabulary = match Vocabulary::from_bytes(map_store::SHIPPED_VOCABULARY) {
        Ok(v) => v,
        Err(e) => {
            let detail = format!("{}: the built-in vocabulary: {e}", path.display());
            return m.status.error(ErrorKind::MapFile, detail);
        }
    };
    let file = map_store::MapFile::from_maps(maps.values(), &vocabulary, feature_level());
    let vocab_id = map_store::vocabulary_id(map_store::SHIPPED_VOCABULARY);
    match map_store::write(path, &file, vocab_id, env!("CARGO_PKG_VERSION")) {
        Ok(bytes) => {
            let s = &mut m.status;
            s.set_value("map_saved_bytes", bytes as f64);
            s.set_value("map_saved_maps", file.maps.len() as f64);
            s.set_value("map_saved_keyframes", file.keyframes() as f64);
            s.set_value("map_saved_points", file.points() as f64);
            s.set_value("map_save_ms", t0.elapsed().as_secs_f64() * 1e3);
            eprintln!(
                "mapper: saved {} maps, {} keyframes, {} points to {} ({bytes} bytes)",
                file.maps.len(),
                file.keyframes(),
                file.points(),
                path.display()
            );
        }
        Err(e) => m.status.error(ErrorKind::MapFile, e.to_string()),
    }
}
