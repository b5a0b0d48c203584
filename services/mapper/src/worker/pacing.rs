//! How often a handler group runs its idle step (local BA and culling) so that it keeps
//! real time: the seed's handler (Fig. 3.3, 5.3) sleeps an interval `t_d` between rounds
//! ("Sleep t_d"; `VI_NOTES.md` calls it `handler_sleep`: an adaptive interval, not the time
//! offset, its rule not given; proposal: shrink it as the backlog grows). Here a handler
//! does not sleep: it blocks on its queue and takes a keyframe the moment it comes. What
//! adapts is the *idle interval*: the idle step runs whenever the queue is empty, and in a
//! backlog at least every `k` keyframes, with `k` the smallest count whose share of idle
//! work still fits the time the keyframes leave:
//!
//! ```text
//! budget per keyframe  b = UTILISATION / Σ_clients rate_c     (keyframes' stream times)
//! k = ⌈ idle / (b − handle) ⌉,  clamped to [1, MAX_INTERVAL];  MAX_INTERVAL when b ≤ handle
//! ```
//!
//! with `handle` and `idle` the smoothed times of one keyframe and one idle step. A group
//! that keeps up idles after every keyframe (the queue is empty); one that falls behind
//! spaces its local BAs out until the queue drains, instead of falling further behind.
//! Lock-step runs use the fixed [`super::MAX_WITHOUT_IDLE`] (their schedule must not depend
//! on the machine).
use std::collections::BTreeMap;

/// Share of the time between keyframes a handler group may fill.
pub const UTILISATION: f64 = 0.8;
/// Most keyframes between two idle steps.
pub const MAX_INTERVAL: usize = 32;
/// Smoothing of the measured times and rates.
const ALPHA: f64 = 0.2;

/// Smoothed costs and keyframe rates of a handler group (module docs).
#[derive(Debug, Clone, Default)]
pub struct IdlePacing {
    handle_ms: Option<f64>,
    idle_ms: Option<f64>,
    /// Per client: the last keyframe's stream time and the smoothed keyframe rate, Hz.
    rates: BTreeMap<u32, (i64, Option<f64>)>,
}

fn smooth(old: Option<f64>, x: f64) -> Option<f64> {
    Some(old.map_or(x, |o| o + ALPHA * (x - o)))
}

impl IdlePacing {
    /// A keyframe of `client` at stream time `t_ns` took `handle_ms` to handle.
    pub fn on_keyframe(&mut self, client: u32, t_ns: i64, handle_ms: f64) {
        self.handle_ms = smooth(self.handle_ms, handle_ms);
        let e = self.rates.entry(client).or_insert((t_ns, None));
        let dt_s = (t_ns - e.0) as f64 * 1e-9;
        if dt_s > 0.0 {
            e.1 = smooth(e.1, 1.0 / dt_s);
        }
        e.0 = e.0.max(t_ns);
    }

    /// An idle step took `idle_ms`.
    pub fn on_idle(&mut self, idle_ms: f64) {
        self.idle_ms = smooth(self.idle_ms, idle_ms);
    }

    /// Keyframes per second the group receives (its clients' smoothed rates summed).
    pub fn rate_hz(&self) -> f64 {
        self.rates.values().filter_map(|r| r.1).sum()
    }

    /// The idle interval `k` (module docs); `default` until costs and a rate are measured.
    pub fn interval(&self, default: usize) -> usize {
        let (Some(handle), Some(idle)) = (self.handle_ms, self.idle_ms) else {
            return default;
        };
        let rate = self.rate_hz();
        if rate <= 0.0 {
            return default;
        }
        let spare = UTILISATION * 1e3 / rate - handle;
        if spare <= 0.0 {
            return MAX_INTERVAL;
        }
        ((idle / spare).ceil() as usize).clamp(1, MAX_INTERVAL)
    }

    /// Whether the idle step is due after a keyframe: the queue is empty, or `since_idle`
    /// keyframes have been handled since the last one and this one makes the interval.
    pub fn idle_due(&self, since_idle: usize, queue_empty: bool, default: usize) -> bool {
        queue_empty || since_idle + 1 >= self.interval(default)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Keyframes of two clients at 2 Hz each (a budget of 200 ms per keyframe): with 20 ms
    /// per keyframe and 90 ms per idle step a backlog idles every keyframe (110 < 200);
    /// at 500 ms per idle step every 3rd (20 + 500/3 < 200); when handling alone takes the
    /// budget, as rarely as allowed.
    #[test]
    fn the_interval_fits_the_idle_work_into_the_time_between_keyframes() {
        let mut p = IdlePacing::default();
        assert_eq!(p.interval(4), 4, "nothing measured yet");
        for k in 0..40 {
            for c in 0..2 {
                p.on_keyframe(c, k * 500_000_000 + i64::from(c), 20.0);
            }
            p.on_idle(90.0);
        }
        assert!((p.rate_hz() - 4.0).abs() < 1e-6, "{}", p.rate_hz());
        assert_eq!(p.interval(4), 1);
        for _ in 0..60 {
            p.on_idle(500.0);
        }
        assert_eq!(p.interval(4), 3);
        assert!(!p.idle_due(1, false, 4) && p.idle_due(2, false, 4) && p.idle_due(0, true, 4));
        for _ in 0..60 {
            p.on_keyframe(0, 40 * 500_000_000, 250.0);
        }
        assert_eq!(p.interval(4), MAX_INTERVAL);
        // Out-of-order or repeated stream times do not make a rate.
        let mut q = IdlePacing::default();
        q.on_keyframe(0, 10, 1.0);
        q.on_keyframe(0, 5, 1.0);
        assert_eq!(q.rate_hz(), 0.0);
    }
}
