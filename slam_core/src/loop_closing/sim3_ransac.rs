//! Geometric verification of a loop candidate (seed §3.4.2): Sim(3) from matched 3D points
//! with Umeyama inside RANSAC, two-way reprojection inliers, LM refinement and guided
//! matching of the candidate's neighbourhood.

use std::collections::HashSet;

use nalgebra::{UnitQuaternion, Vector2, Vector3};

use super::matching::{guided_matches, match_kept_points, match_neighbourhood, NeighbourhoodPoint};
use super::refine::{refine_sim3, RefineParams, Sim3Correspondence};
use crate::camera::PinholeRadtan;
use crate::features::TH_LOW;
use crate::geometry::umeyama;
use crate::lie::Sim3;
use crate::place::FeatureVector;
use crate::ransac::{adaptive_iterations, sample_distinct, SplitMix64};
use crate::server::KeptKeyframe;
use crate::vo::PointId;

/// Parameters of [`compute_sim3`]; defaults follow ORB-SLAM's loop closing (seed §3.4.2).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sim3Params {
    /// Largest Hamming distance of a descriptor match ([`TH_LOW`] = 50).
    pub max_distance: u32,
    /// Nearest / second-nearest ratio of a descriptor match (ORB-SLAM's `SearchByBoW`:
    /// 0.75).
    pub ratio: f32,
    /// Candidates with fewer descriptor matches are skipped (ORB-SLAM: 20).
    pub min_matches: usize,
    /// χ² threshold (2 dof, 99%) of a reprojection inlier, at the keypoint's octave
    /// (`e² / σ² <= 9.21`, `σ = scale_factor^octave` pixels, the scale of each keyframe's
    /// features, [`crate::features::OrbFeatures::scale`]), tested in both images.
    pub chi2: f64,
    /// RANSAC confidence of drawing one all-inlier 3-point sample.
    pub confidence: f64,
    /// Largest number of RANSAC iterations (ORB-SLAM: 300).
    pub max_iterations: usize,
    /// RANSAC inliers needed to go on (ORB-SLAM: 20).
    pub min_ransac_inliers: usize,
    /// LM refinement of the similarity.
    pub refine: RefineParams,
    /// Inliers needed after refinement (ORB-SLAM: 20).
    pub min_refined_inliers: usize,
    /// Guided matching radius at octave 0, pixels (ORB-SLAM: 10), times
    /// `scale_factor^octave` of the projected point's keypoint (the query's pyramid scale).
    pub guided_radius_px: f32,
    /// Largest Hamming distance of a guided match (ORB-SLAM: [`TH_LOW`]).
    pub guided_max_distance: u32,
    /// Total matches (refined inliers + guided matches) to accept the loop (ORB-SLAM: 40).
    pub min_inliers: usize,
    /// Seed of the RANSAC sampler (runs are reproducible).
    pub seed: u64,
    /// When not 0, match the query's points against the points of the candidate and its
    /// best covisible keyframes, this many keyframes in all ([`match_neighbourhood`], brute
    /// force), instead of the candidate keyframe's own points: used for merges, where the
    /// two sessions' keyframes hold different subsets of the scene's points. A larger
    /// window holds more look-alikes of each point (a checkerboard's corners), which the
    /// ratio test then refuses.
    pub window_keyframes: usize,
    /// Repeated structure test: the verification is refused when a RANSAC hypothesis that
    /// puts the candidate's camera elsewhere (by more than 5% of the query points' median
    /// depth) has at least this fraction of the best one's inliers, e.g. a checkerboard
    /// matched one square off. `INFINITY` turns it off; when on, RANSAC runs all
    /// `max_iterations`.
    pub rival_ratio: f32,
}

/// A rival hypothesis is "elsewhere" when the candidate's camera centre moves by more than
/// this fraction of the query points' median depth.
const RIVAL_DISTANCE_OF_DEPTH: f64 = 0.05;

/// Largest change of the scale (|ln|) the reprojection refinement may make to the 3D-3D
/// estimate (×/÷ 1.25).
const MAX_REFINE_LOG_SCALE: f64 = 0.223;

