//! Static initialisation (issue 17, `VI_NOTES.md` §2 "IMU model"): while the device rests,
//! the gyro measures its bias and the accelerometer the reaction to gravity,
//! `ã = b_a - R_wbᵀ g` (seed 5.2 with `v̇ = 0`), so the mean specific force points up in the
//! body frame. A window of samples is taken as static when the spread of the corrected gyro
//! and accelerometer stays below a vibration bound and the mean specific force has the
//! norm of gravity, and the mean rate is no larger than a gyro bias can be (a steady turn
//! is as still as rest). The gyro bias is the window's mean rate; the gravity direction is the
//! mean specific force's (the accelerometer bias, ~0.01-0.1 m/s², is not separable from
//! gravity at rest: it tilts the estimate by up to `|b_a⊥| / 9.81`, 0.1-0.6°). Scale,
//! velocity and yaw are not observable at rest: a monocular-inertial client still needs
//! motion for those ([`super::init`]).
//!
//! Bounds are per axis standard deviations over the window. The defaults admit a multirotor
//! idling on the floor with its motors running (EuRoC V1_01's first 4.7 s: gyro 0.01-0.06
//! rad/s, accelerometer 0.14-0.83 m/s²) and refuse its flight (gyro ≥ 0.1 rad/s or
//! accelerometer ≥ 1.0 m/s² per 2 s window).
use nalgebra::{Rotation3, Vector3};

use super::preint::{ImuMeasurement, MeasurementCorrection};
use super::GRAVITY;

/// Bounds of [`detect_static`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StaticParams {
    /// Window length, s.
    pub window_s: f64,
    /// Largest per-axis standard deviation of the corrected gyro, rad/s.
    pub max_gyro_std: f64,
    /// Largest per-axis standard deviation of the corrected accelerometer, m/s².
    pub max_accel_std: f64,
    /// Largest `| |ā| - 9.81 |`, m/s².
    pub max_gravity_error: f64,
    /// Largest norm of the mean corrected rate, rad/s: what a gyro's bias can be. A slow
    /// turn at a constant rate has the spread of a device at rest (the `loop` scene's
    /// 0.24 rad/s yaw passed the spread bounds and became a 0.24 rad/s "bias"); EuRoC's
    /// ADIS16448 has up to 0.08 rad/s on V1_01.
    pub max_gyro_rate: f64,
}

impl Default for StaticParams {
    fn default() -> Self {
        Self {
            window_s: 2.0,
            max_gyro_std: 0.08,
            max_accel_std: 1.0,
            max_gravity_error: 0.3,
            max_gyro_rate: 0.1,
        }
    }
}

/// What a static window gave.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StaticInit {
    /// The window, IMU clock, ns.
    pub t0_ns: i64,
    /// Its end.
    pub t1_ns: i64,
    /// Gyro bias (the corrected rate's mean), rad/s, body frame.
    pub gyro_bias: Vector3<f64>,
    /// Unit "up" (against gravity) in the body frame: the mean specific force's direction.
    pub up_b: Vector3<f64>,
    /// Norm of the mean specific force, m/s².
    pub accel_norm: f64,
    /// Largest per-axis standard deviation of the gyro / accelerometer over the window.
    pub gyro_std: f64,
    /// See `gyro_std`.
    pub accel_std: f64,
}

impl StaticInit {
    /// A body orientation `R_wb` with the world's z up (`R_wb up_b = e_z`), yaw chosen as the
    /// smallest rotation (yaw is not observable at rest).
    pub fn r_wb(&self) -> Rotation3<f64> {
        Rotation3::rotation_between(&self.up_b, &Vector3::z())
            .unwrap_or_else(|| Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI))
    }
}

/// Mean and largest per-axis standard deviation of `v`.
fn mean_and_std(v: impl Iterator<Item = Vector3<f64>> + Clone) -> (Vector3<f64>, f64) {
    let n = v.clone().count().max(1) as f64;
    let mean = v.clone().fold(Vector3::zeros(), |a, x| a + x) / n;
    let var = v.fold(Vector3::zeros(), |a, x| {
        a + (x - mean).component_mul(&(x - mean))
    }) / n;
    (mean, var.max().sqrt())
}

