//! Bundle adjustment: joint refinement of keyframe poses and map points by minimising the
//! robust reprojection error, shared by the client's local mapping (local BA, seed §3.3) and
//! the server mapper (local and global BA, seed §3.4.1-3.4.2).
//!
//! **Model.** Conventions of [`crate::optim`]: poses are world-to-camera `T_cw`, updated on
//! the left (`T_cw ← Exp(δ) T_cw`, `δ = [ω; v]`, rotation first as in [`crate::lie`]); points `p_w ← p_w + δp`; residuals
//! `π(T_cw p_w) - u` in pixels through the full [`crate::camera::PinholeRadtan`] model
//! (analytic Jacobians through the distortion, [`linearize_reprojection`]); information
//! `1/σ²`, `σ = scale_factor^octave`; Huber kernel (`δ = √5.991`) on `χ² = rᵀ Ω r`.
//!
//! **Solver.** Levenberg-Marquardt (damping `λ · clamp(diag H)`, Nielsen's update of `λ`)
//! on the normal equations with the points eliminated by the Schur complement (3x3 point
//! blocks inverted); the reduced camera system (a
//! [`crate::optim::block_sparse::BlockSparseSystem`]) is solved with faer: dense LLᵀ for few
//! free keyframes, sparse LLᵀ (AMD ordering, symbolic analysis once per call) above
//! [`BaParams::dense_max_keyframes`]; then the points are back-substituted.
//!
//! **Stages (ORB-SLAM's local BA).** [`BaParams::first_stage_iterations`] (5) iterations with
//! the Huber kernel; then observations with `χ² > 5.991` or behind the camera are dropped and
//! [`BaParams::second_stage_iterations`] (10) more iterations run without them (and without
//! the kernel). At the end every observation is classified again at the final state
//! ([`BundleAdjuster::inliers`]).
//!
//! **Gauge.** Keyframes flagged `fixed` stay bit-for-bit unchanged. A monocular problem has
//! a 7-dof gauge: fix at least two keyframes (local BA fixes the covisible keyframes outside
//! the window), or accept that the global BA ([`BundleAdjuster::optimize_global`], keyframe 0
//! fixed) leaves the scale to the damping.
//!
//! ```
//! use nalgebra::{Isometry3, Vector2, Vector3};
//! use slam_core::camera::PinholeRadtan;
//! use slam_core::optim::ba::{BaParams, BaProblem, BundleAdjuster};
//!
//! let cam = PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0);
//! let mut problem = BaProblem::new();
//! let k0 = problem.add_keyframe(Isometry3::identity(), cam, true);
//! let k1 = problem.add_keyframe(Isometry3::translation(-0.5, 0.0, 0.0), cam, true);
//! let p = problem.add_point(Vector3::new(0.1, 0.0, 4.0), false);
//! problem.add_observation(k0, p, Vector2::new(320.0 + 500.0 * 0.0, 240.0), 1.0);
//! problem.add_observation(k1, p, Vector2::new(320.0 - 500.0 * 0.125, 240.0), 1.0);
//! let mut ba = BundleAdjuster::new();
//! let report = ba.optimize(&mut problem, &BaParams::local()).unwrap();
//! assert!(report.final_rmse < 1e-6);
//! assert!((problem.points[p].p_w - Vector3::new(0.0, 0.0, 4.0)).norm() < 1e-6);
//! ```

mod problem;
mod schur;
mod solve;
pub mod synth;

pub use problem::{
    linearize_reprojection, reprojection_residual, BaKeyframe, BaObservation, BaPoint, BaProblem,
    ReprojectionLinearization,
};
pub use solve::{BaParams, BaReport, BundleAdjuster, LinearSolverKind};

#[cfg(test)]
mod tests;
