//! Accuracy of a client's trajectories against the dataset's ground truth, for the run
//! report: [`AteReport`] after a named alignment (Sim(3), SE(3) or 4-DoF with the tilt
//! error, `slam_core::metrics`), and the top-view plot of the Sim(3) ones.
use std::path::Path;

use nalgebra::Isometry3;
use serde::Serialize;
use slam_core::metrics::{self, Alignment, EvalParams, EvalResult};

/// Absolute trajectory error after the alignment it names (as `shoal eval --align
/// <alignment>`).
#[derive(Debug, Clone, Default, Serialize)]
pub struct AteReport {
    /// Alignment of the estimate before the errors: `sim3` (rotation, translation, scale),
    /// `se3` (rotation, translation) or `4dof` (yaw about z, translation).
    pub alignment: String,
    /// Associated poses.
    pub n: usize,
    /// RMSE of the position error, m.
    pub rmse_m: f64,
    /// Largest position error, m.
    pub max_m: f64,
    /// Ground-truth path length over the associated poses, m.
    pub path_length_m: f64,
    /// RMSE in % of the path length.
    pub rmse_percent: f64,
    /// Scale of the alignment (monocular scale with `sim3`; 1 otherwise).
    pub scale: f64,
    /// RPE (translation part, between consecutive associated poses, after the alignment),
    /// RMSE, m: the figure of `shoal eval` with the same alignment.
    pub rpe_rmse_m: Option<f64>,
    /// Tilt (roll/pitch) error, RMSE over the associated poses, degrees: the angle between
    /// the true and the estimated gravity direction in the camera frame (`4dof` only).
    pub tilt_rmse_deg: Option<f64>,
    /// Largest tilt error, degrees (`4dof` only).
    pub tilt_max_deg: Option<f64>,
    /// Top-view plot written.
    pub plot: Option<String>,
}

/// A plot written beside an evaluation: its file, the first title line, and the run's loop
/// closures and merges (marked where they touch `client`'s keyframes).
pub(super) struct PlotSpec<'a> {
    path: std::path::PathBuf,
    title: String,
    client: u32,
    events: &'a [crate::plot::events::CorrectionEvent],
}

impl<'a> PlotSpec<'a> {
    /// `OUT/{name}_c{client}.png`, titled with the dataset, client and `name`.
    pub(super) fn new(
        out: &Path,
        ds: &datasets::Dataset,
        name: &str,
        client: usize,
        events: &'a [crate::plot::events::CorrectionEvent],
    ) -> Self {
        let dataset = ds.root.file_name().map_or_else(
            || ds.root.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        );
        Self {
            path: out.join(format!("{name}_c{client}.png")),
            title: format!("{dataset} / client {client} / {name}"),
            client: client as u32,
            events,
        }
    }
}

/// Stamps and poses (camera → map) of a recorded trajectory.
pub(super) fn split_wire(traj: &[(i64, shm_schema::Pose)]) -> (Vec<i64>, Vec<Isometry3<f64>>) {
    traj.iter()
        .map(|(t, p)| (*t, shoal_runtime::wire::iso_from_wire_unchecked(p)))
        .unzip()
}

/// Evaluates `traj` against the ground truth of `ds` (Sim(3) alignment) and plots it.
pub(super) fn evaluate_client(
    ds: &datasets::Dataset,
    traj: &[(i64, shm_schema::Pose)],
    plot: &PlotSpec,
) -> Option<AteReport> {
    let (est_t, est_p) = split_wire(traj);
    evaluate_poses(ds, &est_t, &est_p, Alignment::Sim3, Some(plot))
}

/// Evaluates the TUM trajectory file `path` like [`evaluate_client`].
pub(super) fn evaluate_file(
    ds: &datasets::Dataset,
    path: &Path,
    plot: &PlotSpec,
) -> Option<AteReport> {
    evaluate_file_aligned(ds, path, Alignment::Sim3, Some(plot))
}