impl Default for Sim3Params {
    fn default() -> Self {
        Self {
            max_distance: TH_LOW,
            ratio: 0.75,
            min_matches: 20,
            chi2: 9.21,
            confidence: 0.99,
            max_iterations: 300,
            min_ransac_inliers: 20,
            refine: RefineParams::default(),
            min_refined_inliers: 20,
            guided_radius_px: 10.0,
            guided_max_distance: TH_LOW,
            min_inliers: 40,
            seed: 0x005e_ed1c,
            window_keyframes: 0,
            rival_ratio: f32::INFINITY,
        }
    }
}

/// A verified similarity between two keyframes ([`compute_sim3`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Sim3Result {
    /// `p_q = s_qm.transform_point(p_m)`: matched keyframe's camera frame → query's.
    pub s_qm: Sim3,
    /// Inlier pairs of server points (query side, matched side): refined descriptor
    /// matches, then guided matches of query keypoints that have a point.
    pub point_pairs: Vec<(PointId, PointId)>,
    /// Guided matches of query keypoints without a point: (keypoint, matched-side point).
    pub extra_observations: Vec<(u32, PointId)>,
    /// Putative descriptor matches between the two keyframes' points.
    pub matches: usize,
    /// Inliers of the best RANSAC hypothesis.
    pub ransac_inliers: usize,
    /// Inliers after refinement (two-way χ² test).
    pub refined_inliers: usize,
    /// `refined_inliers` + guided matches: the support compared with
    /// [`Sim3Params::min_inliers`].
    pub inliers: usize,
}

/// Both reprojections of `c` under `s` (and its inverse) pass the χ² test.
#[inline]
fn is_inlier(
    s: &Sim3,
    s_inv: &Sim3,
    c: &Sim3Correspondence,
    chi2: f64,
    cam_q: &PinholeRadtan,
    cam_m: &PinholeRadtan,
) -> bool {
    let ok = |cam: &PinholeRadtan, p: Vector3<f64>, uv: &Vector2<f64>, w: f64| {
        cam.project(&p)
            .is_some_and(|x| (x - uv).norm_squared() * w <= chi2)
    };
    ok(cam_q, s.transform_point(&c.p_m), &c.uv_q, c.inv_sigma2_q)
        && ok(
            cam_m,
            s_inv.transform_point(&c.p_q),
            &c.uv_m,
            c.inv_sigma2_m,
        )
}

/// Marks the inliers of `s` in `mask`; returns their number.
fn classify(
    s: &Sim3,
    corrs: &[Sim3Correspondence],
    chi2: f64,
    cam_q: &PinholeRadtan,
    cam_m: &PinholeRadtan,
    mask: &mut [bool],
) -> usize {
    let s_inv = s.inverse();
    let mut n = 0;
    for (c, m) in corrs.iter().zip(mask.iter_mut()) {
        *m = is_inlier(s, &s_inv, c, chi2, cam_q, cam_m);
        n += usize::from(*m);
    }
    n
}

/// A finite similarity with a positive scale.
fn valid(s: &Sim3) -> bool {
    s.s.is_finite()
        && s.s > 0.0
        && s.t.iter().all(|v| v.is_finite())
        && s.r.coords.iter().all(|v| v.is_finite())
}

/// Umeyama similarity `p_q ≈ S p_m` of the correspondences `idx` (stack only for 3).
fn umeyama_sim3(corrs: &[Sim3Correspondence], idx: impl Iterator<Item = usize>) -> Option<Sim3> {
    let (src, dst): (Vec<_>, Vec<_>) = idx.map(|i| (corrs[i].p_m, corrs[i].p_q)).unzip();
    let sim = umeyama(&src, &dst, true).ok()?;
    let s = Sim3::new(
        UnitQuaternion::from_rotation_matrix(&sim.rotation),
        sim.translation,
        sim.scale,
    );
    valid(&s).then_some(s)
}

