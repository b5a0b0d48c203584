//! Backward tracking of the frames before the two-view reference (seed §3.3, issue 15).
//!
//! While a session initialises, the reference frame is replaced whenever a frame matches
//! it too little (fast motion, a start on frames with few features), so the frames before
//! the final reference are not among the initialiser's matched frames and used to stay
//! unposed. Their ORB features are kept in a bounded buffer ([`MAX_PRE_INIT`] frames);
//! once the map has [`BACKWARD_AFTER_KEYFRAMES`] keyframes (the two-view map refined by
//! local mapping: on the synthetic test the worst backward pose was 0.18 m when tracked
//! from the bare two-view map, 0.06 m after 3 keyframes, 0.05 m after 5) they are tracked
//! backwards from its oldest keyframe, newest first, each against the next
//! later frame with a constant-velocity prior, by the same projection search and
//! motion-only optimisation as forward tracking (`track.rs`; its fallback too: the
//! reference keyframe's points matched by descriptors), then against the initial map's
//! keyframes. The first frame that cannot be tracked ends the walk: the frames
//! before it stay unposed ("before init").
use std::collections::VecDeque;

use nalgebra::Isometry3;

use super::{LastFrame, VoDiagnostic, VoOutput, VoTracker};
use crate::features::OrbFeatures;
use crate::lie::{se3_exp, se3_log};
use crate::vo::map::KfId;
use crate::vo::search::ProjSearchParams;

/// Keyframes the session's map has (local mapping having refined the first ones) before
/// the frames before its reference are tracked backwards.
pub(super) const BACKWARD_AFTER_KEYFRAMES: usize = 5;

/// Most frames kept for backward tracking (about 3 s at 20 Hz; at 2,000 features a frame
/// about 110 KiB each, 7 MiB at most).
pub(super) const MAX_PRE_INIT: usize = 64;

/// A frame seen while the session initialised.
pub(super) struct PreInitFrame {
    t_ns: i64,
    readout_ns: i64,
    features: OrbFeatures,
}

/// The frames seen while initialising, oldest first, bounded by [`MAX_PRE_INIT`].
#[derive(Default)]
pub(super) struct PreInitBuffer(VecDeque<PreInitFrame>);

impl PreInitBuffer {
    /// Keeps a copy of the frame's features, reusing the oldest frame's buffers when full.
    pub(super) fn push(&mut self, t_ns: i64, readout_ns: i64, feats: &OrbFeatures) {
        let mut f = if self.0.len() >= MAX_PRE_INIT {
            self.0.pop_front()
        } else {
            None
        }
        .unwrap_or(PreInitFrame {
            t_ns,
            readout_ns,
            features: OrbFeatures::default(),
        });
        f.t_ns = t_ns;
        f.readout_ns = readout_ns;
        f.features.keypoints.clear();
        f.features.keypoints.extend_from_slice(&feats.keypoints);
        f.features.descriptors.clear();
        f.features.descriptors.extend_from_slice(&feats.descriptors);
        self.0.push_back(f);
    }

    /// Forgets the frames from `t_ns` on (posed by the initialisation's backfill).
    pub(super) fn keep_before(&mut self, t_ns: i64) {
        self.0.retain(|f| f.t_ns < t_ns);
    }

    /// Forgets every frame (a new session).
    pub(super) fn clear(&mut self) {
        self.0.clear();
    }
}

/// Constant-velocity prior going back in time: `motion = T_cw(earlier) * T_cw(later)⁻¹`
/// over `period_s`.
struct BackwardMotion {
    motion: Isometry3<f64>,
    period_s: f64,
}

impl BackwardMotion {
    /// The pose predicted at `dt_s` before the frame posed `t_cw`.
    fn predict(&self, t_cw: &Isometry3<f64>, dt_s: f64) -> Isometry3<f64> {
        let a = dt_s / self.period_s.max(1e-9);
        se3_exp(&(se3_log(&self.motion) * a)) * t_cw
    }
}

