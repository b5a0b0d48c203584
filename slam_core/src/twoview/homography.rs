//! Homography `x2 ~ H x1` between two views of a plane: normalised DLT, the symmetric
//! transfer score of Mur-Artal et al. 2015 (section IV-2), and the analytical decomposition
//! into motion and plane (Ma, Soatto, Košecká & Sastry, "An Invitation to 3-D Vision",
//! 2004, section 5.3.3), an equivalent of the Faugeras & Lustman (1988) decomposition that
//! ORB-SLAM uses.
//!
//! Points are undistorted normalised image coordinates `(x/z, y/z)`.

use nalgebra::{Matrix3, Rotation3, SymmetricEigen, Vector2, Vector3};

use super::normalize::{apply, hartley, null_matrix, Normal9, Row9};
use crate::lie::skew;
use crate::CoreError;

/// Adds the two DLT rows of `x2 ~ H x1` for one correspondence to the normal matrix.
#[inline]
fn add_rows(ata: &mut Normal9, a: &Vector2<f64>, b: &Vector2<f64>) {
    let (x, y, u, v) = (a.x, a.y, b.x, b.y);
    let r1 = Row9::from([0.0, 0.0, 0.0, -x, -y, -1.0, v * x, v * y, v]);
    let r2 = Row9::from([x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y, -u]);
    ata.ger(1.0, &r1, &r1, 1.0);
    ata.ger(1.0, &r2, &r2, 1.0);
}

/// DLT on already normalised points `x1n[i] -> x2n[i]` for `i` in `indices`. The result maps
/// normalised points; `None` on a degenerate set.
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
        add_rows(&mut ata, &x1n[i], &x2n[i]);
    }
    null_matrix(&ata)
}

/// Normalised DLT homography (Hartley & Zisserman, algorithm 4.2) from all correspondences,
/// `x2 ~ H x1`, scaled to `|H|_F = 1`.
///
/// Errors: different lengths, fewer than 4 points, or a degenerate configuration.
pub fn homography_dlt(x1: &[Vector2<f64>], x2: &[Vector2<f64>]) -> Result<Matrix3<f64>, CoreError> {
    if x1.len() != x2.len() {
        return Err(CoreError::InvalidArgument(
            "homography_dlt: length mismatch".into(),
        ));
    }
    if x1.len() < 4 {
        return Err(CoreError::NotEnoughData(format!(
            "homography_dlt: {} points",
            x1.len()
        )));
    }
    let degenerate = || CoreError::Degenerate("homography_dlt: degenerate points".into());
    let t1 = hartley(x1.iter()).ok_or_else(degenerate)?;
    let t2 = hartley(x2.iter()).ok_or_else(degenerate)?;
    let x1n: Vec<_> = x1.iter().map(|p| apply(&t1, p)).collect();
    let x2n: Vec<_> = x2.iter().map(|p| apply(&t2, p)).collect();
    let hn = solve_normalized(&x1n, &x2n, 0..x1.len()).ok_or_else(degenerate)?;
    denormalize(&hn, &t1, &t2).ok_or_else(degenerate)
}

/// `H = T2⁻¹ Hn T1`, scaled to unit Frobenius norm.
pub(crate) fn denormalize(
    hn: &Matrix3<f64>,
    t1: &Matrix3<f64>,
    t2: &Matrix3<f64>,
) -> Option<Matrix3<f64>> {
    let h = t2.try_inverse()? * hn * t1;
    let n = h.norm();
    (n.is_finite() && n > 0.0).then(|| h / n)
}

/// Transfers `p` through `h` (`None` when it maps to infinity).
#[inline]
fn transfer(h: &Matrix3<f64>, p: &Vector2<f64>) -> Option<Vector2<f64>> {
    let w = h[(2, 0)] * p.x + h[(2, 1)] * p.y + h[(2, 2)];
    if w.abs() < 1e-12 {
        return None;
    }
    Some(Vector2::new(
        (h[(0, 0)] * p.x + h[(0, 1)] * p.y + h[(0, 2)]) / w,
        (h[(1, 0)] * p.x + h[(1, 1)] * p.y + h[(1, 2)]) / w,
    ))
}

/// ORB-SLAM's homography score (Mur-Artal et al. 2015, eq. 2 with `M = H`): for every
/// correspondence the squared transfer errors in both images, in units of the pixel
/// variance (`d² = scale² |x - x̂|² · inv_sigma2`), each adds `chi2 - d²` to the score when
/// `d² < chi2`; a correspondence is an inlier when both are below. `scale` converts
/// normalised coordinates to pixels (the focal length). Writes `inliers` (same length as the
/// points) and returns the score.
pub fn score_homography(
    h: &Matrix3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    scale: f64,
    inv_sigma2: f64,
    chi2: f64,
    inliers: &mut [bool],
) -> f64 {
    let Some(h_inv) = h.try_inverse() else {
        inliers.iter_mut().for_each(|b| *b = false);
        return 0.0;
    };
    let k = scale * scale * inv_sigma2;
    let mut score = 0.0;
    for ((a, b), inl) in x1.iter().zip(x2).zip(inliers.iter_mut()) {
        let mut ok = true;
        for (src, dst, m) in [(a, b, h), (b, a, &h_inv)] {
            match transfer(m, src) {
                Some(p) => {
                    let d2 = (p - dst).norm_squared() * k;
                    if d2 < chi2 {
                        score += chi2 - d2;
                    } else {
                        ok = false;
                    }
                }
                None => ok = false,
            }
        }
        *inl = ok;
    }
    score
}

