//! Trajectory metrics with the definitions of the widely used `evo` tool (evo_ape / evo_rpe
//! defaults), so that our figures can be compared with published ones:
//!
//! - **Association** ([`associate`]): the trajectory with fewer poses is walked in order; each
//!   of its stamps is matched to the nearest stamp of the other one (ties go to the earlier
//!   stamp) when `|Δt| <= max_diff` (default 0.01 s); unmatched poses are dropped. A pose of
//!   the longer trajectory may be matched twice. The optional offset is added to the
//!   estimate's stamps.
//! - **Alignment** ([`align`]): Umeyama over the associated positions (estimate → reference),
//!   rigid (`se3`, evo `-a`) or with scale (`sim3`, evo `-as`), applied to the estimate as
//!   `R R_i`, `s R p_i + t`. The 4-DoF alignment (`4dof`, [`align_yaw_translation`]: yaw
//!   about z + translation, for gravity-aligned visual-inertial trajectories) has no evo
//!   counterpart; it is checked by this module's unit tests only.
//! - **APE, translation part** ([`ape_translation`]): `e_i = |p_est,i - p_ref,i|`.
//! - **RPE, translation part, delta 1 frame** ([`rpe_translation`]): consecutive pairs
//!   `(i, i+δ)`, `i = 0, δ, 2δ, ...` (evo `--delta 1 --delta_unit f`, all_pairs off),
//!   `E_i = (Q_i⁻¹ Q_{i+δ})⁻¹ (P_i⁻¹ P_{i+δ})` with Q the reference and P the estimate,
//!   `e_i = |trans(E_i)|`.
//! - **Statistics** ([`ErrorStats`]): rmse, mean, median (mean of the two middle values for an
//!   even count), population std (ddof 0), min, max, sse.
//! - **Path length** ([`path_length`]): sum of the distances between consecutive positions.
//! - **Tilt (roll/pitch) error** ([`tilt_errors_deg`], not in evo): for camera-to-world poses
//!   in a z-up world, the angle between the true and the estimated gravity direction seen in
//!   the camera frame, `∠(R_wc,refᵀ e_z, R_wc,estᵀ e_z)`, in degrees. It ignores yaw and
//!   position, so it is what a gravity-aware system must keep small; [`evaluate`] gives it
//!   for the alignments that keep the estimate's z axis (none, 4-DoF).

use nalgebra::{Isometry3, Rotation3, Vector2, Vector3};

use crate::geometry::{umeyama, Similarity};
use crate::CoreError;

/// How the estimate is aligned to the reference before computing errors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Alignment {
    /// No alignment (evo without `-a`).
    #[default]
    None,
    /// Rigid alignment, rotation + translation (evo `-a`).
    Se3,
    /// Similarity alignment, rotation + translation + scale (evo `-as`), for monocular runs.
    Sim3,
    /// Yaw about the world z axis + translation, no scale ([`align_yaw_translation`]): the
    /// unobservable directions of a visual-inertial system whose world is gravity-aligned
    /// (z up). No evo counterpart.
    FourDof,
}

impl Alignment {
    /// The name used on the command line and in reports: `none`, `se3`, `sim3` or `4dof`.
    pub fn name(self) -> &'static str {
        match self {
            Alignment::None => "none",
            Alignment::Se3 => "se3",
            Alignment::Sim3 => "sim3",
            Alignment::FourDof => "4dof",
        }
    }

    /// Whether the alignment keeps the estimate's world z axis (identity or a yaw), so the
    /// tilt error ([`tilt_errors_deg`]) of the aligned estimate is meaningful.
    pub fn keeps_vertical(self) -> bool {
        matches!(self, Alignment::None | Alignment::FourDof)
    }
}

/// Timestamp association parameters (evo `--t_max_diff`, `--t_offset`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AssociationParams {
    /// Largest accepted |t_ref - t_est| in ns (evo default 0.01 s).
    pub max_diff_ns: i64,
    /// Offset added to the estimate's stamps before matching, ns.
    pub offset_ns: i64,
}