impl VoTracker {
    /// Once the session's map has [`BACKWARD_AFTER_KEYFRAMES`] keyframes (refined by local
    /// mapping), poses the buffered frames before its oldest keyframe (the two-view
    /// reference) and appends them to `out.backfill`, newest first. Empties the buffer.
    pub(super) fn maybe_track_backwards(&mut self, out: &mut VoOutput) {
        if self.pre_init.0.is_empty() || self.map.keyframes.len() < BACKWARD_AFTER_KEYFRAMES {
            return;
        }
        let mut frames = std::mem::take(&mut self.pre_init);
        self.backward = true;
        let mut kfs: Vec<(i64, KfId)> = self
            .map
            .keyframes
            .values()
            .map(|k| (k.t_ns, k.id))
            .collect();
        kfs.sort_unstable();
        if let [(t_ref, first), (t_later, second), ..] = kfs[..] {
            out.diagnostics.push(VoDiagnostic::BackwardStart {
                before: frames.0.iter().filter(|f| f.t_ns < t_ref).count(),
                kept: frames.0.len(),
                t_ref_ns: t_ref,
            });
            let mut next = self.last_from_kf(first);
            let t_cw_later = self.map.keyframes[&second].t_cw;
            let mut motion = BackwardMotion {
                motion: next.t_cw * t_cw_later.inverse(),
                period_s: (t_later - t_ref) as f64 * 1e-9,
            };
            for f in frames.0.iter().rev().filter(|f| f.t_ns < t_ref) {
                let dt_s = (next.t_ns - f.t_ns) as f64 * 1e-9;
                let guess = motion.predict(&next.t_cw, dt_s);
                let Some(t_cw) = self.track_one_backwards(f, &next, &guess) else {
                    out.diagnostics.push(VoDiagnostic::BackwardStopped {
                        kept: frames.0.len(),
                        t_ns: f.t_ns,
                        inliers: self.inliers.iter().filter(|&&i| i).count(),
                    });
                    break;
                };
                out.backfill.push((f.t_ns, t_cw));
                motion = BackwardMotion {
                    motion: t_cw * next.t_cw.inverse(),
                    period_s: dt_s,
                };
                next = LastFrame {
                    t_ns: f.t_ns,
                    t_cw,
                    features: f.features.clone(),
                    points: self.frame_points.clone(),
                };
            }
        }
        frames.clear();
        self.pre_init = frames;
        self.backward = false;
    }

    /// Poses one earlier frame: the points of `next` (the next later frame) searched around
    /// `guess`, then the initial map's points, each followed by motion-only optimisation.
    fn track_one_backwards(
        &mut self,
        f: &PreInitFrame,
        next: &LastFrame,
        guess: &Isometry3<f64>,
    ) -> Option<Isometry3<f64>> {
        let feats = &f.features;
        self.grid.build(&feats.keypoints);
        self.frame_points.clear();
        self.frame_points.resize(feats.len(), None);
        self.matcher
            .gather_frame(&self.map, &next.points, &next.features);
        let mut t_cw = *guess;
        let mut n = self.search(&t_cw, feats, &ProjSearchParams::motion_model());
        if n < 20 {
            let wide = ProjSearchParams {
                radius: 30.0,
                ..ProjSearchParams::motion_model()
            };
            n = self.search(&t_cw, feats, &wide);
        }
        let mut ok = false;
        if n >= 20 {
            if let Some((pose, inliers)) = self.optimize(f.readout_ns, feats, &t_cw, None, None) {
                ok = inliers >= 10;
                t_cw = if ok { pose } else { t_cw };
            }
        }
        // As forward tracking's fallback: the reference keyframe's points by descriptors.
        if !ok {
            self.frame_points.iter_mut().for_each(|p| *p = None);
            if self.match_reference_keyframe(feats) >= 15 {
                if let Some((pose, inliers)) = self.optimize(f.readout_ns, feats, &t_cw, None, None)
                {
                    ok = inliers >= 10;
                    t_cw = pose;
                }
            }
        }
        if !ok {
            return None;
        }
        self.gather_local_map_candidates();
        self.search(&t_cw, feats, &ProjSearchParams::local_map());
        let (pose, inliers) = self.optimize(f.readout_ns, feats, &t_cw, None, None)?;
        (inliers >= self.params.min_inliers).then_some(pose)
    }
}
