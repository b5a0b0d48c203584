//! `shoal map`: what a saved-map file holds (`info`) and its points for other tools
//! (`export --ply`).
use std::path::PathBuf;

use anyhow::Context;
use map_store::ply::PlyEncoding;

/// `shoal map` subcommands.
#[derive(clap::Subcommand, Debug)]
pub enum MapCommand {
    /// Print what a saved-map file holds: format version, writer, vocabulary, size; per
    /// map its id, keyframes, points, metric / gravity-aligned, clients and time span.
    Info {
        /// The map file (`shoal run --save-map`).
        file: PathBuf,
    },
    /// Write the map points (x y z, map frame) of a saved-map file as PLY.
    Export {
        /// The map file.
        file: PathBuf,
        /// The PLY file to write.
        #[arg(long, value_name = "OUT")]
        ply: PathBuf,
        /// Only the map of this id (as `map info` prints it, e.g. 0x800000_00000000);
        /// default all maps.
        #[arg(long, value_name = "ID", value_parser = parse_map_id)]
        map: Option<u64>,
        /// Binary little-endian PLY (default ASCII).
        #[arg(long)]
        binary: bool,
    },
}

fn parse_map_id(s: &str) -> Result<u64, String> {
    let t = s.replace('_', "");
    match t.strip_prefix("0x") {
        Some(h) => u64::from_str_radix(h, 16),
        None => t.parse(),
    }
    .map_err(|e| format!("map id {s}: {e}"))
}

/// Runs a `shoal map` subcommand.
pub fn run(cmd: &MapCommand) -> anyhow::Result<()> {
    match cmd {
        MapCommand::Info { file } => {
            let (header, maps) = map_store::read(file)?;
            let bytes = std::fs::metadata(file).map_or(0, |m| m.len());
            print!("{}", map_store::info::describe(&header, &maps, file, bytes));
            Ok(())
        }
        MapCommand::Export {
            file,
            ply,
            map,
            binary,
        } => {
            let (_, maps) = map_store::read(file)?;
            if let Some(id) = map {
                anyhow::ensure!(
                    maps.maps.iter().any(|m| m.map.id.raw() == *id),
                    "{}: no map {id:#x}",
                    file.display()
                );
            }
            let encoding = if *binary {
                PlyEncoding::BinaryLittleEndian
            } else {
                PlyEncoding::Ascii
            };
            let f = std::fs::File::create(ply)
                .with_context(|| format!("creating {}", ply.display()))?;
            let mut w = std::io::BufWriter::new(f);
            let n = map_store::ply::write_points(&mut w, &maps, *map, encoding)
                .and_then(|n| std::io::Write::flush(&mut w).map(|_| n))
                .with_context(|| format!("writing {}", ply.display()))?;
            println!("{}: {n} points", ply.display());
            Ok(())
        }
    }
}
