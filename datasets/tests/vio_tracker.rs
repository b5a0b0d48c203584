//! The visual-inertial client core (`slam_core::vio`, issue 17) on rendered sim scenarios,
//! against the monocular VO on the same frames: ATE with an SE(3) alignment (no scale), the
//! scale error (Sim(3) alignment scale), the time to initialise, the frames posed, a 2 s
//! blackout bridged on the IMU, and local mapping's visual-inertial window against the same
//! client without it (accuracy, biases against the truth). Frames are fed on the IMU clock
//! (the ingest applies t_d), the IMU up to 50 ms after each frame (as the tracker service
//! has it by then); local mapping runs inline.
use std::collections::HashMap;

use datasets::sim::{Scenario, SimParams, SimWorld};
use nalgebra::{Isometry3, Vector3};
use slam_core::geometry::umeyama;
use slam_core::imu::{ImuBiases, ImuMeasurement, PreintegrationParams};
use slam_core::vio::{NavParams, Navigator, PoseSource, VioParams, VioStatus, VioTracker};
use slam_core::vo::map::transform_pose_cw;
use slam_core::vo::{
    LocalMappingStats, ViMappingMode, ViMappingParams, VoFrame, VoParams, VoTracker,
};

#[derive(Debug, Clone, Copy, PartialEq)]
enum Mode {
    Mono,
    /// The visual-inertial client, with the IMU's pose prior, with local mapping's
    /// visual-inertial window or without it (the visual local BA only).
    Vio {
        prior: bool,
        window: bool,
    },
}

/// The client with the prior and the window (the defaults).
const VIO: Mode = Mode::Vio {
    prior: true,
    window: true,
};

type MaybePose = Option<Isometry3<f64>>;

/// One run: each frame's final pose (earlier poses re-expressed at each world move).
struct Run {
    times: Vec<i64>,
    poses: Vec<Option<Isometry3<f64>>>,
    sources: Vec<PoseSource>,
    /// Vision's pose and the IMU's prediction of each frame (in the world of that frame).
    vision: Vec<(MaybePose, MaybePose)>,
    orientations: usize,
    new_sessions: usize,
    /// Seconds from the first frame to the initialisation.
    init_s: Option<f64>,
    status: Option<VioStatus>,
    /// The last frame's biases (effective) and IMU time.
    biases: Option<(i64, ImuBiases)>,
    /// Local mapping's totals.
    mapping: LocalMappingStats,
    /// CPU time of the run (this thread), ms.
    cpu_ms: f64,
    /// Frames with a world move.
    moves_at: Vec<usize>,
}

/// CPU time of the current thread, ms (Linux `/proc/thread-self/schedstat`; 0 elsewhere):
/// the machine is shared, so wall time says little. Printed, never asserted.
fn cpu_ms() -> f64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse::<f64>().ok())
        .map_or(0.0, |ns| ns * 1e-6)
}

fn world(scenario: Scenario, seconds: f64) -> SimWorld {
    let mut p = SimParams::new(scenario);
    p.seed = 3;
    p.frames = Some((seconds * p.rate_hz) as usize);
    SimWorld::new(p).expect("sim world")
}

fn imu_at(world: &SimWorld, k: usize) -> ImuMeasurement {
    let s = world.imu_samples()[k];
    ImuMeasurement {
        t_ns: s.t_ns,
        gyro: Vector3::from(s.gyro),
        accel: Vector3::from(s.accel),
    }
}

fn vio_params(world: &SimWorld, prior: bool) -> VioParams {
    let sensor = world.params();
    let preint = PreintegrationParams::new(&sensor.noise, &sensor.imu_intrinsics).expect("preint");
    let mut coupler = slam_core::imu::coupler::CouplerParams::default();
    if let Ok(v) = std::env::var("ACC_PRIOR") {
        coupler.init.prior_accel_bias = v.parse().expect("ACC_PRIOR");
    }
    if let Ok(v) = std::env::var("POSE_SIGMA") {
        coupler.init.pose_sigma_m = v.parse().expect("POSE_SIGMA");
    }
    VioParams {
        coupler,
        pose_prior: prior,
        imu_tracking: std::env::var("SHOAL_VIO_IMU_TRACKING").map_or(true, |v| v != "0"),
        refinements_with_window: std::env::var("REFINE").map_or(1, |v| v.parse().expect("REFINE")),
        ..VioParams::new(preint, world.calib().t_bs)
    }
}

