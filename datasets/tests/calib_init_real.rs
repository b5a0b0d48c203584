//! `slam_core::calib::init` on real data (issue 18): the time offset `t_d` and the
//! camera-IMU rotation `R_cb` from the first seconds of IMU and feature tracks, `R_cb` not
//! given.
//! - EuRoC camera-IMU calibration recording as AprilGrid corner tracks
//!   (`../shared/data/euroc_imu_april`), started from intrinsics 8-12 px off and no
//!   distortion; `R_cb` compared with `T_BS` of `euroc_v101_static/mav0/cam0/sensor.yaml`,
//!   `t_d` with 0 (hardware-synchronised).
//! - GoPro HERO5 clip (`../shared/data/gopro_karma_rs_imu`): ORB tracks from the frames,
//!   the generic camera guess (focal 0.7 × width, no distortion); no reference: `t_d` and
//!   `R_cb` are printed, and `R_cb` is checked to lie near an axis permutation (the GPMF axes
//!   are reordered in `datasets::gopro`, the camera is mounted square to them).
use datasets::april;
use nalgebra::{Matrix3, Rotation3, Vector2};
use slam_core::calib::init::{initialize, InitFrame, InitGuess, InitParams, InitResult};
use slam_core::calib::{ImuSample, Observation};
use slam_core::features::tracks::{FeatureTracker, TrackerParams};
use slam_core::features::{GrayImage, OrbExtractor, OrbFeatures, OrbParams};

fn data() -> std::path::PathBuf {
    match std::env::var_os("SHOAL_DATA") {
        Some(d) if !d.is_empty() => std::path::PathBuf::from(d),
        _ => std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"),
    }
}

/// On failure: what the first steps saw.
fn explain(imu: &[ImuSample], frames: &[InitFrame], guess: &InitGuess, params: &InitParams) {
    use slam_core::calib::init::{timing, visual};
    let obs: usize = frames.iter().map(|f| f.observations.len()).sum();
    let rots = visual::visual_rotations(frames, &guess.camera, None, params);
    let raw = timing::GyroTrack::new(imu, &nalgebra::Vector3::zeros());
    let used = timing::covered(&rots, &raw, params.max_shift_s);
    let mean_angle = rots.iter().map(|r| r.r_c.angle()).sum::<f64>() / rots.len().max(1) as f64;
    let mean_inl = rots.iter().map(|r| r.inliers).sum::<usize>() / rots.len().max(1);
    eprintln!(
        "{} frames, {:.0} observations per frame; {} rotations ({} covered), mean angle {:.4} rad, mean inliers {mean_inl}, rms px {:.2}",
        frames.len(),
        obs as f64 / frames.len().max(1) as f64,
        rots.len(),
        used.len(),
        mean_angle,
        rots.iter().map(|r| r.rms_px).sum::<f64>() / rots.len().max(1) as f64
    );
    if let Some((t_d, q)) = timing::coarse_time_offset(&used, &raw, params) {
        eprintln!("coarse t_d {:+.2} ms, {q:?}", t_d * 1e3);
        for t in [t_d] {
            match slam_core::calib::init::fit_rotation(imu, &used, t, params) {
                Ok(f) => eprintln!("R_bc fit: {f:?}"),
                Err(e) => eprintln!("R_bc fit: {e}"),
            }
        }
    }
}

fn report(name: &str, r: &InitResult) {
    let q = &r.t_d_quality;
    eprintln!(
        "{name}: t_d {:+.2} ms (coarse {:+.2} ms, correlation peak {:.3}, second {:.3} at {:+.0} ms, fine rms {:.2} mrad); \
         R_cb 1σ {:.3}°, hand-eye rms {:.2} mrad, {} outliers; {} / {} rotations; |g| {:.3}, b_g {:.4?}, b_a {:.3?}, σθ {:.2}°",
        r.t_d_s * 1e3, q.coarse_s * 1e3, q.peak, q.second_peak, q.second_peak_s * 1e3,
        q.fine_rms_rad * 1e3, r.r_cb_sigma_rad.to_degrees(), r.r_cb_residual_rad * 1e3,
        r.r_cb_outliers, r.rotations_used, r.rotations_found, r.gravity_norm,
        r.biases.gyro.as_slice(), r.biases.accel.as_slice(), r.sigma_theta_rad.to_degrees()
    );
    eprintln!("{name}: R_cb = {:.4}", r.r_cb.matrix());
}

