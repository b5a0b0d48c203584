//! The tracker core fed in-process with recorded inputs: transport accounting (gaps,
//! duplicates, foreign schema, end of stream), a restart resuming its predecessor's
//! counters, and the VO on a synthetic scene with a mapper answering every keyframe.
use std::collections::BTreeSet;

use datasets::sim::{Scenario, SimParams, SimWorld};
use shm_schema::{
    Feedback, FrameHeader, ImuMsg, MsgMeta, Pose, TrackState, FLAG_BACKFILL, FLAG_END_OF_STREAM,
    FLAG_HANDLED, FLAG_RESEND, FLAG_WORLD_MOVE,
};
use shoal_runtime::{ErrorKind, Status};
use slam_core::ids::SessionId;

use super::*;
use crate::testing::{frame_header, imu_msg};

fn config(no_vo: bool) -> CoreConfig {
    CoreConfig {
        client: 0,
        no_vo,
        no_rs: false,
        window: 100,
        features: 1000,
        inline_mapping: true,
        lockstep_sync: true,
        spool: false,
        publish_features: false,
        mode: crate::ClientMode::Mono,
        imu: Default::default(),
        calib: Default::default(),
        calib_log: false,
        readout: Default::default(),
        anchor: Default::default(),
    }
}

fn header(seq: u64) -> FrameHeader {
    FrameHeader {
        meta: MsgMeta::new(0, 1, seq, 0),
        t_mid_ns: 1_000_000 * seq as i64,
        ..FrameHeader::default()
    }
}

/// Tracks one frame with no wait for the server; the outputs of both steps.
fn step(core: &mut TrackerCore, h: FrameHeader, pixels: &[u8]) -> (Vec<Out>, bool) {
    let frame = FrameIn {
        header: h,
        pixels,
        recv_ns: 0,
        now_ns: 0,
    };
    match core.track(frame).expect("track") {
        FrameStep::Done(out) => (out, false),
        FrameStep::EndOfStream(h) => {
            assert!(core.take_window().is_empty());
            (core.end_of_stream(&h, 0), true)
        }
        FrameStep::Tracked(mut t) => {
            let mut out = std::mem::take(&mut t.out);
            out.extend(core.publish_frame(t, 0));
            (out, false)
        }
    }
}

fn acks(out: &[Out]) -> Vec<u64> {
    out.iter()
        .filter_map(|o| match o {
            Out::Ack(a) => Some(a.frame_seq),
            _ => None,
        })
        .collect()
}

#[test]
fn transport_counts_gaps_duplicates_foreign_frames_and_the_end() {
    let mut core = TrackerCore::new(config(true), Status::new("tracker:0"));
    for seq in [0, 1, 4] {
        let (out, _) = step(&mut core, header(seq), &[]);
        assert_eq!(acks(&out), vec![seq]);
        assert!(matches!(out.last(), Some(Out::Pose(p)) if p.meta.seq == seq));
    }
    let (out, _) = step(&mut core, header(1), &[]);
    assert_eq!(acks(&out), vec![1], "a re-sent frame is acknowledged again");
    assert_eq!(out.len(), 1, "and gets no second pose");
    let mut foreign = header(5);
    foreign.meta.schema_version += 1;
    assert!(step(&mut core, foreign, &[]).0.is_empty());
    let mut eos = header(6);
    eos.meta.flags = FLAG_END_OF_STREAM;
    let (out, ended) = step(&mut core, eos, &[]);
    assert!(ended && core.ended());
    assert!(matches!(&out[0], Out::Ack(a) if a.frame_t_ns == i64::MAX));
    assert!(matches!(&out[1], Out::Pose(p) if p.meta.flags & FLAG_END_OF_STREAM != 0));
    let s = core.finish();
    let c: TrackerCounters = s.counters_as();
    assert_eq!(c.frames_received, 3);
    assert_eq!(c.frames_gap, 2);
    assert_eq!(c.frames_duplicate, 1);
    assert_eq!(s.errors_of(ErrorKind::SchemaVersion), 1);
    assert!(s.finished);
}