/// The static estimate over the samples in `[t_end_ns - window, t_end_ns]` (module docs);
/// `None` when they do not span the window (gaps over 50 ms included) or the device moved.
pub fn detect_static(
    samples: &[ImuMeasurement],
    t_end_ns: i64,
    correction: &MeasurementCorrection,
    params: &StaticParams,
) -> Option<StaticInit> {
    let t0 = t_end_ns - (params.window_s * 1e9) as i64;
    let lo = samples.partition_point(|m| m.t_ns < t0);
    let hi = samples.partition_point(|m| m.t_ns <= t_end_ns);
    let win = samples.get(lo..hi)?;
    let (first, last) = (win.first()?, win.last()?);
    let spans = first.t_ns - t0 <= 50_000_000 && t_end_ns - last.t_ns <= 50_000_000;
    let gapless = win.windows(2).all(|w| w[1].t_ns - w[0].t_ns <= 50_000_000);
    if !(spans && gapless && win.len() >= 10) {
        return None;
    }
    let corrected = win.iter().map(|m| correction.apply(&m.gyro, &m.accel));
    let (gyro_bias, gyro_std) = mean_and_std(corrected.clone().map(|(w, _)| w));
    let (accel, accel_std) = mean_and_std(corrected.map(|(_, a)| a));
    let accel_norm = accel.norm();
    let still = gyro_std <= params.max_gyro_std
        && gyro_bias.norm() <= params.max_gyro_rate
        && accel_std <= params.max_accel_std
        && (accel_norm - GRAVITY).abs() <= params.max_gravity_error;
    still.then(|| StaticInit {
        t0_ns: t0,
        t1_ns: t_end_ns,
        gyro_bias,
        up_b: accel / accel_norm,
        accel_norm,
        gyro_std,
        accel_std,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn samples(
        gyro: impl Fn(usize) -> Vector3<f64>,
        accel: impl Fn(usize) -> Vector3<f64>,
    ) -> Vec<ImuMeasurement> {
        (0..600)
            .map(|k| ImuMeasurement {
                t_ns: k as i64 * 5_000_000,
                gyro: gyro(k),
                accel: accel(k),
            })
            .collect()
    }

    /// At rest with a tilted body, biases and vibration: the gyro bias and the up direction
    /// come back; moving (a slow turn, a steady turn, a push) is refused, and so is a window
    /// with a gap.
    #[test]
    fn a_resting_imu_gives_its_gyro_bias_and_gravity() {
        let r_wb = Rotation3::from_euler_angles(0.3, -0.2, 1.0);
        let bias = Vector3::new(0.01, -0.02, 0.03);
        let up_b = r_wb.inverse() * Vector3::z();
        let wiggle = |k: usize, a: f64| {
            Vector3::new(
                (k as f64 * 1.7).sin(),
                (k as f64 * 2.3).cos(),
                (k as f64 * 0.9).sin(),
            ) * a
        };
        let rest = samples(
            |k| bias + wiggle(k, 0.02),
            |k| up_b * GRAVITY + wiggle(k, 0.3),
        );
        let c = MeasurementCorrection::new(&crate::imu::ImuIntrinsics::default()).expect("ideal");
        let p = StaticParams::default();
        let s = detect_static(&rest, 2_900_000_000, &c, &p).expect("static");
        assert!((s.gyro_bias - bias).norm() < 2e-3, "{:?}", s.gyro_bias);
        let tilt = (s.r_wb() * up_b).angle(&Vector3::z());
        assert!(tilt < 0.2f64.to_radians(), "tilt {tilt}");
        let turning = samples(
            |k| bias + Vector3::z() * (k as f64 * 0.01).sin() * 0.5,
            |_| up_b * GRAVITY,
        );
        assert!(detect_static(&turning, 2_900_000_000, &c, &p).is_none());
        // A steady turn at 0.24 rad/s (the `loop` scene's yaw) is as still as rest.
        let steady = samples(|_| bias + Vector3::z() * 0.24, |_| up_b * GRAVITY);
        assert!(detect_static(&steady, 2_900_000_000, &c, &p).is_none());
        let pushed = samples(
            |_| bias,
            |k| up_b * GRAVITY + Vector3::x() * if k % 200 < 100 { 1.5 } else { -1.5 },
        );
        assert!(detect_static(&pushed, 2_900_000_000, &c, &p).is_none());
        let mut gap = rest.clone();
        gap.retain(|m| !(1_500_000_000..1_700_000_000).contains(&m.t_ns));
        assert!(detect_static(&gap, 2_900_000_000, &c, &p).is_none());
        // Not enough samples before the end of the window.
        assert!(detect_static(&rest, 1_000_000_000, &c, &p).is_none());
    }
}
