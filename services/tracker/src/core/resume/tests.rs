//! The resume in-process: a visual-inertial core on the `drone` scenario until past its
//! inertial initialisation, its spool kept as the ports keep it (the newest write of each
//! keyframe, until sent), then a restarted core given that spool. The successor continues
//! the same session in the same metric world without initialising again; a spool it cannot
//! use is a named error, its keyframes are sent and a new session starts.
use std::collections::BTreeMap;

use datasets::sim::{Scenario, SimParams, SimWorld};
use nalgebra::Isometry3;
use shm_schema::{FrameAck, ImuMsg, PoseSource, TrackedPose, FLAG_IMU_REPLAY, FLAG_WORLD_MOVE};
use shoal_runtime::{ErrorKind, Status};
use slam_core::ids::{ClientKeyframeId, ClientPointId};
use slam_core::metrics::{align, Alignment};

use super::super::{CoreConfig, FrameIn, FrameStep, Out, StartIds, TrackerCore};
use crate::outbox::KeyframeMsg;
use crate::spool::{Recovered, SpoolEntry};
use crate::testing::{frame_header, imu_msg};

/// Frames the predecessor tracks (4.5 s: it initialises at 2.8 s) and the successor.
const KILLED_AT: usize = 90;
const END: usize = 120;

fn config() -> CoreConfig {
    CoreConfig {
        client: 0,
        no_vo: false,
        no_rs: false,
        window: 100,
        features: 1000,
        inline_mapping: true,
        lockstep_sync: true,
        spool: true,
        publish_features: false,
        mode: crate::ClientMode::Vio,
        imu: crate::ImuCalibConfig {
            extrinsics_given: true,
            ..Default::default()
        },
        calib: Default::default(),
        calib_log: false,
        readout: Default::default(),
        anchor: Default::default(),
    }
}

/// What the ports would have done with a core's outputs.
#[derive(Default)]
struct Ports {
    /// The spool folder: the newest write of each keyframe, until sent.
    spool: BTreeMap<(u32, u64), SpoolEntry>,
    /// Frame poses (no backfill, no world move).
    poses: Vec<TrackedPose>,
    world_moves: usize,
    sent: Vec<(u32, u64)>,
    /// The keyframe messages sent.
    msgs: Vec<KeyframeMsg>,
    /// Requests to the IMU ingest to replay samples.
    replays: Vec<FrameAck>,
}

impl Ports {
    fn take(&mut self, out: Vec<Out>) {
        for o in out {
            match o {
                Out::SpoolWrite(e) => {
                    self.spool.insert(e.msg.key(), e);
                }
                Out::SpoolSent((s, id)) => self.spool.retain(|k, _| k.0 != s || k.1 > id),
                Out::Keyframe(m) => {
                    self.sent.push(m.key());
                    self.msgs.push(m);
                }
                Out::Ack(a) if a.meta.flags & FLAG_IMU_REPLAY != 0 => self.replays.push(a),
                Out::Pose(p) if p.meta.flags & FLAG_WORLD_MOVE != 0 => self.world_moves += 1,
                Out::Pose(p) if p.meta.flags == 0 => self.poses.push(p),
                Out::Pose(_) | Out::Ack(_) | Out::CalibLog(_) | Out::Features(..) => {}
            }
        }
    }

    /// The spool as a successor reads it back.
    fn recovered(&self) -> Vec<Recovered> {
        self.spool
            .values()
            .map(|e| Recovered {
                header: e.msg.header,
                records: e.msg.records.to_vec(),
                imu: e.msg.imu.to_vec(),
                points: Some(e.points.clone()),
            })
            .collect()
    }
}

fn world() -> SimWorld {
    let mut p = SimParams::new(Scenario::Drone);
    p.frames = Some(END);
    p.seed = 3;
    SimWorld::new(p).expect("world")
}

