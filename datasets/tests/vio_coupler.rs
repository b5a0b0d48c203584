//! The inertial initialisation on real monocular VO keyframes (issue 17): the client VO runs
//! on the rendered `drone` scenario (global shutter, 20 Hz, its noisy 200 Hz IMU with biases
//! as `shoal sim` writes it), its keyframe poses (moved by local BA as they are) and the IMU
//! feed `slam_core::imu::coupler`, which initialises when the motion allows and refines at
//! 5 s and 15 s. Checked against the truth: the metric scale against the Sim(3) alignment of
//! the VO's keyframes to the ground truth, the gravity direction against the aligned world's,
//! and how soon after the first keyframe it initialised.
use datasets::sim::{Scenario, SimParams, SimWorld};
use nalgebra::{Isometry3, Vector3};
use slam_core::geometry::umeyama;
use slam_core::imu::coupler::{CouplerEvent, CouplerParams, CouplerStatus, InertialCoupler};
use slam_core::imu::init::InertialInit;
use slam_core::imu::{ImuMeasurement, PreintegrationParams};
use slam_core::vo::{VoFrame, VoParams, VoTracker};

/// One success of the coupler and the truth at that moment.
struct Found {
    /// Span of the keyframes used, s.
    span_s: f64,
    init: InertialInit,
    /// Scale of the Sim(3) alignment VO → truth over the keyframes known then.
    true_scale: f64,
    /// Gravity in the VO's world from that alignment.
    true_gravity_w: Vector3<f64>,
}

impl Found {
    fn scale_error_percent(&self) -> f64 {
        (self.init.scale / self.true_scale - 1.0) * 100.0
    }

    fn gravity_error_deg(&self) -> f64 {
        self.init.gravity_w.angle(&self.true_gravity_w).to_degrees()
    }
}

fn world(seconds: f64) -> SimWorld {
    let mut p = SimParams::new(Scenario::Drone);
    p.seed = 3;
    p.frames = Some((seconds * p.rate_hz) as usize);
    SimWorld::new(p).expect("sim world")
}

/// The Sim(3) alignment of the keyframes `(t_ns, T_wc)` (IMU clock) to the truth: (scale, gravity
/// in the VO's world).
fn truth(world: &SimWorld, kfs: &[(i64, Isometry3<f64>)]) -> (f64, Vector3<f64>) {
    let src: Vec<Vector3<f64>> = kfs.iter().map(|k| k.1.translation.vector).collect();
    let dst: Vec<Vector3<f64>> = kfs
        .iter()
        .map(|k| world.pose_cam_at(k.0).translation.vector)
        .collect();
    let sim = umeyama(&src, &dst, true).expect("alignment");
    let g_w = sim.rotation.inverse() * Vector3::new(0.0, 0.0, -9.81);
    (sim.scale, g_w)
}

