//! Anchored inverse-depth triangulation by Gauss-Newton (`VI_NOTES.md` §3 "Features",
//! Fig. 4.1-4.2 of the seed; Mourikis & Roumeliotis 2007 use the same parameterisation).
//!
//! Each observation comes with its camera pose at its own row time. The start is the
//! mid-point of the bearings (linear least squares on `Σ (I - b bᵀ)(X - c)`); Gauss-Newton
//! on `(α, β, ρ)` then minimises the pixel errors through the full camera model.

use nalgebra::{Matrix3, Rotation3, Vector2, Vector3};

use super::measure::InvDepth;
use crate::camera::PinholeRadtan;

/// A camera pose `(R_gc, p_gc)`: camera-to-global.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraPose {
    /// Camera orientation in the global frame.
    pub r_gc: Rotation3<f64>,
    /// Camera centre in the global frame, m.
    pub p_gc: Vector3<f64>,
}

/// A triangulated feature.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Triangulated {
    /// The feature in the anchor camera.
    pub f: InvDepth,
    /// Reprojection RMS over the observations, px.
    pub rms: f64,
    /// Fitted with the [`DepthPrior`]: the views did not have the parallax to fix its depth.
    pub low_parallax: bool,
}

/// A prior `ρ ~ N(rho, sigma²)` (1/m) on the inverse depth of a feature whose views lack
/// the parallax to triangulate it (a hand-held phone over 0.4 s, a distant scene). The prior
/// only keeps the Gauss-Newton fit of `(α, β, ρ)` well posed: the rows are projected on the
/// left null space of all three columns of `H_f` like any feature's, so the depth itself is
/// still treated as unknown, and what is left constrains the rotations, the camera and the
/// timing (`t_r` through the rotation during readout). The prior counts as one residual of
/// 1 px.
#[derive(Debug, Clone, Copy, PartialEq)]
struct DepthPrior {
    /// Prior inverse depth, 1/m.
    rho: f64,
    /// Its 1σ, 1/m.
    sigma: f64,
}

impl DepthPrior {
    /// The prior of a feature classed as low parallax over a baseline `b` (m): its `ρ` lies
    /// in `(0, min_parallax / b)`, so half that, with a 1σ as large. It needs no guess of the
    /// scene's depth: a phone moving 5 mm puts it at 0.5 m, a drone moving 3 m at 300 m. The
    /// baseline is floored at 1 mm (the depth of a pure rotation's features is irrelevant).
    fn for_parallax(min_parallax: f64, b: f64) -> Self {
        let rho = 0.5 * min_parallax / b.max(1e-3);
        Self { rho, sigma: rho }
    }
}

/// Gauss-Newton iterations at most.
const MAX_ITERS: usize = 10;
/// Smallest depth (m) accepted in every camera.
const MIN_DEPTH: f64 = 0.05;
/// Smallest ratio of the bearing system's eigenvalues (parallax) accepted.
const MIN_PARALLAX: f64 = 1e-5;

/// Triangulates a feature seen at `obs` (camera pose at the row time, pixel), anchored in
/// the camera `anchor`. `None` behind a camera, when the rays diverge by more than low
/// parallax explains, or when Gauss-Newton fails. Without parallax (largest baseline over
/// the anchor depth below `min_parallax`, rad): `None`, or, when `low_parallax`, the fit
/// with a [`DepthPrior`] ([`Triangulated::low_parallax`]). Short-baseline features are not
/// triangulated freely because their depth absorbs model errors (wrong intrinsics or
/// distortion at the start), and the linearised null-space rows are then inconsistent.
pub fn triangulate(
    cam: &PinholeRadtan,
    anchor: &CameraPose,
    obs: &[(CameraPose, Vector2<f64>)],
    min_parallax: f64,
    low_parallax: bool,
) -> Option<Triangulated> {
    match free_fit(cam, anchor, obs, min_parallax) {
        Fit::Free(t) => Some(t),
        Fit::Inconsistent => None,
        Fit::LowParallax if !low_parallax => None,
        Fit::LowParallax => {
            let prior = DepthPrior::for_parallax(min_parallax, baseline(obs));
            let start = mean_bearing(cam, anchor, obs, prior.rho)?;
            let (f, cost) = refine(cam, anchor, obs, start, Some(&prior))?;
            Some(Triangulated {
                f,
                rms: (cost / obs.len() as f64).sqrt(),
                low_parallax: true,
            })
        }
    }
}

/// What the fit without a depth prior gave.
enum Fit {
    /// A feature with parallax.
    Free(Triangulated),
    /// Too little parallax to fix the depth: the rays are parallel, or they meet (or
    /// diverge) at a depth whose parallax is below the bound.
    LowParallax,
    /// The rays diverge by more than low parallax explains, a view sees the point behind
    /// it, or Gauss-Newton fails: the feature or the state is wrong, and a depth prior
    /// would only hide it.
    Inconsistent,
}

