//! The Levenberg-Marquardt loop of the bundle adjustment: ORB-SLAM's two stages (robust
//! iterations, outlier rejection, iterations without the outliers), Nielsen's damping update,
//! and the reusable [`BundleAdjuster`] workspace.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Vector3, Vector6};

use super::problem::{reprojection_residual, BaProblem};
use super::schur::{NormalEquations, NONE};
use crate::lie::se3_exp;
use crate::optim::robust::RobustKernel;
use crate::CoreError;

/// Squared error charged to an active observation whose point falls behind its camera during
/// the optimisation (it then has no Jacobian); makes steps that flip points unattractive.
const BEHIND_CAMERA_CHI2: f64 = 1e4;

/// Which factorisation solves the reduced camera system
/// ([`crate::optim::block_sparse::Factorization`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinearSolverKind {
    /// Dense LLᵀ up to [`BaParams::dense_max_keyframes`] free keyframes, sparse above.
    Auto,
    /// Dense LLᵀ (faer) of the full reduced matrix.
    Dense,
    /// Sparse LLᵀ (faer, AMD ordering, symbolic analysis reused across iterations).
    Sparse,
}

/// Parameters of [`BundleAdjuster::optimize`]; the defaults are ORB-SLAM's local BA.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaParams {
    /// LM iterations of the first (robust) stage (5).
    pub first_stage_iterations: usize,
    /// LM iterations of the second stage, run without the observations classified as
    /// outliers after the first one (10). 0 skips the second stage.
    pub second_stage_iterations: usize,
    /// Classify outliers after the first stage and run the second stage (true). When false
    /// only the first stage runs (ORB-SLAM's global BA).
    pub remove_outliers: bool,
    /// Outlier bound on `χ² = rᵀ Ω r` (5.991: chi-square, 2 dof, 95%).
    pub chi2_threshold: f64,
    /// Huber threshold on the whitened residual norm (√5.991 pixels at octave 0).
    pub huber_delta: f64,
    /// Keep the Huber kernel in the second stage (false: plain least squares, as ORB-SLAM).
    pub robust_second_stage: bool,
    /// Initial damping `λ` of each stage; the damped matrix is `H + λ clamp(diag H)` (1e-4).
    pub initial_lambda: f64,
    /// Rejected steps allowed within one iteration before the stage stops (10, as g2o).
    pub max_rejected_steps: usize,
    /// A stage stops when an accepted step reduces the cost by less than this fraction (1e-6,
    /// Ceres' function tolerance).
    pub min_relative_decrease: f64,
    /// Linear solver of the reduced camera system.
    pub solver: LinearSolverKind,
    /// With [`LinearSolverKind::Auto`], the largest number of free keyframes solved densely
    /// (40).
    pub dense_max_keyframes: usize,
}

impl Default for BaParams {
    fn default() -> Self {
        Self::local()
    }
}

impl BaParams {
    /// ORB-SLAM's local BA: 5 robust iterations, outlier rejection, 10 plain iterations.
    pub fn local() -> Self {
        Self {
            first_stage_iterations: 5,
            second_stage_iterations: 10,
            remove_outliers: true,
            chi2_threshold: 5.991,
            huber_delta: 5.991f64.sqrt(),
            robust_second_stage: false,
            initial_lambda: 1e-4,
            max_rejected_steps: 10,
            min_relative_decrease: 1e-6,
            solver: LinearSolverKind::Auto,
            dense_max_keyframes: 40,
        }
    }

    /// ORB-SLAM's global BA: 10 robust iterations, no outlier rejection (the inlier flags are
    /// still reported).
    pub fn global() -> Self {
        Self {
            first_stage_iterations: 10,
            remove_outliers: false,
            ..Self::local()
        }
    }
}