/// A debugging override (`VW_N`, `VW_COV`): unset in the tests.
fn env_or(key: &str, default: usize) -> usize {
    std::env::var(key).map_or(default, |v| v.parse().expect(key))
}

fn run(world: &SimWorld, mode: Mode) -> Run {
    run_anchored(world, mode, None)
}

/// [`run`], the client anchored by `delta` (a rigid move of its world) before frame `k`.
fn run_anchored(world: &SimWorld, mode: Mode, anchor: Option<(usize, Isometry3<f64>)>) -> Run {
    let cpu0 = cpu_ms();
    let cam = world.calib().model;
    let mut mono =
        (mode == Mode::Mono).then(|| VoTracker::new(VoParams::default(), cam).expect("vo"));
    let mut vio = match mode {
        Mode::Vio { prior, window } => {
            let vi_window = ViMappingParams {
                mode: if window {
                    ViMappingMode::InsteadOfVisualBa
                } else {
                    ViMappingMode::Off
                },
                keyframes: env_or("VW_N", 10),
                fixed_covisible: env_or("VW_COV", 10),
                ..Default::default()
            };
            let vp = VoParams {
                vi_window,
                ..VoParams::default()
            };
            let vo = VoTracker::new(vp, cam).expect("vo");
            Some(VioTracker::new(vo, vio_params(world, prior)))
        }
        Mode::Mono => None,
    };
    let r_cb = world.calib().t_bs.rotation.inverse();
    let gyro: Vec<(i64, Vector3<f64>)> = world
        .imu_samples()
        .iter()
        .map(|s| (s.t_ns, Vector3::from(s.gyro)))
        .collect();
    let n = world.n_frames();
    let mut r = Run {
        times: (0..n).map(|k| world.frame_capture_time_ns(k)).collect(),
        poses: vec![None; n],
        sources: vec![PoseSource::None; n],
        vision: vec![(None, None); n],
        orientations: 0,
        new_sessions: 0,
        init_s: None,
        status: None,
        biases: None,
        mapping: LocalMappingStats::default(),
        cpu_ms: 0.0,
        moves_at: Vec::new(),
    };
    let index: HashMap<i64, usize> = r.times.iter().enumerate().map(|(k, &t)| (t, k)).collect();
    let mut session_start = 0;
    let mut next_imu = 0;
    let mut img = vec![0u8; (cam.width * cam.height) as usize];
    for k in 0..n {
        let t_ns = r.times[k];
        while next_imu < gyro.len() && gyro[next_imu].0 <= t_ns + 50_000_000 {
            if let Some(v) = vio.as_mut() {
                v.on_imu(imu_at(world, next_imu)).expect("valid IMU");
            }
            next_imu += 1;
        }
        let frame = VoFrame {
            t_ns,
            ..world.vo_frame(k, &mut img).expect("render")
        };
        let (vo_out, t_cw, source) = match (mono.as_mut(), vio.as_mut()) {
            (Some(vo), _) => {
                let half = world.readout_ns() / 2;
                let angular_velocity = (half > 0)
                    .then(|| slam_core::imu::mean_rate(&gyro, t_ns - half, t_ns + half))
                    .flatten()
                    .map(|w_b| r_cb * w_b);
                let o = vo
                    .process(&VoFrame {
                        angular_velocity,
                        ..frame
                    })
                    .expect("vo");
                let t_cw = o.t_cw;
                let src = if t_cw.is_some() {
                    PoseSource::Visual
                } else {
                    PoseSource::None
                };
                (o, t_cw, src)
            }
            (None, Some(v)) => {
                if let Some((_, delta)) = anchor.filter(|a| a.0 == k) {
                    v.request_anchor(v.vo().session_id(), Some(delta));
                }
                let o = v.process(&frame).expect("vio");
                if anchor.is_some_and(|a| a.0 == k) {
                    assert_eq!(o.anchor, anchor.map(|a| a.1), "anchored at frame {k}");
                }
                if std::env::var("VERBOSE").is_ok() && o.vo.keyframe.is_some() {
                    if let VioStatus::Refused(e) = v.status() {
                        eprintln!("{:.2} s: {e}", (t_ns - r.times[0]) as f64 * 1e-9);
                    }
                }

                if let Some(m) = o.world_move {
                    r.moves_at.push(k);
                    if std::env::var("VERBOSE").is_ok() {
                        let t = (t_ns - r.times[0]) as f64 * 1e-9;
                        eprintln!(
                            "world move at {t:.2} s: scale {:.5}, {:.3}°, init {}",
                            m.world.s,
                            m.world.r.angle().to_degrees(),
                            m.initialisation
                        );
                    }
                    for p in r.poses[session_start..k].iter_mut().flatten() {
                        *p = transform_pose_cw(p, &m.world);
                    }
                    if m.initialisation {
                        r.init_s = Some((t_ns - r.times[0]) as f64 * 1e-9);
                    }
                }
                r.orientations += usize::from(o.source == PoseSource::OrientationOnly);
                r.biases = o.nav.map(|n| (t_ns, n.biases)).or(r.biases);
                r.vision[k] = (o.vo.t_cw, o.prediction.map(|p| p.t_cw));
                (o.vo, o.t_cw, o.source)
            }
            _ => unreachable!(),
        };
        if vo_out.new_session {
            r.new_sessions += 1;
            session_start = k;
        }
        for (t, p) in &vo_out.backfill {
            if let Some(&j) = index.get(t) {
                if j >= session_start {
                    r.poses[j] = Some(*p);
                }
            }
        }
        r.poses[k] = t_cw;
        r.sources[k] = source;
    }
    r.status = vio.as_ref().map(|v| v.status());
    r.mapping = vio
        .map(|v| v.vo().local_mapping_stats())
        .unwrap_or_default();
    r.cpu_ms = cpu_ms() - cpu0;
    r
}

