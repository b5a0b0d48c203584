//! Similarity transforms Sim(3): `x_a = s R x_b + t` (seed §2.2 / §3.4.3, `S = [sR, t]`),
//! with the exponential and logarithm on the tangent `ξ = [ω; ρ; σ]` (rotation, translation,
//! log-scale: rotation first like SE(3); the seed's minimal vector `(ν, ω, σ)` of eq. 2.23
//! lists the translation first), the adjoint, and the right Jacobian and its inverse.
//!
//! `Exp([ω; ρ; σ]) = [e^σ Exp(ω), W(ω, σ) ρ]` with `W = ∫₀¹ e^{σu} Exp(uω) du`
//! ([`sim3_w`]); it is the matrix exponential of [`sim3_hat`].

use std::ops::Mul;
use std::sync::OnceLock;

use nalgebra::{
    Isometry3, Matrix3, Matrix4, SMatrix, SVector, Translation3, UnitQuaternion, Vector3,
};

use super::so3::{quat_exp, quat_log, skew};

/// A 7-vector `[ω; ρ; σ]` of the Sim(3) tangent space.
pub type Vector7 = SVector<f64, 7>;
/// A 7x7 matrix (Sim(3) information, adjoint, Jacobians), rows and columns `[ω; ρ; σ]`.
pub type Matrix7 = SMatrix<f64, 7, 7>;

/// A similarity `x ↦ s R x + t` with `s > 0`.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct Sim3 {
    /// Rotation `R`.
    pub r: UnitQuaternion<f64>,
    /// Translation `t`.
    pub t: Vector3<f64>,
    /// Scale `s > 0`.
    pub s: f64,
}

impl Default for Sim3 {
    fn default() -> Self {
        Self::identity()
    }
}

/// The parts `(ω, ρ, σ)` of a tangent vector.
fn split(xi: &Vector7) -> (Vector3<f64>, Vector3<f64>, f64) {
    (
        Vector3::new(xi[0], xi[1], xi[2]),
        Vector3::new(xi[3], xi[4], xi[5]),
        xi[6],
    )
}

impl Sim3 {
    /// The identity.
    pub fn identity() -> Self {
        Self {
            r: UnitQuaternion::identity(),
            t: Vector3::zeros(),
            s: 1.0,
        }
    }

    /// A similarity from its parts.
    pub fn new(r: UnitQuaternion<f64>, t: Vector3<f64>, s: f64) -> Self {
        Self { r, t, s }
    }

    /// A rigid transform as a similarity with scale `s`.
    pub fn from_isometry(x: &Isometry3<f64>, s: f64) -> Self {
        Self::new(x.rotation, x.translation.vector, s)
    }

    /// The rigid part `[R, t]` (the scale dropped), e.g. a keyframe pose after PGO.
    pub fn to_isometry(&self) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::from(self.t), self.r)
    }

    /// The inverse: `[R⁻¹, -R⁻¹ t / s, 1/s]`.
    pub fn inverse(&self) -> Self {
        let ri = self.r.inverse();
        Self {
            r: ri,
            t: -(ri * self.t) / self.s,
            s: 1.0 / self.s,
        }
    }

    /// `self ∘ other`: `[R₁R₂, s₁R₁t₂ + t₁, s₁s₂]`.
    pub fn compose(&self, other: &Sim3) -> Self {
        Self {
            r: self.r * other.r,
            t: self.r * other.t * self.s + self.t,
            s: self.s * other.s,
        }
    }

    /// Applies the similarity to a point: `s R x + t`.
    pub fn transform_point(&self, x: &Vector3<f64>) -> Vector3<f64> {
        self.r * x * self.s + self.t
    }

    /// The 4x4 matrix `[[sR, t], [0, 1]]`.
    pub fn to_homogeneous(&self) -> Matrix4<f64> {
        let mut m = Matrix4::identity();
        m.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(self.r.to_rotation_matrix().into_inner() * self.s));
        m.fixed_view_mut::<3, 1>(0, 3).copy_from(&self.t);
        m
    }

    /// Exponential of `[ω; ρ; σ]`: `R = Exp(ω)`, `s = e^σ`, `t = W(ω, σ) ρ`.
    pub fn exp(xi: &Vector7) -> Self {
        let (w, rho, sigma) = split(xi);
        Self {
            r: quat_exp(&w),
            t: sim3_w(&w, sigma) * rho,
            s: sigma.exp(),
        }
    }

    /// Logarithm `[ω; ρ; σ]` (angle in `[0, π]`); inverse of [`Sim3::exp`].
    pub fn log(&self) -> Vector7 {
        let w = quat_log(&self.r);
        let sigma = self.s.ln();
        let wm = sim3_w(&w, sigma);
        // W is invertible for θ < 2π (its eigenvalues are averages of e^{σu}·e^{±iθu}).
        let rho = wm.try_inverse().unwrap_or_else(Matrix3::identity) * self.t;
        Vector7::from_column_slice(&[w.x, w.y, w.z, rho.x, rho.y, rho.z, sigma])
    }

    /// Adjoint `[[R, 0, 0], [[t]×R, sR, -t], [0, 0, 1]]`: `S Exp(ξ) S⁻¹ = Exp(Ad_S ξ)`.
    pub fn adjoint(&self) -> Matrix7 {
        let r = self.r.to_rotation_matrix().into_inner();
        let mut m = Matrix7::zeros();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
        m.fixed_view_mut::<3, 3>(3, 0)
            .copy_from(&(skew(&self.t) * r));
        m.fixed_view_mut::<3, 3>(3, 3).copy_from(&(r * self.s));
        m.fixed_view_mut::<3, 1>(3, 6).copy_from(&(-self.t));
        m[(6, 6)] = 1.0;
        m
    }
}

