//! Non-linear refinement of a relative motion `(R, t)`, `|t| = 1`, by Levenberg-Marquardt on
//! the Sampson approximation of the reprojection error of `x2ᵀ [t]x R x1 = 0` (Hartley &
//! Zisserman, section 11.4.3), over the inliers of the chosen model.
//!
//! The linear 8-point / DLT estimates are biased by noise (≈0.2° rotation and ≈0.7°
//! translation-direction error with 1 px noise on 500 matches); this brings them close to
//! the maximum-likelihood motion for the price of a few milliseconds. The same cost is used
//! after a homography, whose two-fold ambiguity is already resolved by cheirality, so the
//! refinement starts next to an isolated minimum.
//!
//! Parametrisation (5 dof): `R ← R Exp(ω)` (right perturbation) and
//! `t ← normalize(t + b1 δ1 + b2 δ2)` with `{b1, b2}` an orthonormal basis of `t⊥`.
//! The Jacobian is by central differences (5 columns), accumulated point by point into the
//! 5x5 normal equations: nothing is allocated.

use nalgebra::{Matrix3, Rotation3, SMatrix, SVector, Vector2, Vector3};

use crate::lie::{skew, so3_exp};

type M5 = SMatrix<f64, 5, 5>;
type V5 = SVector<f64, 5>;

/// Sampson distance of one correspondence for the essential matrix `e` (normalised units).
#[inline]
fn sampson(e: &Matrix3<f64>, a: &Vector2<f64>, b: &Vector2<f64>) -> f64 {
    let x1 = Vector3::new(a.x, a.y, 1.0);
    let x2 = Vector3::new(b.x, b.y, 1.0);
    let ex1 = e * x1;
    let etx2 = e.transpose() * x2;
    let num = x2.dot(&ex1);
    let den = ex1.x * ex1.x + ex1.y * ex1.y + etx2.x * etx2.x + etx2.y * etx2.y;
    if den > 1e-300 {
        num / den.sqrt()
    } else {
        0.0
    }
}

/// Marks the matches whose squared Sampson error under `(r, t)` is at most `max2`
/// (normalised units).
pub(crate) fn classify(
    r: &Rotation3<f64>,
    t: &Vector3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    max2: f64,
    inliers: &mut [bool],
) {
    let e = essential(r, t);
    for ((a, b), m) in x1.iter().zip(x2).zip(inliers.iter_mut()) {
        let d = sampson(&e, a, b);
        *m = d * d <= max2;
    }
}

/// An orthonormal basis of the plane orthogonal to the unit vector `t`.
fn tangent_basis(t: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let a = if t.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let b1 = t.cross(&a).normalize();
    let b2 = t.cross(&b1);
    (b1, b2)
}

/// Applies the 5-vector update.
fn retract(r: &Rotation3<f64>, t: &Vector3<f64>, d: &V5) -> (Rotation3<f64>, Vector3<f64>) {
    let (b1, b2) = tangent_basis(t);
    let r2 = r * so3_exp(&Vector3::new(d[0], d[1], d[2]));
    let t2 = (t + b1 * d[3] + b2 * d[4]).normalize();
    (r2, t2)
}

fn essential(r: &Rotation3<f64>, t: &Vector3<f64>) -> Matrix3<f64> {
    skew(t) * r.matrix()
}

/// Huber weight of a residual with threshold `delta`.
#[inline]
fn huber_w(r: f64, delta: f64) -> f64 {
    let a = r.abs();
    if a <= delta {
        1.0
    } else {
        delta / a
    }
}

/// Huber cost of a residual.
#[inline]
fn huber_cost(r: f64, delta: f64) -> f64 {
    let a = r.abs();
    if a <= delta {
        r * r
    } else {
        2.0 * delta * a - delta * delta
    }
}

fn cost(
    e: &Matrix3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    inl: &[bool],
    delta: f64,
) -> f64 {
    let mut c = 0.0;
    for i in 0..x1.len() {
        if inl[i] {
            c += huber_cost(sampson(e, &x1[i], &x2[i]), delta);
        }
    }
    c
}