/// The RANSAC loop: best hypothesis and its inlier count.
fn ransac(
    corrs: &[Sim3Correspondence],
    cam_q: &PinholeRadtan,
    cam_m: &PinholeRadtan,
    p: &Sim3Params,
) -> Option<(Sim3, usize, usize)> {
    let n = corrs.len();
    let mut rng = SplitMix64::new(p.seed);
    let mut sample = [0usize; 3];
    let mut best: Option<(Sim3, usize)> = None;
    let rivals = p.rival_ratio.is_finite();
    let mut tried: Vec<(Vector3<f64>, usize)> = Vec::new();
    let mut needed = p.max_iterations.max(1);
    let mut it = 0;
    while it < needed {
        it += 1;
        if !sample_distinct(&mut rng, n, &mut sample) {
            return None;
        }
        let src = sample.map(|i| corrs[i].p_m);
        let dst = sample.map(|i| corrs[i].p_q);
        let Ok(sim) = umeyama(&src, &dst, true) else {
            continue;
        };
        let s = Sim3::new(
            UnitQuaternion::from_rotation_matrix(&sim.rotation),
            sim.translation,
            sim.scale,
        );
        if !valid(&s) {
            continue;
        }
        let s_inv = s.inverse();
        let count = corrs
            .iter()
            .filter(|c| is_inlier(&s, &s_inv, c, p.chi2, cam_q, cam_m))
            .count();
        if rivals {
            tried.push((s_inv.t, count));
        }
        if best.is_none_or(|b| count > b.1) {
            best = Some((s, count));
            if !rivals {
                needed =
                    adaptive_iterations(count as f64 / n as f64, 3, p.confidence, p.max_iterations);
            }
        }
    }
    let (s, count) = best?;
    Some((s, count, best_rival(corrs, &s, &tried)))
}

/// The most inliers of a hypothesis in `tried` (the query camera's centre in `m`'s frame,
/// inliers) that puts the query camera farther than [`RIVAL_DISTANCE_OF_DEPTH`] of the
/// median query depth (in `m`'s units) from where `best` puts it.
fn best_rival(corrs: &[Sim3Correspondence], best: &Sim3, tried: &[(Vector3<f64>, usize)]) -> usize {
    if tried.is_empty() {
        return 0;
    }
    let mut depths: Vec<f64> = corrs.iter().map(|c| c.p_q.norm()).collect();
    depths.sort_unstable_by(f64::total_cmp);
    let median_m = depths[depths.len() / 2] / best.s;
    let centre = best.inverse().t;
    tried
        .iter()
        .filter(|(c, _)| (c - centre).norm() > RIVAL_DISTANCE_OF_DEPTH * median_m)
        .map(|e| e.1)
        .max()
        .unwrap_or(0)
}

/// Correspondences and their (query point, matched point, query keypoint) ids.
type Correspondences = (Vec<Sim3Correspondence>, Vec<(PointId, PointId, u32)>);

/// The correspondence of query point `iq` with a point at `p_m` in `m`'s frame, observed in
/// `m` at keypoint `km` (`None`: not observed in `m`, so only its reprojection into the
/// query is tested: weight 0 on `m`'s side). `None` when not finite.
fn correspondence(
    q: &KeptKeyframe,
    iq: usize,
    m: &KeptKeyframe,
    p_m: Vector3<f64>,
    km: Option<usize>,
) -> Option<Sim3Correspondence> {
    let pq = q.points.get(iq)?;
    let kq = q.features.keypoints.get(pq.keypoint as usize)?;
    let (uv_m, inv_sigma2_m) = match km.and_then(|k| m.features.keypoints.get(k)) {
        Some(k) => (
            Vector2::new(f64::from(k.x), f64::from(k.y)),
            m.features.scale.inv_sigma2(k.octave),
        ),
        None => (Vector2::zeros(), 0.0),
    };
    let c = Sim3Correspondence {
        p_q: pq.p_k,
        p_m,
        uv_q: Vector2::new(f64::from(kq.x), f64::from(kq.y)),
        uv_m,
        inv_sigma2_q: q.features.scale.inv_sigma2(kq.octave),
        inv_sigma2_m,
    };
    let finite = c.p_q.iter().chain(c.p_m.iter()).chain(c.uv_q.iter());
    finite.copied().all(f64::is_finite).then_some(c)
}