/// Evaluates the TUM trajectory file `path` with `alignment` (and a plot if asked).
pub(super) fn evaluate_file_aligned(
    ds: &datasets::Dataset,
    path: &Path,
    alignment: Alignment,
    plot: Option<&PlotSpec>,
) -> Option<AteReport> {
    let traj = datasets::trajectory::read_tum(path).ok()?;
    let est_t: Vec<i64> = traj.poses.iter().map(|p| p.t_ns).collect();
    let est_p: Vec<_> = traj.poses.iter().map(|p| p.pose).collect();
    evaluate_poses(ds, &est_t, &est_p, alignment, plot)
}

/// Evaluates poses (camera → map) against the ground truth of `ds` after `alignment`, and
/// plots them when `plot` is given. `None` without ground truth, with fewer than 3 poses,
/// or when the evaluation fails (nothing associates, degenerate alignment).
pub(super) fn evaluate_poses(
    ds: &datasets::Dataset,
    est_t: &[i64],
    est_p: &[Isometry3<f64>],
    alignment: Alignment,
    plot: Option<&PlotSpec>,
) -> Option<AteReport> {
    let gt = ds.ground_truth.as_ref()?;
    if est_t.len() < 3 {
        return None;
    }
    let gt_t: Vec<i64> = gt.iter().map(|g| g.t_ns).collect();
    let gt_p: Vec<_> = gt.iter().map(|g| g.pose).collect();
    let params = EvalParams {
        alignment,
        ..Default::default()
    };
    let r = metrics::evaluate(&gt_t, &gt_p, est_t, est_p, &params).ok()?;
    let mut ate = AteReport::new(&r, alignment);
    if let Some(plot) = plot {
        ate.plot = plot_aligned(&r, est_t, est_p, &gt_p, &ate, plot);
    }
    Some(ate)
}

impl AteReport {
    /// The figures of an evaluation with `alignment` (no plot yet).
    fn new(r: &EvalResult, alignment: Alignment) -> Self {
        Self {
            alignment: alignment.name().to_string(),
            n: r.pairs.len(),
            rmse_m: r.ape.rmse,
            max_m: r.ape.max,
            path_length_m: r.ref_path_length_m,
            rmse_percent: 100.0 * r.ape.rmse / r.ref_path_length_m.max(1e-12),
            scale: r.alignment.scale,
            rpe_rmse_m: r.rpe.map(|e| e.rmse),
            tilt_rmse_deg: r.tilt_deg.map(|e| e.rmse),
            tilt_max_deg: r.tilt_deg.map(|e| e.max),
            plot: None,
        }
    }
}

/// Draws the aligned estimate of `r` over the ground truth into `plot.path`; the file
/// written, if any.
fn plot_aligned(
    r: &EvalResult,
    est_t: &[i64],
    est_p: &[Isometry3<f64>],
    gt_p: &[Isometry3<f64>],
    ate: &AteReport,
    plot: &PlotSpec,
) -> Option<String> {
    let aligned: Vec<_> = r
        .pairs
        .iter()
        .map(|(_, j)| r.alignment.transform_point(&est_p[*j].translation.vector))
        .collect();
    let gt_pts: Vec<_> = gt_p.iter().map(|g| g.translation.vector).collect();
    let mut timed: Vec<(i64, nalgebra::Vector3<f64>)> = r
        .pairs
        .iter()
        .zip(&aligned)
        .map(|((_, j), p)| (est_t[*j], *p))
        .collect();
    timed.sort_by_key(|p| p.0);
    let spec = crate::plot::TrajectoryPlot {
        title: plot.title.clone(),
        subtitle: format!(
            "ATE {:.3} m ({:.2}% of {:.1} m), {} poses, {}-aligned, scale {:.2}",
            ate.rmse_m, ate.rmse_percent, ate.path_length_m, ate.n, ate.alignment, ate.scale
        ),
        est: &aligned,
        gt: &gt_pts,
        marks: crate::plot::events::marks_for_client(plot.events, plot.client, &timed),
    };
    crate::plot::write_trajectory(&spec, &plot.path)
        .ok()
        .map(|_| plot.path.display().to_string())
}
