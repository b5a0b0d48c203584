//! Absolute pose from 3D-2D correspondences, for relocalisation (Mur-Artal et al. 2015,
//! section V-C: EPnP inside RANSAC, then motion-only optimisation).
//!
//! [`solve_pnp_ransac`] draws minimal sets of [`PnpParams::sample_size`] correspondences
//! (deterministic from [`PnpParams::seed`]), solves each with EPnP (Lepetit, Moreno-Noguer
//! & Fua 2009; `pnp/epnp.rs`), counts the correspondences whose reprojection error is
//! within `chi2 / inv_sigma2` (pixels, through
//! [`PnpParams::pixel_scale`]), adapts the number of iterations to the inlier ratio, refits
//! EPnP on the best inlier set, and polishes the pose with the robust motion-only
//! optimisation of [`crate::optim::PoseOptimizer`] (which also gives the final inliers).
//!
//! Observations are undistorted normalised coordinates `(x/z, y/z)`
//! ([`crate::twoview::normalize_pixels`] converts pixels); the pose is `T_cw`.

mod epnp;

use nalgebra::{Isometry3, Point3, Vector2, Vector3};

use crate::camera::PinholeRadtan;
use crate::optim::{PoseObservation, PoseOptParams, PoseOptimizer};
use crate::ransac::{adaptive_iterations, sample_distinct, SplitMix64};
use crate::CoreError;
use epnp::EpnpScratch;

/// Parameters of [`solve_pnp_ransac`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PnpParams {
    /// Pixels per normalised unit (the focal length, `sqrt(fx fy)`).
    pub pixel_scale: f64,
    /// Correspondences per RANSAC sample (5; at least 4).
    pub sample_size: usize,
    /// Largest number of RANSAC iterations (300).
    pub max_iterations: usize,
    /// Stop when an all-inlier sample has been drawn with this probability (0.99).
    pub confidence: f64,
    /// Inlier bound on `χ² = |r|² · inv_sigma2` (5.991).
    pub chi2: f64,
    /// Least number of inliers for a pose (15).
    pub min_inliers: usize,
    /// Seed of the sampler.
    pub seed: u64,
    /// Polish with the motion-only optimisation (true).
    pub refine: bool,
}

impl Default for PnpParams {
    fn default() -> Self {
        Self {
            pixel_scale: 450.0,
            sample_size: 5,
            max_iterations: 300,
            confidence: 0.99,
            chi2: 5.991,
            min_inliers: 15,
            seed: 0x9e3779b9,
            refine: true,
        }
    }
}

impl PnpParams {
    /// Defaults with [`PnpParams::pixel_scale`] from the camera's focal lengths.
    pub fn for_camera(camera: &PinholeRadtan) -> Self {
        Self {
            pixel_scale: (camera.fx * camera.fy).abs().sqrt(),
            ..Self::default()
        }
    }
}

/// A pose found by [`solve_pnp_ransac`].
#[derive(Debug, Clone, PartialEq)]
pub struct PnpResult {
    /// World-to-camera pose.
    pub t_cw: Isometry3<f64>,
    /// Inlier flags (same length as the input).
    pub inliers: Vec<bool>,
    /// Number of inliers.
    pub n_inliers: usize,
    /// RANSAC iterations run.
    pub iterations: usize,
}

/// Reusable state of [`solve_pnp_ransac_with`] (buffers only).
#[derive(Debug, Clone, Default)]
pub struct PnpSolver {
    epnp: EpnpScratch,
    mask: Vec<bool>,
    obs: Vec<PoseObservation>,
    optimizer: PoseOptimizer,
}

impl PnpSolver {
    /// A solver with empty buffers.
    pub fn new() -> Self {
        Self::default()
    }
}

/// The correspondences of one problem with the inlier test `χ² = |r|² · k · inv_sigma2
/// <= chi2` (`k = pixel_scale²` turns normalised residuals into pixels).
#[derive(Clone, Copy)]
struct Correspondences<'a> {
    points_w: &'a [Vector3<f64>],
    xn: &'a [Vector2<f64>],
    inv_sigma2: &'a [f64],
    k: f64,
    chi2: f64,
}

