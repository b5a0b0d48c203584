//! Two-view geometry and monocular map initialisation, after ORB-SLAM (Mur-Artal, Montiel &
//! Tardós 2015, "ORB-SLAM: a Versatile and Accurate Monocular SLAM System", section IV; the
//! seed, section 3.3, uses it unchanged for its client VO).
//!
//! [`initialize`] takes matched, undistorted, normalised image coordinates `(x/z, y/z)` of a
//! reference frame (view 1) and the current frame (view 2) and
//! 1. runs one RANSAC loop of [`TwoViewParams::iterations`] iterations that fits, on the
//!    same random 8-point sets, a fundamental matrix (normalised 8-point) and a homography
//!    (normalised DLT on the first 4 points of the set), scoring both with the symmetric
//!    chi-square scores `S_F`, `S_H` ([`score_fundamental`], [`score_homography`]); the
//!    best models are refitted on their inliers;
//! 2. selects the homography when `R_H = S_H / (S_H + S_F) > 0.45`, else the fundamental
//!    matrix;
//! 3. decomposes the chosen model into motion hypotheses (4 for the essential matrix, 4 for
//!    the homography) and keeps the one that triangulates most inliers in front of both
//!    cameras ([`select`] explains the acceptance rules: ≥ 90% of inliers, no close second,
//!    parallax ≥ 1° for the 50 points seeing most of it, as ORB-SLAM).
//!
//! The motion is `X2 = R X1 + t` (so `T_21`, view 1 to view 2) with `|t| = 1`; points are in
//! view 1's frame at that scale. Thresholds are in pixels through
//! [`TwoViewParams::pixel_scale`] (the focal length), so the chi-square bounds of the paper
//! apply unchanged.

mod fundamental;
mod homography;
mod normalize;
mod refine;
pub mod select;
pub mod triangulate;

pub use fundamental::{
    decompose_essential, essential_from_fundamental, fundamental_8point, score_fundamental, Motion,
};
pub use homography::{decompose_homography, homography_dlt, score_homography, HomographyMotion};
pub use triangulate::{
    check_point, min_parallax_cos, projection_matrix, triangulate_dlt, triangulate_multiview,
    CheckView, TriangulationCheck, TriangulationReject,
};

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3};

use crate::camera::PinholeRadtan;
use crate::ransac::{sample_distinct, SplitMix64};
use crate::CoreError;
use normalize::{apply, hartley};

/// Parameters of [`initialize`]; defaults are ORB-SLAM's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TwoViewParams {
    /// RANSAC iterations, shared by both models (200).
    pub iterations: usize,
    /// Seed of the RANSAC sampler (runs are deterministic).
    pub seed: u64,
    /// Pixels per normalised unit: the focal length (`sqrt(fx fy)`), see
    /// [`TwoViewParams::for_camera`].
    pub pixel_scale: f64,
    /// Keypoint standard deviation in pixels (1: finest octave).
    pub sigma_px: f64,
    /// Homography inlier bound `T_H` and score constant `Γ` (5.991: chi-square, 2 dof, 95%).
    pub chi2_homography: f64,
    /// Fundamental inlier bound `T_F` (3.841: chi-square, 1 dof, 95%).
    pub chi2_fundamental: f64,
    /// Choose the homography when `S_H / (S_H + S_F)` exceeds this (0.45).
    pub homography_ratio: f64,
    /// Also choose the homography when it has at least this fraction of the fundamental
    /// matrix's inliers (0.8; `f64::INFINITY` disables). Not in ORB-SLAM: on a planar scene
    /// every `F = [e']x H` explains the matches as well as `H`, and with keypoint noise close
    /// to `sigma_px` the score ratio then sits at 0.40-0.45, so the score rule alone picks
    /// the degenerate `F` (cf. Chum, Werner & Matas 2005, DEGENSAC).
    pub homography_inlier_ratio: f64,
    /// Squared reprojection bound for triangulated points, in units of `sigma_px²` (5.991).
    pub reproj_chi2: f64,
    /// Points whose rays have a parallax cosine above this are not triangulated
    /// (0.99998 ≈ 0.36°); they still count as explained.
    pub max_parallax_cos: f64,
    /// Refuse the initialisation when fewer than `min_triangulated` explained points have a
    /// parallax of at least this (degrees, 1.0).
    pub min_parallax_deg: f64,
    /// Least number of explained points (50).
    pub min_triangulated: usize,
    /// Least fraction of the model inliers the chosen hypothesis must explain (0.9).
    pub min_good_ratio: f64,
    /// The second-best essential hypothesis must explain fewer than this fraction of the
    /// best's points (0.7).
    pub ambiguity_ratio_f: f64,
    /// The same for the homography hypotheses (0.75).
    pub ambiguity_ratio_h: f64,
    /// Levenberg-Marquardt iterations of the Sampson-error refinement of the chosen motion
    /// (30 per pass, two passes; 0 keeps the linear estimate).
    pub refine_iterations: usize,
}