/// The signed permutation (a proper rotation) nearest `r`, and the angle to it.
fn nearest_permutation(r: &Rotation3<f64>) -> (Matrix3<f64>, f64) {
    let m = r.matrix();
    let mut p = Matrix3::zeros();
    for i in 0..3 {
        let j = (0..3)
            .max_by(|&a, &b| m[(i, a)].abs().total_cmp(&m[(i, b)].abs()))
            .expect("3 columns");
        p[(i, j)] = m[(i, j)].signum();
    }
    let angle = Rotation3::from_matrix_unchecked(p.transpose() * m).angle();
    (p, angle)
}

#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/euroc_imu_april and euroc_v101_static (set SHOAL_DATA)"
)]
#[test]
fn euroc_april_init_without_r_cb() {
    let ds = april::read(&data().join("euroc_imu_april")).expect("april");
    let cam =
        datasets::euroc::read_sensor_yaml(&data().join("euroc_v101_static/mav0/cam0/sensor.yaml"))
            .expect("T_BS");
    let r_cb_ref = cam.t_bs.rotation.to_rotation_matrix().inverse();
    let mut start_cam = ds.camera;
    if std::env::var("INIT_POOR_CAMERA").is_ok() {
        start_cam.fx += 10.0;
        start_cam.fy -= 8.0;
        start_cam.cx += 12.0;
        start_cam.cy -= 9.0;
        (start_cam.k1, start_cam.k2, start_cam.p1, start_cam.p2) = (0.0, 0.0, 0.0, 0.0);
    }
    let seconds: f64 = std::env::var("INIT_SECS").map_or(20.0, |v| v.parse().expect("INIT_SECS"));
    let t0 = ds.imu[0].t_ns;
    let end = t0 + (seconds * 1e9) as i64;
    let imu: Vec<ImuSample> = ds
        .imu
        .iter()
        .take_while(|s| s.t_ns <= end + 300_000_000)
        .map(|s| ImuSample {
            t_ns: s.t_ns,
            gyro: s.gyro.into(),
            accel: s.accel.into(),
        })
        .collect();
    let frames: Vec<InitFrame> = ds
        .frames
        .iter()
        .filter(|f| f.t_ns >= t0 + 250_000_000 && f.t_ns <= end)
        .map(|f| InitFrame {
            t_mid_ns: f.t_ns,
            observations: f
                .observations
                .iter()
                .map(|o| Observation {
                    track: o.track,
                    uv: Vector2::new(o.uv[0], o.uv[1]),
                })
                .collect(),
        })
        .collect();
    let guess = InitGuess {
        camera: start_cam,
        t_r: 0.0,
        r_cb: None,
        p_cb: nalgebra::Vector3::zeros(),
    };
    let params = InitParams {
        imu_noise: ds.noise,
        pair_gap: 6,
        ..InitParams::default()
    };
    let t = std::time::Instant::now();
    let r = initialize(&imu, &frames, &guess, &params)
        .inspect_err(|_| explain(&imu, &frames, &guess, &params))
        .expect("initialised");
    let err = (r.r_cb.inverse() * r_cb_ref).angle().to_degrees();
    report("EuRoC AprilGrid", &r);
    eprintln!(
        "EuRoC AprilGrid over {seconds} s ({} frames): R_cb error vs T_BS {err:.3}°, t_d {:+.2} ms (reference 0), {:.1} s",
        frames.len(),
        r.t_d_s * 1e3,
        t.elapsed().as_secs_f64()
    );
    assert!(err < 1.0, "R_cb {err:.3}° from T_BS");
    assert!(r.t_d_s.abs() < 3e-3, "t_d {} s", r.t_d_s);
}