impl Correspondences<'_> {
    fn len(&self) -> usize {
        self.points_w.len()
    }

    /// Counts the inliers of `pose` into `mask`.
    fn score(&self, pose: &Isometry3<f64>, mask: &mut [bool]) -> usize {
        let mut n = 0;
        let obs = self.points_w.iter().zip(self.xn).zip(self.inv_sigma2);
        for (inlier, ((p_w, x), w)) in mask.iter_mut().zip(obs) {
            let q = pose * Point3::from(*p_w);
            *inlier = q.z > 0.0
                && (Vector2::new(q.x / q.z, q.y / q.z) - x).norm_squared() * self.k * w
                    <= self.chi2;
            n += usize::from(*inlier);
        }
        n
    }
}

/// [`solve_pnp_ransac_with`] with fresh buffers.
pub fn solve_pnp_ransac(
    points_w: &[Vector3<f64>],
    xn: &[Vector2<f64>],
    inv_sigma2: &[f64],
    params: &PnpParams,
) -> Result<PnpResult, CoreError> {
    solve_pnp_ransac_with(&mut PnpSolver::new(), points_w, xn, inv_sigma2, params)
}

/// Robust absolute pose (see the module docs): `points_w[i]` (world) is observed at the
/// normalised coordinates `xn[i]` with information `inv_sigma2[i]` (pixels⁻²).
///
/// Errors: `InvalidArgument` on mismatched lengths, non-finite input, non-positive
/// information or `sample_size < 4`; `NotEnoughData` with fewer correspondences than
/// `max(sample_size, min_inliers)`; `Degenerate` when no pose reaches `min_inliers`.
pub fn solve_pnp_ransac_with(
    solver: &mut PnpSolver,
    points_w: &[Vector3<f64>],
    xn: &[Vector2<f64>],
    inv_sigma2: &[f64],
    params: &PnpParams,
) -> Result<PnpResult, CoreError> {
    check_input(points_w, xn, inv_sigma2, params)?;
    let data = Correspondences {
        points_w,
        xn,
        inv_sigma2,
        k: params.pixel_scale * params.pixel_scale,
        chi2: params.chi2,
    };
    // 1. RANSAC over EPnP minimal sets, adaptive number of iterations.
    let (best, iterations) = ransac_epnp(solver, &data, params);
    let Some((count, pose)) = best else {
        return Err(CoreError::Degenerate("pnp: no EPnP solution".into()));
    };
    if count < params.min_inliers {
        return Err(CoreError::Degenerate(format!(
            "pnp: best pose has {count} inliers (need {})",
            params.min_inliers
        )));
    }
    // 2. EPnP refit on the inliers.
    let mut inliers = vec![false; data.len()];
    let mut pose = refit_on_inliers(solver, &data, pose, count, &mut inliers);
    // 3. Motion-only polish, which also gives the final inliers.
    if params.refine {
        pose = polish(solver, &data, pose, params, &mut inliers);
    }
    let n_inliers = inliers.iter().filter(|&&b| b).count();
    if n_inliers < params.min_inliers {
        return Err(CoreError::Degenerate(format!(
            "pnp: {n_inliers} inliers after refinement"
        )));
    }
    Ok(PnpResult {
        t_cw: pose,
        inliers,
        n_inliers,
        iterations,
    })
}

/// Input checks of [`solve_pnp_ransac_with`].
fn check_input(
    points_w: &[Vector3<f64>],
    xn: &[Vector2<f64>],
    inv_sigma2: &[f64],
    params: &PnpParams,
) -> Result<(), CoreError> {
    let n = points_w.len();
    if xn.len() != n || inv_sigma2.len() != n {
        return Err(CoreError::InvalidArgument(format!(
            "pnp: {} points, {} observations, {} weights",
            n,
            xn.len(),
            inv_sigma2.len()
        )));
    }
    if params.sample_size < 4
        || params.sample_size > 16
        || params.pixel_scale.is_nan()
        || params.pixel_scale <= 0.0
    {
        return Err(CoreError::InvalidArgument(
            "pnp: sample_size must be 4..=16, pixel_scale > 0".into(),
        ));
    }
    if n < params.sample_size.max(params.min_inliers) {
        return Err(CoreError::NotEnoughData(format!(
            "pnp: {n} correspondences"
        )));
    }
    let finite = points_w.iter().all(|p| p.iter().all(|v| v.is_finite()))
        && xn.iter().all(|p| p.iter().all(|v| v.is_finite()))
        && inv_sigma2.iter().all(|w| w.is_finite() && *w > 0.0);
    if !finite {
        return Err(CoreError::InvalidArgument(
            "pnp: non-finite input or non-positive information".into(),
        ));
    }
    Ok(())
}