/// Frames `frames` through `core` as the ports would (lock-step: the IMU up to each frame
/// first, from `imu[*next..]`).
fn drive(
    core: &mut TrackerCore,
    world: &SimWorld,
    frames: std::ops::Range<usize>,
    imu: &[ImuMsg],
    next: &mut usize,
    ports: &mut Ports,
) {
    let c = world.calib().model;
    let mut img = vec![0u8; (c.width * c.height) as usize];
    for k in frames {
        let h = frame_header(world, k);
        let need = core
            .imu_needed_ns(&h, img.len())
            .expect("vio waits for the IMU");
        while core.imu_missing(need) && *next < imu.len() {
            core.on_imu(&imu[*next]);
            *next += 1;
        }
        world.render_frame_into(k, &mut img).expect("render");
        let frame = FrameIn {
            header: h,
            pixels: &img,
            recv_ns: 0,
            now_ns: k as i64 * 1_000_000,
        };
        let FrameStep::Tracked(mut t) = core.track(frame).expect("track") else {
            panic!("frame {k} not taken");
        };
        ports.take(std::mem::take(&mut t.out));
        let out = core.publish_frame(t, k as i64 * 1_000_000 + 500_000);
        ports.take(out);
    }
}

/// What a killed predecessor left (its outputs, its status as its successor finds it, and
/// the IMU samples still to come), computed once for the tests of this file.
fn killed_predecessor(world: &SimWorld) -> &'static (Ports, Status, Vec<ImuMsg>) {
    static LEFT: std::sync::OnceLock<(Ports, Status, Vec<ImuMsg>)> = std::sync::OnceLock::new();
    LEFT.get_or_init(|| run_predecessor(world))
}

/// The IMU stream of `world` as published.
fn imu_stream(world: &SimWorld) -> Vec<ImuMsg> {
    world
        .imu_samples()
        .iter()
        .enumerate()
        .map(|(k, s)| imu_msg(k as u64, s))
        .collect()
}

/// The predecessor's run up to the kill, and its status and samples as the successor
/// finds them: the status of a restarted service, the IMU samples published to the dead
/// process (up to its last frame's lock-step horizon, 100 ms on) gone.
fn run_predecessor(world: &SimWorld) -> (Ports, Status, Vec<ImuMsg>) {
    let imu = imu_stream(world);
    let mut core = TrackerCore::new(config(), Status::new("tracker:0"));
    let (mut ports, mut next) = (Ports::default(), 0);
    drive(&mut core, world, 0..KILLED_AT, &imu, &mut next, &mut ports);
    // The initialisation, and the first window's correction of scale and gravity.
    assert!(ports.world_moves >= 1, "initialised before the kill");
    assert!(ports.sent.is_empty() && ports.spool.len() >= 8);
    let mut status = core.status().clone();
    status.starts = 2;
    let horizon = world.frame_time_ns(KILLED_AT - 1) + 100_000_000;
    let later = imu.into_iter().filter(|m| m.t_ns > horizon).collect();
    (ports, status, later)
}

/// Positions of `poses` (camera-to-world) and the truth at their times.
fn with_truth(
    world: &SimWorld,
    poses: &[TrackedPose],
) -> (Vec<Isometry3<f64>>, Vec<Isometry3<f64>>) {
    let est = poses
        .iter()
        .map(|p| shoal_runtime::wire::iso_from_wire(&p.pose).expect("pose"))
        .collect();
    let gt = poses.iter().map(|p| world.pose_cam_at(p.t_ns)).collect();
    (gt, est)
}

