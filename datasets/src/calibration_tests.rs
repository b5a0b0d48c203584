use super::*;
use crate::sim::{Scenario, SimParams};

/// The `phone` scenario's dataset (rolling shutter, t_d, IMU intrinsics), 5 frames.
fn phone_dataset(dir: &Path) -> crate::Dataset {
    let mut p = SimParams::new(Scenario::Phone);
    p.frames = Some(5);
    crate::sim::generate(&p, dir).expect("write");
    crate::open(dir).expect("open")
}

fn phone_file(ds: &crate::Dataset) -> CalibrationFile {
    let imu = crate::euroc::read_imu_sensor_yaml(&ds.root.join("mav0/imu0/sensor.yaml"))
        .expect("imu yaml");
    CalibrationFile::from_dataset(&ds.camera, Some(&imu))
}

/// A dataset's calibration written and read back is the same, and gives the same camera
/// and IMU calibration as the dataset's own files.
#[test]
fn a_written_file_reads_back_the_same() {
    let dir = tempfile::tempdir().expect("tmp");
    let ds = phone_dataset(&dir.path().join("ds"));
    let mut file = phone_file(&ds);
    file.sigma = Some(SigmaSection {
        time_offset_ns: Some(120.0),
        not_converged: vec!["t_s".into()],
        ..Default::default()
    });
    let path = dir.path().join("calib.toml");
    file.write(&path).expect("write");
    let back = CalibrationFile::read(&path).expect("read");
    assert_eq!(back, file);
    let cam = back.camera_calib();
    assert_eq!(cam.model, ds.camera.model);
    assert_eq!(cam.readout_ns, 25_000_000);
    assert_eq!(cam.time_offset_ns, 40_000_000);
    let d = cam.t_bs.inverse() * ds.camera.t_bs;
    assert!(d.translation.vector.norm() < 1e-12 && d.rotation.angle() < 1e-9);
    let imu = back.imu_calib();
    assert!((imu.intrinsics.expect("T").t_g[(0, 0)] - 1.01).abs() < 1e-12);
    assert!((imu.initial_biases.expect("b").accel.z - 0.12).abs() < 1e-12);
}

/// Applying a calibration moves every frame by the change of t_d, sets t_r on every frame,
/// and replaces the camera; another resolution or a readout beyond the frame period is
/// refused.
#[test]
fn applying_a_calibration_restamps_the_frames() {
    let dir = tempfile::tempdir().expect("tmp");
    let mut ds = phone_dataset(dir.path());
    let t0: Vec<i64> = ds.frames.iter().map(|f| f.t_ns).collect();
    let mut file = phone_file(&ds);
    file.camera.time_offset_ns = 55e6;
    file.camera.readout_ns = 20e6;
    file.camera.intrinsics[0] += 3.0;
    file.apply_to(&mut ds).expect("applied");
    for (f, t) in ds.frames.iter().zip(&t0) {
        assert_eq!(f.t_ns - t, 15_000_000);
        assert_eq!(f.readout_ns, 20_000_000);
    }
    assert_eq!(ds.camera.time_offset_ns, 55_000_000);
    assert!((ds.camera.model.fx - 461.654).abs() < 1e-9);
    let mut wide = file.clone();
    wide.camera.resolution = [640, 480];
    assert!(wide.apply_to(&mut ds).unwrap_err().contains("640x480"));
    let mut slow = file.clone();
    (slow.camera.rate_hz, slow.camera.readout_ns) = (0.0, 40e6);
    let e = slow.apply_to(&mut ds).unwrap_err();
    assert!(e.contains("frame period"), "{e}");
}

/// Unknown keys, impossible values and another version are refused with a message naming
/// the key (and the line, for a TOML error).
#[test]
fn bad_files_are_refused_with_the_reason() {
    let dir = tempfile::tempdir().expect("tmp");
    let ds = phone_dataset(&dir.path().join("ds"));
    let good = toml::to_string(&phone_file(&ds)).expect("toml");
    let cases: [(&str, String, &str); 6] = [
        (
            "unknown key",
            good.replace("[camera]\n", "[camera]\nfocal = 3\n"),
            ":5: unknown field `focal`",
        ),
        (
            "negative focal",
            good.replace("intrinsics = [458.654", "intrinsics = [-458.654"),
            "focal length",
        ),
        (
            "readout beyond the frame",
            good.replace("readout_ns = 25000000.0", "readout_ns = 40000000.0"),
            "frame period",
        ),
        (
            "version",
            good.replace("version = 1", "version = 7"),
            "version 7",
        ),
        (
            "not rigid",
            good.replace("t_bs = [[0.0148", "t_bs = [[1.5148"),
            "camera.t_bs",
        ),
        (
            "model",
            good.replace("\"pinhole-radtan\"", "\"fisheye\""),
            "fisheye",
        ),
    ];
    for (what, text, expected) in cases {
        assert_ne!(text, good, "{what}: the case did not change the file");
        let path = dir.path().join("bad.toml");
        std::fs::write(&path, &text).expect("write");
        let e = CalibrationFile::read(&path).expect_err(what).to_string();
        assert!(
            e.contains("bad.toml") && e.contains(expected),
            "{what}: {e}"
        );
    }
    let e = CalibrationFile::read(&dir.path().join("none.toml")).expect_err("missing");
    assert!(e.to_string().contains("not found"), "{e}");
}

/// `camera.readout_direction` reads back onto the camera model (top to bottom when
/// absent, not written then); an unknown direction is refused, naming the known ones.
#[test]
fn the_readout_direction_is_kept_and_checked() {
    let dir = tempfile::tempdir().expect("tmp");
    let ds = phone_dataset(&dir.path().join("ds"));
    let mut file = phone_file(&ds);
    assert_eq!(file.camera.readout_direction, None);
    assert_eq!(
        file.camera_calib().model.readout,
        ReadoutDirection::TopToBottom
    );
    let path = dir.path().join("calib.toml");
    file.write(&path).expect("write");
    let text = std::fs::read_to_string(&path).expect("text");
    assert!(!text.contains("readout_direction"), "{text}");
    file.camera.readout_direction = Some("right-to-left".into());
    file.write(&path).expect("write");
    let back = CalibrationFile::read(&path).expect("read");
    let cam = back.camera_calib();
    assert_eq!(cam.model.readout, ReadoutDirection::RightToLeft);
    assert_eq!(
        CalibrationFile::from_dataset(&cam, None)
            .camera
            .readout_direction,
        Some("right-to-left".into())
    );
    let bad = text.replace("readout_ns", "readout_direction = \"diagonal\"\nreadout_ns");
    std::fs::write(&path, bad).expect("write");
    let err = CalibrationFile::read(&path)
        .expect_err("refused")
        .to_string();
    assert!(
        err.contains("diagonal") && err.contains("right-to-left"),
        "{err}"
    );
}