impl Default for AssociationParams {
    fn default() -> Self {
        Self {
            max_diff_ns: 10_000_000,
            offset_ns: 0,
        }
    }
}

/// Parameters of [`evaluate`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EvalParams {
    /// Alignment applied to the estimate.
    pub alignment: Alignment,
    /// Timestamp association.
    pub association: AssociationParams,
    /// RPE frame distance δ (evo `--delta`, unit frames); 1 by default.
    pub rpe_delta: usize,
}

impl Default for EvalParams {
    fn default() -> Self {
        Self {
            alignment: Alignment::None,
            association: AssociationParams::default(),
            rpe_delta: 1,
        }
    }
}

/// Summary statistics of a list of errors, as evo computes them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ErrorStats {
    /// sqrt(mean(e²)).
    pub rmse: f64,
    /// Mean.
    pub mean: f64,
    /// Median (mean of the two middle values for an even count).
    pub median: f64,
    /// Population standard deviation (ddof = 0).
    pub std: f64,
    /// Smallest error.
    pub min: f64,
    /// Largest error.
    pub max: f64,
    /// Sum of squared errors.
    pub sse: f64,
    /// Number of errors.
    pub count: usize,
}

impl ErrorStats {
    /// Statistics of `errors`; `None` when empty or when an error is not finite.
    pub fn from_errors(errors: &[f64]) -> Option<Self> {
        if errors.is_empty() || !errors.iter().all(|e| e.is_finite()) {
            return None;
        }
        let n = errors.len() as f64;
        let sse: f64 = errors.iter().map(|e| e * e).sum();
        let mean = errors.iter().sum::<f64>() / n;
        let var = errors.iter().map(|e| (e - mean) * (e - mean)).sum::<f64>() / n;
        let mut sorted = errors.to_vec();
        sorted.sort_by(f64::total_cmp);
        let m = sorted.len() / 2;
        let median = if sorted.len() % 2 == 1 {
            sorted[m]
        } else {
            0.5 * (sorted[m - 1] + sorted[m])
        };
        Some(Self {
            rmse: (sse / n).sqrt(),
            mean,
            median,
            std: var.sqrt(),
            min: sorted[0],
            max: sorted[sorted.len() - 1],
            sse,
            count: errors.len(),
        })
    }
}

/// Nearest match of `s` in `long` (shifted by `shift`) within `max_diff`; ties go to the
/// earlier index. `sorted` selects a binary search.
fn nearest(long: &[i64], shift: i64, s: i64, max_diff: i64, sorted: bool) -> Option<usize> {
    let diff = |j: usize| (i128::from(long[j]) + i128::from(shift) - i128::from(s)).abs();
    let best = if sorted {
        // First index whose stamp is > s; candidates are it and the one before.
        let hi = long.partition_point(|&x| i128::from(x) + i128::from(shift) <= i128::from(s));
        match (hi.checked_sub(1), (hi < long.len()).then_some(hi)) {
            (Some(lo), Some(hi)) => {
                if diff(hi) < diff(lo) {
                    hi
                } else {
                    lo
                }
            }
            (Some(lo), None) => lo,
            (None, Some(hi)) => hi,
            (None, None) => return None,
        }
    } else {
        let mut best: Option<usize> = None;
        for j in 0..long.len() {
            if best.is_none_or(|b| diff(j) < diff(b)) {
                best = Some(j);
            }
        }
        best?
    };
    (diff(best) <= i128::from(max_diff)).then_some(best)
}

/// evo's nearest-timestamp association. Returns `(reference index, estimate index)` pairs in
/// the order of the trajectory with fewer poses (the estimate when both have the same count).
pub fn associate(ref_t: &[i64], est_t: &[i64], params: &AssociationParams) -> Vec<(usize, usize)> {
    let est_longer = est_t.len() > ref_t.len();
    let (short, long, shift) = if est_longer {
        (ref_t, est_t, params.offset_ns)
    } else {
        (est_t, ref_t, -params.offset_ns)
    };
    let sorted = long.windows(2).all(|w| w[0] <= w[1]);
    let mut pairs = Vec::with_capacity(short.len());
    for (i, &s) in short.iter().enumerate() {
        if let Some(j) = nearest(long, shift, s, params.max_diff_ns, sorted) {
            pairs.push(if est_longer { (i, j) } else { (j, i) });
        }
    }
    pairs
}

