//! IMU measurement model, seed eq. 2.53-2.56.
//!
//! ```text
//! a_m = T_a a_s + b_a + n_a          (a_s = R_WB^T (a_W - g_W): specific force, body frame)
//! w_m = T_g w + T_s a_s + b_g + n_g  (w: angular rate of the body in the body frame)
//! b_a' = n_ba,  b_g' = n_bg          (random walks)
//! ```
//!
//! Noise parameters are continuous-time densities as in EuRoC / Kalibr `imu.yaml`. For
//! samples `dt` apart the discrete white noise has `σ_d = σ_c / sqrt(dt)` and the bias takes
//! a random-walk step of `σ_c · sqrt(dt)` per sample. This module holds no random generator:
//! callers pass standard-normal draws, so simulations stay deterministic and testable.
//!
//! [`preint`] preintegrates the measurements between keyframes (Forster et al. 2017);
//! [`init`] finds scale, gravity, velocities and biases from a monocular map's first
//! seconds, and [`coupler`] decides when to run it beside a live VO; [`extrinsic_rotation`]
//! finds the camera-IMU rotation from gyro vs visual rotations when it is not given;
//! [`window`] is the sliding-window visual-inertial optimisation of local mapping.

use nalgebra::{Matrix3, Vector3};

pub mod coupler;
pub mod extrinsic_rotation;
pub mod init;
pub mod preint;
pub mod static_init;
pub mod window;

pub use preint::{
    ImuMeasurement, ImuResidual, MeasurementCorrection, NavState, Preintegrated,
    PreintegrationParams, TimedImuSample,
};

/// Standard gravity magnitude used across the project, m/s².
pub const GRAVITY: f64 = 9.81;

/// Gravity in the world frame (z up), `g_W = (0, 0, -9.81)` m/s².
pub fn gravity_w() -> Vector3<f64> {
    Vector3::new(0.0, 0.0, -GRAVITY)
}

/// Continuous-time IMU noise densities (EuRoC / Kalibr `imu.yaml` keys in brackets).
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct ImuNoise {
    /// Gyro white noise density σ_g, rad/s/√Hz (`gyroscope_noise_density`).
    pub gyro_noise_density: f64,
    /// Accelerometer white noise density σ_a, m/s²/√Hz (`accelerometer_noise_density`).
    pub accel_noise_density: f64,
    /// Gyro bias random walk σ_bg, rad/s²/√Hz (`gyroscope_random_walk`).
    pub gyro_bias_rw: f64,
    /// Accelerometer bias random walk σ_ba, m/s³/√Hz (`accelerometer_random_walk`).
    pub accel_bias_rw: f64,
}

impl Default for ImuNoise {
    /// The EuRoC MAV (ADIS16448) values.
    fn default() -> Self {
        Self {
            gyro_noise_density: 1.6968e-4,
            accel_noise_density: 2.0e-3,
            gyro_bias_rw: 1.9393e-5,
            accel_bias_rw: 3.0e-3,
        }
    }
}

impl ImuNoise {
    /// No noise and constant biases.
    pub fn zero() -> Self {
        Self {
            gyro_noise_density: 0.0,
            accel_noise_density: 0.0,
            gyro_bias_rw: 0.0,
            accel_bias_rw: 0.0,
        }
    }

    /// Discrete white-noise standard deviations `(σ_gyro, σ_accel)` for sample period `dt`
    /// seconds: `σ_c / sqrt(dt)`. Zero for `dt <= 0`.
    pub fn discrete_white_sigma(&self, dt: f64) -> (f64, f64) {
        if dt <= 0.0 {
            return (0.0, 0.0);
        }
        let s = 1.0 / dt.sqrt();
        (self.gyro_noise_density * s, self.accel_noise_density * s)
    }

    /// Per-sample bias random-walk step deviations `(σ_gyro, σ_accel)` for period `dt`:
    /// `σ_c · sqrt(dt)`. Zero for `dt <= 0`.
    pub fn discrete_bias_step_sigma(&self, dt: f64) -> (f64, f64) {
        if dt <= 0.0 {
            return (0.0, 0.0);
        }
        let s = dt.sqrt();
        (self.gyro_bias_rw * s, self.accel_bias_rw * s)
    }
}

/// IMU intrinsics of seed eq. 2.53-2.54: `T_a`, `T_g` (scale and misalignment, close to I)
/// and `T_s` (gyro g-sensitivity).
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct ImuIntrinsics {
    /// Accelerometer scale/misalignment `T_a` (identity by default).
    pub t_a: Matrix3<f64>,
    /// Gyro scale/misalignment `T_g` (identity by default).
    pub t_g: Matrix3<f64>,
    /// Gyro g-sensitivity `T_s`, rad/s per m/s² (zero by default).
    pub t_s: Matrix3<f64>,
}

