//! Motion-only (pose-only) optimisation of a frame against fixed map points, as in
//! ORB-SLAM's tracking (Mur-Artal et al. 2015, section V-D; the seed uses the same
//! refinement for its server keyframes, section 3.4.1): Levenberg-Marquardt on SE(3)
//! minimising the robust reprojection error in pixels, in rounds that reclassify inliers.
//!
//! **Model.** The pose is `T_cw` (world to camera at the frame's mid-row time); increments
//! are on the left, `T_cw ← Exp(δ) T_cw`, `δ = [ω; v]` ([`crate::lie::se3_exp`]). The
//! residual of an observation is `π(p_c) - u` (pixels) with `π` the full
//! [`PinholeRadtan`] projection (distortion included); its Jacobian is analytic:
//! `∂π/∂p_c = diag(fx, fy) · ∂distort/∂x_n · ∂x_n/∂p_c` and `∂p_c/∂δ = R_A [-[q]x | I]`,
//! with `q = T_cw p_w` and `A` the rolling-shutter correction below (identity for a global
//! shutter). Information is `1 / σ²` per observation; the cost is `Σ ρ(rᵀ Ω r)`.
//!
//! **Rounds (ORB-SLAM).** [`PoseOptParams::rounds`] (4) rounds of at most
//! [`PoseOptParams::iterations_per_round`] (10) LM iterations over the current inliers; after
//! each round every observation is classified by `χ² = rᵀ Ω r ≤ chi2` (5.991, 2 dof) at the
//! new pose — outliers can come back. The Huber kernel (`δ = √5.991`) is used in the first
//! [`PoseOptParams::huber_rounds`] (2) rounds, plain least squares afterwards. Unlike
//! ORB-SLAM, a round starts from the previous round's pose, not from the initial guess.
//!
//! **Rolling shutter.** An observation may carry `dt`, its capture time minus the frame's
//! mid-row time (seconds, e.g. [`crate::rolling_shutter::row_offset_s`] of its row). With a
//! constant camera velocity `ξ = [ω; v]` (angular rad/s and linear m/s, both expressed in
//! the camera frame at mid-row: a body twist) the camera pose at that time is
//! `T_wc(dt) = T_wc ∘ Exp(dt ξ)`, so the point is projected from
//! `p_c = Exp(-dt ξ) · T_cw · p_w` (`A = Exp(-dt ξ)`, computed once per call). The velocity
//! is an input (e.g. from the motion model or IMU), not estimated. `velocity = None` or
//! `dt = 0` is the global-shutter case.
//!
//! **Pose prior** ([`PoseOptParams::prior`], `VI_NOTES.md` §4 Table 5.1 "tracking = new pose
//! vs reprojections + IMU prior"): an optional Gaussian prior on the pose, e.g. the pose the
//! IMU predicts. Its residual is `r = [Log(R_cw R_prior,cwᵀ); c - c_prior]` (rotation in the
//! camera frame, then the camera centre `c = -R_cwᵀ t_cw` in the world frame), weighted by
//! a 6x6 information in that order; to first order `∂r/∂δ = [I 0; 0 -R_cwᵀ]` for the left
//! increment `δ = [ω; v]` (the centre does not move with `ω`, so a strong rotation prior does
//! not leak into the translation through the world origin's lever arm). It is added, without
//! a robust kernel, to every LM round's cost and normal equations. Without a prior nothing
//! changes: the code path is the same as before, and the result is bit-identical.
//!
//! **Memory.** [`PoseOptimizer`] keeps its per-observation buffers between calls; once they
//! have grown to the largest problem, nothing is allocated.

use nalgebra::{Isometry3, Matrix2x6, Matrix6, Point3, Vector2, Vector3, Vector6};

use super::robust::RobustKernel;
use crate::camera::{pose_jacobian, PinholeRadtan};
use crate::lie::se3_exp;
use crate::CoreError;

/// One observation of a fixed map point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseObservation {
    /// The map point in the world frame.
    pub point_w: Vector3<f64>,
    /// The observed (distorted) keypoint, pixels.
    pub pixel: Vector2<f64>,
    /// Information `1 / σ²` (pixels⁻²), see [`super::inv_sigma2_for_octave`].
    pub inv_sigma2: f64,
    /// Capture time minus the frame's mid-row time, seconds (0 for a global shutter).
    pub dt: f64,
}

