//! Build script of the `shoal` package.

#[path = "build_support/shoal_data.rs"]
mod shoal_data;

fn main() {
    // Real-data tests (`tests/`): `cfg(shoal_data)` when `../shared/data` (or $SHOAL_DATA) exists.
    shoal_data::emit_data_cfg(std::path::Path::new(env!("CARGO_MANIFEST_DIR")));
}