/// Outcome of a bundle adjustment (the inlier flags are in [`BundleAdjuster::inliers`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaReport {
    /// Robust cost `Σ ρ(χ²)` of the first stage at the initial state, over all observations.
    pub initial_cost: f64,
    /// Cost of the last stage's objective at the final state, over its observations.
    pub final_cost: f64,
    /// RMS reprojection error (pixels, unweighted) over the final inliers, initial state
    /// (0 when there is no inlier).
    pub initial_rmse: f64,
    /// Same at the final state.
    pub final_rmse: f64,
    /// LM iterations (linearisations followed by an accepted or a final rejected step).
    pub iterations: usize,
    /// Rejected LM steps (each costs one more reduced-system solve and cost evaluation).
    pub rejected_steps: usize,
    /// Observations with `χ² <= chi2_threshold` in front of their camera at the final state.
    pub n_inliers: usize,
    /// The other observations.
    pub n_outliers: usize,
    /// Free keyframes and free points.
    pub free_keyframes: usize,
    /// Free (not fixed, observed) points.
    pub free_points: usize,
    /// Linear solver used ([`LinearSolverKind::Dense`] or [`LinearSolverKind::Sparse`]).
    pub solver: LinearSolverKind,
    /// True when the abort flag stopped the optimisation early (the state is still valid).
    pub aborted: bool,
    /// Wall time of the call.
    pub time: Duration,
}

/// Reusable bundle-adjustment workspace. Everything is sized once per problem in
/// [`BundleAdjuster::optimize`] (reusing earlier capacity); the LM iterations allocate
/// nothing (the dense path allocates nothing at all once the workspace has seen a problem of
/// the same size; the sparse path's symbolic analysis allocates once per call).
#[derive(Debug, Default)]
pub struct BundleAdjuster {
    ne: NormalEquations,
    poses: Vec<Isometry3<f64>>,
    points: Vec<Vector3<f64>>,
    cand_poses: Vec<Isometry3<f64>>,
    cand_points: Vec<Vector3<f64>>,
    active: Vec<bool>,
    inliers: Vec<bool>,
}

impl BundleAdjuster {
    /// An empty workspace.
    pub fn new() -> Self {
        Self::default()
    }

    /// Per-observation inlier flags of the last call (indexed like
    /// [`BaProblem::observations`]): `χ² <= chi2_threshold` and in front of the camera at
    /// the final state.
    pub fn inliers(&self) -> &[bool] {
        &self.inliers
    }

    /// Local BA: optimises the poses of the keyframes not marked `fixed` and the points not
    /// marked `fixed` (and observed) in place; see [`BaParams`].
    ///
    /// Errors: `InvalidArgument` on an invalid problem ([`BaProblem::validate`]);
    /// `Degenerate` when the linear solver cannot be set up. A problem with nothing free is
    /// returned unchanged with its classification.
    pub fn optimize(
        &mut self,
        problem: &mut BaProblem,
        params: &BaParams,
    ) -> Result<BaReport, CoreError> {
        self.run(problem, params, false, None)
    }

    /// [`Self::optimize`] that stops between iterations once `abort` is set (ORB-SLAM's
    /// local BA is interrupted when a new keyframe arrives).
    pub fn optimize_with_abort(
        &mut self,
        problem: &mut BaProblem,
        params: &BaParams,
        abort: &AtomicBool,
    ) -> Result<BaReport, CoreError> {
        self.run(problem, params, false, Some(abort))
    }

    /// Global (full) BA: every keyframe is free except keyframe 0 (the gauge), whatever the
    /// `fixed` flags say; point flags are honoured. Use with [`BaParams::global`].
    pub fn optimize_global(
        &mut self,
        problem: &mut BaProblem,
        params: &BaParams,
        abort: Option<&AtomicBool>,
    ) -> Result<BaReport, CoreError> {
        self.run(problem, params, true, abort)
    }

