//! Epipolar geometry `x2ᵀ F x1 = 0`: the normalised eight-point algorithm (Hartley 1997),
//! ORB-SLAM's epipolar score (Mur-Artal et al. 2015, section IV-2), and the essential matrix
//! with its four-fold decomposition (Hartley & Zisserman, section 9.6.2).
//!
//! Because the points are undistorted normalised image coordinates `(x/z, y/z)`, the
//! fundamental matrix estimated here already is an essential matrix up to noise
//! (`E = Kᵀ F K` with `K = I`); [`essential_from_fundamental`] projects it onto the
//! essential manifold.

use nalgebra::{Matrix3, Rotation3, Vector2, Vector3, SVD};

use super::normalize::{apply, hartley, null_matrix, Normal9, Row9};
use crate::CoreError;

/// Eight-point DLT on normalised points for `i` in `indices`, with the rank-2 constraint
/// enforced (smallest singular value set to 0). `None` on a degenerate set.
pub(crate) fn solve_normalized<I>(
    x1n: &[Vector2<f64>],
    x2n: &[Vector2<f64>],
    indices: I,
) -> Option<Matrix3<f64>>
where
    I: IntoIterator<Item = usize>,
{
    let mut ata = Normal9::zeros();
    for i in indices {
        let (a, b) = (&x1n[i], &x2n[i]);
        let r = Row9::from([
            b.x * a.x,
            b.x * a.y,
            b.x,
            b.y * a.x,
            b.y * a.y,
            b.y,
            a.x,
            a.y,
            1.0,
        ]);
        ata.ger(1.0, &r, &r, 1.0);
    }
    let f = null_matrix(&ata)?;
    enforce_rank2(&f)
}