/// Constant camera velocity for the rolling-shutter model: a body twist in the camera frame
/// at mid-row time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Velocity {
    /// Linear velocity `v`, m/s, camera frame.
    pub linear: Vector3<f64>,
    /// Angular velocity `ω`, rad/s, camera frame.
    pub angular: Vector3<f64>,
}

impl Velocity {
    /// The body twist `ξ = [ω; v]` (rotation first, as [`crate::lie::se3_exp`] takes it).
    pub fn twist(&self) -> Vector6<f64> {
        let (w, v) = (&self.angular, &self.linear);
        Vector6::new(w.x, w.y, w.z, v.x, v.y, v.z)
    }

    /// The velocity of a body twist `ξ = [ω; v]`.
    pub fn from_twist(xi: &Vector6<f64>) -> Self {
        Self {
            angular: Vector3::new(xi[0], xi[1], xi[2]),
            linear: Vector3::new(xi[3], xi[4], xi[5]),
        }
    }
}

/// A Gaussian prior on the pose (module docs): `T_cw` and the 6x6 information of the
/// residual `[rotation (camera frame, rad); camera centre (world frame, m)]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PosePrior {
    /// The prior pose, world to camera at mid-row time.
    pub t_cw: Isometry3<f64>,
    /// Information of `[Log(R_cw R_priorᵀ); c - c_prior]` (rad⁻², m⁻²).
    pub information: Matrix6<f64>,
}

impl PosePrior {
    /// A prior with isotropic 1σ `sigma_rad` on the rotation and `sigma_m` on the camera
    /// centre.
    pub fn isotropic(t_cw: Isometry3<f64>, sigma_rad: f64, sigma_m: f64) -> Self {
        let (ir, it) = (1.0 / (sigma_rad * sigma_rad), 1.0 / (sigma_m * sigma_m));
        Self {
            t_cw,
            information: Matrix6::from_diagonal(&Vector6::new(ir, ir, ir, it, it, it)),
        }
    }

    /// Residual `[Log(R_cw R_priorᵀ); c - c_prior]` at `t_cw`.
    fn residual(&self, t_cw: &Isometry3<f64>) -> Vector6<f64> {
        let dr = (t_cw.rotation * self.t_cw.rotation.inverse()).scaled_axis();
        let c = t_cw.inverse_transform_vector(&-t_cw.translation.vector);
        let c0 = self
            .t_cw
            .inverse_transform_vector(&-self.t_cw.translation.vector);
        let dc = c - c0;
        Vector6::new(dr.x, dr.y, dr.z, dc.x, dc.y, dc.z)
    }

    /// `rᵀ Ω r` at `t_cw`.
    fn cost(&self, t_cw: &Isometry3<f64>) -> f64 {
        let r = self.residual(t_cw);
        r.dot(&(self.information * r))
    }

    /// Adds `Jᵀ Ω J` and `Jᵀ Ω r` at `t_cw` to the normal equations (`J = [I 0; 0 -R_cwᵀ]`).
    fn add_to(&self, t_cw: &Isometry3<f64>, h: &mut Matrix6<f64>, g: &mut Vector6<f64>) {
        let r = self.residual(t_cw);
        let mut j = Matrix6::identity();
        let r_wc = t_cw.rotation.inverse().to_rotation_matrix().into_inner();
        j.fixed_view_mut::<3, 3>(3, 3).copy_from(&(-r_wc));
        let jt_omega = j.transpose() * self.information;
        *h += jt_omega * j;
        *g += jt_omega * r;
    }

    /// This prior's share `JᵀΩJ` of the pose optimisation's information at `t_cw`
    /// ([`PoseOptResult::information`] minus it is the reprojections' alone).
    pub fn information_at(&self, t_cw: &Isometry3<f64>) -> Matrix6<f64> {
        let mut h = Matrix6::zeros();
        self.add_to(t_cw, &mut h, &mut Vector6::zeros());
        h
    }

    fn is_finite(&self) -> bool {
        self.information.iter().all(|x| x.is_finite())
            && self.t_cw.translation.vector.iter().all(|x| x.is_finite())
            && self.t_cw.rotation.coords.iter().all(|x| x.is_finite())
    }
}