impl Default for TwoViewParams {
    fn default() -> Self {
        Self {
            iterations: 200,
            seed: 0x5eed,
            pixel_scale: 450.0,
            sigma_px: 1.0,
            chi2_homography: 5.991,
            chi2_fundamental: 3.841,
            homography_ratio: 0.45,
            homography_inlier_ratio: 0.8,
            reproj_chi2: 5.991,
            max_parallax_cos: 0.99998,
            min_parallax_deg: 1.0,
            min_triangulated: 50,
            min_good_ratio: 0.9,
            ambiguity_ratio_f: 0.7,
            ambiguity_ratio_h: 0.75,
            refine_iterations: 30,
        }
    }
}

impl TwoViewParams {
    /// Defaults with [`TwoViewParams::pixel_scale`] set from the camera's focal lengths.
    pub fn for_camera(camera: &PinholeRadtan) -> Self {
        Self {
            pixel_scale: (camera.fx * camera.fy).abs().sqrt(),
            ..Self::default()
        }
    }
}

/// Which model [`initialize`] used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TwoViewModel {
    /// Homography: planar scene or small baseline.
    Homography,
    /// Fundamental / essential matrix: general scene.
    Essential,
}

/// A successful two-view initialisation.
#[derive(Debug, Clone, PartialEq)]
pub struct TwoViewResult {
    /// The model the motion came from.
    pub model: TwoViewModel,
    /// Rotation `R_21` (view 1 to view 2).
    pub rotation: Rotation3<f64>,
    /// Translation `t_21`, unit norm (`X2 = R X1 + t`).
    pub translation: Vector3<f64>,
    /// Triangulated points in view 1's frame (same length as the input; zero where
    /// `triangulated` is false).
    pub points: Vec<Vector3<f64>>,
    /// Points with positive depth, small reprojection error and enough parallax.
    pub triangulated: Vec<bool>,
    /// Inliers: matches whose Sampson error at the refined motion is within
    /// `chi2_fundamental · sigma_px²` (pixels).
    pub inliers: Vec<bool>,
    /// Homography score `S_H`.
    pub score_h: f64,
    /// Fundamental score `S_F`.
    pub score_f: f64,
    /// Parallax (degrees) of the `min_triangulated`-th most parallax-rich explained point.
    pub parallax_deg: f64,
}

impl TwoViewResult {
    /// The motion as a pose `T_21` (maps view-1 coordinates into view 2).
    pub fn pose_21(&self) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::from(self.translation),
            UnitQuaternion::from_rotation_matrix(&self.rotation),
        )
    }

    /// `R_H = S_H / (S_H + S_F)` (0 when both scores are 0).
    pub fn ratio_h(&self) -> f64 {
        let s = self.score_h + self.score_f;
        if s > 0.0 {
            self.score_h / s
        } else {
            0.0
        }
    }
}

/// Converts distorted pixels to undistorted normalised coordinates `(x/z, y/z)` into `out`
/// (cleared first).
pub fn normalize_pixels(
    camera: &PinholeRadtan,
    pixels: &[Vector2<f64>],
    out: &mut Vec<Vector2<f64>>,
) {
    out.clear();
    out.extend(pixels.iter().map(|uv| {
        let xd = Vector2::new(
            (uv.x - camera.cx) / camera.fx,
            (uv.y - camera.cy) / camera.fy,
        );
        camera.undistort(&xd)
    }));
}

/// Best model of the RANSAC loop.
struct Best {
    model: Matrix3<f64>,
    score: f64,
    inliers: Vec<bool>,
}

impl Best {
    fn new(n: usize) -> Self {
        Self {
            model: Matrix3::zeros(),
            score: 0.0,
            inliers: vec![false; n],
        }
    }

