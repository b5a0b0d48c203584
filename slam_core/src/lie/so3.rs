//! SO(3): hat/vee, exponential and logarithm (rotation matrix and unit quaternion), and the
//! left and right Jacobians with their inverses. Tangent `ω ∈ ℝ³` (a rotation vector,
//! angle `θ = |ω|`).
//!
//! With `a = sin θ / θ`, `b = (1 - cos θ) / θ²`, `c = (θ - sin θ) / θ³`:
//! - `Exp(ω) = I + a [ω]× + b [ω]×²` (Rodrigues),
//! - `Jr(ω) = I - b [ω]× + c [ω]×²`, `Jl(ω) = Jr(-ω) = I + b [ω]× + c [ω]×²`,
//! - `Jr(ω)⁻¹ = I + ½ [ω]× + d [ω]×²`, `Jl(ω)⁻¹ = I - ½ [ω]× + d [ω]×²`,
//!   `d = (1 - (θ/2) cot(θ/2)) / θ²`,
//!
//! so that `Exp(ω + δ) ≈ Exp(ω) Exp(Jr(ω) δ) ≈ Exp(Jl(ω) δ) Exp(ω)` and
//! `Log(Exp(ω) Exp(δ)) ≈ ω + Jr(ω)⁻¹ δ`. `Jl(ω)` is also the `V(ω)` of the SE(3)
//! exponential. Every coefficient switches to its Taylor series for small angles, so nothing
//! here loses accuracy or divides by zero near `θ = 0`; the inverses are singular at
//! `θ = 2π` only (the logarithm returns `θ ≤ π`).

use nalgebra::{Matrix3, Quaternion, Rotation3, UnitQuaternion, Vector3};

/// Angles below this (rad) use Taylor expansions in the exponential and logarithm.
const SMALL_ANGLE: f64 = 1e-8;

/// Below this angle (rad) the Jacobian coefficients use Taylor series.
const SMALL_JACOBIAN: f64 = 1e-3;

/// The hat operator of so(3), `ω ↦ [ω]×` (skew-symmetric cross-product matrix), so that
/// `skew(a) * b == a.cross(&b)`.
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// The vee operator of so(3), the inverse of [`skew`]: the vector of the skew-symmetric part
/// of `m`.
pub fn vee(m: &Matrix3<f64>) -> Vector3<f64> {
    Vector3::new(
        m[(2, 1)] - m[(1, 2)],
        m[(0, 2)] - m[(2, 0)],
        m[(1, 0)] - m[(0, 1)],
    ) * 0.5
}

/// `(a, b, c) = (sin θ / θ, (1 - cos θ) / θ², (θ - sin θ) / θ³)` from `θ²`. `b` is
/// evaluated as `2 sin²(θ/2) / θ²` (no cancellation); `a` and `b` use Taylor series below
/// [`SMALL_ANGLE`], `c` below [`SMALL_JACOBIAN`].
fn coeffs(theta2: f64) -> (f64, f64, f64) {
    let theta = theta2.sqrt();
    if theta < SMALL_ANGLE {
        return (
            1.0 - theta2 / 6.0,
            0.5 - theta2 / 24.0,
            1.0 / 6.0 - theta2 / 120.0,
        );
    }
    let s = theta.sin();
    let half = (0.5 * theta).sin() / theta;
    let c = if theta < SMALL_JACOBIAN {
        1.0 / 6.0 - theta2 / 120.0 + theta2 * theta2 / 5040.0
    } else {
        (theta - s) / (theta2 * theta)
    };
    (s / theta, 2.0 * half * half, c)
}

/// `d(θ) = (1 - (θ/2) cot(θ/2)) / θ²`, the `[ω]×²` coefficient of `Jr⁻¹` and `Jl⁻¹`.
fn inv_coeff(theta: f64) -> f64 {
    if theta < SMALL_JACOBIAN {
        1.0 / 12.0 + theta * theta / 720.0
    } else {
        let h = 0.5 * theta;
        (1.0 - h / h.tan()) / (theta * theta)
    }
}

/// SO(3) exponential map (Rodrigues): the rotation by angle `|ω|` about `ω / |ω|`.
pub fn so3_exp(w: &Vector3<f64>) -> Rotation3<f64> {
    let (a, b, _) = coeffs(w.norm_squared());
    let k = skew(w);
    Rotation3::from_matrix_unchecked(Matrix3::identity() + k * a + k * k * b)
}

