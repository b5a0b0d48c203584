//! Map points as PLY (`shoal map export`), for point-cloud tools.
use std::io::Write;

use crate::MapFile;

/// PLY encoding.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlyEncoding {
    /// One `x y z` line per point.
    Ascii,
    /// Little-endian `f64` triples.
    BinaryLittleEndian,
}

/// The points (`x y z`, map frame, `f64`) of the maps of `file` whose id is in `only`
/// (all maps when `None`), in map then point id order, as a PLY file. Returns the count.
pub fn write_points(
    out: &mut impl Write,
    file: &MapFile,
    only: Option<u64>,
    encoding: PlyEncoding,
) -> std::io::Result<usize> {
    let mut points: Vec<[f64; 3]> = Vec::new();
    for m in file
        .maps
        .iter()
        .filter(|m| only.is_none_or(|id| m.map.id.raw() == id))
    {
        let mut ids: Vec<&u64> = m.map.map.points.keys().collect();
        ids.sort_unstable();
        points.extend(ids.into_iter().map(|p| {
            let v = m.map.map.points[p].p_w;
            [v.x, v.y, v.z]
        }));
    }
    let format = match encoding {
        PlyEncoding::Ascii => "ascii",
        PlyEncoding::BinaryLittleEndian => "binary_little_endian",
    };
    write!(
        out,
        "ply\nformat {format} 1.0\ncomment shoal map points (map frame)\nelement vertex {}\nproperty double x\nproperty double y\nproperty double z\nend_header\n",
        points.len()
    )?;
    for p in &points {
        match encoding {
            PlyEncoding::Ascii => writeln!(out, "{} {} {}", p[0], p[1], p[2])?,
            PlyEncoding::BinaryLittleEndian => {
                for v in p {
                    out.write_all(&v.to_le_bytes())?;
                }
            }
        }
    }
    Ok(points.len())
}
