//! Inertial initialisation (`slam_core::imu::init`) on the synthetic world's exact motion: the
//! camera poses of the first seconds, as a monocular map would hold them (an arbitrary world
//! frame and scale), and the world's IMU with biases. Scale, gravity direction, velocities
//! and biases against the truth; with IMU noise and noisy poses; refused on a motion
//! without acceleration.
use datasets::sim::{Scenario, SimParams, SimWorld};
use nalgebra::{Isometry3, Rotation3, Translation3, UnitQuaternion, Vector3};
use slam_core::imu::init::{initialize, InertialInit, InitError, InitParams};
use slam_core::imu::{ImuBiases, ImuNoise, Preintegrated, PreintegrationParams};

/// The monocular map's frame: `p_v = (R_vw p_w + t_vw) / S_TRUE`.
const S_TRUE: f64 = 2.5;

fn r_vw() -> Rotation3<f64> {
    Rotation3::from_scaled_axis(Vector3::new(0.3, -0.5, 1.0))
}

fn t_vw() -> Vector3<f64> {
    Vector3::new(1.0, -2.0, 0.5)
}

fn true_biases() -> ImuBiases {
    ImuBiases {
        gyro: Vector3::new(0.004, -0.006, 0.003),
        accel: Vector3::new(0.05, -0.03, 0.04),
    }
}

/// What a run gave and the truth to compare with.
struct Case {
    world: SimWorld,
    kf_ns: Vec<i64>,
}

impl Case {
    /// The `scenario` world with IMU noise `noise`, keyframes every `step_s` over `span_s`.
    fn new(scenario: Scenario, noise: ImuNoise, span_s: f64, step_s: f64) -> Self {
        let mut p = SimParams::new(scenario);
        p.seed = 5;
        p.frames = Some(((span_s + 1.0) * 20.0) as usize);
        p.noise = noise;
        p.initial_biases = true_biases();
        let world = SimWorld::new(p).expect("world");
        let t0 = world.frame_time_ns(2);
        let n = (span_s / step_s).round() as i64;
        let kf_ns = (0..=n)
            .map(|k| t0 + (k as f64 * step_s * 1e9) as i64)
            .collect();
        Self { world, kf_ns }
    }

    /// Keyframe poses in the monocular map's frame, each perturbed by `pose_noise` (m, rad
    /// in the true scale) with a fixed pseudo-random pattern.
    fn vo_poses(&self, pose_noise: (f64, f64)) -> Vec<Isometry3<f64>> {
        let rv = r_vw();
        self.kf_ns
            .iter()
            .enumerate()
            .map(|(k, &t)| {
                let t_wc = self.world.pose_cam_at(t);
                let w = |i: usize| ((k * 7 + i * 3) as f64 * 1.7).sin();
                let dp = Vector3::new(w(0), w(1), w(2)) * pose_noise.0;
                let dr = Rotation3::from_scaled_axis(Vector3::new(w(3), w(4), w(5)) * pose_noise.1);
                let p = (rv * (t_wc.translation.vector + dp) + t_vw()) / S_TRUE;
                let r = rv * t_wc.rotation.to_rotation_matrix() * dr;
                Isometry3::from_parts(
                    Translation3::from(p),
                    UnitQuaternion::from_rotation_matrix(&r),
                )
            })
            .collect()
    }

    fn preints(&self, noise: &ImuNoise) -> Vec<Preintegrated> {
        let params = PreintegrationParams::new(noise, &Default::default()).expect("params");
        self.kf_ns
            .windows(2)
            .map(|w| {
                Preintegrated::from_window(
                    self.world.imu_samples(),
                    w[0],
                    w[1],
                    ImuBiases::default(),
                    params,
                )
                .expect("IMU brackets the keyframes")
            })
            .collect()
    }

    /// Initialises from the keyframes with `pose_noise` (m, rad) on their poses, telling the
    /// initialiser that noise (the defaults when there is none).
    fn run(&self, noise: &ImuNoise, pose_noise: (f64, f64)) -> Result<InertialInit, InitError> {
        let t_bc = self.world.calib().t_bs;
        let mut params = InitParams::default();
        if pose_noise.0 > 0.0 {
            (params.pose_sigma_m, params.pose_sigma_rad) = pose_noise;
        }
        initialize(
            &self.vo_poses(pose_noise),
            &self.preints(noise),
            &t_bc,
            &params,
        )
    }