/// ORB tracks of the GoPro frames (no gyro prediction: the identity).
fn gopro_tracks(ds: &datasets::Dataset, until_ns: i64) -> Vec<InitFrame> {
    let cam = ds.camera.model;
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut orb = OrbExtractor::new(
        OrbParams {
            n_features: 1000,
            ..OrbParams::default()
        },
        w,
        h,
    )
    .expect("orb");
    let mut tracker = FeatureTracker::new(TrackerParams::default(), w, h).expect("tracker");
    let (mut feats, mut out, mut frames) =
        (OrbFeatures::with_capacity(1000), Vec::new(), Vec::new());
    for f in ds.frames.iter().take_while(|f| f.t_ns <= until_ns) {
        let (iw, ih, img) = datasets::image_io::decode_gray(&f.path).expect("frame");
        assert_eq!((iw as usize, ih as usize), (w, h));
        orb.extract(
            &GrayImage::from_packed(&img, w, h).expect("img"),
            &mut feats,
        )
        .expect("orb");
        tracker.track(&feats, |uv| uv, &mut out).expect("track");
        frames.push(InitFrame {
            t_mid_ns: f.t_ns,
            observations: out
                .iter()
                .map(|p| Observation {
                    track: p.id,
                    uv: Vector2::new(f64::from(p.uv[0]), f64::from(p.uv[1])),
                })
                .collect(),
        });
    }
    frames
}

#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/gopro_karma_rs_imu (set SHOAL_DATA)"
)]
#[test]
fn gopro_init_without_r_cb() {
    let ds = datasets::gopro::read(&data().join("gopro_karma_rs_imu")).expect("gopro");
    let imu: Vec<ImuSample> = ds
        .imu
        .iter()
        .map(|s| ImuSample {
            t_ns: s.t_ns,
            gyro: s.gyro.into(),
            accel: s.accel.into(),
        })
        .collect();
    let t = std::time::Instant::now();
    let frames = gopro_tracks(&ds, i64::MAX);
    let tracking_s = t.elapsed().as_secs_f64();
    let env = |k: &str, d: f64| std::env::var(k).map_or(d, |v| v.parse().expect(k));
    let guess = InitGuess {
        camera: ds.camera.model,
        t_r: env("INIT_TR", 0.0),
        r_cb: None,
        p_cb: nalgebra::Vector3::zeros(),
    };
    let mut params = InitParams {
        pair_gap: env("INIT_GAP", 10.0) as usize,
        ..InitParams::default()
    };
    params.extrinsic.max_sigma_rad = env("INIT_MAX_SIGMA_DEG", 45.0).to_radians();
    let t = std::time::Instant::now();
    let r = initialize(&imu, &frames, &guess, &params)
        .inspect_err(|_| explain(&imu, &frames, &guess, &params))
        .expect("initialised");
    report("GoPro", &r);
    let (p, angle) = nearest_permutation(&r.r_cb);
    eprintln!(
        "GoPro ({} frames, tracking {tracking_s:.1} s, init {:.1} s): t_d {:+.2} ms; R_cb {:.2}° from the axis permutation {p:.0}",
        frames.len(),
        t.elapsed().as_secs_f64(),
        r.t_d_s * 1e3,
        angle.to_degrees()
    );
    assert!(
        angle.to_degrees() < 15.0,
        "R_cb {:.1}° from an axis permutation",
        angle.to_degrees()
    );
    assert!(r.t_d_quality.peak > r.t_d_quality.second_peak);
}