/// Runs the VO over `world` with the coupler beside it (the VO's world is not transformed:
/// every success is a similarity from the same monocular frame).
fn run(world: &SimWorld) -> (Vec<Found>, Vec<String>) {
    let cam = world.calib().model;
    let mut vo = VoTracker::new(VoParams::default(), cam).expect("vo");
    let sensor = world.params();
    let preint = PreintegrationParams::new(&sensor.noise, &sensor.imu_intrinsics).expect("preint");
    // As the tracker: frames on the IMU clock (the ingest applies t_d to the stamps), the
    // gyro's mean rate over each frame's readout for the rolling shutter.
    let params = CouplerParams::default();
    let r_cb = world.calib().t_bs.rotation.inverse();
    let gyro: Vec<(i64, Vector3<f64>)> = world
        .imu_samples()
        .iter()
        .map(|s| (s.t_ns, Vector3::from(s.gyro)))
        .collect();
    let mut coupler = InertialCoupler::new(params, preint, world.calib().t_bs);
    let imu = world.imu_samples();
    let mut next_imu = 0;
    let (mut found, mut refusals) = (Vec::new(), Vec::new());
    let mut img = vec![0u8; (cam.width * cam.height) as usize];
    for k in 0..world.n_frames() {
        let t_ns = world.frame_capture_time_ns(k);
        let half = world.readout_ns() / 2;
        let angular_velocity = (half > 0)
            .then(|| slam_core::imu::mean_rate(&gyro, t_ns - half, t_ns + half))
            .flatten()
            .map(|w_b| r_cb * w_b);
        // The IMU up to a little after the frame (the tracker has it by then).
        while next_imu < imu.len() && imu[next_imu].t_ns <= t_ns + 50_000_000 {
            let s = imu[next_imu];
            coupler.on_imu(ImuMeasurement {
                t_ns: s.t_ns,
                gyro: Vector3::from(s.gyro),
                accel: Vector3::from(s.accel),
            });
            next_imu += 1;
        }
        let frame = VoFrame {
            t_ns,
            angular_velocity,
            ..world.vo_frame(k, &mut img).expect("render")
        };
        let o = vo.process(&frame).expect("vo step");
        assert!(
            !o.new_session || found.is_empty(),
            "the VO lost its map at frame {k}"
        );
        if o.keyframe.is_none() {
            continue;
        }
        let window: Vec<(i64, Isometry3<f64>)> = vo.with_map(|m| {
            m.keyframes
                .values()
                .map(|kf| (kf.t_ns, kf.t_cw.inverse()))
                .collect()
        });
        for (t, t_wc) in &window {
            coupler.set_keyframe(*t, *t_wc);
        }
        let event = coupler.step();
        if let CouplerStatus::Refused(e) = coupler.status() {
            refusals.push(format!("{:.2} s: {e}", coupler.span_s()));
        }
        let init = match event {
            Some(CouplerEvent::Initialised(i) | CouplerEvent::Refined(i)) => i,
            None => continue,
        };
        let (true_scale, true_gravity_w) = truth(world, &window);
        found.push(Found {
            span_s: coupler.span_s(),
            init,
            true_scale,
            true_gravity_w,
        });
    }
    (found, refusals)
}

/// The drone's first 16 s: initialised within 3 s of keyframes, scale within 5% and gravity
/// within 2° at once, refined twice, the refinements within 2% and 1°.
#[test]
fn the_drone_initialises_from_vo_keyframes_and_refines() {
    let world = world(16.5);
    let (found, refusals) = run(&world);
    for r in refusals.iter().take(8) {
        eprintln!("refused at {r}");
    }
    for f in &found {
        eprintln!(
            "span {:.2} s: scale {:.4} (truth {:.4}, {:+.2}%, 1σ {:.2}%), gravity error {:.3}° (1σ {:.3}°), \
             b_g {:.4?}, b_a {:.3?}",
            f.span_s,
            f.init.scale,
            f.true_scale,
            f.scale_error_percent(),
            f.init.scale_sigma * 100.0,
            f.gravity_error_deg(),
            f.init.gravity_sigma.to_degrees(),
            f.init.biases.gyro.as_slice(),
            f.init.biases.accel.as_slice(),
        );
    }
    check(&found, 3, 5.0, 2.0);
}

/// Checks the first success (within 3 s of keyframes, scale within `first_scale_percent`,
/// gravity within 2°), the number of successes and the refinements' bounds
/// (`refined_scale_percent`, 1°).
fn check(found: &[Found], n: usize, first_scale_percent: f64, refined_scale_percent: f64) {
    let first = found.first().expect("initialised");
    assert!(
        first.span_s <= 3.0,
        "initialised only after {:.2} s",
        first.span_s
    );
    assert!(first.scale_error_percent().abs() < first_scale_percent);
    assert!(first.gravity_error_deg() < 2.0);
    assert_eq!(found.len(), n, "initialised and refined {} times", n - 1);
    for f in &found[1..] {
        assert!(f.scale_error_percent().abs() < refined_scale_percent);
        assert!(f.gravity_error_deg() < 1.0);
    }
}