/// Alignment of the run's camera centres (frames `range` only) to the truth; returns
/// (RMSE over the aligned frames, alignment scale, residual per frame).
fn align(world: &SimWorld, r: &Run, with_scale: bool) -> (f64, f64, Vec<Option<f64>>) {
    let mut src = Vec::new();
    let mut dst = Vec::new();
    for (t, p) in r.times.iter().zip(&r.poses) {
        if let Some(p) = p {
            src.push(p.inverse().translation.vector);
            dst.push(world.pose_cam_at(*t).translation.vector);
        }
    }
    let sim = umeyama(&src, &dst, with_scale).expect("alignment");
    let res: Vec<Option<f64>> = r
        .times
        .iter()
        .zip(&r.poses)
        .map(|(t, p)| {
            p.map(|p| {
                let c = sim.rotation * p.inverse().translation.vector * sim.scale + sim.translation;
                (c - world.pose_cam_at(*t).translation.vector).norm()
            })
        })
        .collect();
    (rms(res.iter().flatten().copied()), sim.scale, res)
}

fn rms(v: impl Iterator<Item = f64>) -> f64 {
    let (mut s, mut n) = (0.0, 0usize);
    for x in v {
        s += x * x;
        n += 1;
    }
    if n == 0 {
        return f64::NAN;
    }
    (s / n as f64).sqrt()
}

/// Figures of one run, printed.
struct Figures {
    ate_se3_percent: f64,
    scale_error_percent: f64,
    posed_percent: f64,
    /// Frames tracked with the IMU ([`PoseSource::VisualInertial`]) among those after the
    /// inertial initialisation, %.
    vi_after_init_percent: f64,
}

