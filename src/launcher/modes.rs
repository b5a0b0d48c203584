//! What each client runs (`shoal run --mode`, `tracker.mode`): monocular or
//! visual-inertial, decided per client from its dataset, with the reason the report gives,
//! and the IMU calibration the visual-inertial client is configured with (the calibration
//! file of `shoal run --calib`, else the dataset's `imu0/sensor.yaml`).
use std::path::{Path, PathBuf};

use tracker::{ClientMode, ImuCalibConfig};

/// One client's mode, why, and its IMU calibration.
#[derive(Debug, Clone, PartialEq)]
pub struct ClientSetup {
    /// `Mono` or `Vio` (never `Auto`).
    pub mode: ClientMode,
    /// Why, in words (the report's `mode_reason`).
    pub reason: String,
    /// The IMU calibration written into the tracker's configuration.
    pub imu: ImuCalibConfig,
    /// A calibration file that was there and could not be read (`file: why`).
    pub calibration_error: Option<String>,
    /// The camera's rolling-shutter line order (the dataset's, or the calibration file's).
    pub readout: slam_core::rolling_shutter::ReadoutDirection,
}

/// The `imu0/sensor.yaml` of a EuRoC-layout dataset at `root` (or its `mav0`), if any.
fn imu_sensor_yaml(root: &Path) -> Option<PathBuf> {
    [
        root.join("mav0/imu0/sensor.yaml"),
        root.join("imu0/sensor.yaml"),
    ]
    .into_iter()
    .find(|p| p.is_file())
}

/// The dataset's own IMU calibration and the file it is in: the noise of an AprilGrid
/// recording's `config.yaml`, else its `imu0/sensor.yaml`; `None` when it has neither.
pub fn dataset_imu(
    ds: &datasets::Dataset,
) -> Option<Result<(datasets::euroc::ImuSensorCalib, PathBuf), datasets::DatasetError>> {
    if let Some(y) = ds.imu_calib {
        return Some(Ok((y, ds.root.clone())));
    }
    if ds.kind == datasets::DatasetKind::AprilTracks {
        let noise = datasets::april::read_noise(&ds.root);
        return Some(noise.map(|noise| {
            let y = datasets::euroc::ImuSensorCalib {
                rate_hz: 0.0,
                noise,
                intrinsics: None,
                initial_biases: None,
                time_offset_ns: None,
                readout_ns: None,
            };
            (y, ds.root.join("config.yaml"))
        }));
    }
    let path = imu_sensor_yaml(&ds.root)?;
    Some(datasets::euroc::read_imu_sensor_yaml(&path).map(|y| (y, path)))
}

/// The IMU calibration of `ds`: the calibration file `calib` when given (the launcher
/// has read it already), else its `imu0/sensor.yaml` when it has one (noise, and the IMU
/// intrinsics when given), else EuRoC's defaults; `extrinsics_given` from its camera.
fn imu_calibration(
    ds: &datasets::Dataset,
    calib: Option<&Path>,
) -> (ImuCalibConfig, Option<String>) {
    let mut c = ImuCalibConfig {
        extrinsics_given: ds.camera.t_bs_given,
        ..ImuCalibConfig::default()
    };
    let (y, path) = if let Some(file) = calib {
        match datasets::calibration::CalibrationFile::read(file) {
            Ok(f) => (f.imu_calib(), file.to_path_buf()),
            Err(e) => return (c, Some(e.to_string())),
        }
    } else {
        match dataset_imu(ds) {
            None => return (c, None),
            Some(Ok(y)) => y,
            Some(Err(e)) => return (c, Some(e.to_string())),
        }
    };
    c.gyroscope_noise_density = y.noise.gyro_noise_density;
    c.accelerometer_noise_density = y.noise.accel_noise_density;
    c.gyroscope_random_walk = y.noise.gyro_bias_rw;
    c.accelerometer_random_walk = y.noise.accel_bias_rw;
    if let Some(k) = y.intrinsics {
        let rows = |m: &nalgebra::Matrix3<f64>| {
            let mut a = [0.0; 9];
            for (i, v) in a.iter_mut().enumerate() {
                *v = m[(i / 3, i % 3)];
            }
            a
        };
        (c.t_g, c.t_s, c.t_a) = (rows(&k.t_g), rows(&k.t_s), rows(&k.t_a));
    }
    c.source = path.display().to_string();
    (c, None)
}

