//! Build script: `cfg(shoal_data)` for the tests that read the real sensor data.

#[path = "../build_support/shoal_data.rs"]
mod shoal_data;

fn main() {
    let crate_dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    shoal_data::emit_data_cfg(crate_dir.parent().unwrap_or(crate_dir));
}