fn figures(name: &str, world: &SimWorld, r: &Run, mode: Mode) -> Figures {
    let path = world.path_length_m();
    let posed = r.poses.iter().flatten().count();
    let (ate, _, _) = align(world, r, false);
    let (ate_sim3, scale, _) = align(world, r, true);
    let vi = r
        .sources
        .iter()
        .filter(|s| **s == PoseSource::VisualInertial)
        .count();
    let t_init = r.init_s.map(|s| r.times[0] + (s * 1e9) as i64);
    let after: Vec<_> = r
        .times
        .iter()
        .zip(&r.sources)
        .filter(|(t, _)| t_init.is_some_and(|t0| **t > t0))
        .collect();
    let vi_after = after
        .iter()
        .filter(|(_, s)| **s == PoseSource::VisualInertial)
        .count();
    let f = Figures {
        vi_after_init_percent: vi_after as f64 * 100.0 / after.len().max(1) as f64,
        ate_se3_percent: ate / path * 100.0,
        scale_error_percent: (1.0 / scale - 1.0) * 100.0,
        posed_percent: posed as f64 * 100.0 / r.poses.len() as f64,
    };
    eprintln!(
        "{name} {mode:?}: path {path:.1} m, {} frames, posed {:.1}% ({vi} visual-inertial, {:.1}% of those after the initialisation; {} orientation only), \
         ATE SE(3) {:.4} m = {:.3}%, Sim(3) {:.4} m, scale error {:+.2}%, init at {:?} s, sessions +{}, status {:?}",
        r.poses.len(),
        f.posed_percent,
        f.vi_after_init_percent,
        r.orientations,
        ate,
        f.ate_se3_percent,
        ate_sim3,
        f.scale_error_percent,
        r.init_s,
        r.new_sessions,
        r.status
    );
    f
}

/// Drone (20 s, aggressive 6-DoF, global shutter): VIO with and without the prior, and the
/// monocular VO.
#[test]
fn drone_vio_is_metric_and_accurate() {
    let world = world(Scenario::Drone, 20.0);
    let vio = run(&world, VIO);
    let f = figures("drone", &world, &vio, VIO);
    let no_prior = Mode::Vio {
        prior: false,
        window: true,
    };
    figures("drone", &world, &run(&world, no_prior), no_prior);
    let mono = run(&world, Mode::Mono);
    figures("drone", &world, &mono, Mode::Mono);
    assert_eq!(vio.new_sessions, 0);
    assert!(vio.init_s.is_some_and(|s| s < 4.0), "init {:?}", vio.init_s);
    assert!(f.posed_percent >= 98.0);
    assert!(f.scale_error_percent.abs() < 2.0);
    assert!(f.ate_se3_percent < 0.3, "ATE {:.3}%", f.ate_se3_percent);
    // Tracking with the IMU (issue 17): every frame after the initialisation but a few.
    assert!(f.vi_after_init_percent >= 95.0);
}

/// An anchor to the server map (issue 19: a rigid move of the client's world by yaw and
/// translation, `slam_core::vio::anchor`) applied mid-run moves everything after it by
/// that move and nothing else: the same frames posed, each pose the un-anchored run's moved
/// by it, the biases unchanged. The local window does not jump: the poses tracked after
/// the next world move (the session window 5 s after the initialisation) agree to rounding
/// (measured 0.4 mm, 3e-4°); the frames between the anchor and that move are re-expressed
/// by the move, whose scale (a flat valley, solved to the solver's tolerance from a moved
/// start) differs by 4e-5 between the runs: 8.8 mm, 0.03° there.
#[test]
fn an_anchor_moves_the_client_world_without_a_jump() {
    let world = world(Scenario::Phone, 8.0);
    let plain = run(&world, VIO);
    assert!(
        plain.init_s.is_some_and(|s| s < 4.0),
        "init {:?}",
        plain.init_s
    );
    let k0 = world.n_frames() * 2 / 3;
    let delta = Isometry3::new(Vector3::new(3.0, -2.0, 0.5), Vector3::new(0.0, 0.0, 0.6));
    let moved = run_anchored(&world, VIO, Some((k0, delta)));
    let m = slam_core::lie::Sim3::from_isometry(&delta, 1.0);
    let next_move = moved.moves_at.iter().copied().find(|&k| k > k0);
    let (mut exact, mut after) = ((0.0f64, 0.0f64), (0.0f64, 0.0f64));
    for k in 0..world.n_frames() {
        assert_eq!(plain.sources[k], moved.sources[k], "frame {k}");
        let (Some(a), Some(b)) = (plain.poses[k], moved.poses[k]) else {
            assert_eq!(
                plain.poses[k].is_some(),
                moved.poses[k].is_some(),
                "frame {k}"
            );
            continue;
        };
        let want = if k >= k0 {
            transform_pose_cw(&a, &m)
        } else {
            a
        };
        let (c_want, c_got) = (want.inverse().translation, b.inverse().translation);
        let d = (
            (c_want.vector - c_got.vector).norm(),
            want.rotation.angle_to(&b.rotation).to_degrees(),
        );
        let worst = if next_move.is_some_and(|n| k >= n) {
            &mut after
        } else {
            &mut exact
        };
        *worst = (worst.0.max(d.0), worst.1.max(d.1));
    }
    let bias = |r: &Run| r.biases.expect("biases").1;
    let (ba, bb) = (bias(&plain), bias(&moved));
    let d_bias = (ba.gyro - bb.gyro).norm() + (ba.accel - bb.accel).norm();
    println!(
        "anchor at frame {k0}: poses off the moved un-anchored run by {:.2e} m, {:.2e}° \
         until the next world move (frame {next_move:?}, re-expressed by it), {:.2e} m, \
         {:.2e}° from it on; \
         final biases by {d_bias:.2e}",
        exact.0, exact.1, after.0, after.1
    );
    assert!(exact.0 < 0.02 && exact.1 < 0.1, "{exact:?}");
    assert!(after.0 < 2e-3 && after.1 < 0.01, "{after:?}");
    assert!(d_bias < 1e-3, "{d_bias}");
}