/// Aligns the estimate's positions onto the reference's (index-aligned slices): Umeyama for
/// [`Alignment::Se3`] / [`Alignment::Sim3`], [`align_yaw_translation`] for
/// [`Alignment::FourDof`]. Returns the identity for [`Alignment::None`].
pub fn align(
    reference: &[Isometry3<f64>],
    estimate: &[Isometry3<f64>],
    alignment: Alignment,
) -> Result<Similarity, CoreError> {
    if reference.len() != estimate.len() {
        return Err(CoreError::InvalidArgument(format!(
            "align: {} reference poses but {} estimated poses",
            reference.len(),
            estimate.len()
        )));
    }
    let src: Vec<Vector3<f64>> = estimate.iter().map(|p| p.translation.vector).collect();
    let dst: Vec<Vector3<f64>> = reference.iter().map(|p| p.translation.vector).collect();
    match alignment {
        Alignment::None => Ok(Similarity::identity()),
        Alignment::Se3 => umeyama(&src, &dst, false),
        Alignment::Sim3 => umeyama(&src, &dst, true),
        Alignment::FourDof => align_yaw_translation(&src, &dst),
    }
}

/// Least-squares yaw (rotation about z) + translation taking `src` onto `dst`: minimises
/// `Σ |dst_i - (R_z(ψ) src_i + t)|²` in closed form. With both point sets centred
/// (`x_i = src_i - μ_src`, `y_i = dst_i - μ_dst`), only the xy parts depend on ψ and
/// `ψ = atan2(Σ (x_i × y_i)_z, Σ x_i,xy · y_i,xy)`; `t = μ_dst - R_z(ψ) μ_src`. Scale 1.
///
/// Errors: different lengths, fewer than 2 pairs, non-finite input, or no yaw information
/// (the xy cross-covariance vanishes: all points identical, or all on one vertical line).
pub fn align_yaw_translation(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
) -> Result<Similarity, CoreError> {
    if src.len() != dst.len() {
        return Err(CoreError::InvalidArgument(format!(
            "4-DoF alignment: {} source points but {} destination points",
            src.len(),
            dst.len()
        )));
    }
    if src.len() < 2 {
        return Err(CoreError::NotEnoughData(format!(
            "4-DoF alignment: {} point pairs",
            src.len()
        )));
    }
    if !src
        .iter()
        .chain(dst)
        .all(|p| p.iter().all(|v| v.is_finite()))
    {
        return Err(CoreError::InvalidArgument(
            "4-DoF alignment: non-finite points".into(),
        ));
    }
    let n = src.len() as f64;
    let mean_src = src.iter().sum::<Vector3<f64>>() / n;
    let mean_dst = dst.iter().sum::<Vector3<f64>>() / n;
    let (mut dot, mut cross, mut spread) = (0.0, 0.0, 0.0);
    for (x, y) in src.iter().zip(dst) {
        let x = (x - mean_src).xy();
        let y = (y - mean_dst).xy();
        dot += x.dot(&y);
        cross += x.perp(&y);
        spread += x.norm() * y.norm();
    }
    // |(dot, cross)| <= spread; (near) zero relative to it, there is no yaw to find.
    if Vector2::new(dot, cross).norm() <= 1e-12 * spread {
        return Err(CoreError::Degenerate(
            "4-DoF alignment: no horizontal spread to fix the yaw (points identical or \
             on one vertical line)"
                .into(),
        ));
    }
    let rotation = Rotation3::from_axis_angle(&Vector3::z_axis(), cross.atan2(dot));
    Ok(Similarity {
        rotation,
        translation: mean_dst - rotation * mean_src,
        scale: 1.0,
    })
}

