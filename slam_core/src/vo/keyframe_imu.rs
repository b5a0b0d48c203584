//! The IMU a keyframe of a visual-inertial client carries (issue 17; `VI_NOTES.md` §4,
//! Fig. 5.4: "raw IMU since the last one (with bracketing samples)"): the samples between
//! the previous keyframe of its VO session and itself, and the calibration to preintegrate
//! them, so that local mapping's visual-inertial window ([`super::vi_window`]) re-integrates
//! them at the current biases, inline or on its own thread, from the map alone.
//!
//! - The VO attaches a segment to each keyframe it makes ([`KeyframeImuSource::segment`]),
//!   from samples the visual-inertial client hands it as they arrive
//!   ([`KeyframeImuSource::push`]); the segment is cut at creation, under the map's lock,
//!   before local mapping sees the keyframe, so lock-step runs stay deterministic.
//! - A culled keyframe's segment joins its successor's ([`join_segments`]; `VI_NOTES.md` §4
//!   "[P] A culled keyframe joins its two segments"), so consecutive keyframes of the map
//!   stay linked.
//! - Times are on the IMU clock (`t_imu = t_cam + t_d`, `VI_NOTES.md` §1).
//! - On the wire to the server (issue 19) a segment goes with its border samples
//!   interpolated at exactly the two keyframes' times ([`KeyframeImu::interpolated_samples`],
//!   Fig. 5.4): neighbours share the border sample, no gap, no overlap.
use nalgebra::Isometry3;

use crate::imu::preint::interpolate;
use crate::imu::{ImuMeasurement, PreintegrationParams};

/// The fixed IMU calibration of a visual-inertial client.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct ImuCalibration {
    /// Noise densities and intrinsics of the preintegration.
    pub preint: PreintegrationParams,
    /// Camera to body (IMU): `p_b = T_bc p_c` (EuRoC `T_BS`), metric.
    pub t_bc: Isometry3<f64>,
    /// Camera-IMU time offset: `t_imu = t_cam + t_d`, ns.
    pub t_d_ns: i64,
}

/// A keyframe's IMU segment ([`crate::vo::Keyframe::imu`]).
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct KeyframeImu {
    /// IMU-clock time of the previous keyframe of the session when this one was made (or
    /// of the keyframe it replaced by a join), ns; `None` for a session's first keyframe.
    pub t_prev_ns: Option<i64>,
    /// IMU-clock time of this keyframe (`t_ns + t_d`), ns.
    pub t_ns: i64,
    /// The samples over `[t_prev_ns, t_ns]` with one bracketing sample at each end where
    /// the stream had it, time order.
    pub samples: Vec<ImuMeasurement>,
    /// The calibration to preintegrate them with.
    pub calib: ImuCalibration,
}

impl KeyframeImu {
    /// Whether the samples bracket `[t_prev_ns, t_ns]` (a complete segment: the
    /// preintegration from the previous keyframe exists).
    pub fn is_complete(&self) -> bool {
        match (self.t_prev_ns, self.samples.first(), self.samples.last()) {
            (Some(t0), Some(a), Some(b)) => a.t_ns <= t0 && b.t_ns >= self.t_ns,
            _ => false,
        }
    }

    /// Whether this segment starts at `prev` (the keyframe before it in the map) and is
    /// complete: the two keyframes are linked by an IMU factor.
    pub fn links(&self, prev: &KeyframeImu) -> bool {
        self.t_prev_ns == Some(prev.t_ns) && self.is_complete()
    }

    /// The segment as a keyframe message carries it (`VI_NOTES.md` §4, Fig. 5.4): the
    /// samples strictly inside `(t_prev_ns, t_ns)`, unchanged, between two border samples
    /// linearly interpolated at exactly `t_prev_ns` and `t_ns` from the samples bracketing
    /// them, so that the segments of consecutive keyframes share their border sample
    /// (bit for bit: both interpolate the same two samples). Preintegrating it gives what
    /// preintegrating the bracketed samples gives. `None` when the segment is not complete
    /// ([`Self::is_complete`]; a session's first keyframe, or a border sample missing).
    pub fn interpolated_samples(&self) -> Option<Vec<ImuMeasurement>> {
        let t0 = self.t_prev_ns.filter(|_| self.is_complete())?;
        let s = &self.samples;
        // The sample at `t` or the two around it (they exist: the segment is complete).
        let border = |t: i64| {
            let k = s.partition_point(|m| m.t_ns < t);
            match (k.checked_sub(1).and_then(|j| s.get(j)), s.get(k)) {
                (_, Some(b)) if b.t_ns == t => Some(*b),
                (Some(a), Some(b)) => Some(interpolate(a, b, t)),
                _ => None,
            }
        };
        let inside = s.iter().filter(|m| m.t_ns > t0 && m.t_ns < self.t_ns);
        let mut out = Vec::with_capacity(s.len());
        out.push(border(t0)?);
        out.extend(inside.copied());
        if self.t_ns > t0 {
            out.push(border(self.t_ns)?);
        }
        Some(out)
    }
}