    /// Keeps `model` when its `score` is higher; its inlier `mask` is swapped in.
    fn consider(&mut self, model: Matrix3<f64>, score: f64, mask: &mut Vec<bool>) {
        if score > self.score {
            self.model = model;
            self.score = score;
            std::mem::swap(&mut self.inliers, mask);
        }
    }

    fn n_inliers(&self) -> usize {
        self.inliers.iter().filter(|&&b| b).count()
    }
}

/// The winners of step 1: the best homography and the best fundamental matrix.
struct ModelFits {
    h: Best,
    f: Best,
}

/// Motion hypotheses `(R_21, t_21)` of a decomposed model.
type Motions = Vec<(Rotation3<f64>, Vector3<f64>)>;

/// Step 2's outcome: the chosen model, its inliers and its motion hypotheses.
struct Hypotheses {
    model: TwoViewModel,
    inliers: Vec<bool>,
    motions: Motions,
    /// Ambiguity ratio of [`select::accept`] for this model.
    ambiguity: f64,
}

/// Fits and scores both models on chosen matches (step 1): the matches, their Hartley
/// normalisations and the score parameters.
struct ModelScorer<'a> {
    x1: &'a [Vector2<f64>],
    x2: &'a [Vector2<f64>],
    x1n: Vec<Vector2<f64>>,
    x2n: Vec<Vector2<f64>>,
    t1: Matrix3<f64>,
    t2: Matrix3<f64>,
    /// Pixels per normalised unit.
    s: f64,
    /// `1 / sigma_px²`.
    inv_s2: f64,
    th_h: f64,
    th_f: f64,
}

impl<'a> ModelScorer<'a> {
    fn new(
        x1: &'a [Vector2<f64>],
        x2: &'a [Vector2<f64>],
        params: &TwoViewParams,
    ) -> Result<Self, CoreError> {
        let degenerate =
            || CoreError::Degenerate("two-view: points collapse to one location".into());
        let t1 = hartley(x1.iter()).ok_or_else(degenerate)?;
        let t2 = hartley(x2.iter()).ok_or_else(degenerate)?;
        Ok(Self {
            x1,
            x2,
            x1n: x1.iter().map(|p| apply(&t1, p)).collect(),
            x2n: x2.iter().map(|p| apply(&t2, p)).collect(),
            t1,
            t2,
            s: params.pixel_scale,
            inv_s2: 1.0 / (params.sigma_px * params.sigma_px),
            th_h: params.chi2_homography,
            th_f: params.chi2_fundamental,
        })
    }

    /// Normalised DLT homography of matches `idx`, scored by `S_H` into `best`.
    fn try_homography(
        &self,
        idx: impl Iterator<Item = usize>,
        best: &mut Best,
        mask: &mut Vec<bool>,
    ) {
        if let Some(h) = homography::solve_normalized(&self.x1n, &self.x2n, idx)
            .and_then(|hn| homography::denormalize(&hn, &self.t1, &self.t2))
        {
            let (x1, x2) = (self.x1, self.x2);
            let sc = score_homography(&h, x1, x2, self.s, self.inv_s2, self.th_h, mask);
            best.consider(h, sc, mask);
        }
    }

    /// Normalised 8-point fundamental matrix of matches `idx`, scored by `S_F` into `best`.
    fn try_fundamental(
        &self,
        idx: impl Iterator<Item = usize>,
        best: &mut Best,
        mask: &mut Vec<bool>,
    ) {
        if let Some(f) = fundamental::solve_normalized(&self.x1n, &self.x2n, idx)
            .and_then(|fnorm| fundamental::denormalize(&fnorm, &self.t1, &self.t2))
        {
            let (x1, x2, s, inv_s2) = (self.x1, self.x2, self.s, self.inv_s2);
            let sc = score_fundamental(&f, x1, x2, s, inv_s2, self.th_f, self.th_h, mask);
            best.consider(f, sc, mask);
        }
    }
}