/// Translation part of the absolute pose error per pose: `|p_est,i - p_ref,i|`.
pub fn ape_translation(reference: &[Isometry3<f64>], estimate: &[Isometry3<f64>]) -> Vec<f64> {
    reference
        .iter()
        .zip(estimate)
        .map(|(q, p)| (p.translation.vector - q.translation.vector).norm())
        .collect()
}

/// Translation part of the relative pose error over consecutive pairs `(i, i + delta)`,
/// `i = 0, delta, 2 delta, ...`: `|trans((Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j))|`. Empty when there are
/// fewer than two poses or `delta == 0`.
pub fn rpe_translation(
    reference: &[Isometry3<f64>],
    estimate: &[Isometry3<f64>],
    delta: usize,
) -> Vec<f64> {
    let n = reference.len().min(estimate.len());
    if delta == 0 {
        return Vec::new();
    }
    (0..n)
        .step_by(delta)
        .zip((delta..n).step_by(delta))
        .map(|(i, j)| {
            let q_rel = reference[i].inv_mul(&reference[j]);
            let p_rel = estimate[i].inv_mul(&estimate[j]);
            q_rel.inv_mul(&p_rel).translation.vector.norm()
        })
        .collect()
}

/// Tilt (roll/pitch) error per pose, degrees: for camera-to-world poses `T_wc` in a z-up
/// world, the angle between the gravity direction seen in the reference camera,
/// `R_wc,refᵀ e_z`, and in the estimated one, `R_wc,estᵀ e_z`. Blind to yaw and position;
/// pass the estimate after an alignment that keeps its z axis ([`Alignment::keeps_vertical`]).
pub fn tilt_errors_deg(reference: &[Isometry3<f64>], estimate: &[Isometry3<f64>]) -> Vec<f64> {
    reference
        .iter()
        .zip(estimate)
        .map(|(q, p)| {
            let up_c_ref = q.rotation.inverse_transform_vector(&Vector3::z());
            let up_c_est = p.rotation.inverse_transform_vector(&Vector3::z());
            up_c_ref
                .cross(&up_c_est)
                .norm()
                .atan2(up_c_ref.dot(&up_c_est))
                .to_degrees()
        })
        .collect()
}

/// Length of the path through the positions of `poses`, m.
pub fn path_length(poses: &[Isometry3<f64>]) -> f64 {
    poses
        .windows(2)
        .map(|w| (w[1].translation.vector - w[0].translation.vector).norm())
        .sum()
}

/// Everything [`evaluate`] computes.
#[derive(Debug, Clone, PartialEq)]
pub struct EvalResult {
    /// Associated `(reference index, estimate index)` pairs, in evaluation order.
    pub pairs: Vec<(usize, usize)>,
    /// The alignment applied to the estimate (identity for [`Alignment::None`]).
    pub alignment: Similarity,
    /// APE (translation part) statistics, m.
    pub ape: ErrorStats,
    /// Per-pair APE, m, in the order of [`EvalResult::pairs`].
    pub ape_errors: Vec<f64>,
    /// RPE (translation part) statistics, m (`None` with fewer than two pairs).
    pub rpe: Option<ErrorStats>,
    /// Tilt (roll/pitch) error statistics of the aligned estimate, degrees
    /// ([`tilt_errors_deg`]); `None` unless the alignment keeps the z axis (none, 4-DoF).
    pub tilt_deg: Option<ErrorStats>,
    /// Path length of the associated reference poses, m.
    pub ref_path_length_m: f64,
}