/// Correspondences from descriptor matches between the two keyframes' points.
fn keyframe_correspondences(
    q: &KeptKeyframe,
    m: &KeptKeyframe,
    guides: Option<(&FeatureVector, &FeatureVector)>,
    params: &Sim3Params,
) -> Correspondences {
    let matches = match_kept_points(q, m, guides, params.max_distance, params.ratio);
    let mut out = (Vec::with_capacity(matches.len()), Vec::new());
    for pm in &matches {
        if let Some(pmm) = m.points.get(pm.m as usize) {
            let matched = (pmm.point, pmm.p_k, Some(pmm.keypoint as usize));
            push_correspondence(&mut out, q, pm.q as usize, m, matched);
        }
    }
    out
}

/// Appends the correspondence of query point `iq` with the matched point `(id, p_m, its
/// keypoint in m)` and their ids, when it is finite ([`correspondence`]).
fn push_correspondence(
    out: &mut Correspondences,
    q: &KeptKeyframe,
    iq: usize,
    m: &KeptKeyframe,
    (point, p_m, km): (PointId, Vector3<f64>, Option<usize>),
) {
    if let Some(c) = correspondence(q, iq, m, p_m, km) {
        let pq = &q.points[iq];
        out.0.push(c);
        out.1.push((pq.point, point, pq.keypoint));
    }
}

/// Correspondences from descriptor matches of the query's points against `m`'s
/// neighbourhood ([`match_neighbourhood`]).
fn neighbourhood_correspondences(
    q: &KeptKeyframe,
    m: &KeptKeyframe,
    neighbourhood: &[NeighbourhoodPoint],
    params: &Sim3Params,
) -> Correspondences {
    let matches = match_neighbourhood(
        q,
        neighbourhood,
        params.window_keyframes,
        params.max_distance,
        params.ratio,
    );
    let keypoint_in_m: std::collections::HashMap<PointId, usize> = m
        .points
        .iter()
        .map(|p| (p.point, p.keypoint as usize))
        .collect();
    let mut out = (Vec::with_capacity(matches.len()), Vec::new());
    for pm in &matches {
        let np = &neighbourhood[pm.m as usize];
        let matched = (np.point, np.p_m, keypoint_in_m.get(&np.point).copied());
        push_correspondence(&mut out, q, pm.q as usize, m, matched);
    }
    out
}

/// Geometric verification of loop candidate `m` for query `q` (seed §3.4.2).
///
/// 1. Descriptor matches between the two keyframes' points ([`match_kept_points`]; guided
///    by vocabulary node when `guides = Some((fv_q, fv_m))`, brute force otherwise), or,
///    with [`Sim3Params::window_keyframes`], between the query's points and those of the
///    first keyframes of `neighbourhood` ([`match_neighbourhood`]; a point `m` does not observe is tested by
///    its reprojection into the query only).
/// 2. RANSAC over 3-point samples with [`umeyama`] (with scale), inliers when both
///    reprojections (`S p_m` into `q`, `S⁻¹ p_q` into `m`) pass `χ² <= chi2` at the
///    keypoints' octaves.
/// 3. Refinement ([`refine_sim3`]) on the RANSAC inliers, re-classification of all
///    matches, a second refinement on the new inliers.
/// 4. Guided matching: the points of `neighbourhood` (the points of `m` and its covisible
///    neighbours in `m`'s frame, see
///    [`neighbourhood_points`](super::neighbourhood_points)) not yet matched are projected
///    into `q` and matched by descriptor within a radius.
///
/// Returns `None` when any stage falls short of its threshold or on degenerate input
/// (fewer than 3 matches, non-finite points, zero scale); [`verify_sim3`] says which.
pub fn compute_sim3(
    q: &KeptKeyframe,
    m: &KeptKeyframe,
    guides: Option<(&FeatureVector, &FeatureVector)>,
    neighbourhood: &[NeighbourhoodPoint],
    params: &Sim3Params,
) -> Option<Sim3Result> {
    verify_sim3(q, m, guides, neighbourhood, params).ok()
}