    fn run(
        &mut self,
        problem: &mut BaProblem,
        params: &BaParams,
        global: bool,
        abort: Option<&AtomicBool>,
    ) -> Result<BaReport, CoreError> {
        let start = Instant::now();
        problem.validate()?;
        let positive = |v: f64| v > 0.0 && v.is_finite();
        if !(positive(params.chi2_threshold) && positive(params.huber_delta)) {
            return Err(CoreError::InvalidArgument(
                "ba: chi2_threshold and huber_delta must be positive".into(),
            ));
        }
        let n_obs = problem.observations.len();
        let force = match params.solver {
            LinearSolverKind::Auto => None,
            LinearSolverKind::Dense => Some(false),
            LinearSolverKind::Sparse => Some(true),
        };
        let kfs = &problem.keyframes;
        let (n_cams, sparse) = self.ne.setup(
            problem,
            |k| if global { k == 0 } else { kfs[k].fixed },
            params.dense_max_keyframes,
            force,
        )?;
        self.poses.clear();
        self.poses.extend(problem.keyframes.iter().map(|k| k.t_cw));
        self.points.clear();
        self.points.extend(problem.points.iter().map(|p| p.p_w));
        self.cand_poses.clear();
        self.cand_poses.extend_from_slice(&self.poses);
        self.cand_points.clear();
        self.cand_points.extend_from_slice(&self.points);
        self.active.clear();
        self.active.resize(n_obs, true);
        self.inliers.clear();
        self.inliers.resize(n_obs, false);

        let huber = RobustKernel::Huber {
            delta: params.huber_delta,
        };
        let initial_cost = self.cost(problem, false, &huber);
        let mut report = BaReport {
            initial_cost,
            final_cost: initial_cost,
            initial_rmse: 0.0,
            final_rmse: 0.0,
            iterations: 0,
            rejected_steps: 0,
            n_inliers: 0,
            n_outliers: 0,
            free_keyframes: n_cams,
            free_points: self.ne.n_pts,
            solver: if sparse {
                LinearSolverKind::Sparse
            } else {
                LinearSolverKind::Dense
            },
            aborted: false,
            time: Duration::ZERO,
        };
        let has_free = n_cams > 0 || self.ne.n_pts > 0;
        if has_free {
            let (cost, it, aborted) = self.stage(
                problem,
                params,
                &huber,
                params.first_stage_iterations,
                abort,
                &mut report.rejected_steps,
            );
            report.final_cost = cost;
            report.iterations += it;
            report.aborted = aborted;
            if params.remove_outliers && !aborted {
                self.classify(problem, params.chi2_threshold, false);
                let kernel = if params.robust_second_stage {
                    huber
                } else {
                    RobustKernel::None
                };
                if params.second_stage_iterations > 0 {
                    let (cost, it, aborted) = self.stage(
                        problem,
                        params,
                        &kernel,
                        params.second_stage_iterations,
                        abort,
                        &mut report.rejected_steps,
                    );
                    report.final_cost = cost;
                    report.iterations += it;
                    report.aborted = aborted;
                }
            }
        }
        // Final classification of every observation, then RMSE before / after on the inliers.
        self.classify(problem, params.chi2_threshold, true);
        report.n_inliers = self.inliers.iter().filter(|&&b| b).count();
        report.n_outliers = n_obs - report.n_inliers;
        report.initial_rmse = problem
            .reprojection_rmse(Some(&self.inliers))
            .unwrap_or(0.0);
        for (k, t) in problem.keyframes.iter_mut().zip(&self.poses) {
            k.t_cw = *t;
        }
        for (p, x) in problem.points.iter_mut().zip(&self.points) {
            p.p_w = *x;
        }
        report.final_rmse = problem
            .reprojection_rmse(Some(&self.inliers))
            .unwrap_or(0.0);
        report.time = start.elapsed();
        Ok(report)
    }