/// The successor resumes: one session, keyframe ids continuing, new points in its start's
/// range, no world move, every frame posed by vision, and the poses in the predecessor's
/// metric world (its last 30 metric frames' rigid alignment fits the successor's frames).
#[test]
fn a_restarted_vio_core_resumes_its_predecessors_session() {
    let world = world();
    let (before, status, imu) = killed_predecessor(&world);
    let session = StartIds::new(1).session(1);
    let status = status.clone();
    let newest_old = before.spool.keys().next_back().expect("spooled").1;
    let mut core = TrackerCore::new(config(), status);
    let mut ports = Ports::default();
    ports.take(core.recover_spool(before.recovered(), 0));
    assert!(ports.sent.is_empty(), "the spool is held, not sent");
    drive(&mut core, &world, KILLED_AT..END, imu, &mut 0, &mut ports);
    let c = core.counters().clone();
    assert_eq!(
        (c.vio_resumes, c.keyframes_resumed),
        (1, before.spool.len() as u64)
    );
    assert_eq!(ports.world_moves, 0, "no second initialisation");
    assert!(ports
        .poses
        .iter()
        .all(|p| p.meta.session_id == session && p.metric == 1));
    // Vision poses every frame; with the IMU tracking on, its prior too (the resumed
    // navigator's state), never the IMU alone.
    let (visual, vi) = (PoseSource::Visual as u32, PoseSource::VisualInertial as u32);
    assert!(
        ports
            .poses
            .iter()
            .all(|p| p.source == visual || p.source == vi),
        "every frame posed by vision"
    );
    let with_imu = ports.poses.iter().filter(|p| p.source == vi).count();
    assert!(
        with_imu * 10 >= ports.poses.len() * 9,
        "{with_imu} of {} frames tracked with the resumed IMU state",
        ports.poses.len()
    );
    let new_kfs: Vec<_> = ports.spool.keys().filter(|k| k.1 > newest_old).collect();
    assert!(new_kfs.len() >= 3, "{new_kfs:?}");
    assert!(ports.spool.keys().all(|k| k.0 == session));
    assert!(new_kfs
        .iter()
        .all(|k| k.1 < ClientKeyframeId::first_of_start(2).raw()));
    let old_points: std::collections::HashSet<u64> = before
        .spool
        .values()
        .flat_map(|e| e.points.iter().map(|p| p.id))
        .collect();
    let first_new = ClientPointId::first_of_start(2).raw();
    let new_points = ports.spool.values().flat_map(|e| e.points.iter());
    assert!(new_points
        .filter(|p| !old_points.contains(&p.id))
        .all(|p| p.id >= first_new));
    let report = core.vio_report().expect("vio report");
    assert_eq!(report.status, "initialised");
    assert_eq!(
        (report.resumed, report.resumed_from_keyframe),
        (1, Some(newest_old))
    );
    assert_eq!(report.resumed_after_frames, Some(1));
    check_same_world(&world, &before.poses, &ports.poses);
}

/// The successor's poses are metric on their own (Sim(3) scale ≈ 1, ATE of centimetres)
/// and in the predecessor's world: the yaw-and-translation alignment (the unobservable
/// directions of a gravity-aligned world) of the predecessor's metric frames fits them.
fn check_same_world(world: &SimWorld, before: &[TrackedPose], after: &[TrackedPose]) {
    let (gt_b, est_b) = with_truth(world, &before[before.len() - 30..]);
    let (gt_a, est_a) = with_truth(world, after);
    let rms =
        |gt: &[Isometry3<f64>], est: &[Isometry3<f64>], s: &slam_core::geometry::Similarity| {
            let e: f64 = gt
                .iter()
                .zip(est)
                .map(|(g, e)| {
                    (s.transform_pose(e).translation.vector - g.translation.vector).norm_squared()
                })
                .sum();
            (e / gt.len() as f64).sqrt()
        };
    let own = align(&gt_a, &est_a, Alignment::Sim3).expect("alignment");
    let yaw = align(&gt_b, &est_b, Alignment::FourDof).expect("alignment");
    let se3 = align(&gt_b, &est_b, Alignment::Se3).expect("alignment");
    eprintln!(
        "after the kill: Sim(3) scale {:.4}, ATE {:.4} m; in the predecessor's 4-DoF alignment \
         {:.4} m (its own frames {:.4} m), SE(3) {:.4} m",
        own.scale,
        rms(&gt_a, &est_a, &own),
        rms(&gt_a, &est_a, &yaw),
        rms(&gt_b, &est_b, &yaw),
        rms(&gt_a, &est_a, &se3)
    );
    // The predecessor was killed before its first refinement (5 s of keyframes): the scale
    // is its initialisation's, within 3% here (1.029); a new session's would be arbitrary.
    assert!((own.scale - 1.0).abs() < 0.05, "scale {}", own.scale);
    assert!(rms(&gt_a, &est_a, &own) < 0.02);
    assert!(rms(&gt_a, &est_a, &yaw) < 0.10);
}

