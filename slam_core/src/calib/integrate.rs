//! Raw IMU samples between two times: interpolation, the mid-point segments the filter
//! propagates over, and the integration from a clone to a row time (`VI_NOTES.md` §3
//! "Measurement in row v of image j": "IMU-integrate from clone j, backwards if Δ<0").

use nalgebra::Vector3;

use super::state::{CalibState, NavState};
use super::ImuSample;

/// How far (ns) past the first or last sample a time may lie and still be served by the
/// nearest sample (hold), instead of failing.
pub const HOLD_NS: f64 = 20e6;

/// Raw `(gyro, accel)` at time `t_ns` (linear interpolation between the bracketing
/// samples, held within [`HOLD_NS`] outside them). `None` outside that or without samples.
pub fn sample_at(samples: &[ImuSample], t_ns: f64) -> Option<(Vector3<f64>, Vector3<f64>)> {
    let (first, last) = (samples.first()?, samples.last()?);
    if t_ns <= first.t_ns as f64 {
        return (first.t_ns as f64 - t_ns <= HOLD_NS).then_some((first.gyro, first.accel));
    }
    if t_ns >= last.t_ns as f64 {
        return (t_ns - last.t_ns as f64 <= HOLD_NS).then_some((last.gyro, last.accel));
    }
    let i = samples.partition_point(|s| (s.t_ns as f64) <= t_ns);
    let (a, b) = (&samples[i - 1], &samples[i]);
    let span = (b.t_ns - a.t_ns) as f64;
    let w = if span > 0.0 {
        (t_ns - a.t_ns as f64) / span
    } else {
        0.0
    };
    Some((
        a.gyro + (b.gyro - a.gyro) * w,
        a.accel + (b.accel - a.accel) * w,
    ))
}

/// A piece of an interval: `(dt seconds (signed), raw gyro, raw accel)` at its middle.
pub type Segment = (f64, Vector3<f64>, Vector3<f64>);

/// The pieces of `[t0, t1]` (ns; `t1 < t0` walks backwards) cut at the sample times, each
/// as `(dt seconds (signed), gyro, accel)` with the raw values at the piece's middle.
pub fn segments(samples: &[ImuSample], t0_ns: f64, t1_ns: f64) -> Option<Vec<Segment>> {
    let (lo, hi) = (t0_ns.min(t1_ns), t0_ns.max(t1_ns));
    let mut cuts: Vec<f64> = samples
        .iter()
        .map(|s| s.t_ns as f64)
        .filter(|&t| t > lo && t < hi)
        .collect();
    cuts.insert(0, lo);
    cuts.push(hi);
    if t1_ns < t0_ns {
        cuts.reverse();
    }
    let mut out = Vec::with_capacity(cuts.len());
    for w in cuts.windows(2) {
        let (g, a) = sample_at(samples, 0.5 * (w[0] + w[1]))?;
        out.push(((w[1] - w[0]) * 1e-9, g, a));
    }
    Some(out)
}

/// Integrates `nav` from `t0_ns` to `t1_ns` with the samples corrected by the calibration
/// of `state` ([`CalibState::correct`]); returns the body state at `t1_ns` and the corrected
/// body rate and specific force there.
pub fn integrate(
    state: &CalibState,
    samples: &[ImuSample],
    nav: &NavState,
    t0_ns: f64,
    t1_ns: f64,
) -> Option<(NavState, Vector3<f64>, Vector3<f64>)> {
    let mut out = *nav;
    for (dt, g, a) in segments(samples, t0_ns, t1_ns)? {
        let (w, a_s) = state.correct(&g, &a);
        out.step(&w, &a_s, dt);
    }
    let (g, a) = sample_at(samples, t1_ns)?;
    let (w, a_s) = state.correct(&g, &a);
    Some((out, w, a_s))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::sim::test_state;

    #[test]
    fn forward_then_backward_returns_to_the_start() {
        let samples: Vec<ImuSample> = (0..40)
            .map(|k| {
                let t = k as f64 * 0.005;
                ImuSample {
                    t_ns: (t * 1e9) as i64,
                    gyro: Vector3::new(1.0 + t, -0.5, 0.3 * t),
                    accel: Vector3::new(0.5, 2.0 * t, 9.81),
                }
            })
            .collect();
        let state = test_state();
        let (mid, _, _) = integrate(&state, &samples, &state.nav, 12.3e6, 81.7e6).unwrap();
        let (back, _, _) = integrate(&state, &samples, &mid, 81.7e6, 12.3e6).unwrap();
        assert!((back.p_gb - state.nav.p_gb).norm() < 1e-9);
        assert!((back.v_gb - state.nav.v_gb).norm() < 1e-9);
        assert!(crate::lie::so3_log(&(back.r_gb.inverse() * state.nav.r_gb)).norm() < 1e-9);
        assert!(sample_at(&samples, 1e12).is_none());
        let segs = segments(&samples, 7e6, 2e6).unwrap();
        assert_eq!(segs.len(), 2);
        assert!((segs.iter().map(|s| s.0).sum::<f64>() + 5e-3).abs() < 1e-15);
    }
}