    /// Errors against the truth: (scale %, gravity direction °, velocity RMSE m/s, gyro bias
    /// rad/s, accel bias m/s²).
    fn errors(&self, r: &InertialInit) -> (f64, f64, f64, f64, f64) {
        let g_true = r_vw() * Vector3::new(0.0, 0.0, -9.81);
        let g_err = r.gravity_w.angle(&g_true).to_degrees();
        let traj = self.world.trajectory();
        let start = self.world.params().start_ns;
        let mut v2 = 0.0;
        for (k, &t) in self.kf_ns.iter().enumerate() {
            let v_true = r_vw() * traj.body_state((t - start) as f64 * 1e-9).v_w;
            v2 += (r.velocities_w[k] - v_true).norm_squared();
        }
        let b = true_biases();
        (
            (r.scale / S_TRUE - 1.0) * 100.0,
            g_err,
            (v2 / self.kf_ns.len() as f64).sqrt(),
            (r.biases.gyro - b.gyro).norm(),
            (r.biases.accel - b.accel).norm(),
        )
    }
}

/// Exact IMU and poses: scale, gravity, velocities and gyro bias recovered closely.
#[test]
fn exact_motion_gives_scale_gravity_velocities_and_gyro_bias() {
    let case = Case::new(Scenario::FastRs, ImuNoise::zero(), 3.0, 0.25);
    let r = case
        .run(&ImuNoise::default(), (0.0, 0.0))
        .expect("initialised");
    let (s, g, v, bg, ba) = case.errors(&r);
    eprintln!(
        "exact: scale {s:+.4}% (linear {:.4}), gravity {g:.4}°, v {v:.4} m/s, b_g {bg:.2e}, b_a {ba:.3}, \
         σ_s {:.4}, σ_g {:.3}°, {} iterations",
        r.linear_scale / S_TRUE,
        r.scale_sigma,
        r.gravity_sigma.to_degrees(),
        r.iterations
    );
    assert!(s.abs() < 0.2, "scale error {s}%");
    assert!(g < 0.05, "gravity direction error {g}°");
    assert!(v < 0.01, "velocity RMSE {v} m/s");
    assert!(bg < 2e-4, "gyro bias error {bg}");
    assert!(ba < 0.03, "accelerometer bias error {ba}");
}

/// The ADIS16448 noise of EuRoC on the IMU and 2 mm / 0.1° on the keyframe poses (a good
/// monocular map), 5 s of keyframes (3 s leave a 1σ of 6% on the scale, above the default
/// 5% acceptance): scale within 3σ of its stated uncertainty and within 10%, gravity within
/// 0.5° (the visual-inertial optimisation refines them afterwards).
#[test]
fn noisy_imu_and_poses_still_initialise_within_targets() {
    let noise = ImuNoise::default();
    let case = Case::new(Scenario::FastRs, noise, 5.0, 0.25);
    let r = case
        .run(&noise, (0.002, 0.1f64.to_radians()))
        .expect("initialised");
    let (s, g, v, bg, ba) = case.errors(&r);
    eprintln!(
        "noisy: scale {s:+.3}%, gravity {g:.3}°, v {v:.3} m/s, b_g {bg:.2e}, b_a {ba:.3}, σ_s {:.4}, σ_g {:.3}°",
        r.scale_sigma,
        r.gravity_sigma.to_degrees()
    );
    assert!(s.abs() < 10.0, "scale error {s}%");
    assert!(
        s.abs() < 300.0 * r.scale_sigma,
        "error {s}% beyond 3σ {}",
        r.scale_sigma
    );
    assert!(g < 0.5, "gravity direction error {g}°");
    assert!(v < 0.05, "velocity RMSE {v} m/s");
    assert!(bg < 2e-3, "gyro bias error {bg}");
}

/// The `loop` scenario's first 3 s: a gentle ellipse (about 0.06 m/s² of acceleration, the
/// size of the accelerometer bias): the scale is not determined and the initialiser says so
/// instead of inventing one (exact IMU and poses, so nothing but the motion is to blame).
#[test]
fn a_motion_without_acceleration_is_refused() {
    let case = Case::new(Scenario::Loop, ImuNoise::zero(), 3.0, 0.25);
    match case.run(&ImuNoise::default(), (0.0, 0.0)) {
        Err(e @ (InitError::NotObservable { .. } | InitError::Alignment(_))) => {
            eprintln!("refused: {e}");
        }
        Ok(r) => panic!(
            "initialised on a gentle motion: scale {:.3} (truth {S_TRUE}), σ {:.3}",
            r.scale, r.scale_sigma
        ),
        Err(e) => panic!("other error: {e}"),
    }
}

#[test]
fn bad_input_is_an_error_not_a_panic() {
    let case = Case::new(Scenario::FastRs, ImuNoise::zero(), 1.0, 0.25);
    let poses = case.vo_poses((0.0, 0.0));
    let pre = case.preints(&ImuNoise::default());
    let t_bc = case.world.calib().t_bs;
    let p = InitParams::default();
    assert!(matches!(
        initialize(&poses[..2], &pre[..1], &t_bc, &p),
        Err(InitError::BadInput { .. })
    ));
    assert!(matches!(
        initialize(&poses, &pre[..1], &t_bc, &p),
        Err(InitError::BadInput { .. })
    ));
}