/// Two-view initialisation (Mur-Artal et al. 2015, section IV): see the module docs.
///
/// `x1[i]` and `x2[i]` are the undistorted normalised coordinates of match `i` in view 1
/// (reference) and view 2 (current); [`normalize_pixels`] converts pixels.
///
/// Errors: `InvalidArgument` on different lengths or non-finite coordinates,
/// `NotEnoughData` with fewer than 8 matches, `Degenerate` when the initialisation is
/// refused (no model, too few points explained, ambiguous motion, low parallax — the
/// message says which; the caller simply tries again with a later frame).
pub fn initialize(
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    params: &TwoViewParams,
) -> Result<TwoViewResult, CoreError> {
    check_input(x1, x2, params)?;
    let n = x1.len();
    // 1. RANSAC of H and F on the same samples, then refits on their inliers.
    let fits = fit_models(x1, x2, params)?;
    let (score_h, score_f) = (fits.h.score, fits.f.score);
    // 2. Model selection (R_H) and decomposition into motion hypotheses.
    let hyp = model_hypotheses(fits, x1, x2, params)?;
    // 3. The hypothesis triangulating most inliers in front of both cameras.
    let mut parallax = Vec::with_capacity(n);
    let (k, _, second_good) =
        select::rank(&hyp.motions, x1, x2, &hyp.inliers, params, &mut parallax)
            .ok_or_else(|| CoreError::Degenerate("two-view: no motion hypothesis".into()))?;
    let (r0, t0) = hyp.motions[k];
    let tn = t0.norm();
    if !(tn.is_finite() && tn > 1e-12) {
        return Err(CoreError::Degenerate("two-view: zero translation".into()));
    }
    // 4. Refinement of the motion and the final inliers.
    let refine_motion = hyp.model == TwoViewModel::Essential;
    let (r, t, inliers) =
        refine_and_classify(r0, t0 / tn, hyp.inliers, x1, x2, params, refine_motion);
    // 5. Triangulation and the acceptance rules.
    let n_inliers = inliers.iter().filter(|&&b| b).count();
    let mut points = vec![Vector3::zeros(); n];
    let mut triangulated = vec![false; n];
    let out = Some((points.as_mut_slice(), triangulated.as_mut_slice()));
    let eval = select::evaluate(&r, &t, x1, x2, &inliers, params, out, &mut parallax);
    select::accept(&eval, second_good, n_inliers, params, hyp.ambiguity)?;
    Ok(TwoViewResult {
        model: hyp.model,
        rotation: r,
        translation: t,
        points,
        triangulated,
        inliers,
        score_h,
        score_f,
        parallax_deg: eval.parallax_deg,
    })
}

/// Input checks of [`initialize`].
fn check_input(
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    params: &TwoViewParams,
) -> Result<(), CoreError> {
    let n = x1.len();
    if x2.len() != n {
        return Err(CoreError::InvalidArgument(format!(
            "two-view: {} vs {} points",
            n,
            x2.len()
        )));
    }
    if n < 8 {
        return Err(CoreError::NotEnoughData(format!(
            "two-view: {n} matches (need 8)"
        )));
    }
    if !x1.iter().chain(x2).all(|p| p.iter().all(|v| v.is_finite())) {
        return Err(CoreError::InvalidArgument(
            "two-view: non-finite coordinates".into(),
        ));
    }
    if params.pixel_scale.is_nan()
        || params.sigma_px.is_nan()
        || params.pixel_scale <= 0.0
        || params.sigma_px <= 0.0
    {
        return Err(CoreError::InvalidArgument(
            "two-view: pixel_scale and sigma_px must be > 0".into(),
        ));
    }
    Ok(())
}

/// Step 1: one RANSAC loop fitting a homography (first 4 points of each sample) and a
/// fundamental matrix (all 8) on the same samples, scored by `S_H` and `S_F`; then both
/// refitted on their inliers (twice: the inlier set usually grows once).
fn fit_models(
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    params: &TwoViewParams,
) -> Result<ModelFits, CoreError> {
    let n = x1.len();
    let scorer = ModelScorer::new(x1, x2, params)?;
    let mut fits = ModelFits {
        h: Best::new(n),
        f: Best::new(n),
    };
    let mut mask = vec![false; n];
    let mut rng = SplitMix64::new(params.seed);
    let mut set = [0usize; 8];
    for _ in 0..params.iterations {
        if !sample_distinct(&mut rng, n, &mut set) {
            break;
        }
        scorer.try_homography(set[..4].iter().copied(), &mut fits.h, &mut mask);
        scorer.try_fundamental(set.iter().copied(), &mut fits.f, &mut mask);
    }
    for _ in 0..2 {
        let idx = fits.h.inliers.clone();
        if fits.h.n_inliers() >= 4 {
            scorer.try_homography((0..n).filter(|&i| idx[i]), &mut fits.h, &mut mask);
        }
        let idx = fits.f.inliers.clone();
        if fits.f.n_inliers() >= 8 {
            scorer.try_fundamental((0..n).filter(|&i| idx[i]), &mut fits.f, &mut mask);
        }
    }
    Ok(fits)
}