/// A spool the successor cannot resume (keyframes of another camera): a named error, the
/// held keyframes sent before the first frame's outputs, a new session started.
#[test]
fn an_unusable_spool_is_a_named_error_and_a_fresh_start() {
    let world = world();
    let (before, status, imu) = killed_predecessor(&world);
    let status = status.clone();
    let mut spool = before.recovered();
    for k in &mut spool {
        k.header.intrinsics.pinhole[0] *= 1.5;
    }
    let n = spool.len();
    let mut core = TrackerCore::new(config(), status);
    let mut ports = Ports::default();
    ports.take(core.recover_spool(spool, 0));
    assert!(ports.sent.is_empty(), "held until the first frame");
    drive(
        &mut core,
        &world,
        KILLED_AT..KILLED_AT + 5,
        imu,
        &mut 0,
        &mut ports,
    );
    assert_eq!(
        ports.sent.len(),
        n,
        "the spooled keyframes go to the mapper"
    );
    let c = core.counters().clone();
    assert_eq!((c.vio_resumes, c.keyframes_recovered), (0, n as u64));
    assert_eq!(core.status().errors_of(ErrorKind::VioResume), 1);
    let report = core.vio_report().expect("vio report");
    assert!(report.resume_refused.is_some_and(|r| r.contains("camera")));
    let start2 = StartIds::new(2).session(1);
    assert!(
        ports.poses.iter().all(|p| p.meta.session_id == start2),
        "a new session"
    );
}

/// No IMU segment lost across the kill (issue 19): the successor asks the IMU ingest to
/// replay the samples from the session's newest spooled keyframe on; given them, every
/// keyframe it sends (the predecessor's, rebuilt from the spool, then its own) carries the
/// segment since the previous one, the rebuilt ones the segment they were spooled with
/// (joined after a keyframe culled before them), and the segments tile the session from
/// its first spooled keyframe to its last.
#[test]
fn a_resumed_session_sends_every_keyframe_with_its_imu_segment() {
    let world = world();
    let (before, status, _) = killed_predecessor(&world);
    let mut core = TrackerCore::new(config(), status.clone());
    let mut ports = Ports::default();
    ports.take(core.recover_spool(before.recovered(), 0));
    let newest = before
        .spool
        .values()
        .next_back()
        .expect("spooled")
        .msg
        .header;
    assert_eq!(ports.replays.len(), 1, "one replay request");
    assert_eq!(ports.replays[0].frame_t_ns, newest.imu_t1_ns);
    assert_eq!(core.counters().imu_replays_asked, 1);
    // The ingest replays from the sample at or before the asked time.
    let stream = imu_stream(&world);
    let from = stream.partition_point(|m| m.t_ns <= newest.imu_t1_ns) - 1;
    drive(
        &mut core,
        &world,
        KILLED_AT..END,
        &stream[from..],
        &mut 0,
        &mut ports,
    );
    for kf in core.take_window() {
        let (_, out) = core.send_window_keyframe(&kf, 0);
        ports.take(out);
    }
    let msgs = &ports.msgs;
    assert!(msgs.len() > before.spool.len() + 2, "{} sent", msgs.len());
    for m in msgs {
        if let Some(spooled) = before.spool.get(&m.key()) {
            let (sent, kept) = (&m.imu[..], &spooled.msg.imu[..]);
            assert!(
                sent.ends_with(kept),
                "keyframe {}: its spooled segment",
                m.key().1
            );
        }
    }
    let first = before.spool.values().next().expect("spooled").msg.clone();
    let mut t = first.header.imu_t1_ns;
    for m in msgs.iter().skip_while(|m| m.key() <= first.key()) {
        let h = &m.header;
        assert!(
            h.n_imu > 2,
            "keyframe {} without its segment",
            h.keyframe_id
        );
        assert_eq!(
            (h.imu_t0_ns, m.imu[0].t_ns),
            (t, t),
            "keyframe {}",
            h.keyframe_id
        );
        t = h.imu_t1_ns;
    }
    assert_eq!(t, msgs.last().expect("sent").header.imu_t1_ns);
}