/// SO(3) exponential as a unit quaternion `[cos(θ/2), sin(θ/2) ω/θ]`.
pub fn quat_exp(w: &Vector3<f64>) -> UnitQuaternion<f64> {
    let theta2 = w.norm_squared();
    let (c, s) = if theta2.sqrt() < SMALL_ANGLE {
        // cos(θ/2) ≈ 1 - θ²/8, sin(θ/2)/θ ≈ 1/2 - θ²/48
        (1.0 - theta2 / 8.0, 0.5 - theta2 / 48.0)
    } else {
        let theta = theta2.sqrt();
        let (sh, ch) = (0.5 * theta).sin_cos();
        (ch, sh / theta)
    };
    UnitQuaternion::new_normalize(Quaternion::new(c, w.x * s, w.y * s, w.z * s))
}

/// SO(3) logarithm: the rotation vector `ω` (angle in `[0, π]`) with `so3_exp(ω) == r`.
/// Robust near 0 and near π (goes through the unit quaternion).
pub fn so3_log(r: &Rotation3<f64>) -> Vector3<f64> {
    quat_log(&UnitQuaternion::from_rotation_matrix(r))
}

/// Logarithm of a unit quaternion as a rotation vector (angle in `[0, π]`).
pub fn quat_log(q: &UnitQuaternion<f64>) -> Vector3<f64> {
    // Take the representative with w >= 0 so the angle is in [0, π].
    let (w, v) = if q.w < 0.0 {
        (-q.w, -q.imag())
    } else {
        (q.w, q.imag())
    };
    let n = v.norm();
    if n < SMALL_ANGLE {
        // angle = 2 atan2(n, w) ≈ 2 n / w
        v * (2.0 / w.max(SMALL_ANGLE))
    } else {
        v * (2.0 * n.atan2(w) / n)
    }
}

/// Right Jacobian `Jr(ω) = I - b [ω]× + c [ω]×²`: `Exp(ω + δ) ≈ Exp(ω) Exp(Jr(ω) δ)`.
pub fn so3_jr(w: &Vector3<f64>) -> Matrix3<f64> {
    let (_, b, c) = coeffs(w.norm_squared());
    let k = skew(w);
    Matrix3::identity() - k * b + k * k * c
}

/// Left Jacobian `Jl(ω) = Jr(-ω) = I + b [ω]× + c [ω]×²`, also the `V(ω)` mapping the `v`
/// part of an SE(3) twist to the translation: `Exp(ω + δ) ≈ Exp(Jl(ω) δ) Exp(ω)`.
pub fn so3_jl(w: &Vector3<f64>) -> Matrix3<f64> {
    let (_, b, c) = coeffs(w.norm_squared());
    let k = skew(w);
    Matrix3::identity() + k * b + k * k * c
}

/// Inverse right Jacobian `Jr(ω)⁻¹ = I + ½ [ω]× + d [ω]×²`:
/// `Log(Exp(ω) Exp(δ)) ≈ ω + Jr(ω)⁻¹ δ`.
pub fn so3_jr_inv(w: &Vector3<f64>) -> Matrix3<f64> {
    let k = skew(w);
    Matrix3::identity() + k * 0.5 + k * k * inv_coeff(w.norm())
}

