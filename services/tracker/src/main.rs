//! Thin entry point of the tracker service (the launcher runs the same code through
//! `shoal service tracker`).
use clap::Parser;

fn main() {
    let params = tracker::Params::parse();
    std::process::exit(tracker::main_with(params));
}
