//! [`SimParams`]: everything that defines a simulated dataset.

use nalgebra::{Matrix3, Vector3};
use slam_core::camera::PinholeRadtan;
use slam_core::imu::{ImuBiases, ImuIntrinsics, ImuNoise};

use super::scenario::Scenario;
use crate::DatasetError;

/// Parameters of the synthetic world generator. `SimParams::new(scenario)` gives the
/// defaults; every field can be changed before calling [`super::generate`] or
/// [`super::SimWorld::new`].
#[derive(Debug, Clone, PartialEq)]
pub struct SimParams {
    /// The scenario (paths, default duration and readout).
    pub scenario: Scenario,
    /// Seed of everything random (textures, IMU noise, pixel noise).
    pub seed: u64,
    /// Number of frames per agent (`None`: the scenario's default duration).
    pub frames: Option<usize>,
    /// Rolling-shutter readout time, ms (`None`: the scenario's default; 0 = global shutter).
    pub readout_ms: Option<f64>,
    /// Camera-IMU time offset t_d, ms: true capture time = camera stamp + t_d.
    pub time_offset_ms: f64,
    /// Image width, pixels (intrinsics are the EuRoC ones scaled to the size).
    pub width: u32,
    /// Image height, pixels (the rolling-shutter row count).
    pub height: u32,
    /// Camera frame rate, Hz.
    pub rate_hz: f64,
    /// IMU rate, Hz.
    pub imu_rate_hz: f64,
    /// IMU noise densities (EuRoC values by default; [`ImuNoise::zero`] for none).
    pub noise: ImuNoise,
    /// IMU intrinsics `T_a`, `T_g`, `T_s` (ideal by default).
    pub imu_intrinsics: ImuIntrinsics,
    /// IMU biases at the first sample (they then follow the random walk).
    pub initial_biases: ImuBiases,
    /// Standard deviation of the per-pixel image noise, grey levels (0 = none).
    pub pixel_noise_sigma: f32,
    /// Time of the first IMU sample (trajectory time 0), ns.
    pub start_ns: i64,
}

impl SimParams {
    /// The defaults for `scenario`: 752x480 EuRoC-like camera at 20 Hz, IMU at 200 Hz with
    /// EuRoC noise and small initial biases, pixel noise 1.5, t_d = 0; for
    /// [`Scenario::Phone`] and [`Scenario::Calib`] the camera runs at 30 Hz and the IMU is
    /// [`phone_imu`]'s with t_d = 40 ms.
    pub fn new(scenario: Scenario) -> Self {
        let base = Self::euroc_like(scenario);
        if !matches!(scenario, Scenario::Phone | Scenario::Calib) {
            return base;
        }
        let (noise, imu_intrinsics, initial_biases) = phone_imu();
        Self {
            rate_hz: 30.0,
            time_offset_ms: 40.0,
            noise,
            imu_intrinsics,
            initial_biases,
            ..base
        }
    }

    fn euroc_like(scenario: Scenario) -> Self {
        Self {
            scenario,
            seed: 0,
            frames: None,
            readout_ms: None,
            time_offset_ms: 0.0,
            width: 752,
            height: 480,
            rate_hz: 20.0,
            imu_rate_hz: 200.0,
            noise: ImuNoise::default(),
            imu_intrinsics: ImuIntrinsics::default(),
            initial_biases: ImuBiases {
                gyro: nalgebra::Vector3::new(0.003, -0.002, 0.001),
                accel: nalgebra::Vector3::new(0.02, -0.03, 0.05),
            },
            pixel_noise_sigma: 1.5,
            start_ns: 1_000_000_000_000,
        }
    }

    /// Checks sizes, rates and times.
    pub fn validate(&self) -> Result<(), DatasetError> {
        let bad = |detail: String| Err(DatasetError::InvalidConfig { detail });
        if self.width < 8 || self.height < 8 || self.width > 8192 || self.height > 8192 {
            return bad(format!(
                "image size {}x{} outside 8..=8192",
                self.width, self.height
            ));
        }
        if !(self.rate_hz.is_finite() && self.rate_hz > 0.0 && self.rate_hz <= 1000.0) {
            return bad(format!("camera rate {} Hz outside (0, 1000]", self.rate_hz));
        }
        if !(self.imu_rate_hz.is_finite()
            && self.imu_rate_hz >= 1.0
            && self.imu_rate_hz <= 10_000.0)
        {
            return bad(format!(
                "IMU rate {} Hz outside [1, 10000]",
                self.imu_rate_hz
            ));
        }
        if self.frames == Some(0) || self.frames.is_some_and(|n| n > 1_000_000) {
            return bad("frames must be in 1..=1000000".into());
        }
        let period_ms = 1e3 / self.rate_hz;
        if let Some(r) = self.readout_ms {
            if !(r.is_finite() && r >= 0.0 && r <= period_ms) {
                return bad(format!(
                    "readout {r} ms outside [0, frame period {period_ms} ms]"
                ));
            }
        }
        if !(self.time_offset_ms.is_finite() && self.time_offset_ms.abs() <= 90.0) {
            return bad(format!(
                "time offset {} ms outside [-90, 90]",
                self.time_offset_ms
            ));
        }
        if !(self.pixel_noise_sigma.is_finite() && (0.0..=64.0).contains(&self.pixel_noise_sigma)) {
            return bad(format!(
                "pixel noise {} outside [0, 64]",
                self.pixel_noise_sigma
            ));
        }
        let n = &self.noise;
        let densities = [
            n.gyro_noise_density,
            n.accel_noise_density,
            n.gyro_bias_rw,
            n.accel_bias_rw,
        ];
        if densities.iter().any(|d| !(d.is_finite() && *d >= 0.0)) {
            return bad("IMU noise densities must be finite and >= 0".into());
        }
        if self.start_ns < 0 {
            return bad("start_ns must be >= 0".into());
        }
        Ok(())
    }