/// The RANSAC loop: EPnP on minimal sets of `sample_size` correspondences, the iteration
/// limit adapted to the best inlier ratio so far. Returns the best `(inlier count, pose)`
/// and the iterations run.
fn ransac_epnp(
    solver: &mut PnpSolver,
    data: &Correspondences<'_>,
    params: &PnpParams,
) -> (Option<(usize, Isometry3<f64>)>, usize) {
    let n = data.len();
    let mut rng = SplitMix64::new(params.seed);
    let mut set = [0usize; 16];
    let set = &mut set[..params.sample_size];
    solver.mask.clear();
    solver.mask.resize(n, false);
    let mut best: Option<(usize, Isometry3<f64>)> = None;
    let mut limit = params.max_iterations;
    let mut iterations = 0;
    while iterations < limit {
        iterations += 1;
        if !sample_distinct(&mut rng, n, set) {
            break;
        }
        let Some(pose) = epnp::epnp(
            data.points_w,
            data.xn,
            set.iter().copied(),
            &mut solver.epnp,
        ) else {
            continue;
        };
        let count = data.score(&pose, &mut solver.mask);
        if best.is_none_or(|(c, _)| count > c) {
            best = Some((count, pose));
            limit = adaptive_iterations(
                count as f64 / n as f64,
                params.sample_size,
                params.confidence,
                params.max_iterations,
            );
        }
    }
    (best, iterations)
}

/// Refits EPnP on the inliers of `pose` (twice: the set usually grows), keeping a refit
/// with at least `count` inliers; `inliers` receives the kept pose's inliers.
fn refit_on_inliers(
    solver: &mut PnpSolver,
    data: &Correspondences<'_>,
    mut pose: Isometry3<f64>,
    count: usize,
    inliers: &mut [bool],
) -> Isometry3<f64> {
    data.score(&pose, inliers);
    for _ in 0..2 {
        let idx = (0..data.len()).filter(|&i| inliers[i]);
        if let Some(p) = epnp::epnp(data.points_w, data.xn, idx, &mut solver.epnp) {
            let c = data.score(&p, &mut solver.mask);
            if c >= count {
                pose = p;
                inliers.copy_from_slice(&solver.mask);
            }
        }
    }
    pose
}

/// Motion-only optimisation on a virtual pinhole camera whose "pixels" are normalised
/// coordinates times the focal length; kept (pose and `inliers`) when it has at least
/// `min_inliers`.
fn polish(
    solver: &mut PnpSolver,
    data: &Correspondences<'_>,
    pose: Isometry3<f64>,
    params: &PnpParams,
    inliers: &mut [bool],
) -> Isometry3<f64> {
    let s = params.pixel_scale;
    let cam = PinholeRadtan::pinhole(1, 1, s, s, 0.0, 0.0);
    solver.obs.clear();
    solver.obs.extend((0..data.len()).map(|i| PoseObservation {
        point_w: data.points_w[i],
        pixel: data.xn[i] * s,
        inv_sigma2: data.inv_sigma2[i],
        dt: 0.0,
    }));
    let opt_params = PoseOptParams {
        chi2: params.chi2,
        huber_delta: params.chi2.sqrt(),
        ..PoseOptParams::default()
    };
    let mut mask = std::mem::take(&mut solver.mask);
    let res = solver
        .optimizer
        .optimize(&cam, &pose, &solver.obs, None, &opt_params, &mut mask);
    let mut pose = pose;
    if let Ok(r) = res {
        if r.n_inliers >= params.min_inliers {
            pose = r.t_cw;
            inliers.copy_from_slice(&mask);
        }
    }
    solver.mask = mask;
    pose
}

#[cfg(test)]
mod tests;
