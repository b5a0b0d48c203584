//! Saved maps in a run (`--load-map`, `--save-map`): the file's check before any service
//! starts, and what the report says about it.
use std::path::Path;

use serde::Serialize;

/// A `--load-map` file as the report lists it.
#[derive(Debug, Clone, Default, Serialize, PartialEq)]
pub struct MapLoadReport {
    /// The file.
    pub file: String,
    /// Its size, bytes.
    pub bytes: u64,
    /// Its format version and the shoal version that wrote it.
    pub format_version: u32,
    /// The shoal version that wrote it.
    pub written_by: String,
    /// Maps, keyframes and points it holds.
    pub maps: u64,
    /// Keyframes over all maps.
    pub keyframes: u64,
    /// Points over all maps.
    pub points: u64,
    /// The launcher's check (read, checksum, decode, validation), ms.
    pub check_ms: f64,
    /// The mapper's load (read, check, host), ms (from its status).
    pub mapper_load_ms: Option<f64>,
    /// Keyframes the loop closer inserted from it and its load time, ms.
    pub loop_closer_keyframes: Option<u64>,
    /// The loop closer's load (read, check, BoW vectors, insertion), ms.
    pub loop_closer_load_ms: Option<f64>,
    /// The loop closer used the file's BoW and feature vectors (same vocabulary and
    /// feature level), rather than computing them again.
    pub loop_closer_vectors_from_file: Option<bool>,
    /// `--localize-only`: the clients localised in its maps without adding to them.
    pub localize_only: bool,
    /// `--localize-only`: the mapper found every loaded map as it was loaded at the end
    /// (same digest, [`map_store::map_digest`]); `None` without `--localize-only` or when
    /// the mapper did not say.
    pub maps_unchanged: Option<bool>,
}

/// A `--save-map` file as the report lists it (from the mapper's status).
#[derive(Debug, Clone, Default, Serialize, PartialEq)]
pub struct MapSaveReport {
    /// The file.
    pub file: String,
    /// Written, or why not (the mapper's `map_file` error is in `errors`).
    pub saved: bool,
    /// Its size, bytes.
    pub bytes: u64,
    /// Maps, keyframes and points written.
    pub maps: u64,
    /// Keyframes over all maps.
    pub keyframes: u64,
    /// Points over all maps.
    pub points: u64,
    /// Time to gather, encode (with BoW vectors) and write it, ms.
    pub save_ms: f64,
}

/// Reads the map file at `path` whole (magic, version, length, checksum, decode,
/// validation): the error names the file and the problem.
pub fn check(path: &Path) -> anyhow::Result<MapLoadReport> {
    let t0 = std::time::Instant::now();
    let loaded = map_store::load(path).map_err(|e| anyhow::anyhow!("--load-map: {e}"))?;
    Ok(MapLoadReport {
        file: path.display().to_string(),
        bytes: loaded.bytes,
        format_version: loaded.header.format_version,
        written_by: loaded.header.shoal_version,
        maps: loaded.file.maps.len() as u64,
        keyframes: loaded.file.keyframes() as u64,
        points: loaded.file.points() as u64,
        check_ms: t0.elapsed().as_secs_f64() * 1e3,
        ..MapLoadReport::default()
    })
}

/// Before anything is started or written: `--localize-only`'s combination, and the
/// `--load-map` file read whole (checksum, decode, validation); a bad file ends the command.
pub fn check_inputs(cfg: &crate::config::RunConfig) -> anyhow::Result<Option<MapLoadReport>> {
    let (load, save) = (cfg.load_map.as_deref(), cfg.save_map.as_deref());
    check_localize_only(cfg.localize_only, load, save)?;
    load.map(check).transpose()
}

/// After the output folder is made (the map is often saved in it): the `--save-map` and
/// `--record` files can be created.
pub fn check_outputs(cfg: &crate::config::RunConfig) -> anyhow::Result<()> {
    if let Some(p) = &cfg.save_map {
        check_save_path(p)?;
    }
    if let Some(p) = &cfg.record {
        check_file_path("--record", p)?;
    }
    Ok(())
}