/// Inverse left Jacobian `Jl(ω)⁻¹ = V(ω)⁻¹ = I - ½ [ω]× + d [ω]×²`: maps an SE(3)
/// translation to the `v` part of its logarithm.
pub fn so3_jl_inv(w: &Vector3<f64>) -> Matrix3<f64> {
    let k = skew(w);
    Matrix3::identity() - k * 0.5 + k * k * inv_coeff(w.norm())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn angles() -> Vec<Vector3<f64>> {
        let axis = Vector3::new(0.3, -0.5, 0.8).normalize();
        [
            0.0,
            1e-12,
            1e-9,
            1e-6,
            1e-4,
            9e-4,
            1.1e-3,
            0.01,
            0.3,
            1.0,
            2.5,
            PI - 1e-3,
        ]
        .iter()
        .map(|&t| axis * t)
        .collect()
    }

    #[test]
    fn exp_log_roundtrip() {
        for w in angles().into_iter().chain([
            Vector3::new(1e-10, 0.0, -2e-10),
            Vector3::new(0.0, PI - 1e-9, 0.0),
            Vector3::new(2.0, 1.0, -0.5),
        ]) {
            let r = so3_exp(&w);
            assert!((r.matrix().transpose() * r.matrix() - Matrix3::identity()).norm() < 1e-12);
            let w2 = so3_log(&r);
            assert!(
                (so3_exp(&w2).matrix() - r.matrix()).norm() < 1e-9,
                "{w:?} -> {w2:?}"
            );
            let ref_r = Rotation3::from_scaled_axis(w);
            assert!((ref_r.matrix() - r.matrix()).norm() < 1e-12);
            let q = quat_exp(&w);
            assert!((q.to_rotation_matrix().matrix() - r.matrix()).norm() < 1e-14);
            if w.norm() < PI - 1e-4 {
                assert!(
                    (quat_log(&q) - w).norm() < 1e-14 * (1.0 + w.norm()),
                    "{w:?}"
                );
            }
        }
    }

    #[test]
    fn log_near_pi_keeps_angle() {
        let w = Vector3::new(0.0, 0.0, PI - 1e-7);
        let back = so3_log(&so3_exp(&w));
        assert!((back.norm() - w.norm()).abs() < 1e-8);
        // Past π the logarithm wraps to the short way round.
        let past = so3_log(&so3_exp(&Vector3::new(0.0, 0.0, PI + 0.1)));
        assert!((past - Vector3::new(0.0, 0.0, 0.1 - PI)).norm() < 1e-12);
    }

    #[test]
    fn skew_vee() {
        let a = Vector3::new(1.0, 2.0, 3.0);
        let b = Vector3::new(-0.5, 0.1, 4.0);
        assert!((skew(&a) * b - a.cross(&b)).norm() < 1e-15);
        assert_eq!(vee(&skew(&a)), a);
    }

    /// Central difference of `f` in direction `k` with step `h`.
    fn numeric_col(f: impl Fn(&Vector3<f64>) -> Vector3<f64>, k: usize, h: f64) -> Vector3<f64> {
        let mut d = Vector3::zeros();
        d[k] = h;
        (f(&d) - f(&-d)) / (2.0 * h)
    }

    #[test]
    fn jacobians_match_numeric_derivatives() {
        let h = 1e-6;
        for w in angles() {
            let (jr, jl) = (so3_jr(&w), so3_jl(&w));
            let (jr_inv, jl_inv) = (so3_jr_inv(&w), so3_jl_inv(&w));
            let r = so3_exp(&w);
            for k in 0..3 {
                // Jr: Log(Exp(ω)⁻¹ Exp(ω + δ)) ≈ Jr δ; Jl: Log(Exp(ω + δ) Exp(ω)⁻¹) ≈ Jl δ.
                let num_r = numeric_col(|d| so3_log(&(r.inverse() * so3_exp(&(w + d)))), k, h);
                let num_l = numeric_col(|d| so3_log(&(so3_exp(&(w + d)) * r.inverse())), k, h);
                // Jr⁻¹: Log(Exp(ω) Exp(δ)) ≈ ω + Jr⁻¹ δ; Jl⁻¹: Log(Exp(δ) Exp(ω)) ≈ ω + Jl⁻¹ δ.
                let num_ri = numeric_col(|d| so3_log(&(r * so3_exp(d))), k, h);
                let num_li = numeric_col(|d| so3_log(&(so3_exp(d) * r)), k, h);
                for (num, j, name) in [
                    (num_r, &jr, "Jr"),
                    (num_l, &jl, "Jl"),
                    (num_ri, &jr_inv, "Jr⁻¹"),
                    (num_li, &jl_inv, "Jl⁻¹"),
                ] {
                    let err = (num - j.column(k)).norm();
                    assert!(err < 1e-8, "{name} θ {} col {k}: {err}", w.norm());
                }
            }
            let tol = 1e-12 * (1.0 + jr_inv.norm());
            assert!(
                (jr * jr_inv - Matrix3::identity()).norm() < tol,
                "{}",
                w.norm()
            );
            assert!(
                (jl * jl_inv - Matrix3::identity()).norm() < tol,
                "{}",
                w.norm()
            );
            assert!((so3_jl(&-w) - jr).norm() < 1e-15);
        }
    }

    #[test]
    fn series_match_closed_forms_at_switch() {
        // Both sides of each switch agree to rounding.
        for t in [SMALL_JACOBIAN * (1.0 - 1e-9), SMALL_JACOBIAN * (1.0 + 1e-9)] {
            let h = 0.5 * t;
            let closed = (1.0 - h / h.tan()) / (t * t);
            assert!((inv_coeff(t) - closed).abs() < 1e-9);
        }
        for t in [SMALL_JACOBIAN, SMALL_ANGLE] {
            let (a0, b0, c0) = coeffs((t * (1.0 - 1e-9)).powi(2));
            let (a1, b1, c1) = coeffs((t * (1.0 + 1e-9)).powi(2));
            assert!((a0 - a1).abs() < 1e-15 && (b0 - b1).abs() < 1e-15, "{t}");
            assert!((c0 - c1).abs() < 1e-9, "{t}");
        }
    }
}