#[test]
fn a_restart_resumes_the_counters_of_the_killed_tracker() {
    let mut prev = Status::new("tracker:0");
    prev.starts = 3;
    prev.put_counters(&TrackerCounters {
        keyframes_sent: 10,
        keyframes_acked_seen: 7,
        ..TrackerCounters::default()
    });
    let left = TrackerResume {
        last_frame_seq: Some(41),
        keyframes_unacked: 2,
        keyframes_queued: 1,
    };
    prev.set_resume(RESUME_VERSION, &left);
    let mut core = TrackerCore::new(config(true), prev);
    assert_eq!(core.counters().keyframes_unacked_at_crash, 2);
    assert_eq!(core.counters().keyframes_unsent_at_crash, 1);
    let (out, _) = step(&mut core, header(45), &[]);
    assert!(
        matches!(&out[0], Out::Ack(a) if {
            let s = SessionId::from_raw(a.meta.session_id);
            (s.start(), s.vo_session()) == (3, 1)
        }),
        "a new start has its own sessions"
    );
    step(&mut core, header(47), &[]);
    assert_eq!(core.counters().frames_gap_at_restart, 3);
    assert_eq!(core.counters().frames_gap, 1);
    // The spool's keyframe of the dead process goes out first, and is counted on top.
    let mut h = shm_schema::KeyframeHeader::default();
    h.meta.session_id = StartIds::new(2).session(1);
    h.keyframe_id = 9;
    // It carries an IMU segment that was cut (issue 19): counted, and an error in the status.
    let out = core.recover_keyframe(
        KeyframeMsg {
            header: h,
            records: Vec::new().into(),
            imu: vec![shm_schema::ImuRecord::default(); 2].into(),
            imu_cut: 3,
        },
        5,
    );
    assert!(matches!(&out[0], Out::Keyframe(m) if m.key() == (StartIds::new(2).session(1), 9)));
    let mut s = core.finish();
    let c: TrackerCounters = s.counters_as();
    assert_eq!(c.keyframes_sent, 11);
    assert_eq!(c.keyframes_recovered, 1);
    assert_eq!(
        (
            c.keyframes_with_imu,
            c.keyframe_imu_samples,
            c.keyframe_imu_cut
        ),
        (1, 2, 1)
    );
    assert_eq!(s.errors_of(shoal_runtime::ErrorKind::ImuSegmentCut), 1);
    let next: TrackerResume = s.take_resume(RESUME_VERSION).expect("resume state");
    assert_eq!((next.last_frame_seq, next.keyframes_unacked), (Some(47), 1));
}

#[test]
fn a_resume_state_of_another_format_is_refused_and_the_tracker_starts_afresh() {
    let mut prev = Status::new("tracker:0");
    prev.starts = 2;
    let left = TrackerResume {
        last_frame_seq: Some(41),
        keyframes_unacked: 2,
        keyframes_queued: 0,
    };
    prev.set_resume(RESUME_VERSION + 1, &left);
    let mut core = TrackerCore::new(config(true), prev);
    assert_eq!(core.counters().keyframes_unacked_at_crash, 0);
    step(&mut core, header(0), &[]);
    let c = core.counters().clone();
    assert_eq!((c.frames_received, c.frames_gap_at_restart), (1, 0));
    assert_eq!(core.status().errors_of(ErrorKind::ResumeState), 1);
}

/// A mapper that applies every keyframe at once and answers with its client pose as server
/// pose (`λ = 1`): the frames' server poses then equal their client poses.
fn answer(m: &crate::outbox::KeyframeMsg) -> Feedback {
    let mut meta = MsgMeta::new(0, m.header.meta.session_id, 0, 0);
    meta.flags = FLAG_HANDLED;
    Feedback {
        meta,
        acked_keyframe_id: m.header.keyframe_id,
        acked_session_id: m.header.meta.session_id,
        has_pose: 1,
        server_pose: m.header.pose_ck,
        scale_ratio: 1.0,
        server_map_id: 5,
    }
}

/// What a run of the core gave.
#[derive(Default)]
struct Run {
    poses: Vec<shm_schema::TrackedPose>,
    /// The tracked features of each frame (`publish_features`).
    features: Vec<(
        shm_schema::TrackedFeaturesHeader,
        Vec<shm_schema::TrackedFeature>,
    )>,
    backfilled: usize,
    sent: Vec<(u32, u64)>,
    spooled: BTreeSet<(u32, u64)>,
    awaited: usize,
}

