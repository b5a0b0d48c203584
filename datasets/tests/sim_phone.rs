//! The `phone` synthetic scenario (issue 17): hand-held walk, 30 Hz rolling shutter
//! (t_r 25 ms), phone-grade IMU with biases and non-ideal `T_g`, `T_s`, `T_a`, camera-IMU
//! offset t_d 40 ms. Checked: the written EuRoC folder reads back every true value; the
//! noise-free IMU preintegrates to the exact motion only with the true intrinsics and the
//! frames sit at stamp + t_d on the IMU clock; the monocular VO tracks the rendered frames.

use datasets::euroc::{read_imu_csv, read_imu_sensor_yaml};
use datasets::open;
use datasets::sim::{generate, Scenario, SimParams, SimWorld};
use nalgebra::Vector3;
use slam_core::imu::{gravity_w, ImuIntrinsics, ImuNoise, Preintegrated, PreintegrationParams};
use slam_core::metrics::{evaluate_by_index, Alignment, EvalParams};
use slam_core::vo::{VoParams, VoTracker};

/// The defaults carry the phone's numbers: 30 Hz, t_r 25 ms, t_d 40 ms, 24 s, and IMU
/// errors of the sizes the issue asks for.
#[test]
fn phone_defaults_are_a_phone() {
    let p = SimParams::new(Scenario::Phone);
    assert_eq!(p.rate_hz, 30.0);
    assert_eq!(p.readout_ns(), 25_000_000);
    assert_eq!(p.time_offset_ns(), 40_000_000);
    assert_eq!(p.n_frames(), 720);
    let k = p.imu_intrinsics;
    for m in [k.t_g, k.t_a] {
        let scale = (0..3).map(|i| (m[(i, i)] - 1.0).abs()).fold(0.0, f64::max);
        let skew = (0..3)
            .flat_map(|i| (0..3).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| m[(i, j)].abs())
            .fold(0.0, f64::max);
        assert!((0.005..0.015).contains(&scale), "scale error {scale}");
        assert!((0.003..0.01).contains(&skew), "misalignment {skew}");
    }
    assert!(k.t_s.amax() > 1e-4 && k.t_s.amax() < 1e-3);
    assert!((0.005..0.02).contains(&p.initial_biases.gyro.amax()));
    assert!((0.05..0.2).contains(&p.initial_biases.accel.amax()));
    assert!(p.noise.gyro_noise_density > ImuNoise::default().gyro_noise_density * 0.5);
}

/// `shoal sim --scenario phone` output read back: the camera's t_d and t_r through the
/// dataset reader (frames at stamp + t_d, 30 Hz), and `imu0/sensor.yaml`'s true IMU errors,
/// biases, noise, t_d and t_r exactly; the IMU CSV is the world's IMU bit for bit.
#[test]
fn phone_dataset_round_trips() {
    let tmp = tempfile::tempdir().expect("tmp");
    let mut params = SimParams::new(Scenario::Phone);
    params.frames = Some(5);
    let summary = generate(&params, tmp.path()).expect("generate");
    assert_eq!(summary.time_offset_ns, 40_000_000);
    let world = SimWorld::new(params.clone()).expect("world");

    let ds = open(tmp.path()).expect("open");
    assert!(ds.issues.is_empty(), "{:#?}", ds.issues);
    assert_eq!(ds.camera.time_offset_ns, 40_000_000);
    assert_eq!(ds.camera.readout_ns, 25_000_000);
    assert_eq!(ds.camera.rate_hz, 30.0);
    assert_eq!(ds.frames.len(), 5);
    for (k, f) in ds.frames.iter().enumerate() {
        assert_eq!(f.t_ns, world.frame_capture_time_ns(k));
        assert_eq!(f.readout_ns, 25_000_000);
    }
    assert_eq!(ds.frames[1].t_ns - ds.frames[0].t_ns, 33_333_333);

    let imu0 = tmp.path().join("mav0/imu0");
    let y = read_imu_sensor_yaml(&imu0.join("sensor.yaml")).expect("imu yaml");
    assert_eq!(y.rate_hz, 200.0);
    assert_eq!(y.noise, params.noise);
    assert_eq!(y.intrinsics, Some(params.imu_intrinsics));
    assert!(!params.imu_intrinsics.is_ideal());
    assert_eq!(y.initial_biases, Some(params.initial_biases));
    assert_eq!(y.time_offset_ns, Some(40_000_000));
    assert_eq!(y.readout_ns, Some(25_000_000));

    let mut issues = Vec::new();
    let imu = read_imu_csv(&imu0.join("data.csv"), &mut issues).expect("imu csv");
    assert!(issues.is_empty());
    assert_eq!(imu, world.imu_samples());
    assert_eq!(ds.imu, world.imu_samples());
}

