//! Readers on the real data excerpts in `../shared/data` (ignored when absent: see
//! `build_support/shoal_data.rs`).

mod common;

use common::{data_dir, fnv1a};
use datasets::{decode_gray_into, image_size, open, DatasetKind};
use slam_core::metrics::path_length;

fn check_frame(path: &std::path::Path, w: u32, h: u32, sum: u64, hash: u64) {
    assert_eq!(image_size(path).expect("header"), (w, h));
    let mut buf = vec![0u8; (w * h) as usize];
    decode_gray_into(path, &mut buf, w, h).expect("decode");
    assert_eq!(
        buf.iter().map(|&b| u64::from(b)).sum::<u64>(),
        sum,
        "{}",
        path.display()
    );
    assert_eq!(fnv1a(&buf), hash, "{}", path.display());
    // A buffer or an expected size that does not match is an error naming the file.
    let err = decode_gray_into(path, &mut buf, h, w)
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains(&path.display().to_string()) && err.contains("expected"),
        "{err}"
    );
    assert!(decode_gray_into(path, &mut buf[1..], w, h).is_err());
}

#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/euroc_v101_static (set SHOAL_DATA)"
)]
#[test]
fn euroc_v101_static() {
    let data = data_dir("euroc_v101_static");
    let ds = open(&data.join("euroc_v101_static")).expect("open");
    assert_eq!(ds.kind, DatasetKind::Euroc);
    assert!(ds.issues.is_empty(), "{:?}", ds.issues);
    assert_eq!(ds.frames.len(), 95);
    let m = &ds.camera.model;
    assert_eq!((m.width, m.height), (752, 480));
    assert_eq!(
        (m.fx, m.fy, m.cx, m.cy),
        (458.654, 457.296, 367.215, 248.375)
    );
    assert_eq!(
        (m.k1, m.k2, m.p1, m.p2, m.k3),
        (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0)
    );
    assert_eq!(ds.camera.rate_hz, 20.0);
    assert_eq!((ds.camera.readout_ns, ds.camera.time_offset_ns), (0, 0));
    let t = ds.camera.t_bs.translation.vector;
    assert!((t.x + 0.0216401454975).abs() < 1e-12 && (t.y + 0.064676986768).abs() < 1e-12);
    let r = ds.camera.t_bs.rotation.to_rotation_matrix();
    assert!((r[(0, 1)] + 0.999880929698).abs() < 1e-6 && (r[(1, 0)] - 0.999557249008).abs() < 1e-6);
    assert_eq!(ds.frames[0].t_ns, 1_403_715_273_262_142_976);
    assert!(ds.frames.windows(2).all(|w| w[0].t_ns < w[1].t_ns));
    assert_eq!(ds.imu.len(), 29120);
    assert!((ds.imu[0].accel[0] - 9.087_495_666_666_666).abs() < 1e-12);
    assert!(ds.imu.windows(2).all(|w| w[0].t_ns < w[1].t_ns));
    // Ground truth at every frame (same stamps), camera pose = T_WB T_BS.
    let gt = ds.ground_truth.as_ref().expect("gt");
    assert_eq!(gt.len(), 95);
    assert_eq!(gt[0].t_ns, ds.frames[0].t_ns);
    let body = slam_core::geometry::pose_from_pq(
        [0.878895, 2.1834, 0.948427],
        [0.069433, -0.824237, -0.106942, -0.551702],
    )
    .expect("pose");
    let cam = body * ds.camera.t_bs;
    assert!((gt[0].pose.translation.vector - cam.translation.vector).norm() < 1e-12);
    assert!(gt[0].pose.rotation.angle_to(&cam.rotation) < 1e-7);
    check_frame(
        &ds.frames[0].path,
        752,
        480,
        52_381_130,
        0x1631_0a33_44ec_21c1,
    );
}