impl Default for ImuIntrinsics {
    fn default() -> Self {
        Self {
            t_a: Matrix3::identity(),
            t_g: Matrix3::identity(),
            t_s: Matrix3::zeros(),
        }
    }
}

impl ImuIntrinsics {
    /// True for the plain model `T_a = T_g = I`, `T_s = 0`.
    pub fn is_ideal(&self) -> bool {
        *self == Self::default()
    }
}

/// IMU biases, body frame.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct ImuBiases {
    /// Gyro bias b_g, rad/s.
    pub gyro: Vector3<f64>,
    /// Accelerometer bias b_a, m/s².
    pub accel: Vector3<f64>,
}

/// Noise-free measurement of seed eq. 2.53-2.54: returns `(a_m, w_m)` for the true specific
/// force `a_s` and angular rate `w` (both in the body frame), biases and intrinsics.
pub fn measure(
    specific_force_b: &Vector3<f64>,
    omega_b: &Vector3<f64>,
    biases: &ImuBiases,
    intrinsics: &ImuIntrinsics,
) -> (Vector3<f64>, Vector3<f64>) {
    let a_m = intrinsics.t_a * specific_force_b + biases.accel;
    let w_m = intrinsics.t_g * omega_b + intrinsics.t_s * specific_force_b + biases.gyro;
    (a_m, w_m)
}

/// Specific force in the body frame, `a_s = R_WB^T (a_W - g_W)`, from the world
/// acceleration of the body and its orientation `R_WB`.
pub fn specific_force_b(r_wb: &Matrix3<f64>, accel_w: &Vector3<f64>) -> Vector3<f64> {
    r_wb.transpose() * (accel_w - gravity_w())
}

/// Discrete white measurement noise `(n_a, n_g)` for sample period `dt` from six
/// standard-normal draws (`normals[0..3]` for the accelerometer, `[3..6]` for the gyro).
pub fn white_noise(noise: &ImuNoise, dt: f64, normals: &[f64; 6]) -> (Vector3<f64>, Vector3<f64>) {
    let (sg, sa) = noise.discrete_white_sigma(dt);
    (
        Vector3::new(normals[0], normals[1], normals[2]) * sa,
        Vector3::new(normals[3], normals[4], normals[5]) * sg,
    )
}

/// One bias random-walk step over `dt` (seed eq. 2.55-2.56) from six standard-normal draws
/// (`normals[0..3]` accelerometer, `[3..6]` gyro): `b += σ_c sqrt(dt) ξ`.
pub fn bias_random_walk_step(
    biases: &mut ImuBiases,
    noise: &ImuNoise,
    dt: f64,
    normals: &[f64; 6],
) {
    let (sg, sa) = noise.discrete_bias_step_sigma(dt);
    biases.accel += Vector3::new(normals[0], normals[1], normals[2]) * sa;
    biases.gyro += Vector3::new(normals[3], normals[4], normals[5]) * sg;
}

/// A full noisy measurement: [`measure`] plus [`white_noise`]; returns `(a_m, w_m)`.
pub fn measure_noisy(
    specific_force_b: &Vector3<f64>,
    omega_b: &Vector3<f64>,
    biases: &ImuBiases,
    intrinsics: &ImuIntrinsics,
    noise: &ImuNoise,
    dt: f64,
    normals: &[f64; 6],
) -> (Vector3<f64>, Vector3<f64>) {
    let (a, w) = measure(specific_force_b, omega_b, biases, intrinsics);
    let (n_a, n_g) = white_noise(noise, dt, normals);
    (a + n_a, w + n_g)
}

