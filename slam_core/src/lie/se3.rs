//! SE(3) on [`Isometry3`] with the twist `ξ = [ω; v]` (rotation first, GTSAM's order):
//! exponential, logarithm, adjoint, and the right and left Jacobians with their exact
//! inverses.
//!
//! `Exp([ω; v]) = [Exp(ω), V(ω) v]` with `V = Jl_SO3` ([`so3_jl`]); for a constant body
//! twist, `T(t) = T(0) Exp(t ξ)`. `Log` inverts it with the angle in `[0, π]`.

use nalgebra::{Isometry3, Matrix3, Matrix4, Matrix6, Translation3, Vector3, Vector6};

use super::so3::{quat_exp, quat_log, skew, so3_jl, so3_jl_inv, so3_jr, so3_jr_inv};

/// Below this angle (rad) the coefficients of [`barfoot_q`] use Taylor series.
const SMALL: f64 = 0.05;

/// The rotation part `ω` and translation part `v` of a twist `[ω; v]`.
fn split(xi: &Vector6<f64>) -> (Vector3<f64>, Vector3<f64>) {
    (
        Vector3::new(xi[0], xi[1], xi[2]),
        Vector3::new(xi[3], xi[4], xi[5]),
    )
}

/// Builds the 6x6 block matrix `[[a, 0], [c, d]]`.
fn lower_blocks(a: &Matrix3<f64>, c: &Matrix3<f64>, d: &Matrix3<f64>) -> Matrix6<f64> {
    let mut m = Matrix6::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(a);
    m.fixed_view_mut::<3, 3>(3, 0).copy_from(c);
    m.fixed_view_mut::<3, 3>(3, 3).copy_from(d);
    m
}

/// The hat operator of se(3): `[ω; v] ↦ [[[ω]×, v], [0, 0]]`.
pub fn se3_hat(xi: &Vector6<f64>) -> Matrix4<f64> {
    let (w, v) = split(xi);
    let mut m = Matrix4::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&skew(&w));
    m.fixed_view_mut::<3, 1>(0, 3).copy_from(&v);
    m
}

/// SE(3) exponential of `[ω; v]`: rotation `Exp(ω)`, translation `V(ω) v`.
pub fn se3_exp(xi: &Vector6<f64>) -> Isometry3<f64> {
    let (w, v) = split(xi);
    Isometry3::from_parts(Translation3::from(so3_jl(&w) * v), quat_exp(&w))
}

/// SE(3) logarithm `[ω; v]` with `v = V(ω)⁻¹ t` (GTSAM's `Pose3::Logmap`), angle in `[0, π]`.
pub fn se3_log(x: &Isometry3<f64>) -> Vector6<f64> {
    let w = quat_log(&x.rotation);
    let v = so3_jl_inv(&w) * x.translation.vector;
    Vector6::new(w.x, w.y, w.z, v.x, v.y, v.z)
}