impl Run {
    /// Carries out `out` as the ports would, the mapper answering every keyframe.
    fn take(&mut self, core: &mut TrackerCore, out: Vec<Out>) {
        for o in out {
            match o {
                Out::Keyframe(m) => {
                    assert_eq!(m.header.meta.flags & FLAG_RESEND, 0, "no re-send needed");
                    self.sent.push(m.key());
                    core.on_feedback(&answer(&m));
                }
                Out::Pose(p) if p.meta.flags & FLAG_BACKFILL != 0 => self.backfilled += 1,
                Out::Pose(p) => self.poses.push(p),
                Out::SpoolWrite(e) => assert!(self.spooled.insert(e.msg.key())),
                Out::SpoolSent(k) => assert!(self.spooled.remove(&k), "{k:?} was spooled"),
                Out::Features(h, f) => self.features.push((h, f)),
                Out::Ack(_) | Out::CalibLog(_) => {}
            }
        }
    }
}

/// Drives the synthetic loop's `frames` through the core as the ports would (gyro before
/// each frame, lock-step waits, the mapper answering every keyframe, window sent and end of
/// stream at the end), the frames of `blank` rendered black.
fn drive(frames: usize, blank: std::ops::Range<usize>) -> (Run, Status) {
    let (run, status, _) = drive_with(frames, blank, 6, None);
    (run, status)
}

/// [`drive`] with a VO window of `window` keyframes and the saved map `prior`; also
/// returns the VO map as it was after the last frame.
fn drive_with(
    frames: usize,
    blank: std::ops::Range<usize>,
    window: usize,
    prior: Option<slam_core::vo::ClientMap>,
) -> (Run, Status, slam_core::vo::ClientMap) {
    let mut p = SimParams::new(Scenario::Loop);
    p.frames = Some(frames);
    p.seed = 3;
    // A rolling shutter, so that every frame asks for the gyro over its readout.
    p.readout_ms = Some(20.0);
    let world = SimWorld::new(p).expect("world");
    let cfg = CoreConfig {
        window,
        spool: true,
        publish_features: true,
        ..config(false)
    };
    let mut core = TrackerCore::new(cfg, Status::new("tracker:0"));
    if let Some(m) = prior {
        core.set_prior_map(m);
    }
    let (imu, mut next_imu) = (world.imu_samples(), 0);
    let mut run = Run::default();
    let c = world.calib().model;
    let mut img = vec![0u8; (c.width * c.height) as usize];
    for k in 0..world.n_frames() {
        let h = frame_header(&world, k);
        let need = core.imu_needed_ns(&h, img.len()).expect("gyro wanted");
        while core.imu_missing(need) {
            core.on_imu(&imu_msg(next_imu as u64, &imu[next_imu]));
            next_imu += 1;
        }
        if blank.contains(&k) {
            img.fill(0);
        } else {
            world.render_frame_into(k, &mut img).expect("render");
        }
        let FrameStep::Tracked(mut t) = core
            .track(FrameIn {
                header: h,
                pixels: &img,
                recv_ns: 0,
                now_ns: 0,
            })
            .expect("track")
        else {
            panic!("frame {k} not taken");
        };
        run.take(&mut core, std::mem::take(&mut t.out));
        if let Some(key) = t.await_handled {
            assert!(core.take_handled(key), "{key:?} answered");
            run.awaited += 1;
        }
        let out = core.publish_frame(t, 0);
        run.take(&mut core, out);
    }
    let map = (core.client.as_ref())
        .map(|c| c.vo().with_map(|m| m.clone()))
        .unwrap_or_default();
    for kf in core.take_window() {
        let (_, out) = core.send_window_keyframe(&kf, 0);
        run.take(&mut core, out);
    }
    let mut eos = MsgMeta::new(0, 1, 999, 0);
    eos.flags = FLAG_END_OF_STREAM;
    core.on_imu(&ImuMsg {
        meta: eos,
        ..ImuMsg::default()
    });
    let mut eos_h = header(frames as u64);
    eos_h.meta.flags = FLAG_END_OF_STREAM;
    let out = core.end_of_stream(&eos_h, 0);
    run.take(&mut core, out);
    assert!(core.drained(), "every keyframe acknowledged");
    (run, core.finish(), map)
}

/// The synthetic loop through the core with the gyro, a small VO window (keyframes leave it
/// while tracking), a spool and lock-step waits: every frame posed, every keyframe sent once,
/// acknowledged and dropped from the spool, the server poses those the feedback implies.
#[test]
fn synthetic_frames_through_the_core_lose_no_keyframe() {
    let (run, status) = drive(120, 0..0);
    check_features(&run);
    check_run(&run, status);
}

