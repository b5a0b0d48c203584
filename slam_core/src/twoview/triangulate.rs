//! Linear (DLT) triangulation from two or more views, and the acceptance checks ORB-SLAM
//! applies to a new map point (Mur-Artal et al. 2015, sections IV and VI-B): positive depth
//! in every view, reprojection error below a chi-square bound scaled by the keypoint's
//! variance, and enough parallax.
//!
//! Poses are world-to-camera, `T_cw` (`x_c = T_cw x_w`, see [`crate::geometry`]); a view's
//! projection matrix is `P = [R_cw | t_cw]`. Observations are bearings in the camera frame:
//! unit vectors or undistorted normalised coordinates `(x/z, y/z, 1)` — any positive
//! multiple works.

use nalgebra::{Isometry3, Matrix3x4, Matrix4, RowVector4, SymmetricEigen, Vector2, Vector3};

use crate::camera::PinholeRadtan;

/// The 3x4 projection matrix `[R | t]` of a world-to-camera pose `T_cw` (normalised camera:
/// no intrinsics).
pub fn projection_matrix(t_cw: &Isometry3<f64>) -> Matrix3x4<f64> {
    let r = t_cw.rotation.to_rotation_matrix();
    let t = t_cw.translation.vector;
    let m = r.matrix();
    Matrix3x4::new(
        m[(0, 0)],
        m[(0, 1)],
        m[(0, 2)],
        t.x,
        m[(1, 0)],
        m[(1, 1)],
        m[(1, 2)],
        t.y,
        m[(2, 0)],
        m[(2, 1)],
        m[(2, 2)],
        t.z,
    )
}

/// Adds the rows of `[b]x P` (the cross product of the bearing with the projected point, two
/// of them independent) to the normal matrix `ata`, each row scaled to unit norm so that
/// views and coordinates of different magnitude weigh alike.
fn accumulate_view(ata: &mut Matrix4<f64>, p: &Matrix3x4<f64>, b: &Vector3<f64>) {
    let (r0, r1, r2) = (p.row(0), p.row(1), p.row(2));
    let rows: [RowVector4<f64>; 3] = [
        r2 * b.y - r1 * b.z,
        r0 * b.z - r2 * b.x,
        r1 * b.x - r0 * b.y,
    ];
    for row in rows {
        let n2 = row.norm_squared();
        if n2 > 1e-300 {
            *ata += row.transpose() * row / n2;
        }
    }
}

/// The homogeneous null vector of a 4x4 normal matrix, dehomogenised. `None` for a point at
/// infinity or non-finite data.
fn solve_normal(ata: Matrix4<f64>) -> Option<Vector3<f64>> {
    if !ata.iter().all(|v| v.is_finite()) {
        return None;
    }
    let eig = SymmetricEigen::new(ata);
    let (imin, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    let x = eig.eigenvectors.column(imin);
    if x[3].abs() < 1e-12 * x.norm() {
        return None;
    }
    let p = Vector3::new(x[0] / x[3], x[1] / x[3], x[2] / x[3]);
    p.iter().all(|v| v.is_finite()).then_some(p)
}

/// Linear (DLT) triangulation of one point seen in two views with projection matrices
/// `p1`, `p2` (see [`projection_matrix`]) along bearings `b1`, `b2` (camera frames).
///
/// Minimises the algebraic error of `b × (P X) = 0` (Hartley & Zisserman, section 12.2).
/// Returns the world point, or `None` when the rays are (nearly) parallel so the point is
/// at infinity, or on non-finite input. No depth or error check: see [`check_point`].
pub fn triangulate_dlt(
    p1: &Matrix3x4<f64>,
    b1: &Vector3<f64>,
    p2: &Matrix3x4<f64>,
    b2: &Vector3<f64>,
) -> Option<Vector3<f64>> {
    let mut ata = Matrix4::zeros();
    accumulate_view(&mut ata, p1, b1);
    accumulate_view(&mut ata, p2, b2);
    solve_normal(ata)
}

/// Linear (DLT) triangulation from any number of views: `views` yields
/// `(projection matrix, bearing)` pairs. `None` with fewer than two views, for a point at
/// infinity or on non-finite input.
pub fn triangulate_multiview<'a, I>(views: I) -> Option<Vector3<f64>>
where
    I: IntoIterator<Item = (&'a Matrix3x4<f64>, &'a Vector3<f64>)>,
{
    let mut ata = Matrix4::zeros();
    let mut n = 0usize;
    for (p, b) in views {
        accumulate_view(&mut ata, p, b);
        n += 1;
    }
    if n < 2 {
        return None;
    }
    solve_normal(ata)
}

/// Thresholds of [`check_point`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TriangulationCheck {
    /// Largest accepted squared reprojection error in units of the observation's variance
    /// (`|r|² / σ² ≤ chi2`); 5.991 is the 95% quantile of chi-square with 2 degrees of
    /// freedom (ORB-SLAM's monocular bound).
    pub chi2: f64,
    /// Largest accepted cosine of the parallax angle between the rays from the camera
    /// centres to the point; 0.99998 ≈ 0.36°.
    pub max_parallax_cos: f64,
}

