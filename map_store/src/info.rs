//! What a map file holds, as `shoal map info` prints it.
use std::fmt::Write;
use std::path::Path;

use crate::{Header, MapFile};

/// One map's summary.
#[derive(Debug, Clone, PartialEq)]
pub struct MapInfo {
    /// Map id (raw).
    pub id: u64,
    /// Keyframes.
    pub keyframes: usize,
    /// Points.
    pub points: usize,
    /// Lengths are metres.
    pub metric: bool,
    /// z is up.
    pub gravity_aligned: bool,
    /// Clients with keyframes in it.
    pub clients: Vec<u32>,
    /// Oldest and newest keyframe time, ns (`None` without keyframes).
    pub span_ns: Option<(i64, i64)>,
}

/// The summary of every map of `file`.
pub fn maps(file: &MapFile) -> Vec<MapInfo> {
    file.maps
        .iter()
        .map(|m| {
            let kfs = &m.map.map.keyframes;
            let t0 = kfs.values().map(|k| k.t_ns).min();
            let t1 = kfs.values().map(|k| k.t_ns).max();
            MapInfo {
                id: m.map.id.raw(),
                keyframes: kfs.len(),
                points: m.map.map.points.len(),
                metric: m.map.frame.metric,
                gravity_aligned: m.map.frame.gravity_aligned,
                clients: m.clients.clone(),
                span_ns: t0.zip(t1),
            }
        })
        .collect()
}

/// The text `shoal map info` prints: the file (size, format version, writer, vocabulary
/// identity), then one line per map.
pub fn describe(header: &Header, file: &MapFile, path: &Path, bytes: u64) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "{}: {bytes} bytes, format version {}, written by shoal {}, vocabulary {:#010x}",
        path.display(),
        header.format_version,
        header.shoal_version,
        header.vocabulary_id
    );
    let _ = writeln!(
        s,
        "{} maps, {} keyframes, {} points",
        file.maps.len(),
        file.keyframes(),
        file.points()
    );
    for m in maps(file) {
        let span = m.span_ns.map_or("-".into(), |(a, b)| {
            format!("{:.3}..{:.3} s", a as f64 * 1e-9, b as f64 * 1e-9)
        });
        let _ = writeln!(
            s,
            "map {:#x}: {} keyframes, {} points, {}, {}, clients {:?}, time {span}",
            m.id,
            m.keyframes,
            m.points,
            if m.metric { "metric" } else { "not metric" },
            if m.gravity_aligned {
                "gravity-aligned"
            } else {
                "not gravity-aligned"
            },
            m.clients
        );
    }
    s
}