/// `--localize-only` needs a map to localise in (`--load-map`) and leaves it as it was, so a
/// `--save-map` of the same run would only copy it: both are refused before the start.
pub fn check_localize_only(
    localize_only: bool,
    load_map: Option<&Path>,
    save_map: Option<&Path>,
) -> anyhow::Result<()> {
    if !localize_only {
        return Ok(());
    }
    anyhow::ensure!(
        load_map.is_some(),
        "--localize-only localises in a saved map: give it with --load-map FILE"
    );
    if let Some(p) = save_map {
        anyhow::bail!(
            "--localize-only leaves the loaded map unchanged: --save-map {} would only copy it \
             (run without --localize-only to extend the map and save it)",
            p.display()
        );
    }
    Ok(())
}

/// Checks that the `--save-map` file can be created where it is asked: its folder exists
/// (the mapper writes it at the end of the run; finding out then would lose the maps).
pub fn check_save_path(path: &Path) -> anyhow::Result<()> {
    check_file_path("--save-map", path)
}

/// Checks that the file `path` of option `flag` can be created: its folder exists and it
/// is not a folder.
pub fn check_file_path(flag: &str, path: &Path) -> anyhow::Result<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    anyhow::ensure!(
        dir.is_dir(),
        "{flag} {}: the folder {} does not exist",
        path.display(),
        dir.display()
    );
    anyhow::ensure!(!path.is_dir(), "{flag} {}: is a folder", path.display());
    Ok(())
}

/// A status value as an integer count.
fn count(values: &std::collections::BTreeMap<String, f64>, key: &str) -> u64 {
    values.get(key).map_or(0, |v| *v as u64)
}

/// The save report of `path` from the mapper's status values.
pub fn saved(path: &Path, values: &std::collections::BTreeMap<String, f64>) -> MapSaveReport {
    MapSaveReport {
        file: path.display().to_string(),
        saved: values.contains_key("map_saved_bytes"),
        bytes: count(values, "map_saved_bytes"),
        maps: count(values, "map_saved_maps"),
        keyframes: count(values, "map_saved_keyframes"),
        points: count(values, "map_saved_points"),
        save_ms: values.get("map_save_ms").copied().unwrap_or(0.0),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `--save-map` file in a missing folder, or naming a folder, is refused at the
    /// start; one in an existing folder (or the current one) is accepted.
    #[test]
    fn the_save_map_folder_must_exist() {
        let dir = tempfile::tempdir().expect("tempdir");
        let e = check_save_path(&dir.path().join("missing/m.shoalmap")).expect_err("missing");
        assert!(e.to_string().contains("does not exist"), "{e}");
        let e = check_save_path(dir.path()).expect_err("a folder");
        assert!(e.to_string().contains("is a folder"), "{e}");
        check_save_path(&dir.path().join("m.shoalmap")).expect("existing folder");
        check_save_path(Path::new("m.shoalmap")).expect("current folder");
    }

    /// `--localize-only` without a map, or with `--save-map`, is refused; with a map it is
    /// accepted, and without the flag anything goes.
    #[test]
    fn localize_only_needs_a_map_and_saves_none() {
        let (map, out) = (Some(Path::new("a.shoalmap")), Some(Path::new("b.shoalmap")));
        let e = check_localize_only(true, None, None).expect_err("no map");
        assert!(e.to_string().contains("--load-map"), "{e}");
        let e = check_localize_only(true, map, out).expect_err("saved");
        assert!(e.to_string().contains("b.shoalmap"), "{e}");
        check_localize_only(true, map, None).expect("a map to localise in");
        check_localize_only(false, None, out).expect("no localisation");
    }

    /// The save report comes from the mapper's status values; without them the map was not
    /// saved.
    #[test]
    fn the_save_report_reads_the_mapper_values() {
        let values = [("map_saved_bytes", 1234.0), ("map_saved_keyframes", 13.0)]
            .map(|(k, v)| (k.to_string(), v))
            .into();
        let r = saved(Path::new("a.shoalmap"), &values);
        assert!(r.saved);
        assert_eq!((r.bytes, r.keyframes, r.points), (1234, 13, 0));
        let r = saved(Path::new("a.shoalmap"), &Default::default());
        assert!(!r.saved);
    }
}