impl Default for TriangulationCheck {
    fn default() -> Self {
        Self {
            chi2: 5.991,
            max_parallax_cos: 0.99998,
        }
    }
}

/// One observation used by [`check_point`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CheckView {
    /// World-to-camera pose of the view.
    pub t_cw: Isometry3<f64>,
    /// Observed (distorted) pixel.
    pub pixel: Vector2<f64>,
    /// Information of the observation, `1 / σ²` with σ in pixels (ORB-SLAM:
    /// σ = scale_factor^octave, [`crate::features::PyramidScale::inv_sigma2`]).
    pub inv_sigma2: f64,
}

/// Why [`check_point`] refused a point.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TriangulationReject {
    /// Non-finite coordinates.
    NotFinite,
    /// Zero or negative depth in view `.0`.
    Behind(usize),
    /// Reprojection error above the bound in view `.0`.
    Reprojection(usize),
    /// The rays are too close to parallel for a reliable depth.
    LowParallax,
}

/// Checks a triangulated world point against its observations, in this order: finite
/// coordinates, positive depth in every view, reprojection error (pixels, through `camera`
/// with its distortion) `≤ chi2 / inv_sigma2` in every view, and largest parallax among the
/// pairs of views with cosine `≤ max_parallax_cos`.
///
/// Returns the cosine of the largest parallax angle on success.
pub fn check_point(
    point_w: &Vector3<f64>,
    views: &[CheckView],
    camera: &PinholeRadtan,
    params: &TriangulationCheck,
) -> Result<f64, TriangulationReject> {
    if !point_w.iter().all(|v| v.is_finite()) {
        return Err(TriangulationReject::NotFinite);
    }
    for (i, v) in views.iter().enumerate() {
        let p_c = v.t_cw * nalgebra::Point3::from(*point_w);
        if p_c.z <= 0.0 {
            return Err(TriangulationReject::Behind(i));
        }
        let Some(uv) = camera.project(&p_c.coords) else {
            return Err(TriangulationReject::Behind(i));
        };
        if (uv - v.pixel).norm_squared() * v.inv_sigma2 > params.chi2 {
            return Err(TriangulationReject::Reprojection(i));
        }
    }
    let cos = min_parallax_cos(point_w, views.iter().map(|v| &v.t_cw));
    if cos > params.max_parallax_cos {
        return Err(TriangulationReject::LowParallax);
    }
    Ok(cos)
}