/// The stage at which [`verify_sim3`] gave up, with the support it had reached.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sim3Reject {
    /// Fewer descriptor matches (with finite points) than [`Sim3Params::min_matches`].
    Matches(usize),
    /// RANSAC found no hypothesis, or fewer inliers than `min_ransac_inliers`: (matches,
    /// inliers).
    Ransac(usize, usize),
    /// The refinement failed, or left fewer than `min_refined_inliers`: (RANSAC inliers,
    /// refined inliers).
    Refined(usize, usize),
    /// Refined plus guided matches fewer than `min_inliers`: (refined, total).
    Inliers(usize, usize),
    /// A merge verified between the two keyframes but confirmed in only this many of the
    /// query's covisible keyframes ([`super::LoopDetectorParams::merge_confirmations`]).
    Unconfirmed(usize),
    /// Repeated structure ([`Sim3Params::rival_ratio`]): (best inliers, the best rival's).
    Ambiguous(usize, usize),
}

/// [`compute_sim3`], saying at which stage a rejected candidate failed.
pub fn verify_sim3(
    q: &KeptKeyframe,
    m: &KeptKeyframe,
    guides: Option<(&FeatureVector, &FeatureVector)>,
    neighbourhood: &[NeighbourhoodPoint],
    params: &Sim3Params,
) -> Result<Sim3Result, Sim3Reject> {
    let (corrs, ids) = if params.window_keyframes == 0 || neighbourhood.is_empty() {
        keyframe_correspondences(q, m, guides, params)
    } else {
        neighbourhood_correspondences(q, m, neighbourhood, params)
    };
    let n_matches = corrs.len();
    let (cam_q, cam_m) = (&q.camera, &m.camera);
    if corrs.len() < params.min_matches.max(3) {
        return Err(Sim3Reject::Matches(corrs.len()));
    }
    let (s_ransac, ransac_inliers, rival) =
        ransac(&corrs, cam_q, cam_m, params).ok_or(Sim3Reject::Ransac(corrs.len(), 0))?;
    if ransac_inliers < params.min_ransac_inliers.max(3) {
        return Err(Sim3Reject::Ransac(corrs.len(), ransac_inliers));
    }
    if rival as f32 >= params.rival_ratio * ransac_inliers as f32 {
        return Err(Sim3Reject::Ambiguous(ransac_inliers, rival));
    }
    let mut mask = vec![false; corrs.len()];
    classify(&s_ransac, &corrs, params.chi2, cam_q, cam_m, &mut mask);
    // Least squares on all RANSAC inliers as the refinement's start, if it is no worse.
    let mut s = s_ransac;
    if let Some(s_all) = umeyama_sim3(
        &corrs,
        mask.iter().enumerate().filter(|m| *m.1).map(|m| m.0),
    ) {
        let mut tmp = vec![false; corrs.len()];
        if classify(&s_all, &corrs, params.chi2, cam_q, cam_m, &mut tmp) >= ransac_inliers {
            s = s_all;
            mask = tmp;
        }
    }
    // Reprojection errors do not see the scale when the two cameras are (nearly) at the
    // same place (a similarity about the common centre moves no projection), so the
    // refinement may wander off in scale there: the 3D-3D estimate's scale bounds it.
    let (s_start, mask_start) = (s, mask.clone());
    for _ in 0..2 {
        let (refined, _) = refine_sim3(&s, &corrs, &mask, cam_q, cam_m, &params.refine)
            .ok_or(Sim3Reject::Refined(ransac_inliers, 0))?;
        s = refined;
        classify(&s, &corrs, params.chi2, cam_q, cam_m, &mut mask);
    }
    if !(s.s / s_start.s).is_finite() || (s.s / s_start.s).ln().abs() > MAX_REFINE_LOG_SCALE {
        s = s_start;
        mask = mask_start;
    }
    let refined_inliers = mask.iter().filter(|&&m| m).count();
    if refined_inliers < params.min_refined_inliers.max(3) {
        return Err(Sim3Reject::Refined(ransac_inliers, refined_inliers));
    }

    let mut point_pairs = Vec::with_capacity(refined_inliers + neighbourhood.len() / 4);
    let mut skip: HashSet<PointId> = q.points.iter().map(|p| p.point).collect();
    let mut q_taken = vec![false; q.features.keypoints.len()];
    for (&(pq, pm, kq), _) in ids.iter().zip(&mask).filter(|(_, &m)| m) {
        point_pairs.push((pq, pm));
        skip.insert(pm);
        if let Some(t) = q_taken.get_mut(kq as usize) {
            *t = true;
        }
    }
    let guided = guided_matches(
        q,
        &s,
        neighbourhood,
        &skip,
        &q_taken,
        params.guided_radius_px,
        params.guided_max_distance,
    );
    let mut q_point_of_kp = vec![None; q.features.keypoints.len()];
    for p in &q.points {
        if let Some(slot) = q_point_of_kp.get_mut(p.keypoint as usize) {
            *slot = Some(p.point);
        }
    }
    let mut extra_observations = Vec::new();
    for g in &guided {
        let Some(np) = neighbourhood.get(g.point as usize) else {
            continue;
        };
        match q_point_of_kp.get(g.q_keypoint as usize).copied().flatten() {
            Some(pq) => point_pairs.push((pq, np.point)),
            None => extra_observations.push((g.q_keypoint, np.point)),
        }
    }
    let inliers = refined_inliers + guided.len();
    if inliers < params.min_inliers {
        return Err(Sim3Reject::Inliers(refined_inliers, inliers));
    }
    Ok(Sim3Result {
        s_qm: s,
        point_pairs,
        extra_observations,
        matches: n_matches,
        ransac_inliers,
        refined_inliers,
        inliers,
    })
}

