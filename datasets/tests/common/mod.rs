//! Shared helpers of the integration tests.
#![allow(dead_code)]

use std::path::PathBuf;

/// The real-data folder: `$SHOAL_DATA`, else `<workspace>/../shared/data`. `None` (after
/// printing a SKIP line naming `test`) when it is absent.
pub fn data_dir(test: &str) -> Option<PathBuf> {
    let dir = match std::env::var_os("SHOAL_DATA") {
        Some(d) => PathBuf::from(d),
        None => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"),
    };
    if dir.is_dir() {
        Some(dir)
    } else {
        println!(
            "SKIP {test}: real data folder {} not found (set SHOAL_DATA)",
            dir.display()
        );
        None
    }
}

/// FNV-1a 64 of a byte slice (for image checksums).
pub fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}
