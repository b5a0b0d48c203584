//! `shoal run --calib FILE` (issue 18): the project's calibration file in place of the
//! dataset's own camera model, camera-IMU pose, t_d, t_r and IMU model, in every service
//! that reads the dataset; a file that cannot be read or does not fit is refused before
//! any service starts, naming the file.
mod common;

use common::*;
use datasets::calibration::CalibrationFile;

/// The `phone` dataset with its true calibration saved to a file, then its own
/// `cam0/sensor.yaml` damaged (focal length 40 px off, t_d 0 instead of 40 ms, t_r 10 ms
/// instead of 25): run with the file, the visual-inertial client is metric and accurate on
/// the ground truth's clock; run without it, the damaged calibration shows.
#[test]
fn a_calibration_file_replaces_the_datasets_own() {
    let tmp = tempdir();
    let ds = synthetic(tmp.path(), "phone", 150, None);
    let dataset = datasets::open(&ds[0]).expect("open");
    let imu_yaml = ds[0].join("mav0/imu0/sensor.yaml");
    let imu = datasets::euroc::read_imu_sensor_yaml(&imu_yaml).expect("imu yaml");
    let calib = tmp.path().join("calib.toml");
    CalibrationFile::from_dataset(&dataset.camera, Some(&imu))
        .write(&calib)
        .expect("write calib");
    let cam_yaml = ds[0].join("mav0/cam0/sensor.yaml");
    let text = std::fs::read_to_string(&cam_yaml).expect("cam yaml");
    let damaged = text
        .replace("intrinsics: [458.654", "intrinsics: [498.654")
        .replace("time_offset_ns: 40000000", "time_offset_ns: 0")
        .replace("readout_time_ns: 25000000", "readout_time_ns: 10000000");
    assert_ne!(damaged, text);
    std::fs::write(&cam_yaml, damaged).expect("damage");

    let run = |name: &str, extra: &[&str]| {
        let out = tmp.path().join(name);
        let mut args = vec!["--lockstep", "--mode", "vio"];
        args.extend_from_slice(extra);
        let res = run_pipeline(&[&ds[0]], &out, name, &args);
        assert!(
            res.status.success(),
            "{}",
            String::from_utf8_lossy(&res.stderr)
        );
        report(&out)["clients"][0].clone()
    };
    let calib_arg = calib.to_str().expect("utf-8 path");
    let with = run("with", &["--calib", calib_arg]);
    let without = run("without", &[]);
    let se3 = |c: &serde_json::Value| c["ate_se3"]["rmse_m"].as_f64().unwrap_or(f64::INFINITY);
    let scale = |c: &serde_json::Value| c["ate"]["scale"].as_f64().unwrap_or(0.0);
    eprintln!(
        "with the file: SE(3) {:.4} m, scale {:.4}, {}; without: SE(3) {:.4} m, scale {:.4}, {}",
        se3(&with),
        scale(&with),
        with["vio"]["status"],
        se3(&without),
        scale(&without),
        without["vio"]["status"]
    );
    assert_eq!(with["vio"]["status"], "initialised", "{}", with["vio"]);
    assert!((scale(&with) - 1.0).abs() < 0.03, "scale {}", scale(&with));
    assert!(se3(&with) < 0.05, "SE(3) ATE {} m", se3(&with));
    assert!(
        se3(&without) > 2.0 * se3(&with),
        "the damaged calibration did not show: {} vs {} m",
        se3(&without),
        se3(&with)
    );
}

/// A calibration file with an impossible value, or for another image size, stops the run
/// before any service starts: a non-zero exit, the file and the reason in the message.
#[test]
fn a_bad_calibration_file_is_refused_before_the_run() {
    let tmp = tempdir();
    let ds = synthetic(tmp.path(), "phone", 5, None);
    let dataset = datasets::open(&ds[0]).expect("open");
    let good = CalibrationFile::from_dataset(&dataset.camera, None);
    let cases = [
        (
            "negative_focal",
            {
                let mut c = good.clone();
                c.camera.intrinsics[0] = -400.0;
                c
            },
            "focal length",
        ),
        (
            "other_size",
            {
                let mut c = good.clone();
                c.camera.resolution = [640, 480];
                c.camera.intrinsics[2] = 320.0;
                c
            },
            "640x480",
        ),
    ];
    for (name, file, reason) in cases {
        let path = tmp.path().join(format!("{name}.toml"));
        // The writer does not check: a file edited by hand can say anything.
        std::fs::write(&path, toml::to_string(&file).expect("toml")).expect("write");
        let out = tmp.path().join(name);
        let res = run_pipeline(
            &[&ds[0]],
            &out,
            name,
            &["--lockstep", "--calib", path.to_str().expect("utf-8")],
        );
        let stderr = String::from_utf8_lossy(&res.stderr);
        assert!(!res.status.success(), "{name}: the run went on");
        assert!(
            stderr.contains(&format!("{name}.toml")) && stderr.contains(reason),
            "{name}: {stderr}"
        );
        assert!(!out.join("status").exists(), "{name}: a service started");
    }
}
