//! Shared by the build scripts of the packages whose tests read the real sensor data
//! (`shoal`, `datasets`, `slam_core`; included with `#[path]`): sets `cfg(shoal_data)` when the
//! data folder exists, so those tests are `#[cfg_attr(not(shoal_data), ignore = "...")]` and a
//! run without the data lists them as ignored (named and counted), never as passed.
use std::path::{Path, PathBuf};

/// The real-data folder: `$SHOAL_DATA` when set (a path that does not exist means "no
/// data"; no fallback), else `<workspace>/../shared/data`.
fn data_folder(workspace: &Path) -> PathBuf {
    match std::env::var_os("SHOAL_DATA") {
        Some(d) if !d.is_empty() => PathBuf::from(d),
        _ => workspace.join("../shared/data"),
    }
}

/// The path to watch for the data appearing or disappearing: the folder itself, else its
/// nearest existing parent that does not contain the workspace (cargo scans a watched folder
/// recursively, and a watched path that does not exist re-runs the script, and so rebuilds
/// the package, on every build).
fn watched(dir: &Path, workspace: &Path) -> Option<PathBuf> {
    let ws = workspace.canonicalize().ok()?;
    let mut p = Some(dir);
    while let Some(d) = p {
        if let Ok(c) = d.canonicalize() {
            return (!ws.starts_with(&c)).then_some(c);
        }
        p = d.parent();
    }
    None
}

/// Emits `cargo::rustc-cfg=shoal_data` when the data folder of the workspace at `workspace`
/// exists. With `SHOAL_REQUIRE_DATA=1` (CI) a missing folder fails the build with a message
/// naming it.
pub fn emit_data_cfg(workspace: &Path) {
    println!("cargo::rustc-check-cfg=cfg(shoal_data)");
    println!("cargo::rerun-if-env-changed=SHOAL_DATA");
    println!("cargo::rerun-if-env-changed=SHOAL_REQUIRE_DATA");
    println!("cargo::rerun-if-changed=build.rs");
    let dir = data_folder(workspace);
    if let Some(w) = watched(&dir, workspace) {
        println!("cargo::rerun-if-changed={}", w.display());
    }
    if dir.is_dir() {
        println!("cargo::rustc-cfg=shoal_data");
    } else if std::env::var("SHOAL_REQUIRE_DATA").is_ok_and(|v| v == "1") {
        eprintln!(
            "SHOAL_REQUIRE_DATA=1 but the real-data folder {} does not exist: put the data \
             there or set SHOAL_DATA to its path (without SHOAL_REQUIRE_DATA the tests that \
             need it are reported as ignored)",
            dir.display()
        );
        std::process::exit(1);
    }
}