/// Every tracked frame's features follow its pose (same frame, same time), one per map
/// point it matched, as many as the pose's inliers (a keyframe adds the points it made),
/// inside the image; an untracked frame has none.
fn check_features(run: &Run) {
    let live = (run.poses.iter()).filter(|p| p.meta.flags & FLAG_WORLD_MOVE == 0);
    let tracked: Vec<_> = live
        .filter(|p| p.state == TrackState::Tracking as u32)
        .collect();
    assert_eq!(run.features.len(), tracked.len());
    for (p, (h, f)) in tracked.iter().zip(&run.features) {
        assert_eq!((h.meta.seq, h.t_ns), (p.meta.seq, p.t_ns));
        assert_eq!(h.n_features as usize, f.len());
        // A keyframe's own new points (inline local mapping) are matched too.
        if p.is_keyframe == 0 {
            assert_eq!(f.len(), p.tracked_points as usize, "frame {}", p.meta.seq);
        } else {
            assert!(
                f.len() >= p.tracked_points as usize,
                "keyframe {}",
                p.meta.seq
            );
        }
        let ids: BTreeSet<u64> = f.iter().map(|f| f.map_point_id).collect();
        assert_eq!(ids.len(), f.len(), "a map point twice");
        assert!(f
            .iter()
            .all(|f| (0.0..752.0).contains(&f.u) && (0.0..480.0).contains(&f.v)));
    }
}

/// A client given the map of an earlier run of the same frames (as prior keyframes, a
/// saved map's client form) localises in it at its first frames, before its own VO could
/// initialise: its frames are posed where the earlier run posed them (the same world and
/// scale), its keyframes are its own (its start's ids, never a prior keyframe's, each sent
/// once and none left in the spool), and the prior keyframes that left its window are
/// counted, not sent.
#[test]
fn a_client_given_a_saved_map_starts_in_it() {
    let (run_a, _, map_a) = drive_with(120, 0..0, 100, None);
    let prior = slam_core::vo::prior_client_map(&map_a).expect("prior").map;
    let n_prior = prior.keyframes.len() as u64;
    assert!(n_prior >= 8, "{n_prior} keyframes");
    let (run_b, status, _) = drive_with(120, 0..0, 6, Some(prior));
    let c: TrackerCounters = status.counters_as();
    assert_eq!(
        (c.prior_map_keyframes, c.prior_map_relocalised),
        (n_prior, 1)
    );
    assert!(c.prior_map_frames_tried <= 2, "{c:?}");
    assert_eq!(c.prior_keyframes_dropped, n_prior, "{c:?}");
    let first_own = ClientKeyframeId::first_of_start(1).raw();
    assert!(
        run_b.sent.iter().all(|(_, k)| *k >= first_own),
        "{:?}",
        run_b.sent
    );
    assert!(run_b.sent.len() >= 4, "{:?}", run_b.sent);
    let pose_of = |run: &Run, seq: u64| {
        (run.poses.iter())
            .find(|p| p.meta.seq == seq && p.state == TrackState::Tracking as u32)
            .map(|p| to_iso(&p.pose).translation.vector)
    };
    let mut compared = 0;
    for seq in 0..120 {
        if let (Some(a), Some(b)) = (pose_of(&run_a, seq), pose_of(&run_b, seq)) {
            let scene = 1.0 + a.norm();
            assert!((a - b).norm() < 0.02 * scene, "frame {seq}: {a} vs {b}");
            compared += 1;
        }
    }
    assert!(compared >= 110, "{compared} frames posed by both");
    let distinct: BTreeSet<_> = run_b.sent.iter().collect();
    assert_eq!(distinct.len(), run_b.sent.len(), "each keyframe sent once");
    assert!(
        run_b.spooled.is_empty(),
        "spool left with {:?}",
        run_b.spooled
    );
}