/// Parameters of [`PoseOptimizer::optimize`]; defaults are ORB-SLAM's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseOptParams {
    /// Optimisation rounds with inlier reclassification (4).
    pub rounds: usize,
    /// Largest number of LM iterations (accepted or rejected steps) per round (10).
    pub iterations_per_round: usize,
    /// Inlier bound on `χ² = rᵀ Ω r` (5.991: chi-square, 2 dof, 95%).
    pub chi2: f64,
    /// Rounds (from the first) that use the Huber kernel (2).
    pub huber_rounds: usize,
    /// Huber threshold on the whitened residual norm (√5.991).
    pub huber_delta: f64,
    /// Initial LM damping, relative to the diagonal (1e-4).
    pub initial_lambda: f64,
    /// A round stops when the step norm falls below this (1e-10).
    pub min_step: f64,
    /// A prior on the pose (none by default: pure reprojection, as ORB-SLAM).
    pub prior: Option<PosePrior>,
}

impl Default for PoseOptParams {
    fn default() -> Self {
        Self {
            rounds: 4,
            iterations_per_round: 10,
            chi2: 5.991,
            huber_rounds: 2,
            huber_delta: 5.991f64.sqrt(),
            initial_lambda: 1e-4,
            min_step: 1e-10,
            prior: None,
        }
    }
}

/// Outcome of [`PoseOptimizer::optimize`] (the inlier mask is written to the caller's slice).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseOptResult {
    /// Optimised world-to-camera pose at mid-row time.
    pub t_cw: Isometry3<f64>,
    /// Number of inliers after the last classification.
    pub n_inliers: usize,
    /// Final cost `Σ ρ(χ²)` over the inliers of the last round (kernel of that round).
    pub final_cost: f64,
    /// LM iterations run in total (accepted and rejected steps).
    pub iterations: usize,
    /// Information (Gauss-Newton `JᵀΩJ`, no kernel, prior included) of the left increment
    /// `δ = [ω; v]` at `t_cw` over the final inliers: its inverse is the pose's covariance
    /// ([`centre_covariance`] gives the camera centre's), e.g. the measurement a filter takes.
    pub information: Matrix6<f64>,
}

/// The camera centre's covariance (world frame) of a pose `t_cw` with `information` over
/// the left increment `δ = [ω; v]`: `c = -R_cwᵀ t_cw` moves by `δc = -R_cwᵀ v` (the rotation
/// cancels to first order), so `Σ_c = R_cwᵀ Σ_vv R_cw`. `None` when singular.
pub fn centre_covariance(
    t_cw: &Isometry3<f64>,
    information: &Matrix6<f64>,
) -> Option<nalgebra::Matrix3<f64>> {
    let cov = information.try_inverse()?;
    let r_wc = t_cw.rotation.inverse().to_rotation_matrix().into_inner();
    let c = r_wc * cov.fixed_view::<3, 3>(3, 3) * r_wc.transpose();
    c.iter()
        .all(|x| x.is_finite())
        .then_some((c + c.transpose()) * 0.5)
}

/// Reusable motion-only optimiser (keeps its buffers; see the module docs).
#[derive(Debug, Clone, Default)]
pub struct PoseOptimizer {
    /// Per-observation rolling-shutter correction `Exp(-dt ξ)` (identity when unused).
    shutter: Vec<Isometry3<f64>>,
    /// Whether any observation has a non-identity correction.
    rolling: bool,
}

/// Residual and Jacobian of one observation at a pose.
struct Linearised {
    r: Vector2<f64>,
    j: Matrix2x6<f64>,
}

impl PoseOptimizer {
    /// An optimiser with empty buffers.
    pub fn new() -> Self {
        Self::default()
    }

    /// An optimiser whose buffers already hold `n` observations.
    pub fn with_capacity(n: usize) -> Self {
        Self {
            shutter: Vec::with_capacity(n),
            rolling: false,
        }
    }

    /// The camera-frame point of observation `i` at pose `t_cw` and the point `q = T_cw p_w`.
    #[inline]
    fn camera_point(
        &self,
        t_cw: &Isometry3<f64>,
        i: usize,
        p_w: &Vector3<f64>,
    ) -> (Vector3<f64>, Vector3<f64>) {
        let q = (t_cw * Point3::from(*p_w)).coords;
        if self.rolling {
            ((self.shutter[i] * Point3::from(q)).coords, q)
        } else {
            (q, q)
        }
    }

    /// Residual in pixels (`None` behind the camera).
    #[inline]
    fn residual(
        &self,
        cam: &PinholeRadtan,
        t_cw: &Isometry3<f64>,
        i: usize,
        o: &PoseObservation,
    ) -> Option<Vector2<f64>> {
        let (p, _) = self.camera_point(t_cw, i, &o.point_w);
        cam.project(&p).map(|uv| uv - o.pixel)
    }

