//! SE(3) Lie-group helpers in GTSAM's tangent order `ξ = [ω; v]` (rotation first), as the
//! pose-graph cost of [`super::se3_cost`] uses them: `Log`, `Exp`, the adjoint and the exact
//! inverse right Jacobian (needed so that the optimum is the true minimum of GTSAM's cost,
//! seed eq. 3.9 with rigid transforms).
//!
//! Poses are `T_wk` (`x_w = R x_k + t`); a graph residual is `Log(Z⁻¹ X_i⁻¹ X_j)` and
//! vertices are perturbed on the right, `X ← X Exp(δ)`.

use nalgebra::{Isometry3, Matrix3, Matrix6, Vector3, Vector6};

use crate::geometry::{quat_log, skew};

/// Below this angle (rad) the Jacobian coefficients use Taylor series.
const SMALL: f64 = 0.05;

/// `c(θ) = (1 - (θ/2) cot(θ/2)) / θ²`, the `[ω]×²` coefficient of `V(ω)⁻¹` and `Jr(ω)⁻¹`.
fn inv_v_coeff(theta: f64) -> f64 {
    if theta < 1e-3 {
        1.0 / 12.0 + theta * theta / 720.0
    } else {
        let h = 0.5 * theta;
        (1.0 - h / h.tan()) / (theta * theta)
    }
}

/// `V(ω)⁻¹ = Jl(ω)⁻¹ = I - ½[ω]× + c(θ)[ω]×²`: maps an SE(3) translation to the `v` part
/// of its logarithm.
pub fn so3_v_inv(w: &Vector3<f64>) -> Matrix3<f64> {
    let k = skew(w);
    Matrix3::identity() - k * 0.5 + k * k * inv_v_coeff(w.norm())
}

/// `Jr(ω)⁻¹ = I + ½[ω]× + c(θ)[ω]×²` (inverse right Jacobian of SO(3)).
pub fn so3_jr_inv(w: &Vector3<f64>) -> Matrix3<f64> {
    let k = skew(w);
    Matrix3::identity() + k * 0.5 + k * k * inv_v_coeff(w.norm())
}

/// SE(3) logarithm `[ω; v]` with `v = V(ω)⁻¹ t` (GTSAM's `Pose3::Logmap`).
pub fn se3_log(x: &Isometry3<f64>) -> Vector6<f64> {
    let w = quat_log(&x.rotation);
    let v = so3_v_inv(&w) * x.translation.vector;
    Vector6::new(w.x, w.y, w.z, v.x, v.y, v.z)
}

/// SE(3) exponential of `[ω; v]`: rotation `Exp(ω)`, translation `V(ω) v`.
pub fn se3_exp(xi: &Vector6<f64>) -> Isometry3<f64> {
    // The VO's exponential orders the twist translation first.
    crate::optim::se3::se3_exp(&Vector6::new(xi[3], xi[4], xi[5], xi[0], xi[1], xi[2]))
}

/// Adjoint of `x` in `[ω; v]` order: `[[R, 0], [[t]× R, R]]`, so that
/// `x Exp(ξ) x⁻¹ = Exp(Ad_x ξ)`.
pub fn se3_adjoint(x: &Isometry3<f64>) -> Matrix6<f64> {
    let r = x.rotation.to_rotation_matrix().into_inner();
    let tr = skew(&x.translation.vector) * r;
    let mut m = Matrix6::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    m.fixed_view_mut::<3, 3>(3, 0).copy_from(&tr);
    m.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
    m
}

