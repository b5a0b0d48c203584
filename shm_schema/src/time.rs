//! The time base. Sensor times are `i64` nanoseconds on the sensor clock; latency stamps are
//! `i64` nanoseconds on the host's `CLOCK_MONOTONIC`, comparable across processes.

/// Host `CLOCK_MONOTONIC` now, in nanoseconds. Same clock in every process of the host.
pub fn monotonic_ns() -> i64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec; CLOCK_MONOTONIC always exists on Linux.
    unsafe {
        libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts);
    }
    ts.tv_sec * 1_000_000_000 + ts.tv_nsec
}

/// Capture time of pixel row `row` (0-based; pixel centres at integer rows, as in
/// `slam_core::rolling_shutter` and the synthetic renderer) of a frame whose
/// middle row was exposed at `t_mid_ns`, with readout time `readout_ns` over `rows` rows
/// (seed eq. 2.61-2.63: `t(v) = t_mid + (v - N/2) t_r / N`). Global shutter: `readout_ns = 0`.
pub fn row_time_ns(t_mid_ns: i64, readout_ns: i64, row: u32, rows: u32) -> i64 {
    if rows == 0 || readout_ns == 0 {
        return t_mid_ns;
    }
    let v = row as f64 - rows as f64 / 2.0;
    t_mid_ns + (v * readout_ns as f64 / rows as f64).round() as i64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn monotonic_increases() {
        let a = monotonic_ns();
        let b = monotonic_ns();
        assert!(a > 0 && b >= a);
    }

    #[test]
    fn row_times_span_readout() {
        let (t, tr, n) = (1_000_000_000, 30_000_000, 480);
        let first = row_time_ns(t, tr, 0, n);
        let last = row_time_ns(t, tr, n - 1, n);
        assert_eq!(row_time_ns(t, 0, 7, n), t);
        assert!((last - first - (tr - tr / n as i64)).abs() <= 1);
        assert_eq!(row_time_ns(t, tr, n / 2, n), t);
        assert_eq!(first, t - tr / 2);
    }
}