impl Mul for Sim3 {
    type Output = Sim3;
    fn mul(self, rhs: Sim3) -> Sim3 {
        self.compose(&rhs)
    }
}

impl Mul for &Sim3 {
    type Output = Sim3;
    fn mul(self, rhs: &Sim3) -> Sim3 {
        self.compose(rhs)
    }
}

/// The hat operator of sim(3): `[ω; ρ; σ] ↦ [[[ω]× + σI, ρ], [0, 0]]`.
pub fn sim3_hat(xi: &Vector7) -> Matrix4<f64> {
    let (w, rho, sigma) = split(xi);
    let mut m = Matrix4::zeros();
    m.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(skew(&w) + Matrix3::identity() * sigma));
    m.fixed_view_mut::<3, 1>(0, 3).copy_from(&rho);
    m
}

/// Nodes and weights of 16-point Gauss-Legendre quadrature on `[0, 1]`, computed once by
/// Newton's method on the Legendre polynomial.
fn gauss_legendre() -> &'static [(f64, f64); 16] {
    static GL: OnceLock<[(f64, f64); 16]> = OnceLock::new();
    GL.get_or_init(|| {
        const N: usize = 16;
        let mut out = [(0.0, 0.0); N];
        for (i, o) in out.iter_mut().enumerate() {
            let mut x = (std::f64::consts::PI * (i as f64 + 0.75) / (N as f64 + 0.5)).cos();
            let mut dp = 1.0;
            for _ in 0..100 {
                let (mut p0, mut p1) = (1.0, x);
                for k in 2..=N {
                    let kf = k as f64;
                    let p2 = ((2.0 * kf - 1.0) * x * p1 - (kf - 1.0) * p0) / kf;
                    p0 = p1;
                    p1 = p2;
                }
                dp = N as f64 * (x * p1 - p0) / (x * x - 1.0);
                let dx = p1 / dp;
                x -= dx;
                if dx.abs() < 1e-16 {
                    break;
                }
            }
            let w = 2.0 / ((1.0 - x * x) * dp * dp);
            *o = (0.5 * (1.0 + x), 0.5 * w);
        }
        out
    })
}

/// `W(ω, σ) = ∫₀¹ e^{σu} Exp(uω) du = a I + b [ω]× + c [ω]×²`, the matrix mapping `ρ` to
/// the translation in [`Sim3::exp`]. The three scalar integrals are evaluated by 16-point
/// Gauss-Legendre quadrature (exact to rounding for `|σ| + θ` up to ~10), which avoids the
/// cancellations of the closed forms when `σ` and `θ` are both small.
pub fn sim3_w(w: &Vector3<f64>, sigma: f64) -> Matrix3<f64> {
    let theta = w.norm();
    let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
    for &(u, wt) in gauss_legendre() {
        let e = (sigma * u).exp() * wt;
        let tu = theta * u;
        // sin(θu)/θ and (1 - cos θu)/θ² = 2 sin²(θu/2)/θ², stable for θ → 0.
        let (sinc, vers) = if theta < 1e-8 {
            (u, 0.5 * u * u)
        } else {
            let h = (0.5 * tu).sin() / theta;
            (tu.sin() / theta, 2.0 * h * h)
        };
        a += e;
        b += e * sinc;
        c += e * vers;
    }
    let k = skew(w);
    Matrix3::identity() * a + k * b + k * k * c
}