/// The online path on the GoPro clip, as `shoal calibrate` runs it (`tracker.calib.init =
/// auto`, `init_seconds = 8`, the generic camera, `R_cb` unknown): the camera is
/// gimbal-stabilised and turns only after 11.5 s (one yaw turn), so the try at 8 s finds no
/// time offset and the initialisation waits; the try at the end of the clip finds `t_d`
/// near the offline −11 ms and an `R_cb` observable about the turn's axis only, snapped to
/// the nearest axis permutation, the one of the offline fit (`gopro_init_without_r_cb`,
/// 10.5° away). Then every frame after the first is updated. Measured: 3 tries, 346 of 359
/// rotations used, t_d −11.3 ms, fit 1σ 43°, 13.7° from the permutation; 361 frames updated.
#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/gopro_karma_rs_imu (set SHOAL_DATA)"
)]
#[test]
fn gopro_online_init_waits_for_the_turn() {
    use slam_core::calib::online::{OnlineCalibrator, OnlineParams, OnlineStart, StartKind};
    let ds = datasets::gopro::read(&data().join("gopro_karma_rs_imu")).expect("gopro");
    let cam = ds.camera.model;
    let start = OnlineStart {
        camera: cam,
        t_bs: ds.camera.t_bs,
        t_r_s: 0.0,
        imu: Default::default(),
        biases: Default::default(),
        r_cb_given: false,
    };
    let params = OnlineParams {
        init_seconds: Some(8.0),
        ..OnlineParams::default()
    };
    let mut cal = OnlineCalibrator::new(params, start);
    let (w, h) = (cam.width as usize, cam.height as usize);
    let (mut k_imu, mut updated, mut tries_at_8s) = (0, 0, None);
    for (k, f) in ds.frames.iter().enumerate() {
        while ds
            .imu
            .get(k_imu)
            .is_some_and(|s| s.t_ns <= f.t_ns + 300_000_000)
        {
            let s = &ds.imu[k_imu];
            cal.push_imu(ImuSample {
                t_ns: s.t_ns,
                gyro: s.gyro.into(),
                accel: s.accel.into(),
            });
            k_imu += 1;
        }
        let (_, _, img) = datasets::image_io::decode_gray(&f.path).expect("frame");
        let image = GrayImage::from_packed(&img, w, h).expect("img");
        updated += cal
            .add_image(k as u64, f.t_ns, &image)
            .expect("track")
            .len();
        if f.t_ns >= ds.frames[0].t_ns + 9_000_000_000 && tries_at_8s.is_none() {
            tries_at_8s = Some((cal.init_tries, cal.init_last_error.clone()));
        }
    }
    updated += cal.flush().len();
    let (tries, err) = tries_at_8s.expect("9 s of frames");
    eprintln!("by 9 s: {tries} tries, {err:?}");
    assert!(tries >= 1, "tried at 8 s");
    assert!(
        matches!(
            err,
            Some(slam_core::calib::init::InitError::NoTimeOffset { .. })
        ),
        "no turn before 9 s: {err:?}"
    );
    let init = cal.init_result.clone().expect("ran").expect("initialised");
    report("GoPro online", &init);
    let (snap_sigma, snap_angle) = init.r_cb_snap.expect("R_cb snapped");
    eprintln!(
        "GoPro online: {} tries, fit 1σ {:.1}°, {:.1}° from the permutation; {updated} updated",
        cal.init_tries,
        snap_sigma.to_degrees(),
        snap_angle.to_degrees()
    );
    assert_eq!(cal.start_kind(), Some(StartKind::Initialised));
    assert!(
        init.rotations_used >= 300,
        "{} rotations",
        init.rotations_used
    );
    assert!((init.t_d_s + 0.011).abs() < 0.005, "t_d {} s", init.t_d_s);
    let offline = Matrix3::new(-1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, -1.0, 0.0);
    assert!(
        (init.r_cb.matrix() - offline).abs().max() < 1e-9,
        "R_cb {:.3}",
        init.r_cb.matrix()
    );
    assert!(updated + 1 >= ds.frames.len(), "{updated} updated");
}