#[cfg(test)]
mod rival_tests {
    use super::*;

    /// Correspondences of points on a plane 4 m ahead: `n_true` seen where they are, and
    /// `n_shifted` whose query side is the point one "square" (0.4 m, 10% of the depth)
    /// sideways, as a repeated pattern matched one period off gives.
    fn corrs(n_true: usize, n_shifted: usize, cam: &PinholeRadtan) -> Vec<Sim3Correspondence> {
        let mut rng = SplitMix64::new(7);
        let mut out = Vec::new();
        for i in 0..n_true + n_shifted {
            let u = |r: &mut SplitMix64| (r.next_u64() % 10_000) as f64 / 10_000.0 - 0.5;
            let p_m = Vector3::new(3.0 * u(&mut rng), 2.0 * u(&mut rng), 4.0);
            let shift = if i < n_true { 0.0 } else { 0.4 };
            let p_q = p_m + Vector3::new(shift, 0.0, 0.0);
            out.push(Sim3Correspondence {
                p_q,
                p_m,
                uv_q: cam.project(&p_q).unwrap(),
                uv_m: cam.project(&p_m).unwrap(),
                inv_sigma2_q: 1.0,
                inv_sigma2_m: 1.0,
            });
        }
        out
    }

    #[test]
    fn a_pattern_matched_one_period_off_is_a_rival() {
        let cam = PinholeRadtan::pinhole(640, 480, 450.0, 450.0, 320.0, 240.0);
        let on = Sim3Params {
            rival_ratio: 0.7,
            ..Sim3Params::default()
        };
        // Two equally supported placements: the rival has as many inliers as the best.
        let (_, best, rival) = ransac(&corrs(40, 40, &cam), &cam, &cam, &on).unwrap();
        assert!(
            best >= 40 && rival as f32 >= 0.9 * best as f32,
            "{best} {rival}"
        );
        // One clear placement (a few stray one-off matches): no rival worth the name.
        let (s, best, rival) = ransac(&corrs(60, 8, &cam), &cam, &cam, &on).unwrap();
        assert!(
            best >= 60 && (rival as f32) < 0.7 * best as f32,
            "{best} {rival}"
        );
        assert!(s.t.norm() < 0.05 && (s.s - 1.0).abs() < 0.01);
        // Off: RANSAC stops early and reports no rival.
        let (_, _, rival) =
            ransac(&corrs(40, 40, &cam), &cam, &cam, &Sim3Params::default()).unwrap();
        assert_eq!(rival, 0);
    }
}