/// The Lie bracket matrix `ad_ξ` of sim(3) in `[ω; ρ; σ]` order,
/// `[[[ω]×, 0, 0], [[ρ]×, [ω]× + σI, -ρ], [0, 0, 0]]`, so that `Ad(Exp ξ) = exp(ad_ξ)`.
pub fn sim3_ad(xi: &Vector7) -> Matrix7 {
    let (w, rho, sigma) = split(xi);
    let wx = skew(&w);
    let mut m = Matrix7::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&wx);
    m.fixed_view_mut::<3, 3>(3, 0).copy_from(&skew(&rho));
    m.fixed_view_mut::<3, 3>(3, 3)
        .copy_from(&(wx + Matrix3::identity() * sigma));
    m.fixed_view_mut::<3, 1>(3, 6).copy_from(&(-rho));
    m
}

/// Right Jacobian of Sim(3), `Exp(ξ + δ) ≈ Exp(ξ) Exp(Jr(ξ) δ)`:
/// `Jr(ξ) = ∫₀¹ exp(-u ad_ξ) du = ∫₀¹ Ad(Exp(-uξ)) du`, by the 16-point Gauss-Legendre rule
/// of [`sim3_w`] (exact to rounding for `|σ| + θ` up to ~10).
pub fn sim3_jr(xi: &Vector7) -> Matrix7 {
    let mut m = Matrix7::zeros();
    for &(u, wt) in gauss_legendre() {
        m += Sim3::exp(&(xi * -u)).adjoint() * wt;
    }
    m
}