/// Associates by timestamp, aligns, and computes APE / RPE / path length.
/// Errors when nothing associates or the alignment is degenerate.
pub fn evaluate(
    ref_t: &[i64],
    reference: &[Isometry3<f64>],
    est_t: &[i64],
    estimate: &[Isometry3<f64>],
    params: &EvalParams,
) -> Result<EvalResult, CoreError> {
    if ref_t.len() != reference.len() || est_t.len() != estimate.len() {
        return Err(CoreError::InvalidArgument(
            "evaluate: stamps and poses differ in length".into(),
        ));
    }
    let pairs = associate(ref_t, est_t, &params.association);
    if pairs.is_empty() {
        return Err(CoreError::NotEnoughData(format!(
            "no matching timestamps between reference ({} poses) and estimate ({} poses) \
             with max diff {} s",
            reference.len(),
            estimate.len(),
            params.association.max_diff_ns as f64 * 1e-9
        )));
    }
    evaluate_pairs(reference, estimate, pairs, params)
}

/// Like [`evaluate`] for trajectories without timestamps, associated by index (evo's
/// `kitti` mode): both must have the same number of poses.
pub fn evaluate_by_index(
    reference: &[Isometry3<f64>],
    estimate: &[Isometry3<f64>],
    params: &EvalParams,
) -> Result<EvalResult, CoreError> {
    if reference.len() != estimate.len() {
        return Err(CoreError::InvalidArgument(format!(
            "index association needs equal lengths: reference {} poses, estimate {} poses",
            reference.len(),
            estimate.len()
        )));
    }
    evaluate_pairs(
        reference,
        estimate,
        (0..reference.len()).map(|i| (i, i)).collect(),
        params,
    )
}