/// Sets the smallest singular value of `f` to zero.
fn enforce_rank2(f: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    let svd = SVD::new(*f, true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let mut s = svd.singular_values;
    let imin = s.imin();
    s[imin] = 0.0;
    Some(u * Matrix3::from_diagonal(&s) * v_t)
}

/// `F = T2ᵀ Fn T1`, scaled to unit Frobenius norm.
pub(crate) fn denormalize(
    fnorm: &Matrix3<f64>,
    t1: &Matrix3<f64>,
    t2: &Matrix3<f64>,
) -> Option<Matrix3<f64>> {
    let f = t2.transpose() * fnorm * t1;
    let n = f.norm();
    (n.is_finite() && n > 0.0).then(|| f / n)
}

/// Normalised eight-point fundamental matrix from all correspondences (`x2ᵀ F x1 = 0`),
/// rank 2, unit Frobenius norm.
///
/// Errors: different lengths, fewer than 8 points, or a degenerate configuration.
pub fn fundamental_8point(
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
) -> Result<Matrix3<f64>, CoreError> {
    if x1.len() != x2.len() {
        return Err(CoreError::InvalidArgument(
            "fundamental_8point: length mismatch".into(),
        ));
    }
    if x1.len() < 8 {
        return Err(CoreError::NotEnoughData(format!(
            "fundamental_8point: {} points",
            x1.len()
        )));
    }
    let degenerate = || CoreError::Degenerate("fundamental_8point: degenerate points".into());
    let t1 = hartley(x1.iter()).ok_or_else(degenerate)?;
    let t2 = hartley(x2.iter()).ok_or_else(degenerate)?;
    let x1n: Vec<_> = x1.iter().map(|p| apply(&t1, p)).collect();
    let x2n: Vec<_> = x2.iter().map(|p| apply(&t2, p)).collect();
    let fnorm = solve_normalized(&x1n, &x2n, 0..x1.len()).ok_or_else(degenerate)?;
    denormalize(&fnorm, &t1, &t2).ok_or_else(degenerate)
}

/// Squared distance of `p` to the line `l = (a, b, c)` (`a x + b y + c = 0`).
#[inline]
fn line_dist2(l: &Vector3<f64>, p: &Vector2<f64>) -> f64 {
    let num = l.x * p.x + l.y * p.y + l.z;
    let den = l.x * l.x + l.y * l.y;
    if den > 0.0 {
        num * num / den
    } else {
        f64::INFINITY
    }
}

/// ORB-SLAM's epipolar score (Mur-Artal et al. 2015, eq. 2 with `M = F`): for every
/// correspondence the squared distances of each point to the epipolar line of the other, in
/// units of the pixel variance (`d² = scale² dist² · inv_sigma2`). A correspondence is an
/// inlier when both are below `chi2_inlier` (`T_F` = 3.84, one degree of freedom); each such
/// term adds `chi2_score - d²` (`Γ = T_H` = 5.99, so F and H scores are comparable).
/// `scale` converts normalised coordinates to pixels. Writes `inliers`, returns the score.
#[allow(clippy::too_many_arguments)]
pub fn score_fundamental(
    f: &Matrix3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    scale: f64,
    inv_sigma2: f64,
    chi2_inlier: f64,
    chi2_score: f64,
    inliers: &mut [bool],
) -> f64 {
    let k = scale * scale * inv_sigma2;
    let ft = f.transpose();
    let mut score = 0.0;
    for ((a, b), inl) in x1.iter().zip(x2).zip(inliers.iter_mut()) {
        let l2 = f * Vector3::new(a.x, a.y, 1.0);
        let l1 = ft * Vector3::new(b.x, b.y, 1.0);
        let mut ok = true;
        for d2 in [line_dist2(&l2, b) * k, line_dist2(&l1, a) * k] {
            if d2 < chi2_inlier {
                score += chi2_score - d2;
            } else {
                ok = false;
            }
        }
        *inl = ok;
    }
    score
}

/// A relative motion `(R, t)`: `X2 = R X1 + t`.
pub type Motion = (Rotation3<f64>, Vector3<f64>);

/// Projects a matrix of normalised coordinates onto the essential manifold: singular values
/// `(1, 1, 0)`. `None` when the SVD fails.
pub fn essential_from_fundamental(f: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    let svd = SVD::new(*f, true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let mut s = svd.singular_values;
    let imin = s.imin();
    for (i, v) in s.iter_mut().enumerate() {
        *v = if i == imin { 0.0 } else { 1.0 };
    }
    Some(u * Matrix3::from_diagonal(&s) * v_t)
}

/// The four motions `(R, t)` (`X2 = R X1 + t`, `|t| = 1`) compatible with an essential matrix
/// `E = [t]x R` (Hartley & Zisserman, result 9.19): `(R1, t), (R1, -t), (R2, t), (R2, -t)`.
/// Pick one by cheirality.
///
/// Errors: non-finite input or a failed SVD.
pub fn decompose_essential(e: &Matrix3<f64>) -> Result<[Motion; 4], CoreError> {
    if !e.iter().all(|v| v.is_finite()) {
        return Err(CoreError::InvalidArgument(
            "decompose_essential: non-finite E".into(),
        ));
    }
    let svd = SVD::new(*e, true, true);
    let (Some(mut u), Some(mut v_t)) = (svd.u, svd.v_t) else {
        return Err(CoreError::Degenerate(
            "decompose_essential: SVD failed".into(),
        ));
    };
    // Order so that the null direction is the third column; E's sign is irrelevant, so
    // flip U / V to proper rotations.
    let imin = svd.singular_values.imin();
    if imin != 2 {
        u.swap_columns(imin, 2);
        v_t.swap_rows(imin, 2);
    }
    if u.determinant() < 0.0 {
        u.column_mut(2).neg_mut();
    }
    if v_t.determinant() < 0.0 {
        v_t.row_mut(2).neg_mut();
    }
    let w = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
    let r1 = Rotation3::from_matrix_unchecked(u * w * v_t);
    let r2 = Rotation3::from_matrix_unchecked(u * w.transpose() * v_t);
    let t = u.column(2).normalize();
    Ok([(r1, t), (r1, -t), (r2, t), (r2, -t)])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lie::skew;

    #[test]
    fn eight_point_and_decomposition_recover_the_motion() {
        let r = Rotation3::from_euler_angles(0.1, -0.15, 0.05);
        let t = Vector3::new(0.5, 0.1, -0.2).normalize();
        let mut x1 = Vec::new();
        let mut x2 = Vec::new();
        for i in 0..40 {
            let f = i as f64;
            let x = Vector3::new(
                (f * 0.7).sin(),
                (f * 1.3).cos() * 0.8,
                3.0 + (f * 0.37).sin() * 1.5,
            );
            let y = r * x + t;
            x1.push(Vector2::new(x.x / x.z, x.y / x.z));
            x2.push(Vector2::new(y.x / y.z, y.y / y.z));
        }
        let f = fundamental_8point(&x1, &x2).expect("8pt");
        let e_true = skew(&t) * r.matrix();
        let es = e_true / e_true.norm();
        assert!((f - es).norm().min((f + es).norm()) < 1e-8);
        let mut inl = vec![false; x1.len()];
        score_fundamental(&f, &x1, &x2, 500.0, 1.0, 3.841, 5.991, &mut inl);
        assert!(inl.iter().all(|&b| b));
        let e = essential_from_fundamental(&f).expect("svd");
        let sols = decompose_essential(&e).expect("decompose");
        let best = sols
            .iter()
            .map(|(rr, tt)| (rr.inverse() * r).angle() + (tt - t).norm())
            .fold(f64::INFINITY, f64::min);
        assert!(best < 1e-8, "{best}");
        for (rr, _) in &sols {
            assert!((rr.matrix().determinant() - 1.0).abs() < 1e-9);
        }
        assert!(fundamental_8point(&x1[..7], &x2[..7]).is_err());
        assert!(decompose_essential(&Matrix3::from_element(f64::NAN)).is_err());
    }
}
