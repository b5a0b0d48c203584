//! The synthetic world generator: determinism, IMU consistency with the ground truth, the
//! files it writes, and the geometry of its scenarios.

use std::collections::BTreeMap;
use std::path::Path;

use datasets::sim::{generate, Scenario, SimParams, SimWorld};
use nalgebra::{UnitQuaternion, Vector3};
use slam_core::imu::{gravity_w, ImuBiases, ImuNoise};

fn read_tree(root: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).expect("read_dir") {
            let p = e.expect("entry").path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let rel = p
                    .strip_prefix(root)
                    .expect("prefix")
                    .to_string_lossy()
                    .into_owned();
                out.insert(rel, std::fs::read(&p).expect("read"));
            }
        }
    }
    out
}

#[test]
fn same_seed_gives_identical_bytes_other_seed_differs() {
    let mut params = SimParams::new(Scenario::FastRs);
    params.frames = Some(3);
    let (a, b, c) = (
        tempfile::tempdir().expect("tmp"),
        tempfile::tempdir().expect("tmp"),
        tempfile::tempdir().expect("tmp"),
    );
    generate(&params, a.path()).expect("gen a");
    generate(&params, b.path()).expect("gen b");
    params.seed = 1;
    generate(&params, c.path()).expect("gen c");
    let (ta, tb, tc) = (
        read_tree(a.path()),
        read_tree(b.path()),
        read_tree(c.path()),
    );
    assert_eq!(
        ta.len(),
        3 + 2 + 1 + 2 + 1,
        "{:?}",
        ta.keys().collect::<Vec<_>>()
    );
    assert!(ta == tb, "same seed must give the same bytes");
    let png = |t: &BTreeMap<String, Vec<u8>>| {
        t.iter()
            .filter(|(k, _)| k.ends_with(".png"))
            .map(|(_, v)| v.clone())
            .collect::<Vec<_>>()
    };
    assert_ne!(png(&ta), png(&tc), "another seed must give other images");
}

#[test]
fn written_files_follow_the_euroc_layout_and_conventions() {
    let tmp = tempfile::tempdir().expect("tmp");
    let mut params = SimParams::new(Scenario::FastRs);
    params.frames = Some(4);
    params.time_offset_ms = 2.5;
    let summary = generate(&params, tmp.path()).expect("generate");
    assert_eq!(summary.agents.len(), 1);
    assert_eq!(summary.readout_ns, 30_000_000);
    assert_eq!(summary.time_offset_ns, 2_500_000);
    let root = tmp.path();
    let yaml = std::fs::read_to_string(root.join("mav0/cam0/sensor.yaml")).expect("yaml");
    assert!(yaml.starts_with("%YAML:1.0\n"));
    for key in [
        "T_BS:",
        "rate_hz: 20",
        "resolution: [752, 480]",
        "camera_model: pinhole",
        "intrinsics: [",
        "distortion_model: radial-tangential",
        "distortion_coefficients: [",
        "readout_time_ns: 30000000",
        "time_offset_ns: 2500000",
    ] {
        assert!(yaml.contains(key), "missing {key} in\n{yaml}");
    }
    let imu_yaml = std::fs::read_to_string(root.join("mav0/imu0/sensor.yaml")).expect("imu yaml");
    assert!(imu_yaml.contains("gyroscope_noise_density: 0.00016968"));
    // The true IMU errors, t_d and t_r (ideal intrinsics by default).
    for key in [
        "T_g:\n  cols: 3\n  rows: 3\n  data: [1.0, 0.0, 0.0,\n         0.0, 1.0, 0.0,\n         0.0, 0.0, 1.0]\n",
        "T_s:\n  cols: 3\n  rows: 3\n  data: [0.0, 0.0, 0.0,",
        "T_a:\n  cols: 3\n  rows: 3\n  data: [1.0, 0.0, 0.0,",
        "initial_gyro_bias: [0.003, -0.002, 0.001]",
        "initial_accel_bias: [0.02, -0.03, 0.05]",
        "time_offset_ns: 2500000",
        "readout_time_ns: 30000000",
    ] {
        assert!(imu_yaml.contains(key), "missing {key} in\n{imu_yaml}");
    }
    let data = std::fs::read_to_string(root.join("mav0/cam0/data.csv")).expect("data.csv");
    let stamps: Vec<i64> = data
        .lines()
        .skip(1)
        .map(|l| {
            let (t, f) = l.split_once(',').expect("two columns");
            assert_eq!(f, format!("{t}.png"));
            assert!(root.join("mav0/cam0/data").join(f).is_file());
            t.parse().expect("int")
        })
        .collect();
    assert_eq!(stamps.len(), 4);
    assert!(stamps.windows(2).all(|w| w[1] - w[0] == 50_000_000));
    let tum = std::fs::read_to_string(root.join("groundtruth_cam0.txt")).expect("tum");
    let world = SimWorld::new(params.clone()).expect("world");
    let lines: Vec<&str> = tum.lines().filter(|l| !l.starts_with('#')).collect();
    assert_eq!(lines.len(), 4);
    for (k, (line, stamp)) in lines.iter().zip(&stamps).enumerate() {
        let v: Vec<&str> = line.split(' ').collect();
        assert_eq!(v.len(), 8);
        let (secs, frac) = v[0].split_once('.').expect("decimal");
        assert_eq!(frac.len(), 9);
        assert_eq!(format!("{secs}{frac}").parse::<i64>().expect("ns"), *stamp);
        // The pose is the camera pose at the true mid-row time (stamp + t_d).
        assert_eq!(world.frame_time_ns(k), *stamp);
        let pose = world.pose_cam_at(stamp + 2_500_000);
        let p: Vec<f64> = v[1..4].iter().map(|x| x.parse().expect("f64")).collect();
        assert!((Vector3::new(p[0], p[1], p[2]) - pose.translation.vector).norm() < 1e-8);
    }
    // IMU and state CSVs: EuRoC headers, 7 and 17 columns, same stamps.
    let imu = std::fs::read_to_string(root.join("mav0/imu0/data.csv")).expect("imu");
    let gt = std::fs::read_to_string(root.join("mav0/state_groundtruth_estimate0/data.csv"))
        .expect("gt");
    assert!(imu.starts_with("#timestamp [ns],w_RS_S_x"));
    assert!(gt.starts_with("#timestamp, p_RS_R_x [m]"));
    let imu_rows: Vec<&str> = imu.lines().skip(1).collect();
    let gt_rows: Vec<&str> = gt.lines().skip(1).collect();
    assert_eq!(imu_rows.len(), world.imu_samples().len());
    assert_eq!(imu_rows.len(), gt_rows.len());
    assert!(imu_rows.iter().all(|l| l.split(',').count() == 7));
    assert!(gt_rows.iter().all(|l| l.split(',').count() == 17));
    let first_imu: i64 = imu_rows[0]
        .split(',')
        .next()
        .and_then(|t| t.parse().ok())
        .expect("t");
    let last_imu: i64 = imu_rows[imu_rows.len() - 1]
        .split(',')
        .next()
        .and_then(|t| t.parse().ok())
        .expect("t");
    assert!(first_imu < stamps[0] - 15_000_000 && last_imu > stamps[3] + 15_000_000 + 2_500_000);
}