fn evaluate_pairs(
    reference: &[Isometry3<f64>],
    estimate: &[Isometry3<f64>],
    pairs: Vec<(usize, usize)>,
    params: &EvalParams,
) -> Result<EvalResult, CoreError> {
    let mut q = Vec::with_capacity(pairs.len());
    let mut p = Vec::with_capacity(pairs.len());
    for &(i, j) in &pairs {
        match (reference.get(i), estimate.get(j)) {
            (Some(a), Some(b)) => {
                q.push(*a);
                p.push(*b);
            }
            _ => return Err(CoreError::InvalidArgument("pair index out of range".into())),
        }
    }
    let sim = align(&q, &p, params.alignment)?;
    if params.alignment != Alignment::None {
        for pose in &mut p {
            *pose = sim.transform_pose(pose);
        }
    }
    let ape_errors = ape_translation(&q, &p);
    let ape = ErrorStats::from_errors(&ape_errors)
        .ok_or_else(|| CoreError::InvalidArgument("non-finite poses".into()))?;
    let rpe = ErrorStats::from_errors(&rpe_translation(&q, &p, params.rpe_delta));
    let tilt_deg = if params.alignment.keeps_vertical() {
        ErrorStats::from_errors(&tilt_errors_deg(&q, &p))
    } else {
        None
    };
    Ok(EvalResult {
        pairs,
        alignment: sim,
        ape,
        ape_errors,
        rpe,
        tilt_deg,
        ref_path_length_m: path_length(&q),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};
    use std::f64::consts::PI;

    fn helix(n: usize) -> Vec<Isometry3<f64>> {
        (0..n)
            .map(|i| {
                let a = i as f64 * 0.1;
                Isometry3::from_parts(
                    Translation3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.2 * a),
                    UnitQuaternion::from_scaled_axis(Vector3::new(0.05 * a, 0.0, a)),
                )
            })
            .collect()
    }

    #[test]
    fn stats_known_values() {
        let s = ErrorStats::from_errors(&[1.0, 2.0, 3.0, 4.0]).expect("stats");
        assert_eq!(s.median, 2.5);
        assert_eq!(s.mean, 2.5);
        assert_eq!(s.sse, 30.0);
        assert!((s.rmse - 7.5f64.sqrt()).abs() < 1e-15);
        assert!((s.std - 1.25f64.sqrt()).abs() < 1e-15);
        assert_eq!((s.min, s.max, s.count), (1.0, 4.0, 4));
        assert_eq!(
            ErrorStats::from_errors(&[3.0, 1.0, 2.0])
                .expect("stats")
                .median,
            2.0
        );
        assert!(ErrorStats::from_errors(&[]).is_none());
        assert!(ErrorStats::from_errors(&[f64::NAN]).is_none());
    }

    #[test]
    fn association_like_evo() {
        let p = AssociationParams::default();
        let r = [0, 100_000_000, 200_000_000, 300_000_000];
        let e = [5_000_000, 104_000_000, 250_000_000];
        // est shorter: walk est; 250 ms is 50 ms from both neighbours -> unmatched.
        assert_eq!(associate(&r, &e, &p), vec![(0, 0), (1, 1)]);
        // Tie goes to the earlier stamp.
        let p2 = AssociationParams {
            max_diff_ns: 60_000_000,
            offset_ns: 0,
        };
        assert_eq!(associate(&r, &e, &p2), vec![(0, 0), (1, 1), (2, 2)]);
        // est longer: walk the reference, a stamp of the estimate may be used twice.
        let e2 = [0, 1, 2, 3, 4];
        let r2 = [2, 2];
        assert_eq!(associate(&r2, &e2, &p), vec![(0, 2), (1, 2)]);
        // Offset is added to the estimate.
        let po = AssociationParams {
            max_diff_ns: 1,
            offset_ns: 1000,
        };
        assert_eq!(
            associate(&[1000, 2000], &[0, 1000], &po),
            vec![(0, 0), (1, 1)]
        );
        // Unsorted long trajectory: linear search gives the same answer.
        assert_eq!(
            associate(&[300, 100, 200], &[101, 199], &p),
            vec![(1, 0), (2, 1)]
        );
    }

    #[test]
    fn sim3_removes_scale_rotation_translation() {
        let gt = helix(50);
        let sim = Similarity {
            rotation: Rotation3::from_scaled_axis(Vector3::new(0.4, -0.3, 0.9)),
            translation: Vector3::new(5.0, -1.0, 2.0),
            scale: 0.37,
        };
        let est: Vec<_> = gt.iter().map(|p| sim.transform_pose(p)).collect();
        let t: Vec<i64> = (0..50).map(|i| i * 50_000_000).collect();
        let mut params = EvalParams {
            alignment: Alignment::Sim3,
            ..Default::default()
        };
        let r = evaluate(&t, &gt, &t, &est, &params).expect("eval");
        assert!(r.ape.rmse < 1e-9, "sim3 rmse {}", r.ape.rmse);
        assert!(r.rpe.expect("rpe").rmse < 1e-9);
        assert!((r.alignment.scale - 1.0 / 0.37).abs() < 1e-9);
        params.alignment = Alignment::Se3;
        let r = evaluate(&t, &gt, &t, &est, &params).expect("eval");
        assert!(
            r.ape.rmse > 0.5,
            "se3 must not absorb scale: {}",
            r.ape.rmse
        );
        params.alignment = Alignment::None;
        let r = evaluate(&t, &gt, &t, &est, &params).expect("eval");
        assert!(r.ape.rmse > 1.0);
        assert!((r.ref_path_length_m - path_length(&gt)).abs() < 1e-12);
    }

    #[test]
    fn se3_removes_rigid_motion_and_rpe_is_invariant() {
        let gt = helix(30);
        let rigid = Similarity {
            rotation: Rotation3::from_scaled_axis(Vector3::new(0.1, 0.2, -0.3)),
            translation: Vector3::new(1.0, 2.0, 3.0),
            scale: 1.0,
        };
        let est: Vec<_> = gt.iter().map(|p| rigid.transform_pose(p)).collect();
        let params = EvalParams {
            alignment: Alignment::Se3,
            ..Default::default()
        };
        let r = evaluate_by_index(&gt, &est, &params).expect("eval");
        assert!(r.ape.rmse < 1e-9);
        // RPE is invariant to a global rigid motion even without alignment.
        let rpe = rpe_translation(&gt, &est, 1);
        assert_eq!(rpe.len(), 29);
        assert!(rpe.iter().all(|e| *e < 1e-9));
    }

    #[test]
    fn known_constant_offset() {
        // Estimate shifted by 0.1 m along x: APE = 0.1 everywhere, RPE = 0 without alignment.
        let gt = helix(10);
        let est: Vec<_> = gt
            .iter()
            .map(|p| {
                Isometry3::from_parts(Translation3::new(0.1, 0.0, 0.0) * p.translation, p.rotation)
            })
            .collect();
        let r = evaluate_by_index(&gt, &est, &EvalParams::default()).expect("eval");
        assert!((r.ape.mean - 0.1).abs() < 1e-12 && r.ape.std < 1e-12);
        assert!(r.rpe.expect("rpe").max < 1e-12);
        assert_eq!(rpe_translation(&gt, &est, 3).len(), 3);
        assert!(evaluate_by_index(&gt, &est[..5], &EvalParams::default()).is_err());
        assert!(evaluate(
            &[0],
            &gt[..1],
            &[1_000_000_000],
            &est[..1],
            &EvalParams::default()
        )
        .is_err());
    }

    /// `Σ |dst_i - (R_z(ψ) src_i + t(ψ))|²` with the best translation for that yaw.
    fn yaw_cost(src: &[Vector3<f64>], dst: &[Vector3<f64>], yaw: f64) -> f64 {
        let n = src.len() as f64;
        let r = Rotation3::from_axis_angle(&Vector3::z_axis(), yaw);
        let t = dst.iter().sum::<Vector3<f64>>() / n - r * (src.iter().sum::<Vector3<f64>>() / n);
        src.iter()
            .zip(dst)
            .map(|(x, y)| (r * x + t - y).norm_squared())
            .sum()
    }

    fn positions(poses: &[Isometry3<f64>]) -> Vec<Vector3<f64>> {
        poses.iter().map(|p| p.translation.vector).collect()
    }

    /// A yaw + translation is recovered exactly, and a yaw-only difference has no tilt.
    #[test]
    fn four_dof_recovers_yaw_and_translation() {
        let gt = helix(40);
        let yaw_shift = Similarity {
            rotation: Rotation3::from_axis_angle(&Vector3::z_axis(), 2.5),
            translation: Vector3::new(4.0, -2.0, 0.7),
            scale: 1.0,
        };
        let est: Vec<_> = gt.iter().map(|p| yaw_shift.transform_pose(p)).collect();
        let params = EvalParams {
            alignment: Alignment::FourDof,
            ..Default::default()
        };
        let r = evaluate_by_index(&gt, &est, &params).expect("eval");
        let back = r.alignment.compose(&yaw_shift);
        assert!(back.rotation.angle() < 1e-12 && back.translation.norm() < 1e-12);
        assert_eq!(r.alignment.scale, 1.0);
        assert!(r.ape.max < 1e-12, "ape {}", r.ape.max);
        let tilt = r.tilt_deg.expect("tilt with 4dof");
        assert!(tilt.max < 1e-6 && tilt.count == 40, "tilt {tilt:?}");
        // Without alignment the positions are off, the tilt is still zero.
        let r = evaluate_by_index(&gt, &est, &EvalParams::default()).expect("eval");
        assert!(r.ape.min > 1.0 && r.tilt_deg.expect("tilt").max < 1e-6);
        assert_eq!(Alignment::FourDof.name(), "4dof");
    }

    /// With a roll between the trajectories, the closed-form yaw is the least-squares one
    /// (brute force over the yaw, each with its best translation).
    #[test]
    fn four_dof_yaw_is_least_squares_under_roll() {
        let gt = helix(60);
        let tilted = Similarity {
            rotation: Rotation3::from_axis_angle(&Vector3::x_axis(), 0.08)
                * Rotation3::from_axis_angle(&Vector3::z_axis(), -1.1),
            translation: Vector3::new(0.3, 0.2, -0.1),
            scale: 1.0,
        };
        let src = positions(
            &gt.iter()
                .map(|p| tilted.transform_pose(p))
                .collect::<Vec<_>>(),
        );
        let dst = positions(&gt);
        let sim = align_yaw_translation(&src, &dst).expect("4dof");
        let m = sim.rotation.matrix();
        assert!((m[(2, 2)] - 1.0).abs() < 1e-15, "a rotation about z only");
        let yaw = m[(1, 0)].atan2(m[(0, 0)]);
        let steps = 20_000;
        let (best_yaw, best_cost) = (0..steps)
            .map(|k| {
                let y = -PI + 2.0 * PI * k as f64 / steps as f64;
                (y, yaw_cost(&src, &dst, y))
            })
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .expect("grid");
        let cost = yaw_cost(&src, &dst, yaw);
        assert!(
            cost <= best_cost + 1e-12,
            "closed form {cost} > grid {best_cost}"
        );
        assert!(
            (yaw - best_yaw).abs() < 2.0 * PI / steps as f64,
            "{yaw} vs {best_yaw}"
        );
        assert!((yaw - 1.1).abs() < 0.05, "near the true yaw: {yaw}");
        // The translation is the best one for that yaw.
        let aligned: Vec<_> = src.iter().map(|x| sim.transform_point(x)).collect();
        let residual_mean = aligned
            .iter()
            .zip(&dst)
            .map(|(a, b)| a - b)
            .sum::<Vector3<f64>>();
        assert!(residual_mean.norm() < 1e-9);
    }

    /// Too few poses, identical points or points on one vertical line give an error.
    #[test]
    fn four_dof_degenerate_inputs_are_errors() {
        let p = Vector3::new(1.0, 2.0, 3.0);
        assert!(matches!(
            align_yaw_translation(&[p], &[p]),
            Err(CoreError::NotEnoughData(_))
        ));
        assert!(align_yaw_translation(&[], &[]).is_err());
        assert!(matches!(
            align_yaw_translation(&[p; 5], &[p, p, p, p, 2.0 * p]),
            Err(CoreError::Degenerate(_))
        ));
        let vertical: Vec<_> = (0..5).map(|i| Vector3::new(1.0, 1.0, i as f64)).collect();
        assert!(matches!(
            align_yaw_translation(&vertical, &vertical),
            Err(CoreError::Degenerate(_))
        ));
        assert!(align_yaw_translation(&[p, 2.0 * p], &[p]).is_err());
        let nan = Vector3::new(f64::NAN, 0.0, 0.0);
        assert!(align_yaw_translation(&[p, nan], &[p, 2.0 * p]).is_err());
        let still = vec![Isometry3::translation(1.0, 2.0, 3.0); 4];
        let params = EvalParams {
            alignment: Alignment::FourDof,
            ..Default::default()
        };
        assert!(evaluate_by_index(&still, &still, &params).is_err());
        assert!(evaluate_by_index(&still[..1], &still[..1], &params).is_err());
    }

    /// A trajectory rolled by 2° about the world x axis has a 2° tilt error at every pose,
    /// whatever yaw the 4-DoF alignment picks; Se3/Sim3 give no tilt figure.
    #[test]
    fn tilt_of_a_known_roll() {
        let gt = helix(30);
        let roll = Similarity {
            rotation: Rotation3::from_axis_angle(&Vector3::x_axis(), 2f64.to_radians()),
            translation: Vector3::new(0.0, 0.5, 0.0),
            scale: 1.0,
        };
        let est: Vec<_> = gt.iter().map(|p| roll.transform_pose(p)).collect();
        let errors = tilt_errors_deg(&gt, &est);
        assert!(errors.iter().all(|e| (e - 2.0).abs() < 1e-9), "{errors:?}");
        let mut params = EvalParams {
            alignment: Alignment::FourDof,
            ..Default::default()
        };
        let t = evaluate_by_index(&gt, &est, &params)
            .expect("eval")
            .tilt_deg
            .expect("tilt");
        assert!((t.rmse - 2.0).abs() < 1e-9 && (t.max - 2.0).abs() < 1e-9 && t.count == 30);
        for a in [Alignment::Se3, Alignment::Sim3] {
            params.alignment = a;
            assert!(evaluate_by_index(&gt, &est, &params)
                .expect("eval")
                .tilt_deg
                .is_none());
        }
    }
}
