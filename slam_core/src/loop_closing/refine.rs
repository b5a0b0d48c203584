//! Levenberg-Marquardt refinement of a Sim(3) on two-way reprojection errors (seed §3.4.2;
//! the idea of ORB-SLAM's `OptimizeSim3`, with the 3D points held fixed): every
//! correspondence contributes the error of the matched point `S p_m` projected into the
//! query image and of the query point `S⁻¹ p_q` projected into the matched image, each
//! weighted by its keypoint octave's `1/σ²` and robustified by Huber.
//!
//! Left perturbation `S ← Exp(ξ) S`, `ξ = [ω; ρ; σ]` (rotation first, [`Sim3::exp`]). Accumulation is in
//! place into a 7x7 system on the stack: nothing is allocated per residual.

use nalgebra::{Matrix3, SMatrix, Vector2, Vector3};

use crate::camera::PinholeRadtan;
use crate::lie::{skew, Matrix7, Sim3, Vector7};

/// One 3D-3D correspondence with the two keypoints that observed it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sim3Correspondence {
    /// Point in the query keyframe's camera frame.
    pub p_q: Vector3<f64>,
    /// Point in the matched keyframe's camera frame.
    pub p_m: Vector3<f64>,
    /// Keypoint of the query keyframe, pixels.
    pub uv_q: Vector2<f64>,
    /// Keypoint of the matched keyframe, pixels.
    pub uv_m: Vector2<f64>,
    /// `1/σ²` of the query keypoint (`scale_factor^(-2 octave)`).
    pub inv_sigma2_q: f64,
    /// `1/σ²` of the matched keypoint.
    pub inv_sigma2_m: f64,
}

/// Parameters of [`refine_sim3`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefineParams {
    /// Largest number of LM iterations (accepted or rejected steps).
    pub iterations: usize,
    /// Huber threshold on the whitened error `sqrt(χ²)`; ORB-SLAM uses `sqrt(10)`.
    pub huber_delta: f64,
    /// Initial LM damping, relative to the diagonal of the normal matrix.
    pub initial_lambda: f64,
}

impl Default for RefineParams {
    fn default() -> Self {
        Self {
            iterations: 10,
            huber_delta: 10f64.sqrt(),
            initial_lambda: 1e-3,
        }
    }
}

/// Huber cost `ρ(χ²)` and IRLS weight of a whitened squared error.
#[inline]
fn huber(chi2: f64, delta: f64) -> (f64, f64) {
    let e = chi2.sqrt();
    if e <= delta {
        (chi2, 1.0)
    } else {
        (2.0 * delta * e - delta * delta, delta / e)
    }
}

/// Total robust cost of `s` and, when `system` is given, the Gauss-Newton system `H`, `g`
/// (`g = Jᵀ W r`). A point behind a camera costs as a `100 δ` error and adds no Jacobian,
/// so that costs of different estimates stay comparable.
fn evaluate(
    s: &Sim3,
    corrs: &[Sim3Correspondence],
    active: &[bool],
    cam_q: &PinholeRadtan,
    cam_m: &PinholeRadtan,
    delta: f64,
    mut system: Option<(&mut Matrix7, &mut Vector7)>,
) -> f64 {
    let behind = huber((100.0 * delta) * (100.0 * delta), delta).0;
    let s_inv = s.inverse();
    let r_inv: Matrix3<f64> = s_inv.r.to_rotation_matrix().into_inner() * s_inv.s;
    let mut cost = 0.0;
    if let Some((h, g)) = system.as_mut() {
        h.fill(0.0);
        g.fill(0.0);
    }
    for (i, c) in corrs.iter().enumerate() {
        if !active.is_empty() && !active.get(i).copied().unwrap_or(false) {
            continue;
        }
        // Forward: S p_m into the query image. d(S p_m)/dξ = [-[p']×, I, p'].
        let p1 = s.transform_point(&c.p_m);
        match cam_q.project_with_jacobian(&p1) {
            Some((uv, jp)) => {
                let e = uv - c.uv_q;
                let (rho, w) = huber(e.norm_squared() * c.inv_sigma2_q, delta);
                cost += rho;
                if let Some((h, g)) = system.as_mut() {
                    let mut dp = SMatrix::<f64, 3, 7>::zeros();
                    dp.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-skew(&p1)));
                    dp.fixed_view_mut::<3, 3>(0, 3).fill_with_identity();
                    dp.fixed_view_mut::<3, 1>(0, 6).copy_from(&p1);
                    let j = jp * dp;
                    let wi = w * c.inv_sigma2_q;
                    **h += j.transpose() * j * wi;
                    **g += j.transpose() * e * wi;
                }
            }
            None => cost += behind,
        }
        // Backward: S⁻¹ p_q into the matched image.
        // d(S⁻¹ Exp(-ξ) p_q)/dξ = (1/s) Rᵀ [[p_q]×, -I, -p_q].
        let p2 = s_inv.transform_point(&c.p_q);
        match cam_m.project_with_jacobian(&p2) {
            Some((uv, jp)) => {
                let e = uv - c.uv_m;
                let (rho, w) = huber(e.norm_squared() * c.inv_sigma2_m, delta);
                cost += rho;
                if let Some((h, g)) = system.as_mut() {
                    let mut dq = SMatrix::<f64, 3, 7>::zeros();
                    dq.fixed_view_mut::<3, 3>(0, 0).copy_from(&skew(&c.p_q));
                    dq.fixed_view_mut::<3, 3>(0, 3).fill_with_identity();
                    dq.fixed_view_mut::<3, 3>(0, 3).neg_mut();
                    dq.fixed_view_mut::<3, 1>(0, 6).copy_from(&(-c.p_q));
                    let j = jp * (r_inv * dq);
                    let wi = w * c.inv_sigma2_m;
                    **h += j.transpose() * j * wi;
                    **g += j.transpose() * e * wi;
                }
            }
            None => cost += behind,
        }
    }
    cost
}

