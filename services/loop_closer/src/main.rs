//! Thin entry point of the loop_closer service (the launcher runs the same code through
//! `shoal service loop-closer`).
use clap::Parser;

fn main() {
    let params = loop_closer::Params::parse();
    std::process::exit(loop_closer::main_with(params));
}