#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/euroc_v102_imu_gt (set SHOAL_DATA)"
)]
#[test]
fn euroc_v102_imu_and_gt_without_camera() {
    let data = data_dir("euroc_v102_imu_gt");
    let ds = open(&data.join("euroc_v102_imu_gt")).expect("open");
    assert_eq!(ds.kind, DatasetKind::Euroc);
    assert!(ds.issues.is_empty(), "{:?}", ds.issues);
    assert!(ds.frames.is_empty());
    assert_eq!((ds.camera.model.width, ds.camera.model.height), (0, 0));
    assert_eq!(ds.camera.t_bs, nalgebra::Isometry3::identity());
    assert_eq!(ds.imu.len(), 7999);
    let gt = ds.ground_truth.as_ref().expect("gt");
    assert_eq!(gt.len(), 3340);
    assert_eq!(gt[0].t_ns, 1_403_715_524_922_140_000);
    assert!((gt[0].pose.translation.vector.x - 0.515292).abs() < 1e-12);
    let poses: Vec<_> = gt.iter().map(|p| p.pose).collect();
    let len = path_length(&poses);
    assert!(len > 60.0 && len < 90.0, "V1_02 path {len} m (about 76 m)");
    // Opening the mav0 folder itself works too.
    let ds2 = open(&data.join("euroc_v102_imu_gt/mav0")).expect("open mav0");
    assert_eq!(ds2.imu.len(), 7999);
}

#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/kitti07 (set SHOAL_DATA)"
)]
#[test]
fn kitti07() {
    let data = data_dir("kitti07");
    let ds = open(&data.join("kitti07")).expect("open");
    assert_eq!(ds.kind, DatasetKind::Kitti);
    assert!(ds.issues.is_empty(), "{:?}", ds.issues);
    assert_eq!(ds.frames.len(), 100);
    let m = &ds.camera.model;
    assert_eq!((m.width, m.height), (1226, 370));
    assert_eq!(
        (m.fx, m.fy, m.cx, m.cy),
        (707.0912, 707.0912, 601.8873, 183.1104)
    );
    assert!(m.is_undistorted());
    assert_eq!(ds.camera.readout_ns, 0);
    assert!(ds.imu.is_empty());
    assert_eq!(ds.frames[1].t_ns, 103_875_200);
    assert!((ds.camera.rate_hz - 9.6).abs() < 0.5);
    let gt = ds.ground_truth.as_ref().expect("gt");
    assert_eq!(gt.len(), 100);
    assert_eq!(gt[1].t_ns, ds.frames[1].t_ns);
    let poses: Vec<_> = gt.iter().map(|p| p.pose).collect();
    let len = path_length(&poses);
    assert!((len - 54.4844).abs() < 1e-3, "path length {len}");
    check_frame(
        &ds.frames[0].path,
        1226,
        370,
        40_596_680,
        0x90c2_b7c2_6f4a_32b5,
    );
}

#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/phone_honorv10 (set SHOAL_DATA)"
)]
#[test]
fn phone_honorv10() {
    let data = data_dir("phone_honorv10");
    let ds = open(&data.join("phone_honorv10")).expect("open");
    assert_eq!(ds.kind, DatasetKind::Phone);
    assert!(ds.issues.is_empty(), "{:?}", ds.issues);
    assert_eq!(ds.frames.len(), 25);
    let m = &ds.camera.model;
    assert_eq!((m.width, m.height), (720, 1280));
    assert_eq!((m.fx, m.fy, m.cx, m.cy), (980.4812, 980.4812, 360.0, 640.0));
    assert_eq!(ds.camera.readout_ns, 20_733_000);
    let f0 = &ds.frames[0];
    assert_eq!((f0.readout_ns, f0.exposure_ns), (20_733_000, 10_000_000));
    // SENSOR_TIMESTAMP + exposure/2 + readout/2.
    assert_eq!(f0.t_ns, 28_670_339_410_000 + 5_000_000 + 10_366_500);
    assert!(f0.path.ends_with("frames/0001.png"));
    assert!(ds.frames[24].path.ends_with("frames/0025.png"));
    assert!((ds.camera.rate_hz - 30.0).abs() < 1.0);
    assert_eq!(ds.imu.len(), 81);
    assert_eq!(ds.imu[0].t_ns, 28_670_386_486_113);
    assert!((ds.imu[2].gyro[2] - 8.2030473e-4).abs() < 1e-15);
    assert!(ds.ground_truth.is_none());
    check_frame(&f0.path, 720, 1280, 128_994_821, 0x17ce_8bd6_7b54_adcc);
}