/// The fit without a depth prior, from the rays' mid-point.
fn free_fit(
    cam: &PinholeRadtan,
    anchor: &CameraPose,
    obs: &[(CameraPose, Vector2<f64>)],
    min_parallax: f64,
) -> Fit {
    let Some(x) = midpoint(cam, obs) else {
        return Fit::LowParallax;
    };
    let b = baseline(obs);
    let p_a = anchor.r_gc.inverse() * (x - anchor.p_gc);
    if p_a.z < MIN_DEPTH {
        // Behind: parallel rays bent by noise, or rays that do not meet.
        return if b < min_parallax * p_a.z.abs() {
            Fit::LowParallax
        } else {
            Fit::Inconsistent
        };
    }
    let start = InvDepth {
        alpha: p_a.x / p_a.z,
        beta: p_a.y / p_a.z,
        rho: 1.0 / p_a.z,
    };
    match refine(cam, anchor, obs, start, None) {
        None => Fit::Inconsistent,
        Some((f, _)) if b * f.rho < min_parallax => Fit::LowParallax,
        Some((f, cost)) => Fit::Free(Triangulated {
            f,
            rms: (cost / obs.len() as f64).sqrt(),
            low_parallax: false,
        }),
    }
}

/// The bearings' mean direction in the anchor camera, at inverse depth `rho`.
fn mean_bearing(
    cam: &PinholeRadtan,
    anchor: &CameraPose,
    obs: &[(CameraPose, Vector2<f64>)],
    rho: f64,
) -> Option<InvDepth> {
    let d: Vector3<f64> = obs
        .iter()
        .map(|(pose, uv)| (anchor.r_gc.inverse() * pose.r_gc * cam.unproject(uv)).normalize())
        .sum();
    (d.z > 0.0).then(|| InvDepth {
        alpha: d.x / d.z,
        beta: d.y / d.z,
        rho,
    })
}

/// Gauss-Newton on `(α, β, ρ)` from `f`, with the depth prior if any: the fit and its sum
/// of squared pixel errors (the prior's term left out). `None` when the start is behind a
/// camera or the fit leaves `ρ ≤ 0`.
fn refine(
    cam: &PinholeRadtan,
    anchor: &CameraPose,
    obs: &[(CameraPose, Vector2<f64>)],
    mut f: InvDepth,
    prior: Option<&DepthPrior>,
) -> Option<(InvDepth, f64)> {
    let prior_cost = |f: &InvDepth| prior.map_or(0.0, |p| ((f.rho - p.rho) / p.sigma).powi(2));
    let mut cost = cost_ok(cam, anchor, obs, &f)? + prior_cost(&f);
    for _ in 0..MAX_ITERS {
        let (mut jtj, mut jtr) = normal_equations(cam, anchor, obs, &f)?;
        if let Some(p) = prior {
            let w = p.sigma.powi(-2);
            jtj[(2, 2)] += w;
            jtr.z += w * (p.rho - f.rho);
        }
        let step = (jtj + Matrix3::identity() * 1e-9 * jtj.trace())
            .lu()
            .solve(&jtr)?;
        let cand = InvDepth {
            alpha: f.alpha + step.x,
            beta: f.beta + step.y,
            rho: f.rho + step.z,
        };
        match cost_ok(cam, anchor, obs, &cand).map(|c| c + prior_cost(&cand)) {
            Some(c) if c <= cost => {
                let done = cost - c < 1e-10 * cost.max(1e-12) || step.norm() < 1e-12;
                (f, cost) = (cand, c);
                if done {
                    break;
                }
            }
            _ => break,
        }
    }
    (f.rho > 0.0).then(|| (f, cost - prior_cost(&f)))
}

/// Largest distance between two of the camera centres, m.
fn baseline(obs: &[(CameraPose, Vector2<f64>)]) -> f64 {
    let mut b: f64 = 0.0;
    for (i, a) in obs.iter().enumerate() {
        for c in &obs[i + 1..] {
            b = b.max((a.0.p_gc - c.0.p_gc).norm());
        }
    }
    b
}

/// Least-squares point closest to every bearing ray; `None` without parallax.
fn midpoint(cam: &PinholeRadtan, obs: &[(CameraPose, Vector2<f64>)]) -> Option<Vector3<f64>> {
    let (mut a, mut b) = (Matrix3::zeros(), Vector3::zeros());
    for (pose, uv) in obs {
        let d = pose.r_gc * cam.unproject(uv);
        let m = Matrix3::identity() - d * d.transpose();
        a += m;
        b += m * pose.p_gc;
    }
    let eig = a.symmetric_eigenvalues();
    if eig.min() < MIN_PARALLAX * eig.max() {
        return None;
    }
    a.cholesky().map(|c| c.solve(&b))
}

/// The feature in camera `pose`: `p^c = R_gcᵀ (p_Ca + R_gCa (α,β,1)/ρ - p_gc)`.
fn in_camera(anchor: &CameraPose, pose: &CameraPose, f: &InvDepth) -> Vector3<f64> {
    let p_ca = Vector3::new(f.alpha, f.beta, 1.0) / f.rho;
    pose.r_gc.inverse() * (anchor.p_gc + anchor.r_gc * p_ca - pose.p_gc)
}