/// Inverse right Jacobian of Sim(3), `Log(Exp(ξ) Exp(δ)) ≈ ξ + Jr(ξ)⁻¹ δ`, by its Bernoulli
/// series `Jr⁻¹ = Σ Bₙ⁺ adⁿ / n!`, i.e.
/// `I + ½ad + ad²/12 - ad⁴/720 + ad⁶/30240 - ad⁸/1209600 + ad¹⁰/47900160`. Converges for
/// `|σ ± iθ| < 2π`; the truncation error is below 1e-9 for residuals with `|σ| + θ < 1`,
/// which holds near every optimum (the pose-graph cost itself is always evaluated exactly,
/// so larger residuals only slow the first iterations down).
pub fn sim3_jr_inv(xi: &Vector7) -> Matrix7 {
    let ad = sim3_ad(xi);
    let ad2 = ad * ad;
    // Horner in ad²: I + ad/2 + ad²(1/12 + ad²(-1/720 + ad²(1/30240 + ad²(-1/1209600 + ad²/47900160))))
    let mut p = ad2 * (1.0 / 47_900_160.0);
    p += Matrix7::identity() * (-1.0 / 1_209_600.0);
    p = ad2 * p;
    p += Matrix7::identity() * (1.0 / 30_240.0);
    p = ad2 * p;
    p += Matrix7::identity() * (-1.0 / 720.0);
    p = ad2 * p;
    p += Matrix7::identity() * (1.0 / 12.0);
    Matrix7::identity() + ad * 0.5 + ad2 * p
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    /// `ω = (0.3, -0.5, 0.8)`, `ρ = (0.7, -1.2, 0.4)`, `σ = 0.6`.
    fn xi() -> Vector7 {
        Vector7::from_column_slice(&[0.3, -0.5, 0.8, 0.7, -1.2, 0.4, 0.6])
    }

    fn close(a: &Sim3, b: &Sim3, tol: f64) -> bool {
        (a.t - b.t).norm() < tol && (a.s - b.s).abs() < tol && a.r.angle_to(&b.r) < tol
    }

    #[test]
    fn gauss_legendre_integrates_polynomials_and_exp() {
        let gl = gauss_legendre();
        let sum_w: f64 = gl.iter().map(|g| g.1).sum();
        assert!((sum_w - 1.0).abs() < 1e-14);
        let i5: f64 = gl.iter().map(|&(u, w)| w * u.powi(5)).sum();
        assert!((i5 - 1.0 / 6.0).abs() < 1e-14);
        let ie: f64 = gl.iter().map(|&(u, w)| w * (2.0 * u).exp()).sum();
        assert!((ie - (2f64.exp() - 1.0) / 2.0).abs() < 1e-13);
    }

    #[test]
    fn compose_inverse_and_points() {
        let a = Sim3::exp(&xi());
        let b = Sim3::exp(&(xi() * -0.3 + Vector7::from_element(0.1)));
        let p = Vector3::new(0.3, 2.0, -1.0);
        assert!(close(&(a * a.inverse()), &Sim3::identity(), 1e-12));
        assert!(close(&(a.inverse() * a), &Sim3::identity(), 1e-12));
        let ab = a * b;
        assert!(
            (ab.transform_point(&p) - a.transform_point(&b.transform_point(&p))).norm() < 1e-12
        );
        assert!((a.inverse().transform_point(&a.transform_point(&p)) - p).norm() < 1e-12);
    }

    #[test]
    fn w_matches_closed_form() {
        // a = (e^σ - 1)/σ, b = (e^σ(σ sinθ - θ cosθ) + θ)/(θ(σ²+θ²)),
        // c = (a - (e^σ(σ cosθ + θ sinθ) - σ)/(σ²+θ²))/θ²
        let (w, sigma) = (Vector3::<f64>::new(0.3, -0.5, 0.8), 0.6_f64);
        let th = w.norm();
        let es = f64::exp(sigma);
        let d = sigma * sigma + th * th;
        let a = (es - 1.0) / sigma;
        let b = (es * (sigma * th.sin() - th * th.cos()) + th) / (th * d);
        let c = (a - (es * (sigma * th.cos() + th * th.sin()) - sigma) / d) / (th * th);
        let k = skew(&w);
        let expect = Matrix3::identity() * a + k * b + k * k * c;
        assert!((sim3_w(&w, sigma) - expect).norm() < 1e-13);
    }

    #[test]
    fn exp_is_the_matrix_exponential_of_hat() {
        for s in [0.0, 1e-9, 1e-4, 0.1, 1.0, 2.0] {
            let x = xi() * s;
            let m = sim3_hat(&x).exp();
            let e = Sim3::exp(&x).to_homogeneous();
            assert!((m - e).norm() < 1e-12 * (1.0 + m.norm()), "{s}");
        }
    }

    #[test]
    fn exp_matches_many_small_steps_and_log_inverts() {
        let x = xi();
        let big = Sim3::exp(&x);
        let n = 20_000;
        let step = Sim3::exp(&(x / n as f64));
        let mut acc = Sim3::identity();
        for _ in 0..n {
            acc = acc * step;
        }
        assert!(close(&acc, &big, 1e-8), "{acc:?} vs {big:?}");
        for s in [0.0, 1e-9, 1e-4, 0.1, 1.0, 2.0, 3.0] {
            let v = x * s;
            assert!(
                (Sim3::exp(&v).log() - v).norm() < 1e-11 * (1.0 + v.norm()),
                "{s}"
            );
        }
        // Near π the rotation angle is kept and exp(log(S)) = S.
        let near = Vector7::from_column_slice(&[0.0, PI - 1e-7, 0.0, 0.5, 0.1, -0.2, -0.3]);
        let s = Sim3::exp(&near);
        assert!((s.log()[1] - (PI - 1e-7)).abs() < 1e-8);
        assert!(close(&Sim3::exp(&s.log()), &s, 1e-9));
    }

    #[test]
    fn adjoint_moves_twists_and_is_exp_of_ad() {
        let a = Sim3::exp(&xi());
        let d = Vector7::from_column_slice(&[0.05, -0.1, 0.2, 0.1, 0.2, -0.3, 0.3]);
        let lhs = a * Sim3::exp(&d) * a.inverse();
        let rhs = Sim3::exp(&(a.adjoint() * d));
        assert!(close(&lhs, &rhs, 1e-12));
        let b = Sim3::exp(&(xi() * -0.4));
        assert!(((a * b).adjoint() - a.adjoint() * b.adjoint()).norm() < 1e-12);
        assert!((sim3_ad(&xi()).exp() - a.adjoint()).norm() < 1e-11);
    }

    /// Central difference of `f` along coordinate `k`.
    fn numeric_col(f: impl Fn(&Vector7) -> Vector7, k: usize) -> Vector7 {
        let h = 1e-6;
        let mut d = Vector7::zeros();
        d[k] = h;
        (f(&d) - f(&-d)) / (2.0 * h)
    }

    #[test]
    fn jacobians_match_numeric_derivatives() {
        for s in [0.0, 1e-6, 0.01, 0.3, 1.0] {
            let x = xi() * s;
            let (jr, jr_inv) = (sim3_jr(&x), sim3_jr_inv(&x));
            let ex = Sim3::exp(&x);
            for k in 0..7 {
                let num = numeric_col(|d| (ex * Sim3::exp(d)).log(), k);
                let err = (num - jr_inv.column(k)).norm();
                assert!(err < 1e-7, "Jr⁻¹ s {s} col {k}: {err}");
                let num = numeric_col(|d| (ex.inverse() * Sim3::exp(&(x + d))).log(), k);
                let err = (num - jr.column(k)).norm();
                assert!(err < 1e-7, "Jr s {s} col {k}: {err}");
            }
            assert!((jr * jr_inv - Matrix7::identity()).norm() < 1e-7, "{s}");
        }
    }
}
