//! The IMU samples a visual-inertial client keeps between frames, checked as they arrive
//! (issue 17, "bad input": gaps, duplicated or out-of-order samples, saturated values are
//! counted, named errors, never a panic).
use crate::imu::ImuMeasurement;

/// Limits of [`ImuBuffer::push`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuCheck {
    /// Largest accepted |component| of the specific force, m/s² (ADIS16448: ±18 g).
    pub accel_saturation: f64,
    /// Largest accepted |component| of the angular rate, rad/s (ADIS16448: ±1000°/s).
    pub gyro_saturation: f64,
    /// Longer steps between samples are reported as [`ImuSampleError::Gap`], ns.
    pub max_gap_ns: i64,
}

impl Default for ImuCheck {
    fn default() -> Self {
        Self {
            accel_saturation: 16.0 * crate::imu::GRAVITY,
            gyro_saturation: 17.0,
            max_gap_ns: 50_000_000,
        }
    }
}

/// Why an IMU sample was refused, or what it revealed ([`ImuSampleError::Gap`] only: the
/// sample is kept).
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum ImuSampleError {
    /// Not after the last sample (duplicated or out of order): refused.
    #[error("IMU sample at {t_ns} ns is not after the last one ({last_ns} ns)")]
    NotAfterLast {
        /// The sample's time, ns.
        t_ns: i64,
        /// The last accepted sample's time, ns.
        last_ns: i64,
    },
    /// A non-finite value: refused.
    #[error("IMU sample at {t_ns} ns has a non-finite value")]
    NonFinite {
        /// The sample's time, ns.
        t_ns: i64,
    },
    /// A value at or beyond the sensor's range: refused.
    #[error("IMU sample at {t_ns} ns is saturated")]
    Saturated {
        /// The sample's time, ns.
        t_ns: i64,
    },
    /// The sample came after a gap longer than [`ImuCheck::max_gap_ns`]: **kept**, but no
    /// IMU prediction spans the gap (the frames across it are tracked visually).
    #[error("IMU gap of {gap_ns} ns before the sample at {t_ns} ns")]
    Gap {
        /// The sample's time, ns.
        t_ns: i64,
        /// Time since the last sample, ns.
        gap_ns: i64,
    },
}

impl ImuSampleError {
    /// Whether the sample was refused (every variant but [`ImuSampleError::Gap`]).
    pub fn refused(&self) -> bool {
        !matches!(self, ImuSampleError::Gap { .. })
    }
}

/// Checked IMU samples in time order, pruned by the caller ([`ImuBuffer::keep_from`]).
#[derive(Debug, Clone, Default)]
pub struct ImuBuffer {
    check: ImuCheck,
    samples: Vec<ImuMeasurement>,
    /// End time of the latest gap, ns (no prediction spans it).
    gap_end_ns: Option<i64>,
    /// Time of the last accepted sample (kept when the buffer is pruned empty).
    last_ns: Option<i64>,
}

impl ImuBuffer {
    /// An empty buffer checking samples with `check`.
    pub fn new(check: ImuCheck) -> Self {
        Self {
            check,
            ..Self::default()
        }
    }

    /// Checks and stores `m` (see [`ImuSampleError`]).
    pub fn push(&mut self, m: ImuMeasurement) -> Result<(), ImuSampleError> {
        let t_ns = m.t_ns;
        if let Some(last_ns) = self.last_ns.filter(|&l| l >= t_ns) {
            return Err(ImuSampleError::NotAfterLast { t_ns, last_ns });
        }
        if !(m.gyro.iter().chain(m.accel.iter())).all(|x| x.is_finite()) {
            return Err(ImuSampleError::NonFinite { t_ns });
        }
        let sat = |v: &nalgebra::Vector3<f64>, lim: f64| v.iter().any(|x| x.abs() >= lim);
        if sat(&m.accel, self.check.accel_saturation) || sat(&m.gyro, self.check.gyro_saturation) {
            return Err(ImuSampleError::Saturated { t_ns });
        }
        let gap = self
            .last_ns
            .map(|l| t_ns - l)
            .filter(|&g| g > self.check.max_gap_ns);
        self.samples.push(m);
        self.last_ns = Some(t_ns);
        match gap {
            Some(gap_ns) => {
                self.gap_end_ns = Some(t_ns);
                Err(ImuSampleError::Gap { t_ns, gap_ns })
            }
            None => Ok(()),
        }
    }

    /// The samples, time order.
    pub fn samples(&self) -> &[ImuMeasurement] {
        &self.samples
    }

    /// Whether the samples bracket `[t0_ns, t1_ns]` with no gap inside it.
    pub fn covers(&self, t0_ns: i64, t1_ns: i64) -> bool {
        let (Some(first), Some(last)) = (self.samples.first(), self.samples.last()) else {
            return false;
        };
        first.t_ns <= t0_ns && last.t_ns >= t1_ns && self.gap_end_ns.is_none_or(|g| g <= t0_ns)
    }

    /// Drops the samples no longer needed for windows starting at or after `t_ns` (the last
    /// one before it is kept for the interpolation). Allocates nothing.
    pub fn keep_from(&mut self, t_ns: i64) {
        let k = self.samples.partition_point(|s| s.t_ns <= t_ns);
        if k > 1 {
            self.samples.drain(..k - 1);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn m(t_ns: i64) -> ImuMeasurement {
        ImuMeasurement {
            t_ns,
            gyro: Vector3::new(0.1, 0.0, 0.0),
            accel: Vector3::new(0.0, 0.0, 9.81),
        }
    }

    #[test]
    fn bad_samples_are_named_and_a_gap_is_kept_but_not_spanned() {
        let mut b = ImuBuffer::new(ImuCheck::default());
        assert_eq!(b.push(m(0)), Ok(()));
        assert_eq!(b.push(m(5_000_000)), Ok(()));
        assert_eq!(
            b.push(m(5_000_000)),
            Err(ImuSampleError::NotAfterLast {
                t_ns: 5_000_000,
                last_ns: 5_000_000
            })
        );
        assert!(b.push(m(1)).is_err_and(|e| e.refused()));
        let mut nan = m(6_000_000);
        nan.gyro.x = f64::NAN;
        assert_eq!(
            b.push(nan),
            Err(ImuSampleError::NonFinite { t_ns: 6_000_000 })
        );
        let mut sat = m(6_000_000);
        sat.accel.z = 400.0;
        assert_eq!(
            b.push(sat),
            Err(ImuSampleError::Saturated { t_ns: 6_000_000 })
        );
        assert!(b.covers(1_000_000, 4_000_000));
        let gap = b.push(m(100_000_000)).expect_err("gap");
        assert!(!gap.refused());
        assert_eq!(b.samples().len(), 3);
        assert!(!b.covers(1_000_000, 90_000_000), "a window spans the gap");
        assert_eq!(b.push(m(105_000_000)), Ok(()));
        assert!(b.covers(100_000_000, 105_000_000));
        b.keep_from(101_000_000);
        assert_eq!(b.samples()[0].t_ns, 100_000_000);
    }
}