/// Refines `s0` (`p_q = S p_m`) by Levenberg-Marquardt over the 7 Sim(3) parameters on the
/// two-way reprojection errors of the correspondences with `active[i]` (all when `active`
/// is empty), seed §3.4.2. `cam_q`, `cam_m` are the two keyframes' cameras.
///
/// Returns the refined similarity and its final robust cost, or `None` when the input is
/// degenerate (no active correspondence, non-finite or non-positive scale).
pub fn refine_sim3(
    s0: &Sim3,
    corrs: &[Sim3Correspondence],
    active: &[bool],
    cam_q: &PinholeRadtan,
    cam_m: &PinholeRadtan,
    params: &RefineParams,
) -> Option<(Sim3, f64)> {
    let valid = |s: &Sim3| {
        s.s.is_finite()
            && s.s > 0.0
            && s.t.iter().all(|v| v.is_finite())
            && s.r.coords.iter().all(|v| v.is_finite())
    };
    let n_active = if active.is_empty() {
        corrs.len()
    } else {
        active.iter().filter(|&&a| a).count()
    };
    if n_active == 0 || !valid(s0) {
        return None;
    }
    let delta = params.huber_delta;
    let (mut h, mut g) = (Matrix7::zeros(), Vector7::zeros());
    let mut s = *s0;
    let mut cost = evaluate(
        &s,
        corrs,
        active,
        cam_q,
        cam_m,
        delta,
        Some((&mut h, &mut g)),
    );
    if !cost.is_finite() {
        return None;
    }
    let mut lambda = params.initial_lambda;
    for _ in 0..params.iterations {
        let mut a = h;
        for k in 0..7 {
            a[(k, k)] += lambda * h[(k, k)].max(1e-9);
        }
        let Some(chol) = a.cholesky() else {
            lambda *= 10.0;
            continue;
        };
        let step = chol.solve(&(-g));
        if !step.iter().all(|v| v.is_finite()) {
            break;
        }
        let cand = Sim3::exp(&step).compose(&s);
        if !valid(&cand) {
            lambda *= 10.0;
            continue;
        }
        let c_cost = evaluate(&cand, corrs, active, cam_q, cam_m, delta, None);
        if c_cost.is_finite() && c_cost < cost {
            s = cand;
            lambda = (lambda * 0.1).max(1e-9);
            cost = evaluate(
                &s,
                corrs,
                active,
                cam_q,
                cam_m,
                delta,
                Some((&mut h, &mut g)),
            );
            if step.norm() < 1e-10 {
                break;
            }
        } else {
            lambda *= 10.0;
            if lambda > 1e8 {
                break;
            }
        }
    }
    Some((s, cost))
}
