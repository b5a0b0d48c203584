//! Refinement of a predicted server keyframe pose against the local server map (seed
//! §3.4.1, after eq. 3.4): the client's own point ids give direct matches, the points of
//! the local keyframes (the reference keyframe, its best covisible keyframes, and keyframes
//! near the predicted pose, so that a revisited area is found again) are matched by
//! projection, then the pose-only optimiser (Huber, inlier rounds) refines the pose.
use nalgebra::{Isometry3, Vector3};

use super::handler::HandlerParams;
use super::server_map::ServerMap;
use super::types::ServerKeyframe;
use crate::features::FeatureGrid;
use crate::optim::{PoseObservation, PoseOptimizer};
use crate::vo::search::{pose_observations, LocalMapMatcher, ProjSearchParams};
use crate::vo::{KfId, PointId};
use crate::CoreError;

/// Reusable buffers of the refinement (grown once, then reused).
#[derive(Debug, Default)]
pub(crate) struct Refiner {
    grid: Option<((u32, u32), FeatureGrid)>,
    optimizer: PoseOptimizer,
    matcher: LocalMapMatcher,
    near: Vec<(f64, KfId)>,
    obs: Vec<PoseObservation>,
    obs_kp: Vec<usize>,
    inliers: Vec<bool>,
}

/// Outcome of [`Refiner::refine`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct Refined {
    /// Refined `T_sk` (the prediction when too few inliers).
    pub t_sk: Isometry3<f64>,
    /// Inlier points (also left in `frame_points`).
    pub inliers: usize,
}

impl Refiner {
    /// Refines `pred` (`T_sk`) of `kf`; `frame_points` receives the inlier server point of
    /// each keypoint.
    pub fn refine(
        &mut self,
        map: &ServerMap,
        kf: &ServerKeyframe,
        pred: &Isometry3<f64>,
        reference: Option<KfId>,
        params: &HandlerParams,
        frame_points: &mut Vec<Option<PointId>>,
    ) -> Result<Refined, CoreError> {
        let n = kf.features.len();
        frame_points.clear();
        frame_points.resize(n, None);
        // Direct matches from the client's point ids.
        for (i, c) in kf.client_points.iter().enumerate() {
            if let Some(s) = c.and_then(|c| map.server_point((kf.client_id, kf.session_id), c)) {
                frame_points[i] = Some(s);
            }
        }
        let size = (kf.camera.width, kf.camera.height);
        if self.grid.as_ref().is_none_or(|(s, _)| *s != size) {
            let g = FeatureGrid::new(size.0 as usize, size.1 as usize, 16.0)?;
            self.grid = Some((size, g));
        }
        let Some((_, grid)) = self.grid.as_mut() else {
            return Err(CoreError::InvalidArgument("no feature grid".into()));
        };
        grid.build(&kf.features.keypoints);
        self.gather_local_map(map, pred, reference, params, frame_points);
        let mut t_sk = *pred;
        let wide = ProjSearchParams {
            radius: params.search_radius,
            ratio: 0.8,
            skip_matched_points: true,
            ..ProjSearchParams::motion_model()
        };
        self.search(kf, &t_sk, &wide, frame_points);
        let mut inliers = self.optimize(map, kf, &mut t_sk, params, frame_points)?;
        if inliers >= params.min_refine_inliers {
            let local = ProjSearchParams {
                skip_matched_points: true,
                ..ProjSearchParams::local_map()
            };
            self.search(kf, &t_sk, &local, frame_points);
            inliers = self.optimize(map, kf, &mut t_sk, params, frame_points)?;
        }
        if inliers < params.min_refine_inliers {
            frame_points.iter_mut().for_each(|p| *p = None);
            return Ok(Refined {
                t_sk: *pred,
                inliers: 0,
            });
        }
        Ok(Refined { t_sk, inliers })
    }

    /// Candidates: points of the reference keyframe, its best covisible keyframes and the
    /// keyframes near the predicted pose, without those already matched.
    fn gather_local_map(
        &mut self,
        map: &ServerMap,
        pred: &Isometry3<f64>,
        reference: Option<KfId>,
        params: &HandlerParams,
        frame_points: &[Option<PointId>],
    ) {
        let m = &map.map;
        self.matcher
            .select_keyframes(m, reference, params.local_keyframes);
        // Keyframes near the prediction, looking the same way.
        let depth = reference
            .and_then(|r| m.median_depth(r))
            .unwrap_or(1.0)
            .max(1e-6);
        let radius = params.spatial_radius * depth;
        let center = pred.translation.vector;
        let axis = pred.rotation * Vector3::z();
        self.near.clear();
        for (id, k) in &m.keyframes {
            let t_wc = k.t_cw.inverse();
            let d = (t_wc.translation.vector - center).norm();
            if d <= radius && (t_wc.rotation * Vector3::z()).dot(&axis) >= params.spatial_min_cos {
                self.near.push((d, *id));
            }
        }
        self.near
            .sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        for (_, id) in self.near.iter().take(params.spatial_keyframes) {
            self.matcher.add_keyframe(*id);
        }
        self.matcher.gather_local_map(m, frame_points);
    }

    /// Projection search of the candidates not yet matched; fills free `frame_points`.
    fn search(
        &mut self,
        kf: &ServerKeyframe,
        t_sk: &Isometry3<f64>,
        p: &ProjSearchParams,
        frame_points: &mut [Option<PointId>],
    ) {
        let Some((_, grid)) = self.grid.as_ref() else {
            return;
        };
        self.matcher.search(
            &t_sk.inverse(),
            &kf.camera,
            &kf.features,
            grid,
            p,
            frame_points,
        );
    }

    /// Pose-only optimisation over the matches; outliers are unmatched. Returns the inliers
    /// (0 and `t_sk` unchanged with fewer than 6 matches).
    fn optimize(
        &mut self,
        map: &ServerMap,
        kf: &ServerKeyframe,
        t_sk: &mut Isometry3<f64>,
        params: &HandlerParams,
        frame_points: &mut [Option<PointId>],
    ) -> Result<usize, CoreError> {
        pose_observations(
            &map.map,
            &kf.features,
            frame_points,
            (0, &kf.camera),
            &mut self.obs,
            &mut self.obs_kp,
        );
        if self.obs.len() < 6 {
            return Ok(0);
        }
        self.inliers.clear();
        self.inliers.resize(self.obs.len(), true);
        // A failed optimisation (degenerate geometry) leaves the prediction.
        let Ok(res) = self.optimizer.optimize(
            &kf.camera,
            &t_sk.inverse(),
            &self.obs,
            None,
            &params.pose_opt,
            &mut self.inliers,
        ) else {
            return Ok(0);
        };
        for (j, &k) in self.obs_kp.iter().enumerate() {
            if !self.inliers[j] {
                frame_points[k] = None;
            }
        }
        *t_sk = res.t_cw.inverse();
        Ok(res.n_inliers)
    }
}
