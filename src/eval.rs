//! `shoal eval`: trajectory accuracy of an estimate against ground truth, with the
//! definitions of the `evo` tool (see `slam_core::metrics`): timestamp association
//! (max diff 0.01 s), Umeyama alignment (none / se3 / sim3), APE and RPE (translation part,
//! delta 1 frame), and the ground truth's path length. For gravity-aligned (z up)
//! visual-inertial estimates, `--align 4dof` aligns yaw + translation only and adds the
//! tilt (roll/pitch) error; evo has neither, so `benches/evo_check.py` does not cover them
//! (`slam_core::metrics`' unit tests do).
//!
//! Both files may be TUM (`t tx ty tz qx qy qz qw`) or KITTI (12 numbers per line), detected
//! by column count. A KITTI file has no stamps: a `times.txt` beside it is used when the
//! other file is timestamped; two unstamped files (or one with the same pose count as the
//! other when no times file exists) are associated by index, like `evo_ape kitti`.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use datasets::trajectory::{read_kitti, read_trajectory, Trajectory, TrajectoryFormat};
use nalgebra::Isometry3;
use serde::Serialize;
use slam_core::metrics::{self, Alignment, AssociationParams, ErrorStats, EvalParams};

/// Alignment of the estimate before computing errors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Align {
    /// No alignment (evo without `-a`).
    None,
    /// Rotation + translation (evo `-a`).
    Se3,
    /// Rotation + translation + scale (evo `-as`), for monocular estimates.
    Sim3,
    /// Yaw about z + translation, for gravity-aligned visual-inertial estimates (no evo
    /// counterpart); adds the tilt (roll/pitch) error.
    #[value(name = "4dof")]
    #[serde(rename = "4dof")]
    FourDof,
}

impl From<Align> for Alignment {
    fn from(a: Align) -> Self {
        match a {
            Align::None => Alignment::None,
            Align::Se3 => Alignment::Se3,
            Align::Sim3 => Alignment::Sim3,
            Align::FourDof => Alignment::FourDof,
        }
    }
}

/// Arguments of `shoal eval`.
#[derive(Debug, Clone, clap::Args)]
pub struct EvalArgs {
    /// Estimated trajectory (TUM or KITTI format).
    #[arg(long)]
    pub est: PathBuf,
    /// Ground-truth trajectory (TUM or KITTI format).
    #[arg(long)]
    pub gt: PathBuf,
    /// Alignment of the estimate: none, se3 (evo -a), sim3 (evo -as) or 4dof (yaw +
    /// translation, for gravity-aligned visual-inertial estimates; adds the tilt error).
    #[arg(long, value_enum, default_value_t = Align::Sim3)]
    pub align: Align,
    /// Largest time difference (s) for associating poses (evo --t_max_diff).
    #[arg(long = "max-diff", default_value_t = 0.01)]
    pub max_diff_s: f64,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// Statistics of one error kind, in the unit of the field holding them (m, or degrees for
/// the tilt).
#[derive(Debug, Clone, Serialize)]
pub struct StatsReport {
    /// Root mean square.
    pub rmse: f64,
    /// Mean.
    pub mean: f64,
    /// Median.
    pub median: f64,
    /// Population standard deviation.
    pub std: f64,
    /// Minimum.
    pub min: f64,
    /// Maximum.
    pub max: f64,
    /// Sum of squares.
    pub sse: f64,
    /// Number of errors.
    pub count: usize,
}

impl From<ErrorStats> for StatsReport {
    fn from(s: ErrorStats) -> Self {
        Self {
            rmse: s.rmse,
            mean: s.mean,
            median: s.median,
            std: s.std,
            min: s.min,
            max: s.max,
            sse: s.sse,
            count: s.count,
        }
    }
}

/// The result of `shoal eval`.
#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    /// Estimate file.
    pub est: PathBuf,
    /// Ground-truth file.
    pub gt: PathBuf,
    /// Alignment used.
    pub align: Align,
    /// `timestamps` or `index`.
    pub association: String,
    /// Max association time difference, s.
    pub max_diff_s: f64,
    /// Poses read from the estimate.
    pub n_est: usize,
    /// Poses read from the ground truth.
    pub n_gt: usize,
    /// Associated pose pairs.
    pub n_associated: usize,
    /// Absolute trajectory error (APE, translation part), m.
    pub ate: StatsReport,
    /// Relative pose error (translation part, delta 1 frame), m; `None` with < 2 pairs.
    pub rpe: Option<StatsReport>,
    /// Tilt (roll/pitch) error, degrees: the angle between the true and the estimated
    /// gravity direction in the camera frame (poses camera-to-world, world z up). With
    /// `--align 4dof` or `none` only (a Se3/Sim3 alignment may tilt the estimate).
    pub tilt_deg: Option<StatsReport>,
    /// Alignment scale (1 unless sim3).
    pub scale: f64,
    /// Alignment rotation, row-major 3x3.
    pub rotation: [[f64; 3]; 3],
    /// Alignment translation, m.
    pub translation: [f64; 3],
    /// Path length of the associated ground-truth poses, m.
    pub path_length_m: f64,
    /// Path length of the whole ground-truth file, m.
    pub gt_path_length_m: f64,
    /// ATE rmse as a percentage of `path_length_m` (`None` for a zero-length path).
    pub ate_percent_of_path: Option<f64>,
    /// Lines skipped while reading (`file:line: kind: detail`).
    pub issues: Vec<String>,
}