/// 30 black frames in the middle: the VO is lost, starts a new session after 10 failures
/// and initialises again when the images come back. The old session's keyframes (its whole
/// window, evicted at the session change) go out under the old session's id before any of
/// the new session's, each once and acknowledged; nothing stays in the spool.
#[test]
fn a_session_change_sends_the_old_sessions_keyframes_first_and_loses_none() {
    let (run, status) = drive(180, 60..90);
    check_features(&run);
    let sessions: Vec<u32> = run.sent.iter().map(|k| k.0).collect();
    let first_new = sessions
        .iter()
        .position(|&s| s != sessions[0])
        .expect("a second session");
    assert!(
        sessions[first_new..].iter().all(|&s| s != sessions[0]),
        "old-session keyframes after the new session's: {sessions:?}"
    );
    assert!(first_new >= 4, "{first_new} keyframes of the first session");
    assert!(sessions.len() - first_new >= 4, "{sessions:?}");
    let distinct: BTreeSet<_> = run.sent.iter().collect();
    assert_eq!(
        distinct.len(),
        run.sent.len(),
        "each keyframe sent once: {:?}",
        run.sent
    );
    assert!(run.spooled.is_empty(), "spool left with {:?}", run.spooled);
    let c: TrackerCounters = status.counters_as();
    assert_eq!(c.keyframes_sent, run.sent.len() as u64);
    assert_eq!(c.keyframes_acked_seen, run.sent.len() as u64);
    let tracking = run
        .poses
        .iter()
        .filter(|p| p.state == TrackState::Tracking as u32)
        .count();
    eprintln!(
        "sessions of the sent keyframes {sessions:?}; {tracking} of 180 frames tracking, \
         {} backfilled",
        run.backfilled
    );
    assert!(tracking + run.backfilled >= 140, "{tracking} tracking");
    assert!(status.errors.is_empty(), "{:?}", status.errors);
}

fn check_run(run: &Run, s: Status) {
    let n = run.poses.len() - 1; // the end-of-stream pose
    assert_eq!(n, 120);
    let tracked = run
        .poses
        .iter()
        .filter(|p| p.state == TrackState::Tracking as u32);
    let posed = tracked.count() + run.backfilled;
    assert!(posed >= 118, "{posed} of 120 posed");
    let distinct: BTreeSet<_> = run.sent.iter().collect();
    assert_eq!(distinct.len(), run.sent.len(), "each keyframe sent once");
    assert!(run.sent.len() >= 8, "{} keyframes", run.sent.len());
    assert!(run.awaited >= 1, "keyframes left the window while tracking");
    assert!(run.spooled.is_empty(), "spool left with {:?}", run.spooled);
    let with_server = run.poses.iter().filter(|p| p.has_server_pose != 0);
    let mut checked = 0;
    for p in with_server {
        assert_eq!(p.server_map_id, 5);
        let (a, b) = (to_iso(&p.pose), to_iso(&p.server_pose));
        assert!(
            (a.inverse() * b).translation.vector.norm() < 1e-9,
            "{a} vs {b}"
        );
        checked += 1;
    }
    eprintln!(
        "posed {posed}/120 ({} backfilled), keyframes sent {}, waits {}, server poses {checked}",
        run.backfilled,
        run.sent.len(),
        run.awaited
    );
    assert!(checked >= 60, "{checked} frames with a server pose");
    let c: TrackerCounters = s.counters_as();
    assert_eq!(c.keyframes_sent, run.sent.len() as u64);
    assert_eq!(c.keyframes_acked_seen, run.sent.len() as u64);
    assert_eq!(c.frames_gyro_rs, 120);
    assert_eq!(c.lockstep_imu_timeouts, 0);
    assert!(s.errors.is_empty(), "{:?}", s.errors);
}

fn to_iso(p: &Pose) -> nalgebra::Isometry3<f64> {
    shoal_runtime::wire::iso_from_wire(p).expect("finite pose")
}