/// `two-agents` (24 s each, the gentle ellipses without the hand-held bounce, seed 3 as the
/// rendered data of the pipeline runs): the initialisations come late (15.6 s, 11.6 s) and
/// are accepted 4.8 % and 7.5 % off in scale (1σ 4.8 %); local mapping's whole-session
/// windows (at the first window and 5 s after the initialisation) bring them within
/// 0.83 % and 1.63 % (SE(3) ATE 0.99 % → 0.17 %, 1.53 % → 0.34 % of the path).
#[test]
fn two_agents_gentle_paths_get_their_scale() {
    let mut p = SimParams::new(Scenario::TwoAgents);
    p.seed = 3;
    p.frames = Some((24.0 * p.rate_hz) as usize);
    let scene = std::sync::Arc::new(datasets::sim::Scene::room(p.seed));
    for agent in 0..2 {
        let world = SimWorld::with_scene(p.clone(), agent, scene.clone()).expect("sim world");
        let vio = run(&world, VIO);
        let f = figures(&format!("two-agents {agent}"), &world, &vio, VIO);
        assert_eq!(vio.new_sessions, 0);
        assert!(
            vio.init_s.is_some_and(|s| s > 10.0),
            "init {:?}",
            vio.init_s
        );
        assert!(
            f.scale_error_percent.abs() < 2.0,
            "{agent}: scale {:.2}%",
            f.scale_error_percent
        );
        assert!(
            f.ate_se3_percent < 0.4,
            "{agent}: ATE {:.3}%",
            f.ate_se3_percent
        );
    }
}

/// Phone (10 s hand-held walking, 30 Hz, 25 ms rolling shutter, phone IMU): the issue's
/// targets, ATE ≤ 0.2 % of the path and scale within 1 %, initialised within 3 s
/// (measured: 0.081 %, −0.15 %, 2.5 s).
#[test]
fn phone_vio_is_metric() {
    let world = world(Scenario::Phone, 10.0);
    let vio = run(&world, VIO);
    let f = figures("phone", &world, &vio, VIO);
    let mono = run(&world, Mode::Mono);
    figures("phone", &world, &mono, Mode::Mono);
    assert_eq!(vio.new_sessions, 0);
    assert!(
        vio.init_s.is_some_and(|s| s <= 3.0),
        "init {:?}",
        vio.init_s
    );
    assert!(f.posed_percent >= 98.0);
    assert!(
        f.scale_error_percent.abs() < 1.0,
        "scale {:.2}%",
        f.scale_error_percent
    );
    assert!(f.ate_se3_percent < 0.2, "ATE {:.3}%", f.ate_se3_percent);
}

/// The first 0.8 s of the phone (as the real clip): never initialised, every frame gets a
/// pose or an orientation, and the status says why.
#[test]
fn a_short_phone_clip_gets_orientations_and_no_scale() {
    let world = world(Scenario::Phone, 0.8);
    let vio = run(&world, VIO);
    figures("phone 0.8 s", &world, &vio, VIO);
    assert!(vio.init_s.is_none());
    assert!(!matches!(vio.status, Some(VioStatus::Initialised { .. })));
    assert!(vio.sources.iter().all(|s| *s != PoseSource::None));
    assert!(vio
        .sources
        .iter()
        .all(|s| !matches!(s, PoseSource::VisualInertial | PoseSource::Inertial)));
}

