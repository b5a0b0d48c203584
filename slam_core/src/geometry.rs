//! Small geometry helpers on `nalgebra` f64 types: quaternion conversions, pose interpolation
//! (lerp + slerp) and Umeyama similarity alignment. The Lie-group math (SO(3)/SE(3)/Sim(3)
//! exp, log, Jacobians, skew matrices) is in [`crate::lie`].
//!
//! Conventions: a pose `T_AB` maps points of frame B into frame A (`x_A = T_AB x_B`);
//! quaternions are Hamilton, stored `(w, x, y, z)` where an array is used.

use nalgebra::{Isometry3, Matrix3, Quaternion, Rotation3, Translation3, UnitQuaternion, Vector3};

use crate::lie::{quat_exp, quat_log};
use crate::CoreError;

/// A unit quaternion from `(w, x, y, z)`, normalised. `None` when the input is not finite or
/// its norm is (nearly) zero, so bad input from a file cannot produce NaN poses.
pub fn quat_from_wxyz(wxyz: [f64; 4]) -> Option<UnitQuaternion<f64>> {
    let q = Quaternion::new(wxyz[0], wxyz[1], wxyz[2], wxyz[3]);
    let n = q.norm();
    if !n.is_finite() || n < 1e-12 {
        return None;
    }
    Some(UnitQuaternion::from_quaternion(q))
}

/// The `(w, x, y, z)` components of a unit quaternion.
pub fn quat_to_wxyz(q: &UnitQuaternion<f64>) -> [f64; 4] {
    [q.w, q.i, q.j, q.k]
}

/// A pose from a position and a `(w, x, y, z)` quaternion (`None` on a degenerate quaternion
/// or a non-finite position).
pub fn pose_from_pq(p: [f64; 3], q_wxyz: [f64; 4]) -> Option<Isometry3<f64>> {
    if !p.iter().all(|v| v.is_finite()) {
        return None;
    }
    let q = quat_from_wxyz(q_wxyz)?;
    Some(Isometry3::from_parts(
        Translation3::new(p[0], p[1], p[2]),
        q,
    ))
}

/// Slerp between two rotations along the shortest path: `alpha = 0` gives `a`, `1` gives `b`.
/// Never panics (also for rotations 180° apart).
pub fn slerp(a: &UnitQuaternion<f64>, b: &UnitQuaternion<f64>, alpha: f64) -> UnitQuaternion<f64> {
    let rel = a.inverse() * b;
    a * quat_exp(&(quat_log(&rel) * alpha))
}

/// Pose interpolation: linear in the translation, slerp in the rotation.
/// `alpha = 0` gives `a`, `1` gives `b`; values outside `[0, 1]` extrapolate.
pub fn interpolate_pose(a: &Isometry3<f64>, b: &Isometry3<f64>, alpha: f64) -> Isometry3<f64> {
    let t = a.translation.vector + (b.translation.vector - a.translation.vector) * alpha;
    Isometry3::from_parts(
        Translation3::from(t),
        slerp(&a.rotation, &b.rotation, alpha),
    )
}

/// The pose at time `t` interpolated between `(t0, a)` and `(t1, b)` (integer ns stamps).
/// When `t0 == t1` returns `a`.
pub fn interpolate_pose_at(
    t0: i64,
    a: &Isometry3<f64>,
    t1: i64,
    b: &Isometry3<f64>,
    t: i64,
) -> Isometry3<f64> {
    if t1 == t0 {
        return *a;
    }
    // i128 differences avoid overflow for any pair of i64 stamps.
    let alpha = (i128::from(t) - i128::from(t0)) as f64 / (i128::from(t1) - i128::from(t0)) as f64;
    interpolate_pose(a, b, alpha)
}

/// A similarity `x ↦ s R x + t` estimated by [`umeyama`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Similarity {
    /// Rotation R.
    pub rotation: Rotation3<f64>,
    /// Translation t.
    pub translation: Vector3<f64>,
    /// Scale s (1 when scale was not estimated).
    pub scale: f64,
}