/// A visual-inertial core on the first 30 frames of the `drone` scenario, fed its IMU with
/// a saturated sample, a non-finite one and a 0.2 s gap injected (`extrinsics`: whether the
/// configuration says `T_BS` was given); the poses published and the final status.
fn drive_vio(extrinsics: bool) -> (Vec<shm_schema::TrackedPose>, Status) {
    let mut p = SimParams::new(Scenario::Drone);
    p.frames = Some(30);
    p.seed = 3;
    let world = SimWorld::new(p).expect("world");
    let cfg = CoreConfig {
        mode: crate::ClientMode::Vio,
        imu: crate::ImuCalibConfig {
            extrinsics_given: extrinsics,
            ..Default::default()
        },
        ..config(false)
    };
    let mut core = TrackerCore::new(cfg, Status::new("tracker:0"));
    let mut imu: Vec<ImuMsg> = world
        .imu_samples()
        .iter()
        .enumerate()
        .map(|(k, s)| imu_msg(k as u64, s))
        .collect();
    imu[40].accel[0] = 1e4;
    imu[41].gyro[2] = f64::NAN;
    // 0.2 s without samples after the 100th (their sequence numbers skipped: also counted
    // as dropped).
    let t_gap = imu[100].t_ns;
    imu.retain(|m| m.t_ns <= t_gap || m.t_ns > t_gap + 200_000_000);
    let (mut next, mut poses) = (0, vec![]);
    let c = world.calib().model;
    let mut img = vec![0u8; (c.width * c.height) as usize];
    for k in 0..world.n_frames() {
        let h = frame_header(&world, k);
        let need = core
            .imu_needed_ns(&h, img.len())
            .expect("vio waits for the IMU");
        while core.imu_missing(need) && next < imu.len() {
            core.on_imu(&imu[next]);
            next += 1;
        }
        world.render_frame_into(k, &mut img).expect("render");
        let frame = FrameIn {
            header: h,
            pixels: &img,
            recv_ns: 0,
            now_ns: 0,
        };
        let FrameStep::Tracked(t) = core.track(frame).expect("track") else {
            panic!("frame {k} not taken");
        };
        for o in core.publish_frame(t, 0) {
            if let Out::Pose(p) = o {
                poses.push(p);
            }
        }
    }
    (poses, core.finish())
}

/// Bad IMU input in the visual-inertial mode: the saturated and the non-finite sample are
/// refused and the gap reported, each a counted, named error; no frame is lost, and frames
/// with no pose yet carry a gyro-propagated orientation (never an invented position).
#[test]
fn vio_core_counts_bad_imu_samples_and_poses_every_frame() {
    let (poses, status) = drive_vio(true);
    let c: TrackerCounters = status.counters_as();
    assert_eq!(c.imu_samples_refused, 2, "{c:?}");
    assert_eq!(c.imu_gaps, 1, "{c:?}");
    assert_eq!(status.errors_of(ErrorKind::ImuSaturated), 2);
    assert_eq!(status.errors_of(ErrorKind::ImuGap), 1);
    let frames: Vec<_> = poses.iter().filter(|p| p.meta.flags == 0).collect();
    assert_eq!(frames.len(), 30);
    for p in &frames {
        let source = shm_schema::PoseSource::from_u32(p.source).expect("source");
        let tracking = TrackState::from_u32(p.state) == Some(TrackState::Tracking);
        match source {
            shm_schema::PoseSource::OrientationOnly => {
                assert!(!tracking && p.pose.t == [0.0; 3], "{p:?}")
            }
            shm_schema::PoseSource::None => assert!(!tracking),
            _ => assert!(tracking, "{p:?}"),
        }
    }
    let oriented = frames
        .iter()
        .filter(|p| p.source != shm_schema::PoseSource::None as u32)
        .count();
    assert!(
        oriented >= 28,
        "{oriented} of 30 frames with a pose or orientation"
    );
    let report: VioReport = status.details_as().expect("vio report");
    assert_ne!(report.status, "disabled", "{report:?}");
}

/// `vio` without camera-IMU extrinsics runs monocular and says why.
#[test]
fn vio_without_extrinsics_runs_monocular_and_says_why() {
    let (poses, status) = drive_vio(false);
    let report: VioReport = status.details_as().expect("vio report");
    assert_eq!(report.status, "disabled");
    assert!(report.reason.unwrap_or_default().contains("extrinsics"));
    // Monocular: positions come from vision only (never the IMU, never metric); before the
    // monocular initialisation the gyro gives the camera's orientation through the frames'
    // nominal rotation, never a position.
    use shm_schema::PoseSource as S;
    let visual = poses
        .iter()
        .filter(|p| p.source == S::Visual as u32)
        .count();
    assert!(
        visual >= 20,
        "{visual} of {} frames posed by vision",
        poses.len()
    );
    for p in &poses {
        assert!(p.metric == 0, "{p:?}");
        let source = S::from_u32(p.source).expect("source");
        assert!(!matches!(source, S::Inertial | S::VisualInertial), "{p:?}");
        if source == S::OrientationOnly {
            assert_eq!(p.pose.t, [0.0; 3], "{p:?}");
        }
    }
}
