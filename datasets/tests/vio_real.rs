//! The visual-inertial client on real data (issue 17): EuRoC V1_01's first 4.7 s, the drone
//! at rest on the floor with its motors running (ignored when `../shared/data` is absent:
//! see `build_support/shoal_data.rs`).

mod common;

use common::data_dir;
use datasets::{decode_gray_into, open};
use nalgebra::Vector3;
use slam_core::features::GrayImage;
use slam_core::imu::{ImuIntrinsics, ImuMeasurement, ImuNoise, PreintegrationParams};
use slam_core::vio::{PoseSource, VioParams, VioTracker};
use slam_core::vo::{VoFrame, VoParams, VoTracker};

/// Ground-truth gyro bias of the excerpt's first row (`b_w_RS_S`, rad/s).
fn true_gyro_bias(root: &std::path::Path) -> Vector3<f64> {
    let csv = root.join("euroc_v101_static/mav0/state_groundtruth_estimate0/data.csv");
    let text = std::fs::read_to_string(csv).expect("ground truth");
    let row: Vec<f64> = text
        .lines()
        .find(|l| !l.starts_with('#'))
        .expect("a row")
        .split(',')
        .map(|v| v.trim().parse().expect("number"))
        .collect();
    Vector3::new(row[11], row[12], row[13])
}

/// The static EuRoC excerpt through the VIO client: the device is found at rest, its gyro
/// bias matches the ground truth's, the gravity direction matches the ground truth's
/// attitude (roll/pitch), no scale is invented (no metric pose), every frame gets an
/// orientation, and the orientations after the static initialisation drift less than the
/// uncorrected gyro bias would make them.
#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/euroc_v101_static (set SHOAL_DATA)"
)]
#[test]
fn euroc_at_rest_gives_gravity_and_gyro_bias() {
    let root = data_dir("euroc_v101_static");
    let ds = open(&root.join("euroc_v101_static")).expect("open");
    let cam = ds.camera.model;
    let preint =
        PreintegrationParams::new(&ImuNoise::default(), &ImuIntrinsics::default()).expect("preint");
    let vo = VoTracker::new(VoParams::default(), cam).expect("vo");
    let mut vio = VioTracker::new(vo, VioParams::new(preint, ds.camera.t_bs));
    let (w, h) = (cam.width, cam.height);
    let mut img = vec![0u8; (w * h) as usize];
    let mut next_imu = 0;
    let mut r_wc = Vec::new();
    for f in &ds.frames {
        while next_imu < ds.imu.len() && ds.imu[next_imu].t_ns <= f.t_ns + 10_000_000 {
            let s = &ds.imu[next_imu];
            let m = ImuMeasurement {
                t_ns: s.t_ns,
                gyro: Vector3::from(s.gyro),
                accel: Vector3::from(s.accel),
            };
            vio.on_imu(m).expect("valid IMU");
            next_imu += 1;
        }
        decode_gray_into(&f.path, &mut img, w, h).expect("decode");
        let frame = VoFrame {
            image: GrayImage::new(&img, w as usize, h as usize, w as usize).expect("image"),
            t_ns: f.t_ns,
            readout_ns: 0,
            angular_velocity: None,
        };
        let o = vio.process(&frame).expect("vio");
        assert!(
            o.nav.is_none() && o.source != PoseSource::VisualInertial,
            "no scale at rest"
        );
        let r = o.r_wc.or(o.t_cw.map(|t| t.rotation.inverse()));
        r_wc.push((f.t_ns, r.expect("an orientation for every frame")));
    }
    let (s, up_w) = vio.static_init().expect("found at rest");
    let truth = true_gyro_bias(&root);
    let err = s.gyro_bias - truth;
    eprintln!(
        "static after {:.2} s: gyro bias {:.5?} (truth {:.5?}, error {:.2e} rad/s), |a| {:.3}, \
         spread gyro {:.3} rad/s accel {:.3} m/s², up in the orientations' world {:?}",
        (s.t1_ns - ds.frames[0].t_ns) as f64 * 1e-9,
        s.gyro_bias.as_slice(),
        truth.as_slice(),
        err.norm(),
        s.accel_norm,
        s.gyro_std,
        s.accel_std,
        up_w.map(|u| u.as_slice().to_vec())
    );
    assert!(err.amax() < 2e-3, "gyro bias error {err:?}");
    // Gravity: the body's "up" against the ground truth's (Vicon z up) at the same time.
    let gt = ds.ground_truth.as_ref().expect("ground truth");
    let k = gt.partition_point(|p| p.t_ns < s.t1_ns).min(gt.len() - 1);
    let r_wb_true = gt[k].pose.rotation * ds.camera.t_bs.rotation.inverse();
    let up_b_true = r_wb_true.inverse() * Vector3::z();
    let tilt = s.up_b.angle(&up_b_true).to_degrees();
    eprintln!("gravity direction vs ground truth: {tilt:.3}°");
    assert!(tilt < 1.0, "gravity {tilt}° off");
    // Orientations from the static initialisation on: the relative rotation over the rest
    // of the clip against the ground truth's (the uncorrected bias would turn it by
    // 0.08 rad/s x the interval).
    let i0 = r_wc.partition_point(|(t, _)| *t < s.t1_ns);
    let (t0, r0) = r_wc[i0];
    let (t1, r1) = *r_wc.last().expect("frames");
    let g = |t: i64| {
        gt[gt.partition_point(|p| p.t_ns < t).min(gt.len() - 1)]
            .pose
            .rotation
    };
    let rel = (r0.inverse() * r1) * (g(t0).inverse() * g(t1)).inverse();
    let drift = rel.angle().to_degrees();
    let uncorrected = (truth.norm() * (t1 - t0) as f64 * 1e-9).to_degrees();
    eprintln!(
        "orientation drift over {:.2} s after it: {drift:.3}° (uncorrected bias: {uncorrected:.2}°)",
        (t1 - t0) as f64 * 1e-9
    );
    assert!(drift < 0.1 * uncorrected, "drift {drift}°");
}