    /// The camera: EuRoC cam0 intrinsics and distortion scaled to `width x height`.
    pub fn camera(&self) -> PinholeRadtan {
        let base = PinholeRadtan::euroc_cam0();
        let sx = f64::from(self.width) / f64::from(base.width);
        let sy = f64::from(self.height) / f64::from(base.height);
        PinholeRadtan {
            width: self.width,
            height: self.height,
            fx: base.fx * sx,
            fy: base.fy * sy,
            cx: (base.cx + 0.5) * sx - 0.5,
            cy: (base.cy + 0.5) * sy - 0.5,
            ..base
        }
    }

    /// Frame period, ns.
    pub fn frame_period_ns(&self) -> i64 {
        (1e9 / self.rate_hz).round() as i64
    }

    /// Number of frames per agent (explicit or from the scenario's default duration).
    pub fn n_frames(&self) -> usize {
        self.frames
            .unwrap_or_else(|| (self.scenario.default_duration_s() * self.rate_hz).round() as usize)
    }

    /// Readout time t_r, ns.
    pub fn readout_ns(&self) -> i64 {
        (self
            .readout_ms
            .unwrap_or_else(|| self.scenario.default_readout_ms())
            * 1e6)
            .round() as i64
    }

    /// Camera-IMU time offset t_d, ns.
    pub fn time_offset_ns(&self) -> i64 {
        (self.time_offset_ms * 1e6).round() as i64
    }
}

/// The `phone` scenario's IMU (seed eq. 2.53-2.56): `(noise, intrinsics, initial biases)`
/// of a consumer MEMS part at 200 Hz.
///
/// - White noise: the Bosch BMI160 data sheet (gyro output noise 0.007 °/s/√Hz =
///   1.22e-4 rad/s/√Hz; accelerometer output noise density 180 µg/√Hz = 1.77e-3 m/s²/√Hz,
///   normal mode); the TDK ICM-20600 is quieter (0.004 °/s/√Hz, 100 µg/√Hz).
/// - Bias random walks: data sheets give none; 1e-4 rad/s²/√Hz (five times the EuRoC
///   ADIS16448 figure) and 4e-3 m/s³/√Hz (a consumer part drifting more than the ADIS).
/// - Initial biases ~0.01 rad/s (gyro, within the BMI160's ±3 °/s zero-rate offset) and
///   ~0.1 m/s² (accelerometer, within its ±40 mg offset).
/// - `T_g`, `T_a`: scale errors of 0.5-1.1 % on the diagonal (BMI160 sensitivity tolerance
///   ±1 %) and misalignments of 0.2-0.5° (8.7e-3 rad = 0.5°; cross-axis sensitivity ±1 %);
///   `T_s`: g-sensitivity ~2e-4 rad/s per m/s² (0.1 °/s/g).
pub fn phone_imu() -> (ImuNoise, ImuIntrinsics, ImuBiases) {
    let noise = ImuNoise {
        gyro_noise_density: 0.007_f64.to_radians(),
        accel_noise_density: 180e-6 * 9.81,
        gyro_bias_rw: 1e-4,
        accel_bias_rw: 4e-3,
    };
    let intrinsics = ImuIntrinsics {
        t_g: Matrix3::new(
            1.010, -8.7e-3, 4.0e-3, //
            6.0e-3, 0.992, -5.0e-3, //
            -3.5e-3, 7.0e-3, 1.006,
        ),
        t_s: Matrix3::new(
            2.0e-4, -1.0e-4, 0.5e-4, //
            0.8e-4, -1.5e-4, 1.2e-4, //
            -0.6e-4, 0.4e-4, 2.5e-4,
        ),
        t_a: Matrix3::new(
            0.993, 5.0e-3, -3.0e-3, //
            -6.5e-3, 1.011, 4.0e-3, //
            2.5e-3, -8.0e-3, 1.005,
        ),
    };
    let biases = ImuBiases {
        gyro: Vector3::new(0.012, -0.008, 0.010),
        accel: Vector3::new(0.10, -0.08, 0.12),
    };
    (noise, intrinsics, biases)
}

impl Default for SimParams {
    fn default() -> Self {
        Self::new(Scenario::Loop)
    }
}
