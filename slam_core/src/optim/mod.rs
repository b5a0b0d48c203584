//! Non-linear least-squares building blocks: robust kernels, bundle adjustment and the
//! motion-only (pose-only) optimisation of tracking (Mur-Artal et al. 2015, section V-D).
//!
//! Conventions shared by everything here (and meant for the bundle adjustment that will
//! live beside it, e.g. `optim/ba*.rs`):
//! - Poses are world-to-camera `T_cw`; an increment `δ = [ω; v]` (rotation first, the order
//!   of [`crate::lie`]) is applied on the **left**: `T_cw ← Exp(δ) · T_cw`
//!   ([`crate::lie::se3_exp`]); Jacobian columns follow the same order.
//! - Residuals are `predicted - observed` in pixels; a residual's information is the scalar
//!   `1 / σ²` with `σ = scale_factor^octave` ([`inv_sigma2_for_octave`], tabulated per
//!   feature set in [`crate::features::PyramidScale`]); robust kernels act on the
//!   squared Mahalanobis error `χ² = rᵀ Ω r` ([`robust::RobustKernel`]).
//! - Levenberg-Marquardt with multiplicative damping of the diagonal (`H + λ diag(H)`).

pub mod ba;
pub mod block_sparse;
pub mod pose_only;
pub mod robust;

pub use pose_only::{
    centre_covariance, PoseObservation, PoseOptParams, PoseOptResult, PoseOptimizer, PosePrior,
    Velocity,
};
pub use robust::RobustKernel;

/// ORB-SLAM's information of a keypoint detected at pyramid level `octave` with scale factor
/// `scale_factor` ([`crate::features::ORB_SCALE_FACTOR`] by default): `1 / σ²` with
/// `σ = scale_factor^octave` pixels. Feature sets carry these values per octave
/// ([`crate::features::PyramidScale::inv_sigma2`]).
pub fn inv_sigma2_for_octave(octave: u32, scale_factor: f64) -> f64 {
    let sigma = crate::features::powi_f64(scale_factor, octave.min(64));
    1.0 / (sigma * sigma)
}

#[cfg(test)]
mod tests {
    #[test]
    fn octave_information() {
        let f = crate::features::ORB_SCALE_FACTOR;
        assert_eq!(super::inv_sigma2_for_octave(0, f), 1.0);
        assert!((super::inv_sigma2_for_octave(2, f) - 1.0 / (f * f).powi(2)).abs() < 1e-12);
    }
}

#[cfg(test)]
mod pose_only_tests;
