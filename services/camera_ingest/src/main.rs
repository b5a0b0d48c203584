//! Thin entry point of the camera ingest service (the launcher runs the same code through
//! `shoal service camera-ingest`).
use clap::Parser;

fn main() {
    let params = camera_ingest::Params::parse();
    std::process::exit(camera_ingest::main_with(params));
}