/// Barfoot's `Q(ρ, φ)`, the off-diagonal block of the SE(3) left Jacobian (State Estimation
/// for Robotics, eq. 7.86), with Taylor series of its coefficients for small angles.
fn barfoot_q(rho: &Vector3<f64>, phi: &Vector3<f64>) -> Matrix3<f64> {
    let t = phi.norm();
    let t2 = t * t;
    let (c1, c2, c4) = if t < SMALL {
        // (t - sin t)/t³, (t² + 2cos t - 2)/(2t⁴), (2t - 3 sin t + t cos t)/(2t⁵)
        let t4 = t2 * t2;
        (
            1.0 / 6.0 - t2 / 120.0 + t4 / 5040.0,
            1.0 / 24.0 - t2 / 720.0 + t4 / 40320.0,
            1.0 / 120.0 - t2 / 2520.0 + t4 / 120_960.0,
        )
    } else {
        let (s, c) = t.sin_cos();
        let t3 = t2 * t;
        (
            (t - s) / t3,
            (t2 + 2.0 * c - 2.0) / (2.0 * t3 * t),
            (2.0 * t - 3.0 * s + t * c) / (2.0 * t3 * t2),
        )
    };
    let rx = skew(rho);
    let px = skew(phi);
    let pr = px * rx;
    let rp = rx * px;
    let prp = pr * px;
    let ppr = px * pr;
    let rpp = rp * px;
    rx * 0.5 + (pr + rp + prp) * c1 + (ppr + rpp - prp * 3.0) * c2 + (prp * px + px * prp) * c4
}

/// Exact inverse right Jacobian of SE(3) in `[ω; v]` order:
/// `Log(Exp(ξ) Exp(δ)) = ξ + Jr(ξ)⁻¹ δ + O(|δ|²)`.
/// `Jr(ξ) = [[A, 0], [B, A]]` with `A = Jr_SO3(ω)`, `B = Q(-v, -ω)`, so
/// `Jr⁻¹ = [[A⁻¹, 0], [-A⁻¹ B A⁻¹, A⁻¹]]`.
pub fn se3_jr_inv(xi: &Vector6<f64>) -> Matrix6<f64> {
    let w = Vector3::new(xi[0], xi[1], xi[2]);
    let v = Vector3::new(xi[3], xi[4], xi[5]);
    let a_inv = so3_jr_inv(&w);
    let b = barfoot_q(&(-v), &(-w));
    let off = -(a_inv * b * a_inv);
    let mut m = Matrix6::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&a_inv);
    m.fixed_view_mut::<3, 3>(3, 0).copy_from(&off);
    m.fixed_view_mut::<3, 3>(3, 3).copy_from(&a_inv);
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    fn xi() -> Vector6<f64> {
        Vector6::new(0.4, -0.3, 0.9, 1.5, -0.7, 2.0)
    }

    #[test]
    fn log_inverts_exp() {
        for s in [1e-9, 1e-4, 0.01, 0.3, 1.0, 3.0] {
            let x = xi() * s;
            let back = se3_log(&se3_exp(&x));
            assert!(
                (back - x).norm() < 1e-12 * (1.0 + x.norm()),
                "{s}: {back} vs {x}"
            );
        }
    }

    #[test]
    fn adjoint_moves_twists() {
        let x = se3_exp(&xi());
        let d = Vector6::new(0.1, 0.2, -0.3, 0.5, -0.1, 0.2);
        let lhs = x * se3_exp(&d) * x.inverse();
        let rhs = se3_exp(&(se3_adjoint(&x) * d));
        assert!((se3_log(&(lhs.inverse() * rhs))).norm() < 1e-12);
    }

    #[test]
    fn jr_inv_matches_numeric_derivative() {
        for s in [0.0, 1e-3, 0.04, 0.06, 0.5, 1.0, 2.5] {
            let x = xi() * s;
            let j = se3_jr_inv(&x);
            let ex = se3_exp(&x);
            let h = 1e-6;
            for k in 0..6 {
                let mut d = Vector6::zeros();
                d[k] = h;
                let p = se3_log(&(ex * se3_exp(&d)));
                d[k] = -h;
                let m = se3_log(&(ex * se3_exp(&d)));
                let col = (p - m) / (2.0 * h);
                let err = (col - j.column(k)).norm();
                assert!(err < 1e-7, "s {s} col {k}: {err}\n{col}\n{}", j.column(k));
            }
        }
    }
}