/// Adjoint of `x = [R, t]`: `[[R, 0], [[t]× R, R]]`, so that `x Exp(ξ) x⁻¹ = Exp(Ad_x ξ)`.
pub fn se3_adjoint(x: &Isometry3<f64>) -> Matrix6<f64> {
    let r = x.rotation.to_rotation_matrix().into_inner();
    lower_blocks(&r, &(skew(&x.translation.vector) * r), &r)
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

/// Right Jacobian of SE(3): `Exp(ξ + δ) ≈ Exp(ξ) Exp(Jr(ξ) δ)`.
/// `Jr(ξ) = [[A, 0], [B, A]]` with `A = Jr_SO3(ω)`, `B = Q(-v, -ω)`.
pub fn se3_jr(xi: &Vector6<f64>) -> Matrix6<f64> {
    let (w, v) = split(xi);
    let a = so3_jr(&w);
    lower_blocks(&a, &barfoot_q(&(-v), &(-w)), &a)
}

/// Exact inverse right Jacobian of SE(3):
/// `Log(Exp(ξ) Exp(δ)) = ξ + Jr(ξ)⁻¹ δ + O(|δ|²)`;
/// `Jr⁻¹ = [[A⁻¹, 0], [-A⁻¹ B A⁻¹, A⁻¹]]` with `A`, `B` of [`se3_jr`].
pub fn se3_jr_inv(xi: &Vector6<f64>) -> Matrix6<f64> {
    let (w, v) = split(xi);
    let a_inv = so3_jr_inv(&w);
    let b = barfoot_q(&(-v), &(-w));
    lower_blocks(&a_inv, &(-(a_inv * b * a_inv)), &a_inv)
}

/// Left Jacobian of SE(3), `Jl(ξ) = Jr(-ξ)`: `Exp(ξ + δ) ≈ Exp(Jl(ξ) δ) Exp(ξ)`.
pub fn se3_jl(xi: &Vector6<f64>) -> Matrix6<f64> {
    se3_jr(&-xi)
}

/// Inverse left Jacobian of SE(3), `Jl(ξ)⁻¹ = Jr(-ξ)⁻¹`:
/// `Log(Exp(δ) Exp(ξ)) = ξ + Jl(ξ)⁻¹ δ + O(|δ|²)`.
pub fn se3_jl_inv(xi: &Vector6<f64>) -> Matrix6<f64> {
    se3_jr_inv(&-xi)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn xi() -> Vector6<f64> {
        Vector6::new(0.4, -0.3, 0.9, 1.5, -0.7, 2.0)
    }

    /// Rotation angles up to 3.09 rad (`|ω| = 1.03`).
    const SCALES: [f64; 9] = [0.0, 1e-9, 1e-4, 0.04, 0.06, 0.3, 1.0, 2.5, 3.0];

    #[test]
    fn exp_is_the_matrix_exponential_of_hat() {
        for s in SCALES {
            let x = xi() * s;
            let m = se3_hat(&x).exp();
            let e = se3_exp(&x).to_homogeneous();
            assert!((m - e).norm() < 1e-12 * (1.0 + m.norm()), "{s}");
        }
    }

    #[test]
    fn exp_matches_composition_of_small_steps() {
        let big = se3_exp(&xi());
        let n = 10_000;
        let step = se3_exp(&(xi() / n as f64));
        let mut acc = Isometry3::identity();
        for _ in 0..n {
            acc *= step;
        }
        assert!((acc.translation.vector - big.translation.vector).norm() < 1e-9);
        assert!((acc.rotation.inverse() * big.rotation).angle() < 1e-9);
        let tiny = se3_exp(&(xi() * 1e-9));
        assert!((tiny.translation.vector - Vector3::new(1.5, -0.7, 2.0) * 1e-9).norm() < 1e-18);
    }

    #[test]
    fn log_inverts_exp() {
        for s in SCALES {
            let x = xi() * s;
            let back = se3_log(&se3_exp(&x));
            let tol = if s >= 3.0 { 1e-10 } else { 1e-12 };
            assert!(
                (back - x).norm() < tol * (1.0 + x.norm()),
                "{s}: {back} vs {x}"
            );
        }
        // Near π: the rotation angle is kept, the logarithm stays consistent with exp.
        let w = Vector3::new(0.0, PI - 1e-7, 0.0);
        let near = Vector6::new(w.x, w.y, w.z, 0.3, -0.2, 1.0);
        let back = se3_exp(&se3_log(&se3_exp(&near)));
        let e = se3_exp(&near);
        assert!((back.to_homogeneous() - e.to_homogeneous()).norm() < 1e-8);
    }

    #[test]
    fn adjoint_moves_twists() {
        let x = se3_exp(&xi());
        let d = Vector6::new(0.1, 0.2, -0.3, 0.5, -0.1, 0.2);
        let lhs = x * se3_exp(&d) * x.inverse();
        let rhs = se3_exp(&(se3_adjoint(&x) * d));
        assert!((se3_log(&(lhs.inverse() * rhs))).norm() < 1e-12);
        assert!((se3_adjoint(&Isometry3::identity()) - Matrix6::identity()).norm() < 1e-15);
        let y = se3_exp(&(xi() * -0.3));
        assert!((se3_adjoint(&(x * y)) - se3_adjoint(&x) * se3_adjoint(&y)).norm() < 1e-12);
    }

    /// Central difference of `f` along coordinate `k`.
    fn numeric_col(f: impl Fn(&Vector6<f64>) -> Vector6<f64>, k: usize) -> Vector6<f64> {
        let h = 1e-6;
        let mut d = Vector6::zeros();
        d[k] = h;
        (f(&d) - f(&-d)) / (2.0 * h)
    }

    #[test]
    fn jacobians_match_numeric_derivatives() {
        for s in SCALES {
            let x = xi() * s;
            let ex = se3_exp(&x);
            let (jr, jr_inv) = (se3_jr(&x), se3_jr_inv(&x));
            let (jl, jl_inv) = (se3_jl(&x), se3_jl_inv(&x));
            for k in 0..6 {
                let cols = [
                    (
                        numeric_col(|d| se3_log(&(ex.inverse() * se3_exp(&(x + d)))), k),
                        &jr,
                    ),
                    (
                        numeric_col(|d| se3_log(&(se3_exp(&(x + d)) * ex.inverse())), k),
                        &jl,
                    ),
                    (numeric_col(|d| se3_log(&(ex * se3_exp(d))), k), &jr_inv),
                    (numeric_col(|d| se3_log(&(se3_exp(d) * ex)), k), &jl_inv),
                ];
                for (i, (num, j)) in cols.iter().enumerate() {
                    let err = (num - j.column(k)).norm();
                    assert!(
                        err < 1e-7 * (1.0 + num.norm()),
                        "s {s} col {k} J#{i}: {err}"
                    );
                }
            }
            let tol = 1e-11 * (1.0 + jr_inv.norm());
            assert!((jr * jr_inv - Matrix6::identity()).norm() < tol, "{s}");
            assert!((jl * jl_inv - Matrix6::identity()).norm() < tol, "{s}");
            // Jl = Ad(Exp ξ) Jr.
            assert!(
                (jl - se3_adjoint(&ex) * jr).norm() < 1e-11 * (1.0 + jl.norm()),
                "{s}"
            );
        }
    }
}