/// The VO's camera centres per frame, with the world moved by `x' = s R x + t` after frame
/// `at` (centres after it mapped back to the original world).
fn centres_with_world_move(
    world: &SimWorld,
    at: Option<usize>,
    m: &slam_core::lie::Sim3,
) -> Vec<Option<Vector3<f64>>> {
    let cam = world.calib().model;
    let mut vo = VoTracker::new(VoParams::default(), cam).expect("vo");
    let mut img = vec![0u8; (cam.width * cam.height) as usize];
    let mut out = Vec::new();
    for k in 0..world.n_frames() {
        let frame = world.vo_frame(k, &mut img).expect("render");
        let o = vo.process(&frame).expect("vo step");
        let moved = at.is_some_and(|a| k > a);
        out.push(o.t_cw.map(|t_cw| {
            let c = t_cw.inverse().translation.vector;
            if moved {
                m.inverse().transform_point(&c)
            } else {
                c
            }
        }));
        if Some(k) == at {
            assert!(vo.transform_world(m, std::time::Duration::from_secs(5)));
        }
    }
    out
}

/// Moving the VO's world mid-run (as the tracker does with an inertial initialisation's
/// scale and gravity rotation, or an anchor's translation) keeps it tracking, and the frames after the move are the
/// same poses in the new frame: mapped back, they match a run without the move to well
/// under a millimetre of the original (unit-less) map's 1-metre-ish scale, 0.1% of the
/// path.
#[test]
fn moving_the_vo_world_mid_run_keeps_the_same_trajectory() {
    let world = world(8.0);
    let r = nalgebra::UnitQuaternion::from_scaled_axis(Vector3::new(0.3, -0.2, 1.1));
    let m = slam_core::lie::Sim3::new(r, Vector3::new(4.0, -1.0, 2.5), 2.5);
    let plain = centres_with_world_move(&world, None, &slam_core::lie::Sim3::identity());
    let moved = centres_with_world_move(&world, Some(80), &m);
    let path: f64 = plain
        .iter()
        .flatten()
        .collect::<Vec<_>>()
        .windows(2)
        .map(|w| (w[1] - w[0]).norm())
        .sum();
    let (mut n, mut worst) = (0, 0.0f64);
    for (a, b) in plain.iter().zip(&moved).skip(81) {
        if let (Some(a), Some(b)) = (a, b) {
            n += 1;
            worst = worst.max((a - b).norm());
        }
    }
    let posed_plain = plain.iter().flatten().count();
    let posed_moved = moved.iter().flatten().count();
    eprintln!(
        "world moved at frame 80 (s 2.5): {n} frames compared after it, largest centre \
         difference {worst:.2e} (path {path:.3}); posed {posed_moved} vs {posed_plain} frames"
    );
    assert!(
        n >= 70,
        "the VO stopped tracking after the move: {n} frames"
    );
    assert!(posed_moved + 2 >= posed_plain);
    assert!(
        worst < 1e-3 * path,
        "moved run differs by {worst} (path {path})"
    );
}

/// The hand-held `phone` (walking bounce and sway, 30 Hz with a 25 ms rolling shutter, t_d
/// 40 ms applied to the frame times as the ingest does, the gyro's rate de-rotating the rows
/// as the tracker does, a phone IMU with biases and T_g/T_s/T_a given to the preintegration
/// as its `sensor.yaml` states them). Measured (seed 3): initialised at 2.50 s of keyframes
/// with scale -7.8% (stated 1σ 2.8%), gravity 0.64°; refined at 5.1 s to -3.6% (1σ 1.0%),
/// 0.23°. The same run with a global shutter gives -0.7% and +0.2%, and without the gyro's
/// rate (the VO's motion model de-rotating) -53%: the rows' translation during the readout,
/// which the VO does not model, is the likely rest. Bounds: within 3 s, 10% and 2° at
/// first, 5% and 1° after the refinement.
#[test]
fn the_phone_initialises_from_rolling_shutter_vo_keyframes() {
    let mut p = SimParams::new(Scenario::Phone);
    p.seed = 3;
    p.frames = Some(180);
    let world = SimWorld::new(p).expect("sim world");
    let (found, refusals) = run(&world);
    for r in refusals.iter().take(8) {
        eprintln!("phone refused at {r}");
    }
    for f in &found {
        eprintln!(
            "phone span {:.2} s: scale {:+.2}% (1σ {:.2}%), gravity error {:.3}° (1σ {:.3}°)",
            f.span_s,
            f.scale_error_percent(),
            f.init.scale_sigma * 100.0,
            f.gravity_error_deg(),
            f.init.gravity_sigma.to_degrees(),
        );
    }
    check(&found, 2, 10.0, 5.0);
}