/// One motion hypothesis of a homography: `X2 = R X1 + t` with the plane `nᵀ X1 = d`; the
/// decomposition fixes `d = 1`, so `t` is `t_true / d`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HomographyMotion {
    /// Rotation from view 1 to view 2.
    pub rotation: Rotation3<f64>,
    /// Translation `t / d`.
    pub translation: Vector3<f64>,
    /// Unit plane normal in view 1.
    pub normal: Vector3<f64>,
}

/// Decomposes a homography `H ∝ R + t nᵀ / d` of normalised coordinates into its four
/// motion hypotheses (two physically distinct solutions and their mirror images with
/// `-n, -t`; Ma et al. 2004, section 5.3.3). Pick one by cheirality.
///
/// `h` must have the sign for which `x2ᵀ H x1 > 0` on correspondences (positive depths);
/// [`super::select`] fixes it by a vote before calling.
///
/// Errors: non-finite input, or a homography of (nearly) a pure rotation, whose translation
/// and plane are not determined.
pub fn decompose_homography(h: &Matrix3<f64>) -> Result<[HomographyMotion; 4], CoreError> {
    if !h.iter().all(|v| v.is_finite()) {
        return Err(CoreError::InvalidArgument(
            "decompose_homography: non-finite H".into(),
        ));
    }
    let eig = SymmetricEigen::new(h.transpose() * h);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let l2 = eig.eigenvalues[order[1]];
    if l2.is_nan() || l2 <= 1e-300 {
        return Err(CoreError::Degenerate(
            "decompose_homography: singular H".into(),
        ));
    }
    // Normalise so that the middle singular value is 1.
    let hl = h / l2.sqrt();
    let s1 = (eig.eigenvalues[order[0]] / l2).max(1.0);
    let s3 = (eig.eigenvalues[order[2]] / l2).clamp(0.0, 1.0);
    if s1 - s3 < 1e-9 {
        return Err(CoreError::Degenerate(
            "decompose_homography: H is a rotation (no translation)".into(),
        ));
    }
    let v1 = eig.eigenvectors.column(order[0]).into_owned();
    let v2 = eig.eigenvectors.column(order[1]).into_owned();
    let v3 = eig.eigenvectors.column(order[2]).into_owned();
    let den = (s1 - s3).sqrt();
    let a = (1.0 - s3).sqrt();
    let b = (s1 - 1.0).sqrt();
    let u1 = (v1 * a + v3 * b) / den;
    let u2 = (v1 * a - v3 * b) / den;
    let hv2 = hl * v2;
    let solve = |u: Vector3<f64>| -> HomographyMotion {
        let uu = Matrix3::from_columns(&[v2, u, v2.cross(&u)]);
        let hu = hl * u;
        let ww = Matrix3::from_columns(&[hv2, hu, hv2.cross(&hu)]);
        let r = ww * uu.transpose();
        let n = skew(&v2) * u;
        let t = (hl - r) * n;
        HomographyMotion {
            rotation: Rotation3::from_matrix(&r),
            translation: t,
            normal: n,
        }
    };
    let m1 = solve(u1);
    let m2 = solve(u2);
    let flip = |m: &HomographyMotion| HomographyMotion {
        rotation: m.rotation,
        translation: -m.translation,
        normal: -m.normal,
    };
    Ok([m1, m2, flip(&m1), flip(&m2)])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dlt_and_decomposition_recover_the_motion() {
        let r = Rotation3::from_euler_angles(0.05, -0.2, 0.1);
        let t = Vector3::new(0.3, -0.1, 0.05);
        let n = Vector3::new(0.1, -0.2, 1.0).normalize();
        let d = 3.0;
        let h_true = r.matrix() + t * n.transpose() / d;
        // Points on the plane nᵀX = d.
        let mut x1 = Vec::new();
        let mut x2 = Vec::new();
        for i in 0..30 {
            let f = i as f64;
            let p = Vector3::new((f * 0.7).sin() * 0.5, (f * 1.3).cos() * 0.4, 1.0);
            let lambda = d / n.dot(&p);
            let x = p * lambda;
            let y = r * x + t;
            x1.push(Vector2::new(x.x / x.z, x.y / x.z));
            x2.push(Vector2::new(y.x / y.z, y.y / y.z));
        }
        let h = homography_dlt(&x1, &x2).expect("dlt");
        let hs = h_true / h_true.norm();
        let err = (h - hs).norm().min((h + hs).norm());
        assert!(err < 1e-9, "{err}");
        let mut inl = vec![false; x1.len()];
        let s = score_homography(&h, &x1, &x2, 500.0, 1.0, 5.991, &mut inl);
        assert!(inl.iter().all(|&b| b));
        assert!((s - 2.0 * 5.991 * 30.0).abs() < 1e-3);
        let sols = decompose_homography(&h_true).expect("decompose");
        let best = sols
            .iter()
            .map(|m| {
                (m.rotation.inverse() * r).angle()
                    + (m.translation - t / d).norm()
                    + (m.normal - n).norm()
            })
            .fold(f64::INFINITY, f64::min);
        assert!(best < 1e-9, "{best}");
        assert!(decompose_homography(&Matrix3::identity()).is_err());
        assert!(homography_dlt(&x1[..3], &x2[..3]).is_err());
    }
}