/// The samples of `samples` (time order) over `[t0_ns, t1_ns]` with one bracketing sample
/// at each end when there is one.
pub fn bracket(samples: &[ImuMeasurement], t0_ns: i64, t1_ns: i64) -> &[ImuMeasurement] {
    let start = samples
        .partition_point(|s| s.t_ns <= t0_ns)
        .saturating_sub(1);
    let end = (samples.partition_point(|s| s.t_ns < t1_ns) + 1).min(samples.len());
    &samples[start.min(end)..end]
}

/// The segment of a culled keyframe (`culled`) joined into its successor's (`next`):
/// `next` then starts where `culled` started, with `culled`'s samples before its own. When
/// `next` does not start at `culled` (it was not linked to it) nothing changes.
pub fn join_segments(culled: &KeyframeImu, next: &mut KeyframeImu) {
    if next.t_prev_ns != Some(culled.t_ns) {
        return;
    }
    let first = next.samples.first().map_or(i64::MAX, |s| s.t_ns);
    let cut = culled.samples.partition_point(|s| s.t_ns < first);
    next.samples
        .splice(0..0, culled.samples[..cut].iter().copied());
    next.t_prev_ns = culled.t_prev_ns;
}

/// Samples kept before a session's first keyframe, ns (the two-view reference is at most
/// 64 frames older than the frame that initialises the map).
const KEEP_BEFORE_FIRST_KF_NS: i64 = 4_000_000_000;

/// The VO's IMU samples since its last keyframe, cut into a segment for each new keyframe
/// (module docs).
#[derive(Debug, Clone)]
pub struct KeyframeImuSource {
    calib: ImuCalibration,
    samples: Vec<ImuMeasurement>,
    /// IMU time of the session's last keyframe.
    last_kf_ns: Option<i64>,
}

impl KeyframeImuSource {
    /// An empty source with the client's calibration.
    pub fn new(calib: ImuCalibration) -> Self {
        Self {
            calib,
            samples: Vec::new(),
            last_kf_ns: None,
        }
    }

    /// Takes a sample (ignored when not after the last one). Before the session's first
    /// keyframe only the last few seconds are kept. Amortised O(1).
    pub fn push(&mut self, m: ImuMeasurement) {
        if self.samples.last().is_some_and(|l| l.t_ns >= m.t_ns) {
            return;
        }
        self.samples.push(m);
        if self.last_kf_ns.is_none() && self.samples[0].t_ns < m.t_ns - 2 * KEEP_BEFORE_FIRST_KF_NS
        {
            let keep_from = m.t_ns - KEEP_BEFORE_FIRST_KF_NS;
            let k = self.samples.partition_point(|s| s.t_ns < keep_from);
            self.samples.drain(..k);
        }
    }

    /// The segment of a new keyframe at camera time `t_cam_ns` (after the session's last
    /// one): the samples since the last keyframe; then only the samples from this keyframe
    /// on are kept.
    pub fn segment(&mut self, t_cam_ns: i64) -> KeyframeImu {
        let t_ns = t_cam_ns + self.calib.t_d_ns;
        let t0 = self.last_kf_ns.unwrap_or(t_ns);
        let seg = KeyframeImu {
            t_prev_ns: self.last_kf_ns,
            t_ns,
            samples: bracket(&self.samples, t0, t_ns).to_vec(),
            calib: self.calib,
        };
        self.last_kf_ns = Some(t_ns);
        let k = self
            .samples
            .partition_point(|s| s.t_ns <= t_ns)
            .saturating_sub(1);
        self.samples.drain(..k);
        seg
    }