/// The navigator from the true state: its prediction over one frame (50 ms) and over a 2 s
/// dropout against the sim's exact motion (drone IMU noise, true biases).
#[test]
fn navigator_predicts_the_true_motion() {
    let world = world(Scenario::Drone, 6.0);
    let gt = world.ground_truth_states();
    let imu: Vec<ImuMeasurement> = (0..world.imu_samples().len())
        .map(|k| imu_at(&world, k))
        .collect();
    let params = vio_params(&world, true);
    let t_bc = world.calib().t_bs;
    let mut worst = [(0.0f64, 0.0f64); 2];
    for (i, steps) in [10usize, 400].into_iter().enumerate() {
        for start in (100..gt.len() - steps - 10).step_by(97) {
            let (a, b) = (&gt[start], &gt[start + steps]);
            let nav = Navigator::new(
                a.nav_state(a.biases),
                a.t_ns,
                t_bc,
                params.preint,
                NavParams::default(),
            );
            let pred = nav
                .predict(&imu, b.t_ns, &Vector3::zeros())
                .expect("covered");
            let truth_cw = world.pose_cam_at(b.t_ns).inverse();
            let dp = (pred.t_cw.inverse().translation.vector
                - truth_cw.inverse().translation.vector)
                .norm();
            let dr = pred.t_cw.rotation.angle_to(&truth_cw.rotation).to_degrees();
            worst[i].0 = worst[i].0.max(dp);
            worst[i].1 = worst[i].1.max(dr);
            let dv = (pred.nav.v - b.v_w).norm();
            assert!(dv < 0.05 * (steps as f64 / 10.0), "velocity error {dv}");
        }
    }
    eprintln!(
        "navigator: worst over 50 ms {:.2e} m {:.2e}°, over 2 s {:.3} m {:.3}°",
        worst[0].0, worst[0].1, worst[1].0, worst[1].1
    );
    assert!(worst[0].0 < 1e-3 && worst[0].1 < 0.01);
    assert!(worst[1].0 < 0.05 && worst[1].1 < 0.1);
}

