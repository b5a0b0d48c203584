//! Where the loop closures and map merges of a run happened, from the mapper's journal
//! (`OUT/mapper_journal.bin`): each correction the mapper received names its query and
//! matched keyframes (server ids, [`slam_core::ids::KeyframeId`]: client and client keyframe id),
//! whose times the journal's keyframe entries give.
use std::collections::HashMap;
use std::path::Path;

use nalgebra::Vector3;
use shoal_runtime::journal::{read_journal, Entry};

use super::{Mark, MarkKind};

/// A keyframe of a correction: client and data time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct KeyframeAt {
    /// Client index.
    pub client: u32,
    /// Keyframe time, ns (the frame's time).
    pub t_ns: i64,
}

/// A correction the mapper received.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CorrectionEvent {
    /// Merge or pose-graph correction (loop).
    pub kind: MarkKind,
    /// The query (current) keyframe of the loop.
    pub query: KeyframeAt,
    /// The matched (earlier) keyframe.
    pub matched: KeyframeAt,
}

/// The corrections in the journal at `path` (none when it is missing or unreadable), in
/// order; a correction naming a keyframe the journal does not hold is left out.
pub fn corrections_from_journal(path: &Path) -> Vec<CorrectionEvent> {
    let Ok(contents) = read_journal(path) else {
        return Vec::new();
    };
    let mut t_of: HashMap<(u32, u64), i64> = HashMap::new();
    let mut out = Vec::new();
    for e in &contents.entries {
        match e {
            Entry::Keyframe { client, header, .. } => {
                t_of.insert((*client, header.keyframe_id), header.t_ns);
            }
            Entry::Correction { header, .. } => {
                let at = |server_id: u64| {
                    let id = slam_core::ids::KeyframeId::from_raw(server_id);
                    let client = id.client().raw();
                    t_of.get(&(client, id.client_kf()))
                        .map(|t| KeyframeAt { client, t_ns: *t })
                };
                let kind = if header.kind == shm_schema::CORRECTION_MERGE {
                    MarkKind::Merge
                } else {
                    MarkKind::Loop
                };
                if let (Some(query), Some(matched)) = (at(header.query_kf), at(header.matched_kf)) {
                    out.push(CorrectionEvent {
                        kind,
                        query,
                        matched,
                    });
                }
            }
            Entry::Idle { .. } | Entry::MapPoints { .. } => {}
        }
    }
    out
}

/// The position of the pose nearest in time to `t_ns` among `poses` (time, position; sorted
/// by time), if one is within `max_dt_ns`.
fn nearest(poses: &[(i64, Vector3<f64>)], t_ns: i64, max_dt_ns: i64) -> Option<Vector3<f64>> {
    let k = poses.partition_point(|p| p.0 < t_ns);
    [k.checked_sub(1), Some(k)]
        .into_iter()
        .flatten()
        .filter_map(|i| poses.get(i))
        .min_by_key(|p| (p.0 - t_ns).abs())
        .filter(|p| (p.0 - t_ns).abs() <= max_dt_ns)
        .map(|p| p.1)
}

/// The marks of `client`'s plot: each correction one of whose keyframes is the client's,
/// placed on `poses` (time, aligned position; sorted by time) at that keyframe (0.5 s at
/// most away), with a line to the other keyframe when it is the client's too.
pub fn marks_for_client(
    events: &[CorrectionEvent],
    client: u32,
    poses: &[(i64, Vector3<f64>)],
) -> Vec<Mark> {
    const MAX_DT_NS: i64 = 500_000_000;
    let place = |k: &KeyframeAt| {
        (k.client == client)
            .then(|| nearest(poses, k.t_ns, MAX_DT_NS))
            .flatten()
    };
    events
        .iter()
        .filter_map(|e| {
            let (q, m) = (place(&e.query), place(&e.matched));
            let (at, to) = match (q, m) {
                (Some(q), m) => (q, m),
                (None, Some(m)) => (m, None),
                (None, None) => return None,
            };
            Some(Mark {
                kind: e.kind,
                at,
                to,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn marks_go_to_the_client_keyframes() {
        let poses: Vec<(i64, Vector3<f64>)> = (0..10)
            .map(|i| (i * 100_000_000, Vector3::new(i as f64, 0.0, 0.0)))
            .collect();
        let kf = |client, t_ns| KeyframeAt { client, t_ns };
        let events = [
            CorrectionEvent {
                kind: MarkKind::Loop,
                query: kf(0, 810_000_000),
                matched: kf(0, 100_000_000),
            },
            CorrectionEvent {
                kind: MarkKind::Merge,
                query: kf(1, 500_000_000),
                matched: kf(0, 290_000_000),
            },
            CorrectionEvent {
                kind: MarkKind::Merge,
                query: kf(1, 0),
                matched: kf(2, 0),
            },
        ];
        let m = marks_for_client(&events, 0, &poses);
        assert_eq!(m.len(), 2);
        assert_eq!(
            (m[0].kind, m[0].at.x, m[0].to.map(|p| p.x)),
            (MarkKind::Loop, 8.0, Some(1.0))
        );
        assert_eq!(
            (m[1].kind, m[1].at.x, m[1].to),
            (MarkKind::Merge, 3.0, None)
        );
        let late = marks_for_client(&events, 0, &poses[9..]);
        assert_eq!(late.len(), 1, "0.5 s at most away");
        assert_eq!((late[0].at.x, late[0].to), (9.0, None));
        assert!(corrections_from_journal(Path::new("/nonexistent/journal")).is_empty());
    }
}
