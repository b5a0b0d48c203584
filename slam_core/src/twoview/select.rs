//! Choosing among the motion hypotheses of a homography or an essential matrix by
//! triangulating the inliers (cheirality), as ORB-SLAM's initialiser does (Mur-Artal et al.
//! 2015, section IV-4): a hypothesis is accepted when it clearly explains more points than
//! any other, nearly all inliers are triangulated, and the parallax is large enough.

use nalgebra::{Isometry3, Matrix3x4, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3};

use super::triangulate::{projection_matrix, triangulate_dlt};
use super::TwoViewParams;
use crate::CoreError;

/// What one hypothesis explains.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Evaluation {
    /// Inliers with positive depth and small reprojection error in both views.
    pub good: usize,
    /// Parallax (degrees) of the `min_triangulated`-th most parallax-rich good point.
    pub parallax_deg: f64,
}

/// Two-view geometry of one hypothesis `X2 = R X1 + t` in normalised coordinates.
struct Views {
    p1: Matrix3x4<f64>,
    p2: Matrix3x4<f64>,
    r: Rotation3<f64>,
    t: Vector3<f64>,
    /// Centre of camera 2 in frame 1.
    c2: Vector3<f64>,
}

impl Views {
    fn new(r: &Rotation3<f64>, t: &Vector3<f64>) -> Self {
        let pose = Isometry3::from_parts(
            Translation3::from(*t),
            UnitQuaternion::from_rotation_matrix(r),
        );
        Self {
            p1: projection_matrix(&Isometry3::identity()),
            p2: projection_matrix(&pose),
            r: *r,
            t: *t,
            c2: -(r.inverse() * t),
        }
    }
}

/// Squared reprojection error of a camera-frame point against a normalised observation,
/// in normalised units; infinite behind the camera.
#[inline]
fn reproj2(p: &Vector3<f64>, x: &Vector2<f64>) -> f64 {
    if p.z <= 0.0 {
        return f64::INFINITY;
    }
    (Vector2::new(p.x / p.z, p.y / p.z) - x).norm_squared()
}

/// Triangulates every inlier under hypothesis `(r, t)` and counts the good ones; fills
/// `points` (frame-1 coordinates) and `triangulated` (good and with enough parallax) when
/// given, and uses `parallax` as scratch for the parallax order statistic.
#[allow(clippy::too_many_arguments)]
pub(crate) fn evaluate(
    r: &Rotation3<f64>,
    t: &Vector3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    inliers: &[bool],
    params: &TwoViewParams,
    mut out: Option<(&mut [Vector3<f64>], &mut [bool])>,
    parallax: &mut Vec<f64>,
) -> Evaluation {
    let v = Views::new(r, t);
    let max_err2 = params.reproj_chi2 * params.sigma_px * params.sigma_px
        / (params.pixel_scale * params.pixel_scale);
    parallax.clear();
    let mut good = 0;
    for i in 0..x1.len() {
        if let Some((pts, tri)) = out.as_mut() {
            pts[i] = Vector3::zeros();
            tri[i] = false;
        }
        if !inliers[i] {
            continue;
        }
        let b1 = Vector3::new(x1[i].x, x1[i].y, 1.0);
        let b2 = Vector3::new(x2[i].x, x2[i].y, 1.0);
        let Some(p) = triangulate_dlt(&v.p1, &b1, &v.p2, &b2) else {
            continue;
        };
        let n1 = p.norm();
        let d2 = p - v.c2;
        let cos = p.dot(&d2) / (n1 * d2.norm());
        if !cos.is_finite() {
            continue;
        }
        let q = v.r * p + v.t;
        // Depth sign is only meaningful with some parallax (ORB-SLAM's rule).
        let enough_parallax = cos < params.max_parallax_cos;
        if enough_parallax && (p.z <= 0.0 || q.z <= 0.0) {
            continue;
        }
        if reproj2(&p, &x1[i]) > max_err2 || reproj2(&q, &x2[i]) > max_err2 {
            continue;
        }
        good += 1;
        parallax.push(cos.clamp(-1.0, 1.0).acos().to_degrees());
        if let Some((pts, tri)) = out.as_mut() {
            pts[i] = p;
            tri[i] = enough_parallax;
        }
    }
    // ORB-SLAM's measure: the parallax of the `min_triangulated`-th largest parallax (so at
    // least that many points see the motion from more than `min_parallax_deg` apart), not
    // the median, which far points of a forward-moving camera keep tiny for long.
    let parallax_deg = if parallax.is_empty() {
        0.0
    } else {
        let k = params.min_triangulated.min(parallax.len() - 1);
        let idx = parallax.len() - 1 - k;
        let (_, m, _) = parallax.select_nth_unstable_by(idx, |a, b| a.total_cmp(b));
        *m
    };
    Evaluation { good, parallax_deg }
}

/// Evaluates every hypothesis and returns the index of the one explaining most inliers,
/// its evaluation and the number of points the second best explains. `None` without
/// hypotheses.
#[allow(clippy::too_many_arguments)]
pub(crate) fn rank(
    hypotheses: &[(Rotation3<f64>, Vector3<f64>)],
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    inliers: &[bool],
    params: &TwoViewParams,
    parallax: &mut Vec<f64>,
) -> Option<(usize, Evaluation, usize)> {
    let mut best: Option<(usize, Evaluation)> = None;
    let mut second_good = 0;
    for (k, (r, t)) in hypotheses.iter().enumerate() {
        let e = evaluate(r, t, x1, x2, inliers, params, None, parallax);
        match best {
            Some((_, b)) if e.good <= b.good => second_good = second_good.max(e.good),
            Some((_, b)) => {
                second_good = second_good.max(b.good);
                best = Some((k, e));
            }
            None => best = Some((k, e)),
        }
    }
    best.map(|(k, e)| (k, e, second_good))
}

/// ORB-SLAM's acceptance rules for the best hypothesis `e` (section IV-4): it explains at
/// least `max(min_good_ratio · inliers, min_triangulated)` points, the second best explains
/// at most `ambiguity_ratio` times as many, and the parallax is at least
/// `min_parallax_deg` for the `min_triangulated`-th largest parallax. The error message says
/// which rule failed.
pub(crate) fn accept(
    e: &Evaluation,
    second_good: usize,
    n_inliers: usize,
    params: &TwoViewParams,
    ambiguity_ratio: f64,
) -> Result<(), CoreError> {
    let needed =
        ((params.min_good_ratio * n_inliers as f64).ceil() as usize).max(params.min_triangulated);
    if e.good < needed {
        return Err(CoreError::Degenerate(format!(
            "two-view: best hypothesis explains {} of {} inliers (need {needed})",
            e.good, n_inliers
        )));
    }
    if second_good as f64 > ambiguity_ratio * e.good as f64 {
        return Err(CoreError::Degenerate(format!(
            "two-view: ambiguous motion ({} vs {} good points)",
            e.good, second_good
        )));
    }
    if e.parallax_deg < params.min_parallax_deg {
        return Err(CoreError::Degenerate(format!(
            "two-view: parallax {:.3} deg < {} deg",
            e.parallax_deg, params.min_parallax_deg
        )));
    }
    Ok(())
}
