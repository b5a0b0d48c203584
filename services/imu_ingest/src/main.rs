//! Thin entry point of the IMU ingest service (the launcher runs the same code through
//! `shoal service imu-ingest`).
use clap::Parser;

fn main() {
    let params = imu_ingest::Params::parse();
    std::process::exit(imu_ingest::main_with(params));
}
