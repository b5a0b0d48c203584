//! Thin entry point of the mapper service (the launcher runs the same code through
//! `shoal service mapper`).
use clap::Parser;

fn main() {
    let params = mapper::Params::parse();
    std::process::exit(mapper::main_with(params));
}