#[test]
fn two_agents_write_two_layouts_in_one_world_frame() {
    let tmp = tempfile::tempdir().expect("tmp");
    let mut params = SimParams::new(Scenario::TwoAgents);
    params.frames = Some(2);
    let s = generate(&params, tmp.path()).expect("generate");
    assert_eq!(s.agents.len(), 2);
    for a in ["agent0", "agent1"] {
        assert!(tmp.path().join(a).join("mav0/cam0/data.csv").is_file());
        assert!(tmp.path().join(a).join("groundtruth_cam0.txt").is_file());
    }
    // Overlap: every pose of agent 1 has a pose of agent 0 nearby looking the same way.
    let (a0, a1) = (
        Scenario::TwoAgents.trajectory(0).expect("a0"),
        Scenario::TwoAgents.trajectory(1).expect("a1"),
    );
    for i in 0..64 {
        let q = a1.pose_cam(f64::from(i) * 0.5);
        let near = (0..640).any(|j| {
            let r = a0.pose_cam(f64::from(j) * 0.05);
            let d = (r.translation.vector - q.translation.vector).norm();
            let ang = (r.rotation * Vector3::z()).angle(&(q.rotation * Vector3::z()));
            d < 1.2 && ang < 0.35
        });
        assert!(near, "agent 1 at {i} s has no overlapping view of agent 0");
    }
}

/// Integrates noise-free IMU samples from the ground-truth state and compares after 1 s.
fn integrate_and_compare(scenario: Scenario, start_idx: usize, max_pos: f64, max_rot: f64) {
    let mut params = SimParams::new(scenario);
    params.noise = ImuNoise::zero();
    params.initial_biases = ImuBiases::default();
    params.frames = Some(60);
    let world = SimWorld::new(params).expect("world");
    let imu = world.imu_samples();
    let gt = world.ground_truth_states();
    let g = gravity_w();
    let s0 = gt[start_idx];
    let (mut r, mut v, mut p) = (s0.q_wb, s0.v_w, s0.p_wb);
    for k in start_idx..start_idx + 200 {
        let (a, b) = (&imu[k], &imu[k + 1]);
        let dt = (b.t_ns - a.t_ns) as f64 * 1e-9;
        let w = (Vector3::from(a.gyro) + Vector3::from(b.gyro)) * 0.5;
        let r1 = r * UnitQuaternion::from_scaled_axis(w * dt);
        let acc0 = r * Vector3::from(a.accel) + g;
        let acc1 = r1 * Vector3::from(b.accel) + g;
        p += v * dt + (acc0 * 2.0 + acc1) * (dt * dt / 6.0);
        v += (acc0 + acc1) * (0.5 * dt);
        r = r1;
    }
    let s1 = gt[start_idx + 200];
    let dp = (p - s1.p_wb).norm();
    let dr = (r.inverse() * s1.q_wb).angle();
    let dv = (v - s1.v_w).norm();
    eprintln!(
        "{scenario}: 1 s of IMU integration: dp {dp:.2e} m, dv {dv:.2e} m/s, dr {dr:.2e} rad"
    );
    assert!(
        dp < max_pos && dr < max_rot && dv < 2.0 * max_pos,
        "{scenario}: dp {dp} m, dv {dv} m/s, dr {dr} rad"
    );
}