fn read(path: &Path) -> anyhow::Result<Trajectory> {
    let t =
        read_trajectory(path).with_context(|| format!("reading trajectory {}", path.display()))?;
    if t.poses.is_empty() {
        let first = t.issues.first().map_or(String::new(), |i| {
            format!(
                " (first problem: {}:{}: {}: {})",
                i.path.display(),
                i.line,
                i.kind,
                i.detail
            )
        });
        bail!("{}: no valid poses{first}", path.display());
    }
    Ok(t)
}

/// A KITTI file re-read with the `times.txt` beside it, if there is one.
fn with_times(t: Trajectory, path: &Path) -> anyhow::Result<Trajectory> {
    if t.format != TrajectoryFormat::Kitti || t.timestamped {
        return Ok(t);
    }
    let times = path.parent().unwrap_or(Path::new(".")).join("times.txt");
    if !times.is_file() {
        return Ok(t);
    }
    read_kitti(path, Some(&times))
        .with_context(|| format!("reading {} with {}", path.display(), times.display()))
}

fn split(t: &Trajectory) -> (Vec<i64>, Vec<Isometry3<f64>>) {
    t.poses.iter().map(|p| (p.t_ns, p.pose)).unzip()
}

/// Reads both files, associates, aligns and computes the metrics.
pub fn run(args: &EvalArgs) -> anyhow::Result<EvalReport> {
    if !(args.max_diff_s.is_finite() && args.max_diff_s >= 0.0) {
        bail!(
            "--max-diff must be a non-negative number of seconds, got {}",
            args.max_diff_s
        );
    }
    let mut est = read(&args.est)?;
    let mut gt = read(&args.gt)?;
    if est.timestamped != gt.timestamped {
        est = with_times(est, &args.est)?;
        gt = with_times(gt, &args.gt)?;
    }
    let params = EvalParams {
        alignment: args.align.into(),
        association: AssociationParams {
            max_diff_ns: (args.max_diff_s * 1e9).round() as i64,
            offset_ns: 0,
        },
        rpe_delta: 1,
    };
    let (gt_t, gt_p) = split(&gt);
    let (est_t, est_p) = split(&est);
    let by_time = est.timestamped && gt.timestamped;
    if !by_time && est_p.len() != gt_p.len() {
        bail!(
            "{} has no time stamps (KITTI format, no times.txt beside it): index association needs \
             equal pose counts, but the estimate has {} poses and the ground truth {}",
            if est.timestamped { args.gt.display() } else { args.est.display() },
            est_p.len(),
            gt_p.len()
        );
    }
    let res = if by_time {
        metrics::evaluate(&gt_t, &gt_p, &est_t, &est_p, &params)
    } else {
        metrics::evaluate_by_index(&gt_p, &est_p, &params)
    }
    .with_context(|| {
        format!(
            "evaluating {} against {}",
            args.est.display(),
            args.gt.display()
        )
    })?;
    let m = res.alignment.rotation.matrix();
    let tr = res.alignment.translation;
    let issues = est
        .issues
        .iter()
        .chain(&gt.issues)
        .map(|i| format!("{}:{}: {}: {}", i.path.display(), i.line, i.kind, i.detail))
        .collect();
    Ok(EvalReport {
        est: args.est.clone(),
        gt: args.gt.clone(),
        align: args.align,
        association: if by_time { "timestamps" } else { "index" }.into(),
        max_diff_s: args.max_diff_s,
        n_est: est_p.len(),
        n_gt: gt_p.len(),
        n_associated: res.pairs.len(),
        ate: res.ape.into(),
        rpe: res.rpe.map(Into::into),
        tilt_deg: res.tilt_deg.map(Into::into),
        scale: res.alignment.scale,
        rotation: [0, 1, 2].map(|r| [m[(r, 0)], m[(r, 1)], m[(r, 2)]]),
        translation: [tr.x, tr.y, tr.z],
        path_length_m: res.ref_path_length_m,
        gt_path_length_m: metrics::path_length(&gt_p),
        ate_percent_of_path: (res.ref_path_length_m > 0.0)
            .then(|| 100.0 * res.ape.rmse / res.ref_path_length_m),
        issues,
    })
}