/// A debugging run (`SECS`, `SCENARIO` = drone (default), loop, fast-rs, blackout or phone,
/// `PRIOR`, `NO_WINDOW`, `REFINE` = `VioParams::refinements_with_window`, `VW_N` and
/// `VW_COV` = the window's free and fixed covisible keyframes, `ACC_PRIOR` and `POSE_SIGMA`
/// = the initialisation's accelerometer-bias prior and keyframe position σ,
/// `SHOAL_VIO_IMU_TRACKING`, `VERBOSE` for the world moves and refusals): per-frame residuals.
#[test]
#[ignore = "debugging aid"]
fn debug_drone() {
    let secs: f64 = std::env::var("SECS").map_or(8.0, |s| s.parse().expect("SECS"));
    let scenario = match std::env::var("SCENARIO").as_deref() {
        Ok("loop") => Scenario::Loop,
        Ok("fast-rs") => Scenario::FastRs,
        Ok("blackout") => Scenario::Blackout,
        Ok("phone") => Scenario::Phone,
        _ => Scenario::Drone,
    };
    let world = world(scenario, secs);
    let mode = Mode::Vio {
        prior: std::env::var("PRIOR").is_ok(),
        window: std::env::var("NO_WINDOW").is_err(),
    };
    let vio = run(&world, mode);
    figures("debug", &world, &vio, mode);
    let (_, _, res) = align(&world, &vio, false);
    {
        let (mut src, mut dst) = (Vec::new(), Vec::new());
        for k in 100..215.min(vio.times.len()) {
            if let Some(p) = vio.vision[k].0 {
                src.push(p.inverse().translation.vector);
                dst.push(world.pose_cam_at(vio.times[k]).translation.vector);
            }
        }
        let sim = umeyama(&src, &dst, false).expect("al");
        let abs = |p: Isometry3<f64>| {
            let c = sim.rotation * p.inverse().translation.vector + sim.translation;
            (c - world.pose_cam_at(0).translation.vector, c)
        };
        for k in 215..245.min(vio.times.len()) {
            let g = world.pose_cam_at(vio.times[k]).translation.vector;
            let v = vio.vision[k].0.map(|p| (abs(p).1 - g).norm() * 100.0);
            let pr = vio.vision[k].1.map(|p| (abs(p).1 - g).norm() * 100.0);
            eprintln!("ABS {k} vision {v:.2?} cm pred {pr:.2?} cm");
        }
    }
    for k in 1..vio.times.len() {
        let (Some(a), (Some(b), pred)) = (vio.vision[k - 1].0, vio.vision[k]) else {
            continue;
        };
        let ta = world.pose_cam_at(vio.times[k - 1]).inverse();
        let tb = world.pose_cam_at(vio.times[k]).inverse();
        let d_true = tb * ta.inverse();
        let err = |d: Isometry3<f64>| {
            let e = d * d_true.inverse();
            (
                e.translation.vector.norm() * 100.0,
                e.rotation.angle().to_degrees(),
            )
        };
        let vis = err(b * a.inverse());
        let pr = pred.map(|p| err(p * a.inverse()));
        eprintln!(
            "REL {k} t {:.3} vision {:.2} cm {:.3} deg pred {:?}",
            vio.times[k] as f64 * 1e-9,
            vis.0,
            vis.1,
            pr.map(|(c, d)| format!("{c:.2} cm {d:.3} deg"))
        );
    }
    for k in (0..vio.times.len()).step_by(10) {
        let c = vio.poses[k].map(|p| p.inverse().translation.vector);
        let g = world.pose_cam_at(vio.times[k]).translation.vector;
        let gt = world.ground_truth_states();
        let i = gt
            .partition_point(|s| s.t_ns < vio.times[k])
            .min(gt.len() - 1);
        eprintln!(
            "{k} t {:.3} {:?} est {:?} truth {:.3?} res {:?} v_true {:.3?} bg_true {:.4?} ba_true {:.3?}",
            vio.times[k] as f64 * 1e-9,
            vio.sources[k],
            c.map(|c| format!("{:.3?}", c.as_slice())),
            g.as_slice(),
            res[k],
            gt[i].v_w.as_slice(),
            gt[i].biases.gyro.as_slice(),
            gt[i].biases.accel.as_slice(),
        );
    }
}

/// `blackout` (the loop carried by hand, with 2 s of blank frames in the middle of 24 s): no
/// new VO session,
/// the frames of the gap posed by the IMU, and the error after the gap at most twice the
/// error before it (one SE(3) alignment over all frames).
#[test]
fn blackout_is_bridged_on_the_imu() {
    let world = world(Scenario::Blackout, 24.0);
    let gap = Scenario::Blackout.blank_frames(world.n_frames(), world.params().rate_hz);
    let vio = run(&world, VIO);
    let f = figures("blackout", &world, &vio, VIO);
    let (_, _, res) = align(&world, &vio, false);
    let before = rms(res[..gap.start].iter().flatten().copied());
    let after = rms(res[gap.end..].iter().flatten().copied());
    let inertial = vio.sources[gap.clone()]
        .iter()
        .filter(|s| **s == PoseSource::Inertial)
        .count();
    eprintln!(
        "blackout frames {gap:?}: {inertial} posed by the IMU, ATE before {before:.4} m, after {after:.4} m, \
         sessions +{}",
        vio.new_sessions
    );
    assert_eq!(vio.new_sessions, 0, "a new VO session started");
    assert!(
        inertial == gap.len(),
        "{inertial} of {} gap frames posed by the IMU",
        gap.len()
    );
    assert!(after <= 2.0 * before, "after {after} > 2 × before {before}");
    // The targets (measured: 0.105 %, scale −0.04 %).
    assert!(f.ate_se3_percent < 0.2, "ATE {:.3}%", f.ate_se3_percent);
    assert!(
        f.scale_error_percent.abs() < 1.0,
        "scale {:.2}%",
        f.scale_error_percent
    );
}

/// RMS tilt (roll/pitch) error of the posed frames, °: the angle between the estimated and
/// the true gravity direction in the camera (both worlds are z up).
fn tilt_rms_deg(world: &SimWorld, r: &Run) -> f64 {
    let z = Vector3::z();
    rms(r.times.iter().zip(&r.poses).filter_map(|(t, p)| {
        let est = p.as_ref()?.rotation * z;
        let truth = world.pose_cam_at(*t).rotation.inverse() * z;
        Some(est.angle(&truth).to_degrees())
    }))
}