    /// Residual and analytic Jacobian (left perturbation of `T_cw`).
    fn linearise(
        &self,
        cam: &PinholeRadtan,
        t_cw: &Isometry3<f64>,
        i: usize,
        o: &PoseObservation,
    ) -> Option<Linearised> {
        let (p, q) = self.camera_point(t_cw, i, &o.point_w);
        let (uv, du_dp) = cam.project_with_jacobian(&p)?;
        // The increment moves q = T_cw p_w; p = A q with the rolling-shutter rotation A.
        let a = if self.rolling {
            du_dp * self.shutter[i].rotation.to_rotation_matrix().into_inner()
        } else {
            du_dp
        };
        let j = pose_jacobian(&a, &q);
        Some(Linearised { r: uv - o.pixel, j })
    }

    /// Robust cost over the inliers at `t_cw`; `None` when an inlier falls behind the camera.
    fn cost(
        &self,
        cam: &PinholeRadtan,
        t_cw: &Isometry3<f64>,
        obs: &[PoseObservation],
        inl: &[bool],
        k: &RobustKernel,
        prior: Option<&PosePrior>,
    ) -> Option<f64> {
        let mut c = prior.map_or(0.0, |p| p.cost(t_cw));
        for (i, o) in obs.iter().enumerate() {
            if inl[i] {
                let r = self.residual(cam, t_cw, i, o)?;
                c += k.cost(r.norm_squared() * o.inv_sigma2);
            }
        }
        Some(c)
    }

    /// Optimises `t_cw` (initial guess) against `obs`; see the module docs. Writes the final
    /// inlier classification to `inliers` (same length as `obs`).
    ///
    /// Errors: `InvalidArgument` on mismatched lengths, a non-finite guess, observation or
    /// velocity, or non-positive information; `NotEnoughData` with fewer than 3 observations.
    /// A pose that cannot be improved is returned as is (with its classification).
    pub fn optimize(
        &mut self,
        camera: &PinholeRadtan,
        t_cw: &Isometry3<f64>,
        obs: &[PoseObservation],
        velocity: Option<&Velocity>,
        params: &PoseOptParams,
        inliers: &mut [bool],
    ) -> Result<PoseOptResult, CoreError> {
        if inliers.len() != obs.len() {
            return Err(CoreError::InvalidArgument(format!(
                "pose-only: {} observations but {} inlier flags",
                obs.len(),
                inliers.len()
            )));
        }
        if obs.len() < 3 {
            return Err(CoreError::NotEnoughData(format!(
                "pose-only: {} observations",
                obs.len()
            )));
        }
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        if !finite(t_cw.translation.vector.as_slice()) || !finite(t_cw.rotation.coords.as_slice()) {
            return Err(CoreError::InvalidArgument(
                "pose-only: non-finite initial pose".into(),
            ));
        }
        if params.prior.as_ref().is_some_and(|p| !p.is_finite()) {
            return Err(CoreError::InvalidArgument(
                "pose-only: non-finite pose prior".into(),
            ));
        }
        if obs.iter().any(|o| {
            !finite(o.point_w.as_slice())
                || !finite(o.pixel.as_slice())
                || !o.dt.is_finite()
                || o.inv_sigma2.is_nan()
                || o.inv_sigma2 <= 0.0
        }) {
            return Err(CoreError::InvalidArgument(
                "pose-only: invalid observation".into(),
            ));
        }
        // Rolling-shutter corrections, once per call.
        self.shutter.clear();
        self.rolling = false;
        if let Some(v) = velocity {
            if !finite(v.linear.as_slice()) || !finite(v.angular.as_slice()) {
                return Err(CoreError::InvalidArgument(
                    "pose-only: non-finite velocity".into(),
                ));
            }
            let xi = v.twist();
            if xi != Vector6::zeros() && obs.iter().any(|o| o.dt != 0.0) {
                self.rolling = true;
                self.shutter
                    .extend(obs.iter().map(|o| se3_exp(&(xi * -o.dt))));
            }
        }
        inliers.iter_mut().for_each(|b| *b = true);
        let mut pose = *t_cw;
        let mut iterations = 0;
        let mut final_cost = 0.0;
        for round in 0..params.rounds {
            let kernel = if round < params.huber_rounds {
                RobustKernel::Huber {
                    delta: params.huber_delta,
                }
            } else {
                RobustKernel::None
            };
            let (p, c, it) = self.lm_round(camera, pose, obs, inliers, &kernel, params);
            pose = p;
            final_cost = c;
            iterations += it;
            // Reclassify every observation at the new pose.
            let mut n_in = 0;
            for (i, o) in obs.iter().enumerate() {
                inliers[i] = self
                    .residual(camera, &pose, i, o)
                    .is_some_and(|r| r.norm_squared() * o.inv_sigma2 <= params.chi2);
                n_in += usize::from(inliers[i]);
            }
            if n_in < 3 {
                break;
            }
        }
        let n_inliers = inliers.iter().filter(|&&b| b).count();
        let information = self.information(camera, &pose, obs, inliers, params.prior.as_ref());
        Ok(PoseOptResult {
            t_cw: pose,
            n_inliers,
            final_cost,
            iterations,
            information,
        })
    }