/// Sum of squared pixel errors; `None` if a depth is below [`MIN_DEPTH`].
fn cost_ok(
    cam: &PinholeRadtan,
    anchor: &CameraPose,
    obs: &[(CameraPose, Vector2<f64>)],
    f: &InvDepth,
) -> Option<f64> {
    if f.rho <= 0.0 {
        return None;
    }
    let mut c = 0.0;
    for (pose, uv) in obs {
        let p = in_camera(anchor, pose, f);
        if p.z < MIN_DEPTH {
            return None;
        }
        c += (uv - cam.project(&p)?).norm_squared();
    }
    Some(c)
}

/// `(JᵀJ, Jᵀr)` of the pixel errors in `(α, β, ρ)`, `r = z - π`.
fn normal_equations(
    cam: &PinholeRadtan,
    anchor: &CameraPose,
    obs: &[(CameraPose, Vector2<f64>)],
    f: &InvDepth,
) -> Option<(Matrix3<f64>, Vector3<f64>)> {
    let ir = 1.0 / f.rho;
    let d_pca = Matrix3::from_columns(&[
        Vector3::new(ir, 0.0, 0.0),
        Vector3::new(0.0, ir, 0.0),
        -Vector3::new(f.alpha, f.beta, 1.0) * (ir * ir),
    ]);
    let (mut jtj, mut jtr) = (Matrix3::zeros(), Vector3::zeros());
    for (pose, uv) in obs {
        let (z, j_pi) = cam.project_with_jacobian(&in_camera(anchor, pose, f))?;
        let j = j_pi * (pose.r_gc.inverse() * anchor.r_gc).matrix() * d_pca;
        jtj += j.transpose() * j;
        jtr += j.transpose() * (uv - z);
    }
    Some((jtj, jtr))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One observation: the camera's pose and the pixel.
    type View = (CameraPose, Vector2<f64>);

    /// A distorted camera and the point (0.3, -0.4, 3) seen from `poses`.
    fn views(poses: &[CameraPose]) -> (PinholeRadtan, Vector3<f64>, Vec<View>) {
        let cam = PinholeRadtan::from_coefficients(
            640,
            480,
            [450.0, 452.0, 320.0, 240.0],
            [-0.25, 0.07, 1e-3, -5e-4, 0.0],
        );
        let x = Vector3::new(0.3, -0.4, 3.0);
        let obs = poses
            .iter()
            .map(|p| (*p, cam.project(&(p.r_gc.inverse() * (x - p.p_gc))).unwrap()))
            .collect();
        (cam, x, obs)
    }

    #[test]
    fn recovers_a_point_from_three_views() {
        let poses: Vec<CameraPose> = (0..3)
            .map(|k| CameraPose {
                r_gc: Rotation3::from_scaled_axis(Vector3::new(0.02 * k as f64, -0.03, 0.01)),
                p_gc: Vector3::new(0.1 * k as f64, 0.02 * k as f64, 0.0),
            })
            .collect();
        let (cam, x, obs) = views(&poses);
        let t = triangulate(&cam, &poses[2], &obs, 0.01, false).expect("triangulates");
        let back = in_camera(
            &poses[2],
            &CameraPose {
                r_gc: Rotation3::identity(),
                p_gc: Vector3::zeros(),
            },
            &t.f,
        );
        assert!((back - x).norm() < 1e-8, "{back} vs {x}");
        assert!(t.rms < 1e-8);
        let same = vec![obs[0]; 3];
        assert!(
            triangulate(&cam, &poses[0], &same, 0.0, false).is_none(),
            "no parallax"
        );
    }

    /// Views from one centre (pure rotation): no free fit, but with the depth prior the
    /// bearing exactly, at the prior depth, flagged as low parallax.
    #[test]
    fn a_pure_rotation_is_fitted_with_the_depth_prior() {
        let poses: Vec<CameraPose> = (0..4)
            .map(|k| CameraPose {
                r_gc: Rotation3::from_scaled_axis(Vector3::new(0.01 * k as f64, -0.02, 0.005)),
                p_gc: Vector3::zeros(),
            })
            .collect();
        let (cam, x, obs) = views(&poses);
        assert!(triangulate(&cam, &poses[3], &obs, 0.02, false).is_none());
        let t = triangulate(&cam, &poses[3], &obs, 0.02, true).expect("fitted");
        assert!(t.low_parallax && t.rms < 1e-6, "rms {}", t.rms);
        let prior = DepthPrior::for_parallax(0.02, 0.0).rho;
        assert!(
            (t.f.rho - prior).abs() < 1e-9,
            "ρ {} kept at the prior",
            t.f.rho
        );
        let bearing = poses[3].r_gc.inverse() * x;
        assert!((t.f.alpha - bearing.x / bearing.z).abs() < 1e-9);
        assert!((t.f.beta - bearing.y / bearing.z).abs() < 1e-9);
    }
}