#[test]
fn noise_free_imu_integrates_back_to_ground_truth() {
    integrate_and_compare(Scenario::Loop, 100, 1e-4, 1e-5);
    integrate_and_compare(Scenario::TwoAgents, 300, 1e-4, 1e-5);
    integrate_and_compare(Scenario::FastRs, 50, 5e-3, 5e-4);
}

#[test]
fn imu_biases_and_noise_are_recorded() {
    let mut params = SimParams::new(Scenario::Loop);
    params.frames = Some(20);
    let world = SimWorld::new(params.clone()).expect("world");
    let gt = world.ground_truth_states();
    assert_eq!(gt[0].biases, params.initial_biases);
    // The bias walks; the measurement minus bias and truth stays within a few discrete sigmas.
    assert_ne!(gt[100].biases, gt[0].biases);
    let mut ideal = params.clone();
    ideal.noise = ImuNoise::zero();
    ideal.initial_biases = ImuBiases::default();
    let exact = SimWorld::new(ideal).expect("world");
    let (sg, sa) = params.noise.discrete_white_sigma(0.005);
    let triples = gt.iter().zip(world.imu_samples()).zip(exact.imu_samples());
    for (k, ((s, m), e)) in triples.enumerate() {
        let ng = Vector3::from(m.gyro) - Vector3::from(e.gyro) - s.biases.gyro;
        let na = Vector3::from(m.accel) - Vector3::from(e.accel) - s.biases.accel;
        assert!(ng.amax() < 6.0 * sg && na.amax() < 6.0 * sa, "sample {k}");
    }
}

#[test]
fn scenario_geometry() {
    for (sc, frames, min_len, max_len) in [
        (Scenario::Loop, 1280, 60.0, 66.0),
        (Scenario::TwoAgents, 640, 28.0, 34.0),
        (Scenario::FastRs, 640, 29.0, 35.0),
    ] {
        let world = SimWorld::new(SimParams::new(sc)).expect("world");
        assert_eq!(world.n_frames(), frames);
        let len = world.path_length_m();
        eprintln!(
            "{sc}: {} frames, {:.2} s, camera path {len:.2} m",
            world.n_frames(),
            world.duration_s()
        );
        assert!((min_len..max_len).contains(&len), "{sc}: path {len} m");
        // The loop closes: the end of lap 1 is the start of lap 2.
        if sc == Scenario::Loop {
            let t = world.frame_capture_time_ns(0);
            let d = world.pose_cam_at(t).translation.vector
                - world.pose_cam_at(t + 32_000_000_000).translation.vector;
            assert!(d.norm() < 0.35, "loop revisit offset {}", d.norm());
        }
    }
}

#[test]
fn invalid_parameters_are_rejected() {
    let mut p = SimParams::new(Scenario::Loop);
    p.width = 0;
    assert!(SimWorld::new(p.clone()).is_err());
    p.width = 752;
    p.readout_ms = Some(-1.0);
    assert!(generate(&p, Path::new("/nonexistent/never")).is_err());
    p.readout_ms = Some(f64::NAN);
    assert!(p.validate().is_err());
    p.readout_ms = None;
    p.frames = Some(0);
    assert!(p.validate().is_err());
    let world = SimWorld::new(SimParams {
        frames: Some(2),
        ..SimParams::new(Scenario::Loop)
    })
    .expect("world");
    let mut small = vec![0u8; 10];
    assert!(world.render_frame_into(0, &mut small).is_err());
}

/// `blackout`: the `loop` path with the middle 2 s of frames all black; the other frames
/// render the scene.
#[test]
fn blackout_blanks_the_middle_two_seconds() {
    let mut params = SimParams::new(Scenario::Blackout);
    params.frames = Some(60);
    let world = SimWorld::new(params).expect("world");
    let mut img = vec![0u8; 752 * 480];
    assert_eq!(Scenario::Blackout.blank_frames(60, 20.0), 10..50);
    world.render_frame_into(9, &mut img).expect("render");
    assert!(
        img.iter().filter(|&&v| v > 0).count() > img.len() / 2,
        "frame 9 shows the scene"
    );
    img.fill(7);
    world.render_frame_into(10, &mut img).expect("render");
    assert!(img.iter().all(|&v| v == 0), "frame 10 is blank");
    world.render_frame_into(49, &mut img).expect("render");
    assert!(img.iter().all(|&v| v == 0), "frame 49 is blank");
    world.render_frame_into(50, &mut img).expect("render");
    assert!(img.iter().any(|&v| v > 0), "frame 50 shows the scene");
    assert!(world.render_frame_into(20, &mut img[1..]).is_err());
}