/// Renders the report as text (a table) or as one JSON object.
pub fn render(report: &EvalReport, json: bool) -> String {
    if json {
        return serde_json::to_string(report).unwrap_or_else(|e| format!("{{\"error\":\"{e}\"}}"));
    }
    let mut s = format!(
        "est: {}\ngt:  {}\nalignment: {} (scale {:.6}), association by {}: {} of {} est / {} gt poses\n",
        report.est.display(),
        report.gt.display(),
        Alignment::from(report.align).name(),
        report.scale,
        report.association,
        report.n_associated,
        report.n_est,
        report.n_gt
    );
    s += &format!(
        "{:<10}{:>12}{:>12}{:>12}{:>12}{:>12}{:>12}\n",
        "[m]", "rmse", "mean", "median", "std", "min", "max"
    );
    let mut row = |name: &str, st: &StatsReport| {
        s += &format!(
            "{:<10}{:>12.6}{:>12.6}{:>12.6}{:>12.6}{:>12.6}{:>12.6}\n",
            name, st.rmse, st.mean, st.median, st.std, st.min, st.max
        );
    };
    row("ATE", &report.ate);
    if let Some(r) = &report.rpe {
        row("RPE(1f)", r);
    }
    if let Some(t) = &report.tilt_deg {
        row("tilt[deg]", t);
    }
    s += &format!(
        "path length {:.3} m (associated gt; whole gt {:.3} m), ATE rmse = {}\n",
        report.path_length_m,
        report.gt_path_length_m,
        report
            .ate_percent_of_path
            .map_or("n/a".to_string(), |p| format!("{p:.3} % of path"))
    );
    if !report.issues.is_empty() {
        s += &format!("{} input lines skipped:\n", report.issues.len());
        for i in report.issues.iter().take(10) {
            s += &format!("  {i}\n");
        }
    }
    s
}

/// Prints the report to stdout (see [`render`]).
pub fn print(report: &EvalReport, json: bool) {
    println!("{}", render(report, json).trim_end());
}