    /// The session's last keyframe was made at camera time `t_cam_ns` by an earlier source
    /// (a session continued after a restart): the next segment starts there, with the
    /// samples pushed from then on (older ones are dropped when the next keyframe is cut).
    pub fn continue_after(&mut self, t_cam_ns: i64) {
        self.last_kf_ns = Some(t_cam_ns + self.calib.t_d_ns);
    }

    /// A new VO session: its first keyframe has no predecessor (the samples are kept).
    pub fn new_session(&mut self) {
        self.last_kf_ns = None;
    }

    /// The calibration.
    pub fn calibration(&self) -> &ImuCalibration {
        &self.calib
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::imu::Preintegrated;
    use nalgebra::Vector3;

    fn m(t_ns: i64) -> ImuMeasurement {
        ImuMeasurement {
            t_ns,
            gyro: Vector3::new(t_ns as f64, 0.0, 0.0),
            accel: Vector3::zeros(),
        }
    }

    fn source() -> KeyframeImuSource {
        let preint =
            PreintegrationParams::new(&Default::default(), &Default::default()).expect("params");
        KeyframeImuSource::new(ImuCalibration {
            preint,
            t_bc: Isometry3::identity(),
            t_d_ns: 2,
        })
    }

    /// Samples every 10 ns; keyframes at camera times 18, 48 (IMU 20, 50), 78 (IMU 80):
    /// each segment brackets the span from its predecessor; a culled middle keyframe's
    /// segment joins the next one's without duplicates.
    #[test]
    fn segments_bracket_the_span_and_join_on_culling() {
        let mut s = source();
        for t in (0..=100).step_by(10) {
            s.push(m(t));
        }
        s.push(m(100));
        let a = s.segment(18);
        assert_eq!((a.t_prev_ns, a.t_ns), (None, 20));
        assert!(!a.is_complete());
        let b = s.segment(48);
        let times = |k: &KeyframeImu| k.samples.iter().map(|x| x.t_ns).collect::<Vec<_>>();
        assert_eq!(times(&b), vec![20, 30, 40, 50]);
        assert!(b.links(&a) && b.is_complete());
        let mut c = s.segment(78);
        assert_eq!(times(&c), vec![50, 60, 70, 80]);
        assert!(c.links(&b) && !c.links(&a));
        join_segments(&b, &mut c);
        assert_eq!(times(&c), vec![20, 30, 40, 50, 60, 70, 80]);
        assert!(c.links(&a));
        // A segment whose end sample has not arrived is incomplete.
        let d = s.segment(108);
        assert!(!d.is_complete());
        assert_eq!(bracket(&[m(0), m(10)], 3, 7).len(), 2);
        assert!(bracket(&[], 3, 7).is_empty());
    }

    /// A sample of a smooth signal at `t_ns` (3 ms spacing, not a multiple of the
    /// keyframe times, so the borders fall between samples).
    fn smooth(t_ns: i64) -> ImuMeasurement {
        let t = t_ns as f64 * 1e-9;
        ImuMeasurement {
            t_ns,
            gyro: Vector3::new((3.0 * t).sin(), 0.2 * t, (2.0 * t).cos()),
            accel: Vector3::new(0.5 * t, (t * 5.0).cos(), 9.81 + 0.1 * t),
        }
    }

    /// Fig. 5.4: the wire segment starts and ends exactly at the two keyframes' IMU times,
    /// its interior samples are the stream's, unchanged, and it preintegrates to what the
    /// bracketed samples give; two consecutive segments tile the time axis (one shared
    /// border sample, bit for bit, no gap, no overlap).
    #[test]
    fn interpolated_segments_have_exact_borders_and_tile() {
        let mut s = source();
        for k in 0..200 {
            s.push(smooth(k * 3_000_000));
        }
        let _first = s.segment(10_000_000);
        let a = s.segment(100_000_001);
        let b = s.segment(250_000_007);
        let (wa, wb) = (
            a.interpolated_samples().expect("complete"),
            b.interpolated_samples().expect("complete"),
        );
        let t0 = a.t_prev_ns.expect("has a predecessor");
        assert_eq!((t0, a.t_ns), (10_000_002, 100_000_003));
        assert_eq!(wa.first().map(|m| m.t_ns), Some(t0));
        assert_eq!(wa.last().map(|m| m.t_ns), Some(a.t_ns));
        let interior: Vec<_> = a
            .samples
            .iter()
            .filter(|m| m.t_ns > t0 && m.t_ns < a.t_ns)
            .copied()
            .collect();
        assert_eq!(&wa[1..wa.len() - 1], &interior[..]);
        assert!(wa.windows(2).all(|w| w[0].t_ns < w[1].t_ns));
        // The interpolated border lies on the segment between its two neighbours.
        let (p, q) = (a.samples[0], a.samples[1]);
        let f = (t0 - p.t_ns) as f64 / (q.t_ns - p.t_ns) as f64;
        assert!((wa[0].gyro - (p.gyro + (q.gyro - p.gyro) * f)).norm() < 1e-15);
        // Tiling: b starts where a ends, with the same sample.
        assert_eq!(b.t_prev_ns, Some(a.t_ns));
        assert_eq!(wb.first(), wa.last());
        let covered: i64 = [&wa, &wb]
            .iter()
            .map(|w| w[w.len() - 1].t_ns - w[0].t_ns)
            .sum();
        assert_eq!(covered, b.t_ns - t0);
        // Same preintegration as the bracketed samples.
        let bias = crate::imu::ImuBiases::default();
        let params = a.calib.preint;
        let raw = Preintegrated::from_window(&a.samples, t0, a.t_ns, bias, params);
        let wire = Preintegrated::from_window(&wa, t0, a.t_ns, bias, params);
        let (raw, wire) = (raw.expect("raw"), wire.expect("wire"));
        let dr = (raw.delta_r().matrix() - wire.delta_r().matrix()).norm();
        assert!(dr < 1e-12, "{dr}");
        assert!((raw.delta_v() - wire.delta_v()).norm() < 1e-12);
        assert!((raw.delta_p() - wire.delta_p()).norm() < 1e-12);
        assert!((raw.covariance() - wire.covariance()).norm() < 1e-12);
    }

    /// No wire segment for a session's first keyframe or an incomplete one; a segment
    /// whose border falls on a sample keeps that sample.
    #[test]
    fn interpolated_samples_need_a_complete_segment() {
        let mut s = source();
        for t in (0..=100).step_by(10) {
            s.push(m(t));
        }
        assert_eq!(s.segment(18).interpolated_samples(), None);
        let b = s.segment(48);
        let w = b.interpolated_samples().expect("complete");
        let times: Vec<i64> = w.iter().map(|x| x.t_ns).collect();
        assert_eq!(times, vec![20, 30, 40, 50]);
        assert_eq!(w, b.samples);
        assert_eq!(s.segment(108).interpolated_samples(), None);
    }

    /// A source continuing a session (a restarted tracker) cuts the next segment from the
    /// session's last keyframe: the same segment a source that made that keyframe cuts, so
    /// the keyframes stay linked across the restart; without the samples back to it the
    /// segment is incomplete (no wire records), never silently shorter.
    #[test]
    fn a_continued_source_links_to_the_last_keyframe_of_the_session() {
        let mut first = source();
        for t in (0..=100).step_by(10) {
            first.push(m(t));
        }
        let _ = first.segment(18);
        let b = first.segment(48);
        let c_ref = first.segment(78);
        let mut next = source();
        next.continue_after(48);
        for t in (50..=100).step_by(10) {
            next.push(m(t));
        }
        let c = next.segment(78);
        assert_eq!(c, c_ref);
        assert!(c.links(&b));
        let mut late = source();
        late.continue_after(48);
        for t in (60..=100).step_by(10) {
            late.push(m(t));
        }
        let short = late.segment(78);
        assert_eq!(short.t_prev_ns, Some(50));
        assert!(!short.is_complete() && short.interpolated_samples().is_none());
    }

    /// Before the first keyframe only the last seconds are kept.
    #[test]
    fn samples_before_the_first_keyframe_are_bounded() {
        let mut s = source();
        for k in 0..4000 {
            s.push(m(k * 5_000_000));
        }
        assert!(s.samples.len() <= 1601, "{}", s.samples.len());
        let t_last = s.samples.last().expect("samples").t_ns;
        assert!(s.samples[0].t_ns <= t_last - KEEP_BEFORE_FIRST_KF_NS);
    }
}