    /// Robust cost of the active observations (all when `all`) at the current state
    /// (`candidate == false`) or at the candidate state.
    fn cost(&self, problem: &BaProblem, candidate: bool, kernel: &RobustKernel) -> f64 {
        let (poses, points) = if candidate {
            (&self.cand_poses, &self.cand_points)
        } else {
            (&self.poses, &self.points)
        };
        let mut c = 0.0;
        for (i, o) in problem.observations.iter().enumerate() {
            if !self.active[i] {
                continue;
            }
            let kf = &problem.keyframes[o.keyframe];
            let chi2 = match reprojection_residual(
                &kf.camera,
                &poses[o.keyframe],
                &points[o.point],
                &o.pixel,
            ) {
                Some(r) => r.norm_squared() * o.inv_sigma2,
                None => BEHIND_CAMERA_CHI2,
            };
            c += kernel.cost(chi2);
        }
        c
    }

    /// Marks observations behind the camera or with `χ² > chi2` at the current state:
    /// clears their `active` flag (`final_pass == false`) or sets the inlier flags.
    fn classify(&mut self, problem: &BaProblem, chi2: f64, final_pass: bool) {
        for (i, o) in problem.observations.iter().enumerate() {
            let kf = &problem.keyframes[o.keyframe];
            let ok = reprojection_residual(
                &kf.camera,
                &self.poses[o.keyframe],
                &self.points[o.point],
                &o.pixel,
            )
            .is_some_and(|r| r.norm_squared() * o.inv_sigma2 <= chi2);
            if final_pass {
                self.inliers[i] = ok;
            } else {
                self.active[i] &= ok;
            }
        }
    }

    /// One LM stage over the active observations. Returns (cost, iterations, aborted).
    fn stage(
        &mut self,
        problem: &BaProblem,
        params: &BaParams,
        kernel: &RobustKernel,
        max_iterations: usize,
        abort: Option<&AtomicBool>,
        rejected: &mut usize,
    ) -> (f64, usize, bool) {
        let mut cost = self.cost(problem, false, kernel);
        let mut lambda = params.initial_lambda.max(1e-12);
        let mut nu = 2.0;
        let mut iterations = 0;
        for _ in 0..max_iterations {
            if abort.is_some_and(|a| a.load(Ordering::Relaxed)) {
                return (cost, iterations, true);
            }
            self.ne
                .linearize(problem, &self.poses, &self.points, &self.active, kernel);
            iterations += 1;
            let mut accepted = false;
            let mut rel_decrease = 0.0;
            for _ in 0..params.max_rejected_steps.max(1) {
                if self.ne.solve_step(problem, lambda).is_ok() {
                    self.apply_candidate();
                    let new_cost = self.cost(problem, true, kernel);
                    let pred = self.ne.predicted_reduction(lambda);
                    let rho = 0.5 * (cost - new_cost) / pred.max(f64::MIN_POSITIVE);
                    if new_cost.is_finite() && new_cost < cost && rho > 0.0 {
                        std::mem::swap(&mut self.poses, &mut self.cand_poses);
                        std::mem::swap(&mut self.points, &mut self.cand_points);
                        rel_decrease = (cost - new_cost) / cost.max(f64::MIN_POSITIVE);
                        cost = new_cost;
                        lambda *= (1.0 / 3.0f64).max(1.0 - (2.0 * rho - 1.0).powi(3));
                        nu = 2.0;
                        accepted = true;
                        break;
                    }
                }
                *rejected += 1;
                lambda *= nu;
                nu *= 2.0;
                if !lambda.is_finite() || lambda > 1e32 {
                    break;
                }
            }
            if !accepted || rel_decrease < params.min_relative_decrease {
                break;
            }
        }
        (cost, iterations, false)
    }

    /// Candidate state: `Exp(δc) T_cw` for free keyframes, `p + δp` for free points.
    fn apply_candidate(&mut self) {
        for (k, &c) in self.ne.cam_of_kf.iter().enumerate() {
            self.cand_poses[k] = if c == NONE {
                self.poses[k]
            } else {
                let d: Vector6<f64> = self.ne.dc[c as usize];
                se3_exp(&d) * self.poses[k]
            };
        }
        for (j, &p) in self.ne.pt_of_point.iter().enumerate() {
            self.cand_points[j] = if p == NONE {
                self.points[j]
            } else {
                self.points[j] + self.ne.dp[p as usize]
            };
        }
    }
}