/// Step 2: the homography when `R_H = S_H / (S_H + S_F) > homography_ratio` (or when it
/// keeps `homography_inlier_ratio` of F's inliers), else the essential matrix from F; the
/// chosen model decomposed into its motion hypotheses.
fn model_hypotheses(
    fits: ModelFits,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    params: &TwoViewParams,
) -> Result<Hypotheses, CoreError> {
    let total = fits.h.score + fits.f.score;
    if total <= 0.0 {
        return Err(CoreError::Degenerate("two-view: no model found".into()));
    }
    let (n_h, n_f) = (fits.h.n_inliers() as f64, fits.f.n_inliers() as f64);
    let use_h = fits.h.score / total > params.homography_ratio
        || n_h >= params.homography_inlier_ratio * n_f;
    if use_h {
        let motions = homography_motions(&fits.h, x1, x2, params)?;
        Ok(Hypotheses {
            model: TwoViewModel::Homography,
            inliers: fits.h.inliers,
            motions,
            ambiguity: params.ambiguity_ratio_h,
        })
    } else {
        let e = essential_from_fundamental(&fits.f.model)
            .ok_or_else(|| CoreError::Degenerate("two-view: SVD of F failed".into()))?;
        Ok(Hypotheses {
            model: TwoViewModel::Essential,
            inliers: fits.f.inliers,
            motions: decompose_essential(&e)?.to_vec(),
            ambiguity: params.ambiguity_ratio_f,
        })
    }
}

/// The motion hypotheses of the best homography: its sign made to give positive depths,
/// polished on its inliers, decomposed.
fn homography_motions(
    best_h: &Best,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    params: &TwoViewParams,
) -> Result<Motions, CoreError> {
    let mut h = best_h.model;
    // Sign with positive depths: x2ᵀ H x1 > 0 on most inliers.
    let votes: f64 = (0..x1.len())
        .filter(|&i| best_h.inliers[i])
        .map(|i| {
            let v =
                Vector3::new(x2[i].x, x2[i].y, 1.0).dot(&(h * Vector3::new(x1[i].x, x1[i].y, 1.0)));
            v.signum()
        })
        .sum();
    if votes < 0.0 {
        h = -h;
    }
    // Polish H itself: on a plane the epipolar (Sampson) cost used below for F is
    // ill-conditioned (every [e']x H fits the points).
    if params.refine_iterations > 0 {
        let delta = params.chi2_homography.sqrt() * params.sigma_px / params.pixel_scale;
        let iterations = params.refine_iterations;
        h = refine::refine_homography(&h, x1, x2, &best_h.inliers, delta, iterations);
    }
    let sols = decompose_homography(&h)?;
    Ok(sols.iter().map(|m| (m.rotation, m.translation)).collect())
}

/// Step 4. Essential path (`refine_motion`): refine (Huber at the inlier bound) on the
/// matches whose Sampson error is small at the current motion, with a shrinking gate of 16,
/// 4, 4 times the squared inlier bound (the linear model is biased, up to ~1° and ~5° on
/// noisy data, and so is its inlier set; a gate at the bound itself would truncate the
/// noise and bias the result). Both paths then classify the inliers at the final motion.
fn refine_and_classify(
    r0: Rotation3<f64>,
    t0: Vector3<f64>,
    mut inliers: Vec<bool>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    params: &TwoViewParams,
    refine_motion: bool,
) -> (Rotation3<f64>, Vector3<f64>, Vec<bool>) {
    let delta = params.chi2_fundamental.sqrt() * params.sigma_px / params.pixel_scale;
    let (mut r, mut t) = (r0, t0);
    if params.refine_iterations > 0 && refine_motion {
        for gate in [16.0, 4.0, 4.0] {
            refine::classify(&r, &t, x1, x2, gate * delta * delta, &mut inliers);
            (r, t) =
                refine::refine_motion(&r, &t, x1, x2, &inliers, delta, params.refine_iterations);
        }
    }
    refine::classify(&r, &t, x1, x2, delta * delta, &mut inliers);
    (r, t, inliers)
}

#[cfg(test)]
pub(crate) mod synth;
#[cfg(test)]
mod tests;
#[cfg(test)]
mod timing;