/// A device whose camera-IMU rotation is not given: `R_bc` and the gyro bias from the
/// visual rotations of the keyframes (0.1° pose noise) and the noisy gyro of the `drone`
/// scenario, 5 s of keyframes every 0.25 s (issue 17: estimated before the initialisation).
#[test]
fn camera_imu_rotation_from_gyro_and_visual_rotations() {
    use slam_core::imu::extrinsic_rotation::estimate_extrinsic_rotation;
    let noise = ImuNoise::default();
    let case = Case::new(Scenario::Drone, noise, 5.0, 0.25);
    let poses = case.vo_poses((0.002, 0.1f64.to_radians()));
    let r_c: Vec<Rotation3<f64>> = poses
        .windows(2)
        .map(|w| (w[0].rotation.inverse() * w[1].rotation).to_rotation_matrix())
        .collect();
    let est = estimate_extrinsic_rotation(&r_c, &case.preints(&noise), &Default::default())
        .expect("estimated");
    let r_bc_true = case.world.calib().t_bs.rotation.to_rotation_matrix();
    let err = (est.r_bc.inverse() * r_bc_true).angle().to_degrees();
    let bg_err = (est.gyro_bias - true_biases().gyro).norm();
    eprintln!(
        "R_bc error {err:.4}° (1σ {:.4}°), b_g error {bg_err:.2e} rad/s, rms {:.4}°, {} outliers of {}",
        est.sigma_rad.to_degrees(),
        est.rms_rad.to_degrees(),
        est.outliers,
        r_c.len()
    );
    assert!(err < 0.3, "R_bc error {err}°");
    assert!(err < 3.0 * est.sigma_rad.to_degrees() + 0.01, "beyond 3σ");
    assert!(bg_err < 2e-3, "gyro bias error {bg_err}");
}

/// Experiment (ignored): how the `loop` scenario's scale information grows with the span
/// of keyframes, and what limits it. EuRoC noise; keyframes every 0.5 s; pose noise
/// `POSE_MM` (default 2 mm, and 0.05°/mm); `SIM_NO_RW`: the simulated biases do not walk
/// (the estimator's noise model is unchanged); `ACC_PRIOR`: the accelerometer bias prior σ.
/// Measured (session 13, seed 5): with 0.2 mm poses the constant-bias estimate after 60 s
/// is +3.6 % off with σ 0.54 % (and +9.6 % with σ 1.0 % after 20 s), but +0.6 % (σ 0.55 %)
/// when the simulated accelerometer bias does not walk: EuRoC's random walk (3e-3
/// m/s³/√Hz, about 0.02 m/s² a minute) is as large as the ellipse's accelerations, so the
/// scale of `loop` is not determined to 1 % by its motion (BENCHMARKS.md, issue 17).
#[test]
#[ignore = "experiment: prints the scale error and σ per span"]
fn loop_scale_information_over_time() {
    let noise = ImuNoise::default();
    for span in [5.0, 10.0, 15.0, 20.0, 30.0, 45.0, 60.0] {
        let mut sim_noise = noise;
        if std::env::var("SIM_NO_RW").is_ok() {
            sim_noise.accel_bias_rw = 0.0;
            sim_noise.gyro_bias_rw = 0.0;
        }
        let case = Case::new(Scenario::Loop, sim_noise, span, 0.5);
        let t_bc = case.world.calib().t_bs;
        let mut params = InitParams {
            max_scale_sigma: 10.0,
            max_gravity_sigma: 1.0,
            ..InitParams::default()
        };
        if let Ok(v) = std::env::var("ACC_PRIOR") {
            params.prior_accel_bias = v.parse().expect("ACC_PRIOR");
        }
        let pm: f64 = std::env::var("POSE_MM").map_or(2.0, |v| v.parse().expect("POSE_MM"));
        let pn = (pm * 1e-3, (0.05 * pm).to_radians());
        (params.pose_sigma_m, params.pose_sigma_rad) = pn;
        match initialize(&case.vo_poses(pn), &case.preints(&noise), &t_bc, &params) {
            Ok(r) => {
                let (s, g, _, _, ba) = case.errors(&r);
                eprintln!(
                    "span {span:5.1} s: scale {s:+.2}% σ {:.2}%, gravity {g:.3}°, b_a err {ba:.3}",
                    r.scale_sigma * 100.0
                );
            }
            Err(e) => eprintln!("span {span:5.1} s: {e}"),
        }
    }
}