#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/kitti06_frames (set SHOAL_DATA)"
)]
#[test]
fn not_a_dataset_folder() {
    let data = data_dir("kitti06_frames");
    let err = open(&data.join("kitti06_frames")).map(|_| ()).unwrap_err();
    assert!(
        matches!(err, datasets::DatasetError::UnknownFormat { .. }),
        "{err}"
    );
    assert!(err.to_string().contains("kitti06_frames"));
}

/// The EuRoC camera-IMU calibration recording as AprilGrid detections (issue 18): 72 s,
/// 1439 frames, 14,374 IMU samples, every corner line parsed into at most 144 tracks.
#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/euroc_imu_april (set SHOAL_DATA)"
)]
#[test]
fn euroc_imu_april_detections() {
    let ds =
        datasets::april::read(&data_dir("euroc_imu_april").join("euroc_imu_april")).expect("read");
    assert_eq!(ds.frames.len(), 1439);
    assert_eq!(ds.imu.len(), 14_374);
    assert!(
        ds.issues.is_empty(),
        "{:?}",
        &ds.issues[..ds.issues.len().min(3)]
    );
    assert_eq!((ds.camera.width, ds.camera.height), (752, 480));
    let corners: usize = ds.frames.iter().map(|f| f.observations.len()).sum();
    let tracks: std::collections::BTreeSet<_> = ds
        .frames
        .iter()
        .flat_map(|f| f.observations.iter().map(|o| o.track))
        .collect();
    eprintln!("{corners} corners in {} tracks", tracks.len());
    assert!(
        tracks.len() <= 144 && corners > 10_000,
        "{corners} corners, {} tracks",
        tracks.len()
    );
}

/// The GoPro HERO5 clip with its GPMF streams (issue 18): 362 JPEG frames at 29.97 Hz,
/// 854x480, the ~400 Hz gyro with the ~200 Hz accelerometer interpolated to its times,
/// reordered to (right/left, forward/back, up/down): gravity on the third axis.
#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/gopro_karma_rs_imu (set SHOAL_DATA)"
)]
#[test]
fn gopro_karma_clip() {
    let ds = open(&data_dir("gopro_karma_rs_imu").join("gopro_karma_rs_imu")).expect("open");
    assert_eq!(ds.kind, DatasetKind::GoPro);
    assert_eq!(ds.frames.len(), 362);
    assert!(
        ds.issues.is_empty(),
        "{:?}",
        &ds.issues[..ds.issues.len().min(3)]
    );
    assert_eq!((ds.camera.model.width, ds.camera.model.height), (854, 480));
    assert!(
        (ds.camera.rate_hz - 29.97).abs() < 0.01,
        "{}",
        ds.camera.rate_hz
    );
    assert!(
        (4700..=4795).contains(&ds.imu.len()),
        "{} IMU samples",
        ds.imu.len()
    );
    let n = ds.imu.len() as f64;
    let mean: Vec<f64> = (0..3)
        .map(|k| ds.imu.iter().map(|s| s.accel[k]).sum::<f64>() / n)
        .collect();
    eprintln!("mean specific force {mean:.2?} m/s²");
    assert!(
        mean[2] > 8.5 && mean[0].abs() < 2.0 && mean[1].abs() < 5.0,
        "{mean:?}"
    );
    let mut buf = vec![0u8; 854 * 480];
    decode_gray_into(&ds.frames[100].path, &mut buf, 854, 480).expect("decode");
    let mean_px = buf.iter().map(|&b| f64::from(b)).sum::<f64>() / buf.len() as f64;
    assert!((20.0..235.0).contains(&mean_px), "{mean_px}");
}
