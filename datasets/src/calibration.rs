//! The project's calibration file (issue 18): what `shoal calibrate` writes and `shoal run
//! --calib FILE` reads. TOML, versioned, every key known (`deny_unknown_fields`), values
//! checked before anything runs. Conventions of `VI_NOTES.md` §0-2:
//!
//! - `camera.t_bs`: the camera's pose in the body (IMU) frame, EuRoC's `T_BS`
//!   (`x_B = T_BS x_S`), row-major 4x4; the lever arm of the seed is `p_cb = -R_BSᵀ t_BS`.
//! - `camera.time_offset_ns`: `t_d` for **middle-row** stamps (`t_imu = t_mid + t_d`);
//!   `camera.readout_ns`: `t_r`, the whole frame's readout (0 = global shutter). Kalibr's
//!   layout stamps the first row instead ([`crate::kalibr`]).
//! - `camera.readout_direction` (optional): the order the rolling shutter reads the lines,
//!   `"top-to-bottom"` (the default), `"bottom-to-top"`, `"left-to-right"` or
//!   `"right-to-left"` (a phone's portrait frames are read along x; `VI_NOTES.md` §1).
//! - `imu`: the Kalibr noise densities and the seed's IMU model (eq. 2.53-2.56)
//!   `a_m = T_a a_s + b_a`, `ω_m = T_g ω + T_s a_s + b_g`, matrices row-major.
//! - `sigma` (optional): the estimate's 1σ, and the parameters a calibration run could not
//!   determine (their σ did not shrink), which are then not estimates but the starting values.
use std::path::Path;

use nalgebra::{Isometry3, Matrix3, Matrix4, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use slam_core::imu::{ImuBiases, ImuIntrinsics, ImuNoise};
use slam_core::rolling_shutter::ReadoutDirection;

use crate::euroc::ImuSensorCalib;
use crate::{CameraCalib, DatasetError, PinholeRadtan};

/// The `format` key of every calibration file.
pub const FORMAT: &str = "shoal-calibration";
/// The version this build reads and writes.
pub const VERSION: u32 = 1;

/// A calibration file (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationFile {
    /// Always [`FORMAT`].
    pub format: String,
    /// [`VERSION`].
    pub version: u32,
    /// What produced it (free text).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub comment: Option<String>,
    /// The camera and its pose and timing against the IMU.
    pub camera: CameraSection,
    /// The IMU.
    pub imu: ImuSection,
    /// The estimate's 1σ, when the file is an estimate.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma: Option<SigmaSection>,
}

/// `[camera]` of a [`CalibrationFile`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSection {
    /// Projection and distortion model.
    pub model: CameraModel,
    /// `[width, height]`, pixels.
    pub resolution: [u32; 2],
    /// `[fx, fy, cx, cy]`, pixels.
    pub intrinsics: [f64; 4],
    /// `[k1, k2, p1, p2]`.
    pub distortion: [f64; 4],
    /// Nominal frame rate, Hz (0 = unknown).
    #[serde(default)]
    pub rate_hz: f64,
    /// Rolling-shutter readout time of a whole frame, ns (0 = global shutter).
    pub readout_ns: f64,
    /// The order the lines are read ([`slam_core::rolling_shutter::ReadoutDirection`]
    /// names); absent: top to bottom.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub readout_direction: Option<String>,
    /// Camera-IMU time offset t_d of middle-row stamps, ns (`t_imu = t_mid + t_d`).
    pub time_offset_ns: f64,
    /// Camera pose in the body (IMU) frame, `T_BS`, rows.
    pub t_bs: [[f64; 4]; 4],
}

/// The camera models a calibration file may name.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum CameraModel {
    /// Pinhole with radial-tangential distortion (seed eq. 2.57-2.60, k3 = 0).
    #[serde(rename = "pinhole-radtan")]
    PinholeRadtan,
}

/// `[imu]` of a [`CalibrationFile`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImuSection {
    /// Sample rate, Hz (0 = unknown).
    #[serde(default)]
    pub rate_hz: f64,
    /// Gyro white noise density, rad/s/√Hz.
    pub gyroscope_noise_density: f64,
    /// Gyro bias random walk, rad/s²/√Hz.
    pub gyroscope_random_walk: f64,
    /// Accelerometer white noise density, m/s²/√Hz.
    pub accelerometer_noise_density: f64,
    /// Accelerometer bias random walk, m/s³/√Hz.
    pub accelerometer_random_walk: f64,
    /// Gyro scale and misalignment `T_g`, rows (identity when absent).
    #[serde(default = "identity3")]
    pub t_g: [[f64; 3]; 3],
    /// Gyro g-sensitivity `T_s`, rad/s per m/s², rows (zero when absent).
    #[serde(default)]
    pub t_s: [[f64; 3]; 3],
    /// Accelerometer scale and misalignment `T_a`, rows (identity when absent).
    #[serde(default = "identity3")]
    pub t_a: [[f64; 3]; 3],
    /// Gyro bias, rad/s.
    #[serde(default)]
    pub gyro_bias: [f64; 3],
    /// Accelerometer bias, m/s².
    #[serde(default)]
    pub accel_bias: [f64; 3],
}

