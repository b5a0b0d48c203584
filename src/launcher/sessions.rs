//! End of a run: a client's per-frame poses in one frame across its VO sessions, and in the
//! server map (issue 15, part 2; the math is `slam_core::sessions`).
//!
//! A restarted tracker (or one that lost tracking) starts a new session with its own map
//! frame and scale. Once the server merged the sessions, `trajectory_c{i}.txt` expresses
//! every session's frames in the frame of the session with the most frames, and
//! `trajectory_server_c{i}.txt` every frame in the final server map; the report says which
//! sessions were re-expressed (scale, keyframes used) and which could not be, and why.
use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;
use shoal_runtime::wire::{iso_from_wire_unchecked, wire_from_iso};
use slam_core::sessions::{
    in_server_map, in_session_frame, session_links, NoLink, SessionLink, SessionPose, TimedPose,
};

/// One session of a client, as the report gives it.
#[derive(Debug, Clone, Default, Serialize, PartialEq)]
pub struct SessionEntry {
    /// VO session id (as in the messages' `session_id`).
    pub session: u32,
    /// Frames posed in this session.
    pub frames: u64,
    /// Its keyframes with a pose in the final server map.
    pub keyframes_in_server_map: u64,
    /// Scale of its map in the server map (None without a link).
    pub scale_to_server: Option<f64>,
    /// RMS distance of its aligned keyframes to their server poses, server-map units.
    pub keyframe_rmse: Option<f64>,
    /// Its frames were rewritten into the reference session's frame in `trajectory_c{i}.txt`.
    pub reexpressed: bool,
    /// Why not (when it is not the reference and was not re-expressed); its frames are left
    /// out of `trajectory_c{i}.txt` when the run has a reference session.
    pub reason: Option<String>,
}

/// What the report says about a client's sessions.
#[derive(Debug, Clone, Default, Serialize, PartialEq)]
pub struct SessionsReport {
    /// The session whose frame `trajectory_c{i}.txt` is in (the linked session with the
    /// most frames); None with one session or when no session reached the server map.
    pub reference_session: Option<u32>,
    /// Frames of other sessions rewritten into the reference frame.
    pub frames_reexpressed: u64,
    /// Frames of other sessions left out (their session has no link).
    pub frames_left_out: u64,
    /// Frames of `trajectory_server_c{i}.txt` placed relative to their session's keyframes'
    /// final server poses (0: the live server poses are written instead).
    pub frames_server_from_keyframes: u64,
    /// Per session, oldest first.
    pub sessions: Vec<SessionEntry>,
    /// `trajectory_c{i}.txt` is in the frame of a map loaded by `--load-map` (the client's
    /// map merged into it): every frame of the linked sessions, as in
    /// `trajectory_server_c{i}.txt`.
    pub in_loaded_map: bool,
}

/// The outputs for one client.
pub struct OneFrame {
    /// Per-frame poses for `trajectory_c{i}.txt`, by time.
    pub trajectory: Vec<(i64, shm_schema::Pose)>,
    /// Per-frame server-map poses, by time (None: no session linked).
    pub server: Option<Vec<(i64, shm_schema::Pose)>>,
    /// What was done.
    pub report: SessionsReport,
}

fn to_wire(p: &TimedPose) -> (i64, shm_schema::Pose) {
    (p.t_ns, wire_from_iso(&p.t_wc))
}

fn read_keyframes(path: &Path) -> Vec<TimedPose> {
    datasets::trajectory::read_tum(path).map_or_else(
        |_| Vec::new(),
        |t| {
            t.poses
                .iter()
                .map(|p| TimedPose {
                    t_ns: p.t_ns,
                    t_wc: p.pose,
                })
                .collect()
        },
    )
}