/// Worst residual norms (R, v, p) over 0.1-2 s windows of the noise-free phone IMU (true
/// intrinsics and biases in the stream) preintegrated with the `assumed` intrinsics.
fn worst_residual(world: &SimWorld, assumed: &ImuIntrinsics) -> Vector3<f64> {
    let (imu, gt) = (world.imu_samples(), world.ground_truth_states());
    let params = PreintegrationParams::new(&ImuNoise::zero(), assumed).expect("params");
    let b = params.correction.effective_biases(&gt[0].biases);
    let mut worst = Vector3::zeros();
    for len in [20, 100, 200, 400] {
        for i in (0..gt.len().saturating_sub(len)).step_by(41) {
            let (si, sj) = (&gt[i], &gt[i + len]);
            let pre = Preintegrated::from_window(imu, si.t_ns, sj.t_ns, b, params).expect("window");
            let r = pre
                .residual(&si.nav_state(b), &sj.nav_state(b), &gravity_w())
                .r;
            for k in 0..3 {
                worst[k] = f64::max(worst[k], r.fixed_rows::<3>(3 * k).norm());
            }
        }
    }
    worst
}

/// The phone's noise-free 200 Hz IMU over 10 s preintegrates to the exact motion with its
/// true `T_g`, `T_s`, `T_a` (through `MeasurementCorrection`) and misses it by orders of
/// magnitude when they are taken as ideal; and the gyro integrated between the true
/// capture times (stamp + t_d) of frames one second apart gives the camera's ground-truth
/// rotation, while integrating between the bare stamps does not.
#[test]
fn phone_imu_follows_the_trajectory_with_its_intrinsics_and_offset() {
    let mut p = SimParams::new(Scenario::Phone);
    p.frames = Some(300); // 10 s
    p.noise = ImuNoise::zero();
    let world = SimWorld::new(p.clone()).expect("world");
    let good = worst_residual(&world, &p.imu_intrinsics);
    let ideal = worst_residual(&world, &ImuIntrinsics::default());
    println!(
        "phone 200 Hz, true intrinsics: worst |r_R| {:.2e} rad, |r_v| {:.2e} m/s, |r_p| {:.2e} m; \
         ideal assumed: {:.2e} rad, {:.2e} m/s, {:.2e} m",
        good.x, good.y, good.z, ideal.x, ideal.y, ideal.z
    );
    assert!(good.max() < 1e-3, "{good}");
    for k in 0..3 {
        assert!(ideal[k] > 10.0 * good[k], "{ideal} vs {good}");
    }

    let params = PreintegrationParams::new(&ImuNoise::zero(), &p.imu_intrinsics).expect("params");
    let b = params.correction.effective_biases(&p.initial_biases);
    let t_bs = world.trajectory().t_bs;
    let rot_err = |k0: usize, k1: usize, shift_ns: i64| {
        let (t0, t1) = (
            world.frame_time_ns(k0) + shift_ns,
            world.frame_time_ns(k1) + shift_ns,
        );
        let pre = Preintegrated::from_window(world.imu_samples(), t0, t1, b, params).expect("pre");
        let c0 = world.pose_cam_at(world.frame_capture_time_ns(k0));
        let c1 = world.pose_cam_at(world.frame_capture_time_ns(k1));
        let truth_b = (c0 * t_bs.inverse()).rotation.inverse() * (c1 * t_bs.inverse()).rotation;
        let imu_b = nalgebra::UnitQuaternion::from_rotation_matrix(&pre.delta_r());
        (truth_b.inverse() * imu_b).angle()
    };
    let (mut with_td, mut without) = (0.0f64, 0.0f64);
    for k in (0..260).step_by(20) {
        with_td = with_td.max(rot_err(k, k + 30, world.time_offset_ns()));
        without = without.max(rot_err(k, k + 30, 0));
    }
    println!("gyro vs camera rotation over 1 s: {with_td:.2e} rad at stamp + t_d, {without:.2e} at the stamps");
    assert!(with_td < 1e-4, "{with_td}");
    assert!(without > 20.0 * with_td.max(1e-6), "{without}");
}