/// Mean angular rate over `[t0_ns, t1_ns]` from gyro samples `(t_ns, ω)` sorted by time:
/// the integral of the linearly interpolated rate divided by the span, i.e. the rotation
/// vector of the integrated gyro over the interval per second (exact to first order). Used
/// to rotate rolling-shutter rows to the frame's mid-row time. `None` when the samples do
/// not bracket the interval (the caller waits for more or falls back to another estimate).
pub fn mean_rate(samples: &[(i64, Vector3<f64>)], t0_ns: i64, t1_ns: i64) -> Option<Vector3<f64>> {
    if t1_ns < t0_ns || samples.len() < 2 {
        return None;
    }
    let (first, last) = (samples[0].0, samples[samples.len() - 1].0);
    if first > t0_ns || last < t1_ns {
        return None;
    }
    let rate_at = |i: usize, t: i64| {
        let (ta, wa) = samples[i];
        let (tb, wb) = samples[i + 1];
        let a = if tb > ta {
            (t - ta) as f64 / (tb - ta) as f64
        } else {
            0.0
        };
        wa + (wb - wa) * a
    };
    // Segment containing t0.
    let mut i = samples.partition_point(|s| s.0 <= t0_ns).saturating_sub(1);
    if t1_ns == t0_ns {
        return Some(rate_at(i.min(samples.len() - 2), t0_ns));
    }
    let mut sum = Vector3::zeros();
    let mut t = t0_ns;
    while t < t1_ns && i + 1 < samples.len() {
        let end = samples[i + 1].0.min(t1_ns);
        if end > t {
            // Trapezoid over [t, end] of the linear segment.
            let w = (rate_at(i, t) + rate_at(i, end)) * 0.5;
            sum += w * (end - t) as f64;
            t = end;
        }
        i += 1;
    }
    Some(sum / (t1_ns - t0_ns) as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ideal_model_adds_only_biases() {
        let b = ImuBiases {
            gyro: Vector3::new(0.01, 0.0, -0.02),
            accel: Vector3::new(0.1, 0.2, 0.3),
        };
        let a_s = Vector3::new(0.0, 0.0, 9.81);
        let w = Vector3::new(0.5, -0.1, 0.2);
        let (a_m, w_m) = measure(&a_s, &w, &b, &ImuIntrinsics::default());
        assert_eq!(a_m, a_s + b.accel);
        assert_eq!(w_m, w + b.gyro);
        assert!(ImuIntrinsics::default().is_ideal());
    }

    #[test]
    fn intrinsics_apply_scale_and_g_sensitivity() {
        let mut k = ImuIntrinsics::default();
        k.t_a[(0, 0)] = 1.01;
        k.t_g[(1, 0)] = 0.002;
        k.t_s[(2, 2)] = 1e-3;
        let a_s = Vector3::new(1.0, 0.0, 9.81);
        let w = Vector3::new(1.0, 0.0, 0.0);
        let (a_m, w_m) = measure(&a_s, &w, &ImuBiases::default(), &k);
        assert!((a_m.x - 1.01).abs() < 1e-15);
        assert!((w_m.y - 0.002).abs() < 1e-15);
        assert!((w_m.z - 9.81e-3).abs() < 1e-15);
        assert!(!k.is_ideal());
    }

    #[test]
    fn specific_force_at_rest_points_up() {
        let f = specific_force_b(&Matrix3::identity(), &Vector3::zeros());
        assert_eq!(f, Vector3::new(0.0, 0.0, GRAVITY));
    }

    #[test]
    fn discrete_sigmas_follow_sqrt_dt() {
        let n = ImuNoise::default();
        let dt = 0.005;
        let (sg, sa) = n.discrete_white_sigma(dt);
        assert!((sg - 1.6968e-4 / dt.sqrt()).abs() < 1e-15);
        assert!((sa - 2.0e-3 * 200f64.sqrt()).abs() < 1e-12);
        let (bg, ba) = n.discrete_bias_step_sigma(dt);
        assert!((bg - 1.9393e-5 * dt.sqrt()).abs() < 1e-15);
        assert!((ba - 3.0e-3 * dt.sqrt()).abs() < 1e-15);
        assert_eq!(n.discrete_white_sigma(0.0), (0.0, 0.0));
        let mut b = ImuBiases::default();
        bias_random_walk_step(&mut b, &n, dt, &[1.0; 6]);
        assert!((b.accel.x - ba).abs() < 1e-15 && (b.gyro.z - bg).abs() < 1e-15);
        let (a, w) = measure_noisy(
            &Vector3::zeros(),
            &Vector3::zeros(),
            &ImuBiases::default(),
            &ImuIntrinsics::default(),
            &n,
            dt,
            &[1.0, 0.0, 0.0, 0.0, 0.0, -1.0],
        );
        assert!((a.x - sa).abs() < 1e-15 && (w.z + sg).abs() < 1e-15);
    }

    #[test]
    fn mean_rate_integrates_the_interpolated_gyro() {
        // ω(t) = (t, 2, -t) with t in ms at 5 ms spacing; the mean over [2, 13] ms is
        // (7.5, 2, -7.5).
        let s: Vec<(i64, Vector3<f64>)> = (0..6)
            .map(|k| {
                let t = k as f64 * 5.0;
                ((t * 1e6) as i64, Vector3::new(t, 2.0, -t))
            })
            .collect();
        let m = mean_rate(&s, 2_000_000, 13_000_000).unwrap();
        assert!((m - Vector3::new(7.5, 2.0, -7.5)).norm() < 1e-9, "{m}");
        assert!(mean_rate(&s, -1, 10_000_000).is_none(), "not bracketed");
        assert!(mean_rate(&s, 20_000_000, 26_000_000).is_none());
        let p = mean_rate(&s, 7_000_000, 7_000_000).unwrap();
        assert!((p.x - 7.0).abs() < 1e-9);
    }
}
