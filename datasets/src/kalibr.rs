//! Kalibr's calibration layout (issue 18): `camchain-imucam.yaml` read (a `--init` file) and
//! written, `imu.yaml` written, beside the project's own file ([`crate::calibration`]).
//!
//! **Time** (`VI_NOTES.md` §1 table). Kalibr's rolling-shutter model stamps the **first**
//! row: row v is taken at `t_cam + timeshift_cam_imu + v · line_delay` on the IMU clock. The
//! project's file keeps the **middle-row** `t_d` and the whole readout `t_r` for the
//! dataset's own stamps, so `timeshift_cam_imu = t_d − t_r/2` and `line_delay = t_r / rows`
//! (and back: `t_r = line_delay · rows`, `t_d = timeshift_cam_imu + t_r/2`). A global-shutter
//! camera (`t_r = 0`) has `timeshift_cam_imu = t_d` and no `line_delay` written. Kalibr's
//! model reads rows top to bottom only: a camera of another `readout_direction` is written
//! like a global-shutter fit of a rolling-shutter camera, `timeshift_cam_imu = t_d` (the
//! middle line's) and no `line_delay` ([`camera_of`]; `shoal calibrate` says so).
//!
//! **Pose.** `T_cam_imu` maps IMU-frame points into the camera (`T_c_i`): the inverse of
//! EuRoC's `T_BS`, the camera's pose in the body frame that the project's file holds.
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::calibration::{isometry, rows4, write_atomically, CalibrationFile};
use crate::DatasetError;

/// One camera of a `camchain-imucam.yaml` (the keys this project reads and writes; others
/// that Kalibr writes, such as `cam_overlaps`, are ignored when read).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct KalibrCamera {
    /// `pinhole` (the only projection read).
    pub camera_model: String,
    /// `[fu, fv, pu, pv]`, pixels.
    pub intrinsics: Vec<f64>,
    /// `radtan` (the only distortion read).
    pub distortion_model: String,
    /// `[k1, k2, r1, r2]`.
    pub distortion_coeffs: Vec<f64>,
    /// IMU to camera, `T_c_i`, rows (absent in a camera-only `camchain.yaml`).
    #[serde(rename = "T_cam_imu", default, skip_serializing_if = "Option::is_none")]
    pub t_cam_imu: Option<Vec<Vec<f64>>>,
    /// `t_imu = t_cam + shift` for the first row, s.
    #[serde(default)]
    pub timeshift_cam_imu: f64,
    /// Time between two rows, s (rolling shutter).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub line_delay: Option<f64>,
    /// `[width, height]`.
    pub resolution: Vec<u32>,
    /// The image topic.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rostopic: Option<String>,
}

/// A `camchain-imucam.yaml` with its `cam0`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Camchain {
    cam0: KalibrCamera,
}

/// The IMU of Kalibr's `imu.yaml` (`imu0:`), with the seed's IMU model under `shoal_*`
/// keys (Kalibr's own scale-misalignment matrices are parametrised differently).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct KalibrImu {
    accelerometer_noise_density: f64,
    accelerometer_random_walk: f64,
    gyroscope_noise_density: f64,
    gyroscope_random_walk: f64,
    model: String,
    rostopic: String,
    time_offset: f64,
    update_rate: f64,
    shoal_t_g: Vec<Vec<f64>>,
    shoal_t_s: Vec<Vec<f64>>,
    shoal_t_a: Vec<Vec<f64>>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct ImuChain {
    imu0: KalibrImu,
}

fn nested<const N: usize>(rows: &[[f64; N]; N]) -> Vec<Vec<f64>> {
    rows.iter().map(|r| r.to_vec()).collect()
}

/// `cam0` of a calibration in Kalibr's layout (module docs).
pub fn camera_of(c: &CalibrationFile) -> KalibrCamera {
    let cam = &c.camera;
    let rows = cam.resolution[1] as f64;
    let rows_down =
        cam.readout_direction() == Ok(slam_core::rolling_shutter::ReadoutDirection::TopToBottom);
    let t_r = if rows_down { cam.readout_ns } else { 0.0 };
    let t_bs = isometry(&cam.t_bs).unwrap_or_else(|_| nalgebra::Isometry3::identity());
    KalibrCamera {
        camera_model: "pinhole".into(),
        intrinsics: cam.intrinsics.to_vec(),
        distortion_model: "radtan".into(),
        distortion_coeffs: cam.distortion.to_vec(),
        t_cam_imu: Some(nested(&rows4(&t_bs.inverse()))),
        timeshift_cam_imu: (cam.time_offset_ns - t_r / 2.0) * 1e-9,
        line_delay: (t_r > 0.0).then(|| t_r * 1e-9 / rows),
        resolution: cam.resolution.to_vec(),
        rostopic: Some("/cam0/image_raw".into()),
    }
}