/// The cosine of the largest angle, seen from `point_w`, between two of the camera centres
/// of `poses` (1 with fewer than two poses).
pub fn min_parallax_cos<'a, I>(point_w: &Vector3<f64>, poses: I) -> f64
where
    I: IntoIterator<Item = &'a Isometry3<f64>>,
{
    // Rays from the camera centres; small fixed buffer, larger sets fall back to a pass
    // over the first 16 views (plenty for map points).
    let mut rays = [Vector3::zeros(); 16];
    let mut n = 0;
    for pose in poses.into_iter().take(16) {
        let centre = pose.inverse_transform_vector(&-pose.translation.vector);
        let ray = point_w - centre;
        let norm = ray.norm();
        rays[n] = if norm > 0.0 { ray / norm } else { ray };
        n += 1;
    }
    let mut best = 1.0f64;
    for i in 0..n {
        for j in i + 1..n {
            best = best.min(rays[i].dot(&rays[j]));
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, Translation3, UnitQuaternion};

    fn pose(rx: f64, ry: f64, rz: f64, t: [f64; 3]) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(t[0], t[1], t[2]),
            UnitQuaternion::from_euler_angles(rx, ry, rz),
        )
    }

    #[test]
    fn two_and_multi_view_are_exact_without_noise() {
        let poses = [
            pose(0.0, 0.0, 0.0, [0.0, 0.0, 0.0]),
            pose(0.02, -0.1, 0.01, [-0.5, 0.05, 0.1]),
            pose(-0.03, 0.12, 0.0, [0.6, -0.1, 0.0]),
        ];
        let x = Vector3::new(0.3, -0.4, 4.0);
        let ps: Vec<_> = poses.iter().map(projection_matrix).collect();
        let bs: Vec<_> = poses
            .iter()
            .map(|p| (p * Point3::from(x)).coords.normalize())
            .collect();
        let y = triangulate_dlt(&ps[0], &bs[0], &ps[1], &bs[1]).expect("finite");
        assert!((y - x).norm() < 1e-9);
        let z = triangulate_multiview(ps.iter().zip(&bs)).expect("finite");
        assert!((z - x).norm() < 1e-9);
        assert!(triangulate_multiview(ps.iter().zip(&bs).take(1)).is_none());
        // Parallel rays (same centre): point at infinity or unconstrained, never NaN.
        let r = triangulate_dlt(&ps[0], &bs[0], &ps[0], &bs[0]);
        assert!(r.is_none_or(|p| p.iter().all(|v| v.is_finite())));
    }

    #[test]
    fn noisy_triangulation_error_is_small_and_checks_work() {
        let cam = PinholeRadtan::euroc_cam0();
        let poses = [
            pose(0.0, 0.0, 0.0, [0.0, 0.0, 0.0]),
            pose(0.0, 0.05, 0.0, [-0.4, 0.0, 0.0]),
        ];
        let mut worst: f64 = 0.0;
        for k in 0..50 {
            let f = k as f64;
            let x = Vector3::new(
                (f * 0.37).sin(),
                (f * 0.71).cos() * 0.6,
                3.0 + (f * 0.13).sin(),
            );
            let mut views = [CheckView {
                t_cw: poses[0],
                pixel: Vector2::zeros(),
                inv_sigma2: 1.0,
            }; 2];
            let mut bs = [Vector3::zeros(); 2];
            for (i, p) in poses.iter().enumerate() {
                let uv = cam.project(&(p * Point3::from(x)).coords).expect("front");
                // +-0.5 px deterministic noise
                let uv = uv + Vector2::new(0.5 * (f * 1.3 + i as f64).sin(), 0.5 * (f * 2.1).cos());
                bs[i] = cam.unproject(&uv);
                views[i] = CheckView {
                    t_cw: *p,
                    pixel: uv,
                    inv_sigma2: 1.0,
                };
            }
            let y = triangulate_dlt(
                &projection_matrix(&poses[0]),
                &bs[0],
                &projection_matrix(&poses[1]),
                &bs[1],
            )
            .expect("finite");
            worst = worst.max((y - x).norm() / x.z);
            let chk = TriangulationCheck::default();
            assert!(check_point(&y, &views, &cam, &chk).is_ok());
            // A point behind the cameras, and a far-off point, are refused.
            assert_eq!(
                check_point(&(-y), &views, &cam, &chk),
                Err(TriangulationReject::Behind(0))
            );
            assert!(matches!(
                check_point(&(y + Vector3::new(0.2, 0.0, 0.0)), &views, &cam, &chk),
                Err(TriangulationReject::Reprojection(_))
            ));
        }
        // 0.5 px noise, 0.4 m baseline, ~3 m depth: relative depth error ~1%.
        assert!(worst < 0.03, "worst relative error {worst}");
        // Same centres: low parallax.
        let far = Vector3::new(0.0, 0.0, 1e6);
        let views = [
            CheckView {
                t_cw: poses[0],
                pixel: cam.project(&far).expect("front"),
                inv_sigma2: 1.0,
            },
            CheckView {
                t_cw: poses[0],
                pixel: cam.project(&far).expect("front"),
                inv_sigma2: 1.0,
            },
        ];
        assert_eq!(
            check_point(&far, &views, &cam, &TriangulationCheck::default()),
            Err(TriangulationReject::LowParallax)
        );
    }
}