/// Per-frame poses (with their sessions, any order) of client `c` of the run in `out`.
pub fn one_frame(
    out: &Path,
    c: usize,
    poses: &[(i64, shm_schema::Pose)],
    sessions: &[u32],
) -> OneFrame {
    let mut frames: Vec<SessionPose> = poses
        .iter()
        .zip(sessions)
        .map(|((t_ns, p), &session)| SessionPose {
            session,
            pose: TimedPose {
                t_ns: *t_ns,
                t_wc: iso_from_wire_unchecked(p),
            },
        })
        .collect();
    frames.sort_by_key(|f| f.pose.t_ns);
    frames.dedup_by_key(|f| f.pose.t_ns);
    // The keyframes of the final server map, and the same frames' poses as tracked (the
    // mapper's `keyframes_client_c{i}.txt` holds only the current session's).
    let server_kfs = read_keyframes(&out.join(format!("keyframes_server_c{c}.txt")));
    let client_kfs: Vec<TimedPose> = server_kfs
        .iter()
        .filter_map(|k| {
            let i = frames.binary_search_by_key(&k.t_ns, |f| f.pose.t_ns).ok()?;
            Some(frames[i].pose)
        })
        .collect();
    let links = session_links(&frames, &client_kfs, &server_kfs);
    let mut report = session_entries(&frames, &links);
    let linked = |s: &&SessionEntry| s.scale_to_server.is_some();
    let reference = report
        .sessions
        .iter()
        .filter(linked)
        .max_by_key(|s| s.frames);
    report.reference_session = reference.map(|s| s.session).filter(|_| links.len() > 1);
    let trajectory = match report.reference_session {
        Some(r) => reexpress(&frames, &links, r, &mut report),
        None => frames.iter().map(|f| to_wire(&f.pose)).collect(),
    };
    let server: Vec<_> = in_server_map(&frames, &links)
        .iter()
        .flatten()
        .map(to_wire)
        .collect();
    report.frames_server_from_keyframes = server.len() as u64;
    OneFrame {
        trajectory,
        server: (!server.is_empty()).then_some(server),
        report,
    }
}

/// The sessions' entries (links, frame counts), without the re-expression.
fn session_entries(
    frames: &[SessionPose],
    links: &BTreeMap<u32, Result<SessionLink, NoLink>>,
) -> SessionsReport {
    let sessions = links
        .iter()
        .map(|(&session, link)| {
            let n = frames.iter().filter(|f| f.session == session).count() as u64;
            let ok = link.as_ref().ok();
            SessionEntry {
                session,
                frames: n,
                keyframes_in_server_map: match link {
                    Ok(l) => l.keyframes.len() as u64,
                    Err(NoLink::TooFewKeyframes(k)) => *k as u64,
                    Err(NoLink::Degenerate(_)) => 0,
                },
                scale_to_server: ok.map(|l| l.to_server.scale),
                keyframe_rmse: ok.map(|l| l.rmse),
                reexpressed: false,
                reason: match link {
                    Ok(_) => None,
                    Err(NoLink::TooFewKeyframes(k)) => Some(format!(
                        "{k} of its keyframes in the server map (needs {})",
                        slam_core::sessions::MIN_KEYFRAMES
                    )),
                    Err(NoLink::Degenerate(e)) => Some(e.clone()),
                },
            }
        })
        .collect();
    SessionsReport {
        sessions,
        ..SessionsReport::default()
    }
}

/// The frames in the frame of session `reference`; fills the report's counts.
fn reexpress(
    frames: &[SessionPose],
    links: &BTreeMap<u32, Result<SessionLink, NoLink>>,
    reference: u32,
    report: &mut SessionsReport,
) -> Vec<(i64, shm_schema::Pose)> {
    let out = in_session_frame(frames, links, reference);
    for (f, o) in frames.iter().zip(&out) {
        if f.session == reference {
            continue;
        }
        match o {
            Some(_) => report.frames_reexpressed += 1,
            None => report.frames_left_out += 1,
        }
    }
    for s in report.sessions.iter_mut() {
        s.reexpressed = s.session != reference && s.scale_to_server.is_some();
    }
    out.iter().flatten().map(to_wire).collect()
}
