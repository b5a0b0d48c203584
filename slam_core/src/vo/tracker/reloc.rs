//! Relocalisation against the keyframes of the client map (seed §3.3: "track the last
//! frame or relocalise"): when neither the motion model nor the reference keyframe gives a
//! pose, the frame's descriptors are matched to candidate keyframes, the matches that hit
//! map points give 2D-3D correspondences, and a PnP RANSAC (EPnP + motion-only polish,
//! `crate::pnp`) followed by the motion-only optimisation decides.
//!
//! Without a place-recognition vocabulary on the client, candidates are taken from the
//! whole map in rounds: the keyframes around the reference keyframe first, then the others
//! from the newest down, at most [`VoParams::reloc_candidates`](super::VoParams) per
//! frame, continuing where the previous frame stopped, so a lost client sweeps its whole
//! window within a few frames at a bounded cost per frame.
use nalgebra::{Isometry3, Vector2, Vector3};

use super::{VoFrame, VoTracker};
use crate::features::{match_brute_force, rotation_consistency, MatchParams, OrbFeatures};
use crate::pnp::{solve_pnp_ransac_with, PnpParams};
use crate::vo::map::{KfId, PointId};

/// Least descriptor matches with map points to try a PnP on a candidate.
const MIN_MATCHES: usize = 15;

impl VoTracker {
    /// Tries to relocalise the frame; on success `frame_points` holds the inlier matches,
    /// the reference keyframe is the candidate that worked, and the pose and inlier count
    /// are returned.
    pub(super) fn relocalize(
        &mut self,
        frame: &VoFrame<'_>,
        feats: &OrbFeatures,
    ) -> Option<(Isometry3<f64>, usize)> {
        let candidates = self.reloc_candidates();
        let mut matches = Vec::new();
        let mp = MatchParams {
            ratio: 0.75,
            ..MatchParams::default()
        };
        let pnp = PnpParams {
            min_inliers: MIN_MATCHES,
            ..PnpParams::for_camera(&self.camera)
        };
        let mut pts: Vec<Vector3<f64>> = Vec::new();
        let mut xn: Vec<Vector2<f64>> = Vec::new();
        let mut w: Vec<f64> = Vec::new();
        let mut idx: Vec<(usize, PointId)> = Vec::new();
        for k in candidates {
            let Some(kf) = self.map.keyframes.get(&k) else {
                continue;
            };
            match_brute_force(
                &kf.features.descriptors,
                &feats.descriptors,
                &mp,
                &mut matches,
            );
            rotation_consistency(&mut matches, &kf.features.keypoints, &feats.keypoints, 30);
            pts.clear();
            xn.clear();
            w.clear();
            idx.clear();
            for m in &matches {
                let Some(p) = kf.points.get(m.query as usize).copied().flatten() else {
                    continue;
                };
                let Some(point) = self.map.points.get(&p) else {
                    continue;
                };
                let kp = feats.keypoints[m.train as usize];
                let b = self
                    .camera
                    .unproject(&Vector2::new(kp.x as f64, kp.y as f64));
                if b.z <= 1e-9 {
                    continue;
                }
                pts.push(point.p_w);
                xn.push(Vector2::new(b.x / b.z, b.y / b.z));
                w.push(feats.scale.inv_sigma2(kp.octave));
                idx.push((m.train as usize, p));
            }
            if pts.len() < MIN_MATCHES {
                continue;
            }
            let Ok(res) = solve_pnp_ransac_with(&mut self.pnp, &pts, &xn, &w, &pnp) else {
                continue;
            };
            self.frame_points.iter_mut().for_each(|p| *p = None);
            for (j, &(i, p)) in idx.iter().enumerate() {
                if res.inliers[j] {
                    self.frame_points[i] = Some(p);
                }
            }
            let Some((pose, inl)) = self.optimize(frame.readout_ns, feats, &res.t_cw, None, None)
            else {
                continue;
            };
            if inl >= MIN_MATCHES {
                self.ref_kf = Some(k);
                self.relocalized += 1;
                return Some((pose, inl));
            }
        }
        self.frame_points.iter_mut().for_each(|p| *p = None);
        None
    }

    /// This frame's candidate keyframes: the reference keyframe's neighbourhood, then a
    /// round-robin slice of the rest of the map (newest first).
    fn reloc_candidates(&mut self) -> Vec<KfId> {
        let n = self.params.reloc_candidates.max(1);
        let mut out: Vec<KfId> = Vec::with_capacity(n);
        if self.reloc_cursor.is_none() {
            if let Some(r) = self.ref_kf.filter(|r| self.map.keyframes.contains_key(r)) {
                out.push(r);
                out.extend(self.map.covisible(r, n.saturating_sub(1), 1));
            }
        }
        let all: Vec<KfId> = self.map.keyframes.keys().rev().copied().collect();
        if all.is_empty() {
            return out;
        }
        let start = self.reloc_cursor.unwrap_or(0) % all.len();
        let mut taken = 0;
        while out.len() < n && taken < all.len() {
            let k = all[(start + taken) % all.len()];
            taken += 1;
            if !out.contains(&k) {
                out.push(k);
            }
        }
        self.reloc_cursor = Some((start + taken) % all.len());
        out
    }
}