impl Similarity {
    /// The identity transform.
    pub fn identity() -> Self {
        Self {
            rotation: Rotation3::identity(),
            translation: Vector3::zeros(),
            scale: 1.0,
        }
    }

    /// The inverse similarity: `x ↦ s⁻¹ Rᵀ (x - t)`.
    pub fn inverse(&self) -> Self {
        let r_inv = self.rotation.inverse();
        let s_inv = 1.0 / self.scale;
        Self {
            rotation: r_inv,
            translation: -(r_inv * self.translation) * s_inv,
            scale: s_inv,
        }
    }

    /// `self ∘ other`: `other` first, then `self`.
    pub fn compose(&self, other: &Self) -> Self {
        Self {
            rotation: self.rotation * other.rotation,
            translation: self.transform_point(&other.translation),
            scale: self.scale * other.scale,
        }
    }

    /// Applies the similarity to a point: `s R x + t`.
    pub fn transform_point(&self, x: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * x * self.scale + self.translation
    }

    /// Applies the similarity to a pose `T_WX` (as evo does when aligning a trajectory):
    /// rotation `R R_x`, position `s R p_x + t`.
    pub fn transform_pose(&self, pose: &Isometry3<f64>) -> Isometry3<f64> {
        let p = self.transform_point(&pose.translation.vector);
        let r = UnitQuaternion::from_rotation_matrix(&self.rotation) * pose.rotation;
        Isometry3::from_parts(Translation3::from(p), r)
    }
}