/// Writes `dir/camchain-imucam.yaml` and `dir/imu.yaml` (module docs).
pub fn write(c: &CalibrationFile, dir: &Path) -> Result<(), DatasetError> {
    let ser = |e: serde_saphyr::SerializeError| DatasetError::InvalidConfig {
        detail: format!("Kalibr YAML not serialisable: {e}"),
    };
    let chain = Camchain { cam0: camera_of(c) };
    let text = serde_saphyr::to_string(&chain).map_err(ser)?;
    write_atomically(&dir.join("camchain-imucam.yaml"), &text)?;
    let i = &c.imu;
    let imu = ImuChain {
        imu0: KalibrImu {
            accelerometer_noise_density: i.accelerometer_noise_density,
            accelerometer_random_walk: i.accelerometer_random_walk,
            gyroscope_noise_density: i.gyroscope_noise_density,
            gyroscope_random_walk: i.gyroscope_random_walk,
            model: "calibrated".into(),
            rostopic: "/imu0".into(),
            time_offset: 0.0,
            update_rate: i.rate_hz,
            shoal_t_g: nested(&i.t_g),
            shoal_t_s: nested(&i.t_s),
            shoal_t_a: nested(&i.t_a),
        },
    };
    let text = serde_saphyr::to_string(&imu).map_err(ser)?;
    write_atomically(&dir.join("imu.yaml"), &text)
}

