//! Shared helpers of the integration tests.
#![allow(dead_code)]

use std::path::PathBuf;

/// The real-data folder: `$SHOAL_DATA` when set, else `<workspace>/../shared/data` (the
/// rule of `build_support/shoal_data.rs`, which ignores the tests that call this when the
/// folder is absent). Panics, failing the test, when the folder or its sub-folder `sub` is
/// missing: a test that runs never passes without its data.
pub fn data_dir(sub: &str) -> PathBuf {
    let dir = match std::env::var_os("SHOAL_DATA") {
        Some(d) if !d.is_empty() => PathBuf::from(d),
        _ => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"),
    };
    assert!(
        dir.join(sub).is_dir(),
        "real data {} not found (set SHOAL_DATA to the data folder)",
        dir.join(sub).display()
    );
    dir
}

/// FNV-1a 64 of a byte slice (for image checksums).
pub fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}