/// Umeyama's least-squares similarity (Umeyama 1991, "Least-squares estimation of
/// transformation parameters between two point patterns"): finds `R, t, s` minimising
/// `Σ |dst_i - (s R src_i + t)|²`. With `with_scale == false`, `s = 1` (rigid alignment).
///
/// With `Σ_xy = 1/n Σ (dst_i - μ_dst)(src_i - μ_src)ᵀ = U D Vᵀ`, `S = diag(1, 1, ±1)` (the
/// reflection fix: -1 when `det U det V < 0`), `R = U S Vᵀ`, `s = tr(D S) / σ²_src`,
/// `t = μ_dst - s R μ_src`.
///
/// Errors: different lengths, fewer than 2 pairs, non-finite input, or a degenerate
/// configuration (covariance rank < 2: all points identical or otherwise collapsed).
pub fn umeyama(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
    with_scale: bool,
) -> Result<Similarity, CoreError> {
    if src.len() != dst.len() {
        return Err(CoreError::InvalidArgument(format!(
            "umeyama: {} source points but {} destination points",
            src.len(),
            dst.len()
        )));
    }
    if src.len() < 2 {
        return Err(CoreError::NotEnoughData(format!(
            "umeyama: {} point pairs",
            src.len()
        )));
    }
    let n = src.len() as f64;
    let mean_src = src.iter().fold(Vector3::zeros(), |a, x| a + x) / n;
    let mean_dst = dst.iter().fold(Vector3::zeros(), |a, y| a + y) / n;
    let mut sigma2_src = 0.0;
    let mut cov = Matrix3::<f64>::zeros();
    for (x, y) in src.iter().zip(dst) {
        let dx = x - mean_src;
        sigma2_src += dx.norm_squared();
        cov += (y - mean_dst) * dx.transpose();
    }
    sigma2_src /= n;
    cov /= n;
    if !cov.iter().all(|v| v.is_finite()) || !sigma2_src.is_finite() {
        return Err(CoreError::InvalidArgument(
            "umeyama: non-finite points".into(),
        ));
    }
    let svd = nalgebra::SVD::new(cov, true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(CoreError::Degenerate(
            "umeyama: SVD did not converge".into(),
        ));
    };
    let d = svd.singular_values; // sorted in descending order
    let rank = d.iter().filter(|&&x| x > f64::EPSILON).count();
    if rank < 2 {
        return Err(CoreError::Degenerate(format!(
            "umeyama: degenerate point configuration (covariance rank {rank} < 2)"
        )));
    }
    let mut s_diag = Vector3::new(1.0, 1.0, 1.0);
    if u.determinant() * v_t.determinant() < 0.0 {
        s_diag[2] = -1.0;
    }
    let r = u * Matrix3::from_diagonal(&s_diag) * v_t;
    let scale = if with_scale {
        if sigma2_src <= 0.0 {
            return Err(CoreError::Degenerate("umeyama: zero source spread".into()));
        }
        d.dot(&s_diag) / sigma2_src
    } else {
        1.0
    };
    let t = mean_dst - r * mean_src * scale;
    Ok(Similarity {
        rotation: Rotation3::from_matrix_unchecked(r),
        translation: t,
        scale,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn approx(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
    }

    #[test]
    fn quaternion_helpers() {
        assert!(quat_from_wxyz([0.0; 4]).is_none());
        assert!(quat_from_wxyz([f64::NAN, 0.0, 0.0, 1.0]).is_none());
        let q = quat_from_wxyz([2.0, 0.0, 0.0, 0.0]).expect("valid");
        assert_eq!(quat_to_wxyz(&q), [1.0, 0.0, 0.0, 0.0]);
        assert!(pose_from_pq([f64::INFINITY, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]).is_none());
    }

    #[test]
    fn interpolation_midpoint() {
        let a = Isometry3::new(Vector3::new(0.0, 0.0, 0.0), Vector3::zeros());
        let b = Isometry3::new(Vector3::new(2.0, 4.0, 0.0), Vector3::new(0.0, 0.0, 1.0));
        let m = interpolate_pose_at(100, &a, 300, &b, 200);
        assert!((m.translation.vector - Vector3::new(1.0, 2.0, 0.0)).norm() < 1e-12);
        assert!(approx(m.rotation.angle(), 0.5, 1e-12));
        // 180° apart must not panic.
        let c = Isometry3::new(
            Vector3::zeros(),
            Vector3::new(std::f64::consts::PI, 0.0, 0.0),
        );
        let h = interpolate_pose(&a, &c, 0.5);
        assert!(approx(
            h.rotation.angle(),
            std::f64::consts::FRAC_PI_2,
            1e-9
        ));
        assert_eq!(interpolate_pose_at(5, &a, 5, &b, 5), a);
    }

    #[test]
    fn umeyama_recovers_similarity() {
        let truth = Similarity {
            rotation: Rotation3::from_scaled_axis(Vector3::new(0.3, -0.2, 1.1)),
            translation: Vector3::new(1.0, -2.0, 0.5),
            scale: 2.5,
        };
        let src: Vec<_> = (0..20)
            .map(|i| {
                let f = i as f64;
                Vector3::new(f.sin() * 3.0, (0.7 * f).cos(), 0.1 * f * f)
            })
            .collect();
        let dst: Vec<_> = src.iter().map(|x| truth.transform_point(x)).collect();
        let est = umeyama(&src, &dst, true).expect("umeyama");
        assert!(approx(est.scale, 2.5, 1e-10));
        assert!((est.rotation.matrix() - truth.rotation.matrix()).norm() < 1e-10);
        assert!((est.translation - truth.translation).norm() < 1e-9);
        let rigid = umeyama(&src, &dst, false).expect("umeyama");
        assert_eq!(rigid.scale, 1.0);
        assert!(rigid.rotation.matrix().determinant() > 0.0);
    }

    #[test]
    fn umeyama_reflection_fix_and_degenerate() {
        // Mirrored planar points: the best proper rotation must be returned, never a reflection.
        let src = vec![
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(1.0, 0.0, 0.0),
            Vector3::new(0.0, 2.0, 0.0),
            Vector3::new(1.0, 1.0, 0.5),
        ];
        let dst: Vec<_> = src.iter().map(|p| Vector3::new(-p.x, p.y, p.z)).collect();
        let est = umeyama(&src, &dst, false).expect("umeyama");
        assert!(approx(est.rotation.matrix().determinant(), 1.0, 1e-12));
        let same = vec![Vector3::new(1.0, 1.0, 1.0); 5];
        assert!(matches!(
            umeyama(&same, &same, true),
            Err(CoreError::Degenerate(_))
        ));
        assert!(umeyama(&src, &dst[..2], true).is_err());
        assert!(umeyama(&src[..1], &dst[..1], true).is_err());
    }
}