/// Refines `(r, t)` (unit `t`) on the inliers with at most `max_iters` LM iterations; Huber
/// loss with threshold `delta` (normalised units). Returns the refined motion, never one
/// with a higher cost than the input.
pub(crate) fn refine_motion(
    r: &Rotation3<f64>,
    t: &Vector3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    inliers: &[bool],
    delta: f64,
    max_iters: usize,
) -> (Rotation3<f64>, Vector3<f64>) {
    let (mut r, mut t) = (*r, t.normalize());
    if !t.iter().all(|v| v.is_finite()) {
        return (r, t);
    }
    let mut e = essential(&r, &t);
    let mut c = cost(&e, x1, x2, inliers, delta);
    let mut lambda = 1e-3;
    const H: f64 = 1e-7;
    for _ in 0..max_iters {
        // Perturbed essential matrices for the central differences.
        let mut ep = [Matrix3::zeros(); 5];
        let mut em = [Matrix3::zeros(); 5];
        for k in 0..5 {
            let mut d = V5::zeros();
            d[k] = H;
            let (rp, tp) = retract(&r, &t, &d);
            ep[k] = essential(&rp, &tp);
            let (rm, tm) = retract(&r, &t, &(-d));
            em[k] = essential(&rm, &tm);
        }
        let mut hess = M5::zeros();
        let mut g = V5::zeros();
        for i in 0..x1.len() {
            if !inliers[i] {
                continue;
            }
            let res = sampson(&e, &x1[i], &x2[i]);
            let mut j = V5::zeros();
            for k in 0..5 {
                j[k] =
                    (sampson(&ep[k], &x1[i], &x2[i]) - sampson(&em[k], &x1[i], &x2[i])) / (2.0 * H);
            }
            let w = huber_w(res, delta);
            hess.ger(w, &j, &j, 1.0);
            g += j * (w * res);
        }
        let mut improved = false;
        for _ in 0..8 {
            let mut a = hess;
            for k in 0..5 {
                a[(k, k)] += lambda * hess[(k, k)].max(1e-12);
            }
            let Some(chol) = a.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let d = -chol.solve(&g);
            let (r2, t2) = retract(&r, &t, &d);
            let e2 = essential(&r2, &t2);
            let c2 = cost(&e2, x1, x2, inliers, delta);
            if c2.is_finite() && c2 < c {
                let rel = (c - c2) / c.max(1e-300);
                (r, t, e, c) = (r2, t2, e2, c2);
                lambda = (lambda * 0.1).max(1e-9);
                improved = rel > 1e-10;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    (r, t)
}

#[cfg(test)]
pub(crate) fn test_cost(
    r: &Rotation3<f64>,
    t: &Vector3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
) -> f64 {
    cost(&essential(r, t), x1, x2, &vec![true; x1.len()], 1.0)
}

/// Symmetric transfer residuals of one correspondence under `h` (normalised units; zeros
/// when a point maps to infinity).
#[inline]
fn transfer_residuals(
    h: &Matrix3<f64>,
    h_inv: &Matrix3<f64>,
    a: &Vector2<f64>,
    b: &Vector2<f64>,
) -> [f64; 4] {
    let map = |m: &Matrix3<f64>, p: &Vector2<f64>| -> Option<Vector2<f64>> {
        let q = m * Vector3::new(p.x, p.y, 1.0);
        (q.z.abs() > 1e-12).then(|| Vector2::new(q.x / q.z, q.y / q.z))
    };
    match (map(h, a), map(h_inv, b)) {
        (Some(p), Some(q)) => [p.x - b.x, p.y - b.y, q.x - a.x, q.y - a.y],
        _ => [0.0; 4],
    }
}

fn transfer_cost(
    h: &Matrix3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    inl: &[bool],
    delta: f64,
) -> f64 {
    let Some(h_inv) = h.try_inverse() else {
        return f64::INFINITY;
    };
    let mut c = 0.0;
    for i in 0..x1.len() {
        if inl[i] {
            for r in transfer_residuals(h, &h_inv, &x1[i], &x2[i]) {
                c += huber_cost(r, delta);
            }
        }
    }
    c
}

/// Refines a homography (`x2 ~ H x1`, normalised coordinates) on the inliers by LM on the
/// symmetric transfer error with a Huber loss (threshold `delta`). `H` is kept at unit
/// Frobenius norm and perturbed in the 8-dimensional tangent space of that sphere;
/// central-difference Jacobian. Never returns a matrix with a higher cost than the input.
pub(crate) fn refine_homography(
    h: &Matrix3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    inliers: &[bool],
    delta: f64,
    max_iters: usize,
) -> Matrix3<f64> {
    type M8 = SMatrix<f64, 8, 8>;
    type V8 = SVector<f64, 8>;
    let mut h = h / h.norm();
    if !h.iter().all(|v| v.is_finite()) {
        return h;
    }
    let mut c = transfer_cost(&h, x1, x2, inliers, delta);
    let mut lambda = 1e-3;
    const EPS: f64 = 1e-7;
    for _ in 0..max_iters {
        // Orthonormal basis of the tangent space at h (Gram-Schmidt on the unit matrices).
        let mut basis = [Matrix3::zeros(); 8];
        let mut nb = 0;
        for k in 0..9 {
            if nb == 8 {
                break;
            }
            let mut b = Matrix3::zeros();
            b[(k / 3, k % 3)] = 1.0;
            b -= h * h.dot(&b);
            for q in &basis[..nb] {
                b -= q * q.dot(&b);
            }
            let n = b.norm();
            if n > 1e-6 {
                basis[nb] = b / n;
                nb += 1;
            }
        }
        if nb < 8 {
            break;
        }
        let step = |d: &V8| -> Matrix3<f64> {
            let mut m = h;
            for k in 0..8 {
                m += basis[k] * d[k];
            }
            m / m.norm()
        };
        let mut hp = [(Matrix3::zeros(), Matrix3::zeros()); 8];
        let mut hm = [(Matrix3::zeros(), Matrix3::zeros()); 8];
        for k in 0..8 {
            let mut d = V8::zeros();
            d[k] = EPS;
            let (p, m) = (step(&d), step(&(-d)));
            match (p.try_inverse(), m.try_inverse()) {
                (Some(pi), Some(mi)) => {
                    hp[k] = (p, pi);
                    hm[k] = (m, mi);
                }
                _ => return h,
            }
        }
        let Some(h_inv) = h.try_inverse() else {
            return h;
        };
        let mut hess = M8::zeros();
        let mut g = V8::zeros();
        for i in 0..x1.len() {
            if !inliers[i] {
                continue;
            }
            let r0 = transfer_residuals(&h, &h_inv, &x1[i], &x2[i]);
            let mut j = [V8::zeros(); 4];
            for k in 0..8 {
                let rp = transfer_residuals(&hp[k].0, &hp[k].1, &x1[i], &x2[i]);
                let rm = transfer_residuals(&hm[k].0, &hm[k].1, &x1[i], &x2[i]);
                for c in 0..4 {
                    j[c][k] = (rp[c] - rm[c]) / (2.0 * EPS);
                }
            }
            for c in 0..4 {
                let w = huber_w(r0[c], delta);
                hess.ger(w, &j[c], &j[c], 1.0);
                g += j[c] * (w * r0[c]);
            }
        }
        let mut improved = false;
        for _ in 0..8 {
            let mut a = hess;
            for k in 0..8 {
                a[(k, k)] += lambda * hess[(k, k)].max(1e-12);
            }
            let Some(chol) = a.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let d = -chol.solve(&g);
            let h2 = step(&d);
            let c2 = transfer_cost(&h2, x1, x2, inliers, delta);
            if c2.is_finite() && c2 < c {
                let rel = (c - c2) / c.max(1e-300);
                (h, c) = (h2, c2);
                lambda = (lambda * 0.1).max(1e-9);
                improved = rel > 1e-10;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    h
}