    /// `Σ JᵀΩJ` over the inliers at `pose` (no kernel), plus the prior's.
    fn information(
        &self,
        cam: &PinholeRadtan,
        pose: &Isometry3<f64>,
        obs: &[PoseObservation],
        inl: &[bool],
        prior: Option<&PosePrior>,
    ) -> Matrix6<f64> {
        let mut h = Matrix6::zeros();
        for (i, o) in obs.iter().enumerate() {
            if let Some(l) = inl[i].then(|| self.linearise(cam, pose, i, o)).flatten() {
                h += l.j.transpose() * l.j * o.inv_sigma2;
            }
        }
        if let Some(p) = prior {
            p.add_to(pose, &mut h, &mut Vector6::zeros());
        }
        h
    }

    /// One round of LM over the current inliers. Returns the pose, its cost and the number of
    /// iterations.
    fn lm_round(
        &self,
        cam: &PinholeRadtan,
        mut pose: Isometry3<f64>,
        obs: &[PoseObservation],
        inl: &[bool],
        kernel: &RobustKernel,
        params: &PoseOptParams,
    ) -> (Isometry3<f64>, f64, usize) {
        let prior = params.prior.as_ref();
        let Some(mut cost) = self.cost(cam, &pose, obs, inl, kernel, prior) else {
            // Some inlier is behind the camera: cost only the visible ones.
            return (pose, f64::INFINITY, 0);
        };
        let mut lambda = params.initial_lambda;
        let mut iters = 0;
        let mut need_build = true;
        let (mut h, mut g) = (Matrix6::zeros(), Vector6::zeros());
        while iters < params.iterations_per_round {
            if need_build {
                h = Matrix6::zeros();
                g = Vector6::zeros();
                for (i, o) in obs.iter().enumerate() {
                    if !inl[i] {
                        continue;
                    }
                    let Some(l) = self.linearise(cam, &pose, i, o) else {
                        continue;
                    };
                    let w = o.inv_sigma2 * kernel.weight(l.r.norm_squared() * o.inv_sigma2);
                    h += l.j.transpose() * l.j * w;
                    g += l.j.transpose() * l.r * w;
                }
                if let Some(p) = prior {
                    p.add_to(&pose, &mut h, &mut g);
                }
                need_build = false;
            }
            iters += 1;
            let mut a = h;
            for k in 0..6 {
                a[(k, k)] += lambda * h[(k, k)].max(1e-12);
            }
            let Some(chol) = a.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let delta = -chol.solve(&g);
            let cand = se3_exp(&delta) * pose;
            match self.cost(cam, &cand, obs, inl, kernel, prior) {
                Some(c) if c.is_finite() && c <= cost => {
                    pose = cand;
                    cost = c;
                    lambda = (lambda * 0.1).max(1e-12);
                    need_build = true;
                    if delta.norm() < params.min_step {
                        break;
                    }
                }
                _ => {
                    lambda *= 10.0;
                    if lambda > 1e12 {
                        break;
                    }
                }
            }
        }
        (pose, cost, iters)
    }
}

#[cfg(test)]
impl PoseOptimizer {
    /// Residual and Jacobian of observation `i` (tests only).
    pub(crate) fn test_linearise(
        &self,
        cam: &PinholeRadtan,
        t_cw: &Isometry3<f64>,
        i: usize,
        o: &PoseObservation,
    ) -> Option<(Vector2<f64>, Matrix2x6<f64>)> {
        self.linearise(cam, t_cw, i, o).map(|l| (l.r, l.j))
    }
}