/// The last frame's (gyro, accel) bias errors against the truth (effective biases).
fn bias_errors(world: &SimWorld, r: &Run) -> (f64, f64) {
    let (t, b) = r.biases.expect("biases");
    let gt = world.ground_truth_states();
    let i = gt.partition_point(|s| s.t_ns <= t).saturating_sub(1);
    let truth = vio_params(world, true)
        .preint
        .correction
        .effective_biases(&gt[i].biases);
    ((b.gyro - truth.gyro).norm(), (b.accel - truth.accel).norm())
}

/// Local mapping's visual-inertial window against the same client without it (the visual
/// local BA only), on the drone (20 s, global shutter) and the phone (10 s, 25 ms rolling
/// shutter, phone IMU): the window runs on every keyframe after the initialisation, never
/// fails, keeps or improves the trajectory (SE(3) ATE) and keeps the tilt within 0.15°,
/// and the biases it tracks end near the truth, which the client without it (biases from
/// the initialisation and its refinements only) does not reach. Thresholds: the measured
/// figures with margin (printed with `--nocapture`; drone: 0.058% vs 0.076%, tilt 0.090°
/// vs 0.077°, biases 2.0e-4 rad/s and 0.010 m/s² vs 1.1e-4 and 0.019; phone: 0.081% vs
/// 0.616%, 0.083° vs 0.318°, 3.5e-4 and 0.006 vs 1.1e-3 and 0.021).
#[test]
fn vi_window_refines_the_trajectory_and_tracks_the_biases() {
    let without = Mode::Vio {
        prior: true,
        window: false,
    };
    // (scenario, seconds, largest gyro bias error rad/s, accel bias error m/s²).
    for (scenario, secs, max_bg, max_ba) in [
        (Scenario::Drone, 20.0, 3e-4, 0.015),
        (Scenario::Phone, 10.0, 6e-4, 0.015),
    ] {
        let world = world(scenario, secs);
        let name = format!("{scenario:?}");
        let (a, b) = (run(&world, VIO), run(&world, without));
        let (fa, fb) = (
            figures(&name, &world, &a, VIO),
            figures(&name, &world, &b, without),
        );
        let (ta, tb) = (tilt_rms_deg(&world, &a), tilt_rms_deg(&world, &b));
        let (ea, eb) = (bias_errors(&world, &a), bias_errors(&world, &b));
        let m = a.mapping;
        eprintln!(
            "{name}: window ATE SE(3) {:.3}% tilt {ta:.3}° bias errors {:.2e} rad/s {:.4} m/s²; \
             without {:.3}% {tb:.3}° {:.2e} rad/s {:.4} m/s²",
            fa.ate_se3_percent, ea.0, ea.1, fb.ate_se3_percent, eb.0, eb.1
        );
        eprintln!(
            "  {} windows ({} skipped, {} failed) on {} keyframes mapped; wall mean {:.1} ms, \
             max {:.1} ms; CPU of the run {:.0} ms with, {:.0} ms without ({:.1} ms more per \
             window)",
            m.vi_windows,
            m.vi_skipped,
            m.vi_failed,
            m.steps,
            m.vi_ms_total / m.vi_windows.max(1) as f64,
            m.vi_ms_max,
            a.cpu_ms,
            b.cpu_ms,
            (a.cpu_ms - b.cpu_ms) / m.vi_windows.max(1) as f64
        );
        assert_eq!(a.new_sessions, 0, "{name}");
        assert!(m.vi_windows * 10 >= m.steps * 6, "{name}: {m:?}");
        assert_eq!((m.vi_failed, b.mapping.vi_windows), (0, 0), "{name}");
        assert!(
            fa.ate_se3_percent <= 1.1 * fb.ate_se3_percent,
            "{name}: ATE"
        );
        assert!(ta < 0.15, "{name}: tilt {ta}° (without the window {tb}°)");
        assert!(ea.0 < max_bg && ea.1 < max_ba, "{name}: biases {ea:?}");
        assert!(
            eb.0 > max_bg || eb.1 > max_ba,
            "{name}: without, biases {eb:?}"
        );
    }
}