/// `[sigma]` of a [`CalibrationFile`]: the 1σ of each estimated parameter, in the units of
/// its key (`p_cb_m`: the lever arm `p_cb`, m).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(missing_docs)]
pub struct SigmaSection {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub intrinsics: Option<[f64; 4]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub distortion: Option<[f64; 4]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub readout_ns: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time_offset_ns: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub p_cb_m: Option<[f64; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub t_g: Option<[[f64; 3]; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub t_s: Option<[[f64; 3]; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub t_a: Option<[[f64; 3]; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gyro_bias: Option<[f64; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub accel_bias: Option<[f64; 3]>,
    /// Parameters whose σ did not shrink in the run: their values are the starting ones.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub not_converged: Vec<String>,
}

fn identity3() -> [[f64; 3]; 3] {
    [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
}

fn rows3(m: &Matrix3<f64>) -> [[f64; 3]; 3] {
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

fn matrix3(a: &[[f64; 3]; 3]) -> Matrix3<f64> {
    Matrix3::from_fn(|r, c| a[r][c])
}

/// `T` as its 4x4 rows.
pub fn rows4(t: &Isometry3<f64>) -> [[f64; 4]; 4] {
    let m = t.to_homogeneous();
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

/// The rigid transform of 4x4 rows, or why not (the rotation must be orthonormal to 1e-4,
/// the last row `0 0 0 1`).
pub fn isometry(a: &[[f64; 4]; 4]) -> Result<Isometry3<f64>, String> {
    let m = Matrix4::from_fn(|r, c| a[r][c]);
    if m.iter().any(|v| !v.is_finite()) {
        return Err("not finite".into());
    }
    if (m.fixed_view::<1, 4>(3, 0) - nalgebra::RowVector4::new(0.0, 0.0, 0.0, 1.0)).norm() > 1e-9 {
        return Err("last row is not 0 0 0 1".into());
    }
    let r: Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into();
    let err = (r.transpose() * r - Matrix3::identity()).norm();
    if err > 1e-4 || r.determinant() < 0.0 {
        return Err(format!("rotation not orthonormal (|RᵀR − I| = {err:.1e})"));
    }
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_eps(
        &r,
        1e-12,
        100,
        Rotation3::identity(),
    ));
    let t = Vector3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]);
    Ok(Isometry3::from_parts(Translation3::from(t), q))
}

impl CalibrationFile {
    /// The file of a dataset's calibration: its camera and its `imu0/sensor.yaml` (EuRoC's
    /// defaults and an ideal IMU when it has none).
    pub fn from_dataset(camera: &CameraCalib, imu: Option<&ImuSensorCalib>) -> Self {
        let m = &camera.model;
        let noise = imu.map_or(ImuNoise::default(), |i| i.noise);
        let k = imu.and_then(|i| i.intrinsics).unwrap_or_default();
        let b = imu.and_then(|i| i.initial_biases).unwrap_or_default();
        Self {
            format: FORMAT.into(),
            version: VERSION,
            comment: None,
            camera: CameraSection {
                model: CameraModel::PinholeRadtan,
                resolution: [m.width, m.height],
                intrinsics: [m.fx, m.fy, m.cx, m.cy],
                distortion: [m.k1, m.k2, m.p1, m.p2],
                rate_hz: camera.rate_hz,
                readout_ns: camera.readout_ns as f64,
                readout_direction: (m.readout != ReadoutDirection::TopToBottom)
                    .then(|| m.readout.name().to_string()),
                time_offset_ns: camera.time_offset_ns as f64,
                t_bs: rows4(&camera.t_bs),
            },
            imu: ImuSection {
                rate_hz: imu.map_or(0.0, |i| i.rate_hz),
                gyroscope_noise_density: noise.gyro_noise_density,
                gyroscope_random_walk: noise.gyro_bias_rw,
                accelerometer_noise_density: noise.accel_noise_density,
                accelerometer_random_walk: noise.accel_bias_rw,
                t_g: rows3(&k.t_g),
                t_s: rows3(&k.t_s),
                t_a: rows3(&k.t_a),
                gyro_bias: b.gyro.into(),
                accel_bias: b.accel.into(),
            },
            sigma: None,
        }
    }

    /// Reads and checks a calibration file; any problem is an error naming the file and,
    /// for a TOML error, the line.
    pub fn read(path: &Path) -> Result<Self, DatasetError> {
        let text = crate::text::read_text(path, "calibration file")?;
        let bad = |line: usize, detail: String| DatasetError::Parse {
            path: path.to_path_buf(),
            line,
            detail,
        };
        let file: Self = toml::from_str(&text).map_err(|e| {
            let line = e.span().map_or(0, |s| {
                1 + text.as_bytes()[..s.start.min(text.len())]
                    .iter()
                    .filter(|&&b| b == b'\n')
                    .count()
            });
            bad(line, e.message().to_string())
        })?;
        file.validate().map_err(|d| bad(0, d))?;
        Ok(file)
    }

    /// Writes the file atomically (a temporary file beside it, then a rename).
    pub fn write(&self, path: &Path) -> Result<(), DatasetError> {
        let text = toml::to_string(self).map_err(|e| DatasetError::InvalidConfig {
            detail: format!("calibration not serialisable: {e}"),
        })?;
        write_atomically(path, &text)
    }

    /// Every value checked: format and version, a positive focal length, the principal point
    /// in the image, finite distortion, `0 ≤ t_r <` the frame period (when the rate is
    /// known), `|t_d| ≤ 1 s`, a rigid `T_BS`, noise densities ≥ 0, invertible `T_g`, `T_a`.
    pub fn validate(&self) -> Result<(), String> {
        if self.format != FORMAT {
            return Err(format!("format \"{}\", expected \"{FORMAT}\"", self.format));
        }
        if self.version != VERSION {
            return Err(format!(
                "version {} of the calibration format; this build reads version {VERSION}",
                self.version
            ));
        }
        self.camera.validate()?;
        self.imu.validate()
    }

    /// The camera's calibration (`t_bs_given`: the file states the camera-IMU pose).
    pub fn camera_calib(&self) -> CameraCalib {
        let c = &self.camera;
        let [w, h] = c.resolution;
        let [k1, k2, p1, p2] = c.distortion;
        let mut model = PinholeRadtan::from_coefficients(w, h, c.intrinsics, [k1, k2, p1, p2, 0.0]);
        model.readout = c.readout_direction().unwrap_or_default();
        CameraCalib {
            model,
            t_bs: isometry(&c.t_bs).unwrap_or_else(|_| Isometry3::identity()),
            t_bs_given: true,
            readout_ns: c.readout_ns.round() as i64,
            time_offset_ns: c.time_offset_ns.round() as i64,
            rate_hz: c.rate_hz,
        }
    }

    /// The IMU's calibration, as an `imu0/sensor.yaml` would give it.
    pub fn imu_calib(&self) -> ImuSensorCalib {
        let i = &self.imu;
        ImuSensorCalib {
            rate_hz: i.rate_hz,
            noise: ImuNoise {
                gyro_noise_density: i.gyroscope_noise_density,
                accel_noise_density: i.accelerometer_noise_density,
                gyro_bias_rw: i.gyroscope_random_walk,
                accel_bias_rw: i.accelerometer_random_walk,
            },
            intrinsics: Some(ImuIntrinsics {
                t_a: matrix3(&i.t_a),
                t_g: matrix3(&i.t_g),
                t_s: matrix3(&i.t_s),
            }),
            initial_biases: Some(ImuBiases {
                gyro: i.gyro_bias.into(),
                accel: i.accel_bias.into(),
            }),
            time_offset_ns: Some(self.camera.time_offset_ns.round() as i64),
            readout_ns: Some(self.camera.readout_ns.round() as i64),
        }
    }

    /// Puts this calibration in place of `ds`'s own: the camera model (the resolution must
    /// be the dataset's when it has one), `T_BS`, `t_r` (every frame's too) and `t_d`: each
    /// frame stamp moves by the difference to the offset the dataset had applied. Refused
    /// when `t_r` is not shorter than the dataset's frame period.
    pub fn apply_to(&self, ds: &mut crate::Dataset) -> Result<(), String> {
        let new = self.camera_calib();
        let old = &ds.camera;
        let (w, h) = (old.model.width, old.model.height);
        if w > 0 && h > 0 && (w, h) != (new.model.width, new.model.height) {
            return Err(format!(
                "the calibration is for {}x{} images, the dataset's are {w}x{h}",
                new.model.width, new.model.height
            ));
        }
        let rate = if old.rate_hz > 0.0 {
            old.rate_hz
        } else {
            new.rate_hz
        };
        check_readout(new.readout_ns as f64, rate)?;
        let shift = new.time_offset_ns - old.time_offset_ns;
        for f in &mut ds.frames {
            f.t_ns += shift;
            if ds.first_row_stamps {
                // t_mid = stamp + t_r/2 + t_d (VI_NOTES.md §1).
                f.t_ns += new.readout_ns / 2 - f.readout_ns / 2;
            }
            f.readout_ns = new.readout_ns;
        }
        ds.camera = CameraCalib {
            rate_hz: if new.rate_hz > 0.0 {
                new.rate_hz
            } else {
                old.rate_hz
            },
            ..new
        };
        Ok(())
    }
}

fn check_readout(readout_ns: f64, rate_hz: f64) -> Result<(), String> {
    if !(readout_ns.is_finite() && readout_ns >= 0.0) {
        return Err(format!("camera.readout_ns {readout_ns} must be ≥ 0"));
    }
    if rate_hz > 0.0 && readout_ns >= 1e9 / rate_hz {
        return Err(format!(
            "camera.readout_ns {readout_ns} is not shorter than the frame period {:.0} ns ({rate_hz} Hz)",
            1e9 / rate_hz
        ));
    }
    Ok(())
}

impl CameraSection {
    /// The readout direction, top to bottom when absent; an unknown name is an error that
    /// lists the known ones.
    pub fn readout_direction(&self) -> Result<ReadoutDirection, String> {
        let Some(name) = &self.readout_direction else {
            return Ok(ReadoutDirection::TopToBottom);
        };
        ReadoutDirection::parse(name).map_err(|e| format!("camera.readout_direction {e}"))
    }

    fn validate(&self) -> Result<(), String> {
        let [w, h] = self.resolution;
        let [fx, fy, cx, cy] = self.intrinsics;
        if w == 0 || h == 0 {
            return Err(format!("camera.resolution {w}x{h} is empty"));
        }
        if !(fx.is_finite() && fy.is_finite() && fx > 0.0 && fy > 0.0) {
            return Err(format!(
                "camera.intrinsics: focal length ({fx}, {fy}) must be > 0"
            ));
        }
        if !(cx > 0.0 && cx < w as f64 && cy > 0.0 && cy < h as f64) {
            return Err(format!(
                "camera.intrinsics: principal point ({cx}, {cy}) outside the {w}x{h} image"
            ));
        }
        if self
            .distortion
            .iter()
            .any(|d| !d.is_finite() || d.abs() > 10.0)
        {
            return Err(format!(
                "camera.distortion {:?} out of range",
                self.distortion
            ));
        }
        if !(self.rate_hz.is_finite() && self.rate_hz >= 0.0) {
            return Err(format!("camera.rate_hz {} must be ≥ 0", self.rate_hz));
        }
        check_readout(self.readout_ns, self.rate_hz)?;
        self.readout_direction()?;
        if !(self.time_offset_ns.is_finite() && self.time_offset_ns.abs() <= 1e9) {
            return Err(format!(
                "camera.time_offset_ns {} beyond ±1 s",
                self.time_offset_ns
            ));
        }
        isometry(&self.t_bs)
            .map(|_| ())
            .map_err(|e| format!("camera.t_bs: {e}"))
    }
}

impl ImuSection {
    fn validate(&self) -> Result<(), String> {
        let densities = [
            ("gyroscope_noise_density", self.gyroscope_noise_density),
            ("gyroscope_random_walk", self.gyroscope_random_walk),
            (
                "accelerometer_noise_density",
                self.accelerometer_noise_density,
            ),
            ("accelerometer_random_walk", self.accelerometer_random_walk),
            ("rate_hz", self.rate_hz),
        ];
        if let Some((k, v)) = densities
            .iter()
            .find(|(_, v)| !(v.is_finite() && *v >= 0.0))
        {
            return Err(format!("imu.{k} {v} must be finite and ≥ 0"));
        }
        for (k, m) in [("t_g", &self.t_g), ("t_a", &self.t_a)] {
            let d = matrix3(m).determinant();
            if !(d.is_finite() && d > 0.5 && d < 2.0) {
                return Err(format!(
                    "imu.{k} is not a scale/misalignment near I (det {d})"
                ));
            }
        }
        let finite = self.t_s.iter().flatten().all(|v| v.is_finite())
            && self
                .gyro_bias
                .iter()
                .chain(&self.accel_bias)
                .all(|v| v.is_finite());
        if !finite {
            return Err("imu.t_s or a bias is not finite".into());
        }
        Ok(())
    }
}

/// Writes `text` to `path` through a temporary file in the same folder and a rename.
pub(crate) fn write_atomically(path: &Path, text: &str) -> Result<(), DatasetError> {
    let io = |source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    std::fs::write(&tmp, text).map_err(io)?;
    std::fs::rename(&tmp, path).map_err(io)
}

#[cfg(test)]
#[path = "calibration_tests.rs"]
mod tests;