/// The monocular VO on the first 6 s of rendered phone frames (rolling shutter compensated
/// from the VO's motion model, no IMU): tracked fraction, and ATE after Sim(3) alignment of
/// the tracked camera centres to the true ones at stamp + t_d.
#[test]
fn the_vo_tracks_the_phone_walk() {
    let mut p = SimParams::new(Scenario::Phone);
    p.seed = 5;
    p.frames = Some(180);
    let world = SimWorld::new(p).expect("world");
    let cam = world.calib().model;
    let mut vo = VoTracker::new(VoParams::default(), cam).expect("vo");
    let mut img = vec![0u8; (cam.width * cam.height) as usize];
    let (mut est, mut truth) = (Vec::new(), Vec::new());
    let mut first_tracked = None;
    for k in 0..world.n_frames() {
        let frame = world.vo_frame(k, &mut img).expect("render");
        let o = vo.process(&frame).expect("vo step");
        assert!(
            !o.new_session || est.is_empty(),
            "the VO lost its map at frame {k}"
        );
        if let Some(t_cw) = o.t_cw {
            first_tracked.get_or_insert(k);
            est.push(t_cw.inverse());
            truth.push(world.pose_cam_at(world.frame_capture_time_ns(k)));
        }
    }
    let n = world.n_frames();
    let first = first_tracked.expect("the VO never tracked");
    let fraction = est.len() as f64 / (n - first) as f64;
    let params = EvalParams {
        alignment: Alignment::Sim3,
        ..EvalParams::default()
    };
    let r = evaluate_by_index(&truth, &est, &params).expect("evaluate");
    let ate = r.ape.rmse;
    let path = r.ref_path_length_m;
    eprintln!(
        "phone VO: first pose at frame {first}, tracked {}/{} after it ({:.1}%), ATE rmse {:.4} m \
         (max {:.4} m) over a {:.2} m path ({:.2}%), Sim(3) scale {:.3}",
        est.len(),
        n - first,
        fraction * 100.0,
        ate,
        r.ape.max,
        path,
        ate / path * 100.0,
        r.alignment.scale
    );
    assert!(first < 30, "first pose only at frame {first}");
    assert!(fraction > 0.95, "tracked {fraction}");
    assert!(ate < 0.02 * path, "ATE {ate} over {path} m");
}

/// `read_imu_sensor_yaml` on a real EuRoC-style file (no shoal extensions: the truths are
/// `None`) and on broken ones (wrong matrix size, negative density: errors).
#[test]
fn imu_sensor_yaml_without_extensions_and_broken() {
    let tmp = tempfile::tempdir().expect("tmp");
    let path = tmp.path().join("sensor.yaml");
    let euroc = "%YAML:1.0\nsensor_type: imu\nT_BS:\n  cols: 4\n  rows: 4\n  data: [1.0, 0.0, 0.0, 0.0,\n         0.0, 1.0, 0.0, 0.0,\n         0.0, 0.0, 1.0, 0.0,\n         0.0, 0.0, 0.0, 1.0]\nrate_hz: 200\ngyroscope_noise_density: 1.6968e-04\ngyroscope_random_walk: 1.9393e-05\naccelerometer_noise_density: 2.0000e-3\naccelerometer_random_walk: 3.0000e-3\n";
    std::fs::write(&path, euroc).expect("write");
    let y = read_imu_sensor_yaml(&path).expect("euroc yaml");
    assert_eq!(y.noise, ImuNoise::default());
    assert_eq!(
        (
            y.intrinsics,
            y.initial_biases,
            y.time_offset_ns,
            y.readout_ns
        ),
        (None, None, None, None)
    );
    let bad_matrix = format!("{euroc}T_g:\n  cols: 2\n  rows: 2\n  data: [1.0, 0.0, 0.0, 1.0]\n");
    std::fs::write(&path, bad_matrix).expect("write");
    assert!(read_imu_sensor_yaml(&path).is_err());
    std::fs::write(&path, euroc.replace("2.0000e-3", "-2.0e-3")).expect("write");
    assert!(read_imu_sensor_yaml(&path).is_err());
    std::fs::write(&path, format!("{euroc}initial_gyro_bias: [0.1, 0.2]\n")).expect("write");
    assert!(read_imu_sensor_yaml(&path).is_err());
}