/// The mode of a client asked to run `requested` on `ds`, and why.
/// `calib`: the run's calibration file of this client, already applied to `ds`.
pub fn client_setup(
    requested: ClientMode,
    ds: &datasets::Dataset,
    calib: Option<&Path>,
) -> ClientSetup {
    let (imu, calibration_error) = imu_calibration(ds, calib);
    let has_imu = !ds.imu.is_empty();
    let missing = match (has_imu, ds.camera.t_bs_given) {
        (false, _) => Some("the dataset has no IMU stream"),
        (true, false) => Some("the dataset gives no camera-IMU extrinsics (T_BS)"),
        (true, true) => None,
    };
    let (mode, reason) = match (requested, missing) {
        (ClientMode::Calib, _) if !has_imu => (
            ClientMode::Calib,
            "asked (--mode calib), but the dataset has no IMU stream: nothing to calibrate \
             against"
                .to_string(),
        ),
        (ClientMode::Calib, _) => (ClientMode::Calib, "asked (--mode calib)".to_string()),
        (ClientMode::Mono, _) => (ClientMode::Mono, "asked (--mode mono)".to_string()),
        (ClientMode::Vio, None) => (ClientMode::Vio, "asked (--mode vio)".to_string()),
        (ClientMode::Vio, Some(why)) => (
            ClientMode::Vio,
            format!("asked (--mode vio), but {why}: it will not initialise inertially"),
        ),
        (ClientMode::Auto, None) => (
            ClientMode::Vio,
            "the dataset has an IMU stream and camera-IMU extrinsics".to_string(),
        ),
        (ClientMode::Auto, Some(why)) if has_imu => (
            ClientMode::Vio,
            format!(
                "{why}: visual-inertial client without inertial initialisation (monocular \
                 poses, gyro orientations for the frames vision does not pose)"
            ),
        ),
        (ClientMode::Auto, Some(why)) => (ClientMode::Mono, why.to_string()),
    };
    ClientSetup {
        mode,
        reason,
        imu,
        calibration_error,
        readout: ds.camera.model.readout,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use datasets::sim::{Scenario, SimParams};

    fn sim_dataset(dir: &Path, scenario: Scenario) -> datasets::Dataset {
        let mut p = SimParams::new(scenario);
        p.frames = Some(3);
        datasets::sim::generate(&p, dir).expect("write");
        datasets::open(dir).expect("open")
    }

    /// `auto` picks `vio` on a synthetic dataset (IMU and T_BS), with its sensor.yaml's
    /// noise and intrinsics; `mono` when asked; without extrinsics `vio` with no inertial
    /// initialisation, and the reason; `mono` without an IMU.
    #[test]
    fn auto_mode_follows_the_dataset() {
        let dir = tempfile::tempdir().expect("tmp");
        let mut ds = sim_dataset(dir.path(), Scenario::Phone);
        let s = client_setup(ClientMode::Auto, &ds, None);
        assert_eq!(s.mode, ClientMode::Vio, "{}", s.reason);
        assert!(s.imu.extrinsics_given && s.calibration_error.is_none());
        assert!(s.imu.source.ends_with("sensor.yaml"), "{}", s.imu.source);
        assert_ne!(s.imu.t_a, ImuCalibConfig::default().t_a, "phone T_a read");
        assert!(s.imu.preintegration().is_ok());
        assert_eq!(
            client_setup(ClientMode::Mono, &ds, None).mode,
            ClientMode::Mono
        );
        ds.camera.t_bs_given = false;
        let s = client_setup(ClientMode::Auto, &ds, None);
        assert_eq!(s.mode, ClientMode::Vio);
        assert!(
            s.reason.contains("without inertial initialisation"),
            "{}",
            s.reason
        );
        let s = client_setup(ClientMode::Vio, &ds, None);
        assert_eq!(s.mode, ClientMode::Vio);
        assert!(s.reason.contains("will not initialise"), "{}", s.reason);
        ds.imu.clear();
        let s = client_setup(ClientMode::Auto, &ds, None);
        assert_eq!(s.mode, ClientMode::Mono);
        assert!(s.reason.contains("no IMU"), "{}", s.reason);
    }

    /// A broken sensor.yaml is reported, and the defaults are used.
    #[test]
    fn broken_calibration_is_reported() {
        let dir = tempfile::tempdir().expect("tmp");
        let ds = sim_dataset(dir.path(), Scenario::Drone);
        let yaml = imu_sensor_yaml(dir.path()).expect("sensor.yaml");
        std::fs::write(&yaml, "gyroscope_noise_density: -1\n").expect("write");
        let s = client_setup(ClientMode::Auto, &ds, None);
        assert!(s.calibration_error.is_some());
        assert_eq!(s.imu.source, "default");
    }
}