#[cfg(test)]
mod tests {
    use super::*;
    use datasets::trajectory::{write_kitti, write_tum};
    use datasets::StampedPose;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    fn traj(n: usize, scale: f64, dt_ns: i64) -> Vec<StampedPose> {
        (0..n)
            .map(|i| {
                let a = i as f64 * 0.2;
                StampedPose {
                    t_ns: 1_000_000_000 + i as i64 * 100_000_000 + dt_ns,
                    pose: Isometry3::from_parts(
                        Translation3::from(Vector3::new(a.cos(), a.sin(), 0.1 * a) * scale),
                        UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.0, a)),
                    ),
                }
            })
            .collect()
    }

    #[test]
    fn tum_and_kitti_files() {
        let dir = tempfile::tempdir().expect("tmp");
        let gt_path = dir.path().join("gt.txt");
        let est_path = dir.path().join("est.txt");
        write_tum(&gt_path, &traj(40, 1.0, 0)).expect("gt");
        write_tum(&est_path, &traj(30, 0.5, 3_000_000)).expect("est");
        let mut args = EvalArgs {
            est: est_path.clone(),
            gt: gt_path.clone(),
            align: Align::Sim3,
            max_diff_s: 0.01,
            json: true,
        };
        let r = run(&args).expect("run");
        assert_eq!((r.n_associated, r.association.as_str()), (30, "timestamps"));
        assert!(r.ate.rmse < 1e-9 && (r.scale - 2.0).abs() < 1e-9);
        assert!(render(&r, true).starts_with('{'));
        args.align = Align::Se3;
        assert!(run(&args).expect("run").ate.rmse > 0.1);
        // KITTI without stamps against KITTI: by index.
        let k_gt = dir.path().join("k_gt.txt");
        let k_est = dir.path().join("k_est.txt");
        write_kitti(&k_gt, &traj(30, 1.0, 0)).expect("kgt");
        write_kitti(&k_est, &traj(30, 0.5, 0)).expect("kest");
        let r = run(&EvalArgs {
            est: k_est,
            gt: k_gt,
            align: Align::Sim3,
            max_diff_s: 0.01,
            json: false,
        })
        .expect("run");
        assert_eq!(r.association, "index");
        assert!(r.ate.rmse < 1e-9);
        assert!(render(&r, false).contains("ATE"));
        args.max_diff_s = f64::NAN;
        assert!(run(&args).is_err());
    }

    /// `--align 4dof` removes a yaw + translation, keeps a roll, and reports it as tilt.
    #[test]
    fn four_dof_reports_tilt() {
        use clap::ValueEnum;
        use nalgebra::Rotation3;
        use slam_core::geometry::Similarity;
        let dir = tempfile::tempdir().expect("tmp");
        let gt_path = dir.path().join("gt.txt");
        let est_path = dir.path().join("est.txt");
        let gt = traj(40, 1.0, 0);
        let moved = |roll_deg: f64| Similarity {
            rotation: Rotation3::from_axis_angle(&Vector3::x_axis(), roll_deg.to_radians())
                * Rotation3::from_axis_angle(&Vector3::z_axis(), 0.9),
            translation: Vector3::new(2.0, -1.0, 0.3),
            scale: 1.0,
        };
        let est_of = |sim: Similarity| -> Vec<StampedPose> {
            gt.iter()
                .map(|p| StampedPose {
                    t_ns: p.t_ns,
                    pose: sim.transform_pose(&p.pose),
                })
                .collect()
        };
        write_tum(&gt_path, &gt).expect("gt");
        write_tum(&est_path, &est_of(moved(0.0))).expect("est");
        let args = EvalArgs {
            est: est_path.clone(),
            gt: gt_path,
            align: Align::from_str("4dof", false).expect("4dof parses"),
            max_diff_s: 0.01,
            json: false,
        };
        let r = run(&args).expect("run");
        assert!(r.ate.rmse < 1e-9 && r.scale == 1.0, "{r:?}");
        assert!(r.tilt_deg.as_ref().expect("tilt").max < 1e-6);
        let text = render(&r, false);
        assert!(
            text.contains("alignment: 4dof") && text.contains("tilt[deg]"),
            "{text}"
        );
        assert!(render(&r, true).contains(r#""align":"4dof""#));
        write_tum(&est_path, &est_of(moved(3.0))).expect("est");
        let tilt = run(&args).expect("run").tilt_deg.expect("tilt");
        assert!((tilt.rmse - 3.0).abs() < 1e-6 && (tilt.max - 3.0).abs() < 1e-6);
        let sim3 = EvalArgs {
            align: Align::Sim3,
            ..args
        };
        assert!(run(&sim3).expect("run").tilt_deg.is_none());
    }
}