/// Reads `cam0` of a Kalibr `camchain-imucam.yaml` (or `camchain.yaml`) into `base`: its
/// intrinsics, distortion, resolution, and when given `T_cam_imu`, the time shift and the
/// line delay (module docs). Other projections or distortion models, wrong sizes and a
/// non-rigid transform are errors naming the file.
pub fn read_camchain_into(path: &Path, base: &mut CalibrationFile) -> Result<(), DatasetError> {
    let text = crate::text::read_text(path, "Kalibr camchain")?;
    let bad = |detail: String| DatasetError::Parse {
        path: path.to_path_buf(),
        line: 0,
        detail,
    };
    let chain: Camchain =
        serde_saphyr::from_str(&text).map_err(|e| bad(format!("invalid camchain YAML: {e}")))?;
    let k = chain.cam0;
    if k.camera_model != "pinhole" || k.distortion_model != "radtan" {
        return Err(bad(format!(
            "cam0 is {}/{}: only pinhole/radtan is read",
            k.camera_model, k.distortion_model
        )));
    }
    let (Ok(intr), Ok(dist), Ok(res)) = (
        <[f64; 4]>::try_from(k.intrinsics.as_slice()),
        <[f64; 4]>::try_from(k.distortion_coeffs.as_slice()),
        <[u32; 2]>::try_from(k.resolution.as_slice()),
    ) else {
        return Err(bad(
            "cam0: intrinsics, distortion_coeffs or resolution of the wrong size".into(),
        ));
    };
    let cam = &mut base.camera;
    (cam.intrinsics, cam.distortion, cam.resolution) = (intr, dist, res);
    if let Some(t) = k.t_cam_imu {
        let rows: Vec<[f64; 4]> = t
            .iter()
            .filter_map(|r| <[f64; 4]>::try_from(r.as_slice()).ok())
            .collect();
        let m = <[[f64; 4]; 4]>::try_from(rows.as_slice())
            .map_err(|_| bad("cam0.T_cam_imu is not 4x4".into()))?;
        let t_ci = isometry(&m).map_err(|e| bad(format!("cam0.T_cam_imu: {e}")))?;
        cam.t_bs = rows4(&t_ci.inverse());
    }
    cam.readout_ns = k.line_delay.unwrap_or(0.0) * res[1] as f64 * 1e9;
    cam.time_offset_ns = k.timeshift_cam_imu * 1e9 + cam.readout_ns / 2.0;
    base.validate().map_err(bad)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{Scenario, SimParams};

    /// The phone scenario's calibration written in Kalibr's layout and read back gives the
    /// same camera, pose and timing (first-row shift and line delay converted both ways).
    #[test]
    fn kalibr_layout_round_trip() {
        let dir = tempfile::tempdir().expect("tmp");
        let mut p = SimParams::new(Scenario::Phone);
        p.frames = Some(3);
        crate::sim::generate(&p, dir.path()).expect("write");
        let ds = crate::open(dir.path()).expect("open");
        let file = CalibrationFile::from_dataset(&ds.camera, None);
        write(&file, dir.path()).expect("kalibr");
        let text = std::fs::read_to_string(dir.path().join("camchain-imucam.yaml")).expect("r");
        let k = camera_of(&file);
        // t_d 40 ms, t_r 25 ms: the first row is 27.5 ms after the stamp on the IMU clock.
        assert!((k.timeshift_cam_imu - 0.0275).abs() < 1e-12, "{text}");
        assert!((k.line_delay.expect("rs") - 0.025 / 480.0).abs() < 1e-15);
        let mut back = CalibrationFile::from_dataset(&crate::euroc::no_camera_calib(), None);
        read_camchain_into(&dir.path().join("camchain-imucam.yaml"), &mut back).expect("read");
        let (a, b) = (&file.camera, &back.camera);
        assert_eq!(
            (a.intrinsics, a.distortion, a.resolution),
            (b.intrinsics, b.distortion, b.resolution)
        );
        assert!((a.time_offset_ns - b.time_offset_ns).abs() < 1e-3);
        assert!((a.readout_ns - b.readout_ns).abs() < 1e-3);
        let d = isometry(&a.t_bs).expect("a").inverse() * isometry(&b.t_bs).expect("b");
        assert!(d.translation.vector.norm() < 1e-9 && d.rotation.angle() < 1e-9);
        let imu = std::fs::read_to_string(dir.path().join("imu.yaml")).expect("imu");
        assert!(
            imu.contains("imu0:") && imu.contains("gyroscope_noise_density"),
            "{imu}"
        );
        // Read along x: Kalibr's rows cannot say it, so the middle line's t_d and no delay.
        let mut cols = file.clone();
        cols.camera.readout_direction = Some("right-to-left".into());
        let k = camera_of(&cols);
        assert!((k.timeshift_cam_imu - 0.040).abs() < 1e-12 && k.line_delay.is_none());
    }

    /// Kalibr's own example (the EuRoC camchain of its wiki, global shutter): read as is.
    #[test]
    fn kalibrs_example_is_read() {
        let dir = tempfile::tempdir().expect("tmp");
        let path = dir.path().join("camchain-imucam.yaml");
        std::fs::write(
            &path,
            "cam0:\n  camera_model: pinhole\n  intrinsics: [461.629, 460.152, 362.680, 246.049]\n  \
             distortion_model: radtan\n  distortion_coeffs: [-0.27695497, 0.06712482, 0.00087538, 0.00011556]\n  \
             T_cam_imu:\n  - [0.01779318, 0.99967549,-0.01822936, 0.07008565]\n  \
             - [-0.9998017, 0.01795239, 0.00860714,-0.01771023]\n  \
             - [0.00893160, 0.01807260, 0.99979678, 0.00399246]\n  - [0.0, 0.0, 0.0, 1.0]\n  \
             timeshift_cam_imu: -8.121e-05\n  rostopic: /cam0/image_raw\n  resolution: [752, 480]\n  \
             cam_overlaps: []\n",
        )
        .expect("write");
        let mut c = CalibrationFile::from_dataset(&crate::euroc::no_camera_calib(), None);
        read_camchain_into(&path, &mut c).expect("read");
        assert_eq!(c.camera.resolution, [752, 480]);
        assert!((c.camera.time_offset_ns + 81_210.0).abs() < 1e-6);
        assert_eq!(c.camera.readout_ns, 0.0);
        std::fs::write(&path, "cam0:\n  camera_model: omni\n").expect("write");
        let e = read_camchain_into(&path, &mut c)
            .expect_err("omni")
            .to_string();
        assert!(e.contains("camchain-imucam.yaml"), "{e}");
    }
}
