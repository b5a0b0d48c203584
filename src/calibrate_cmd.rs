//! `shoal calibrate` (issue 18): replays a dataset through the pipeline with its tracker in
//! the calibration mode (camera and IMU through shared memory like every run), then writes
//! the estimate with its 1σ as the project's calibration file (`DIR/calibration.toml`, what
//! `shoal run --calib` reads) and in Kalibr's layout (`DIR/camchain-imucam.yaml`,
//! `DIR/imu.yaml`), prints a table and draws the convergence plot (`DIR/convergence.png`,
//! each parameter with ±3σ over time, after the seed's Fig. 4.5-4.6).
//!
//! Starting values: `--init FILE` (Kalibr's `camchain-imucam.yaml` or the project's file)
//! over the dataset's own, which for a dataset without a camera model is the reader's
//! generic guess. Parameters whose σ did not shrink to half the prior's are listed as not
//! converged, in the table and the file, instead of being offered as estimates.
use std::path::{Path, PathBuf};

use anyhow::Context;
use datasets::calibration::{CalibrationFile, SigmaSection};
use tracker::core::{CalibReport, CalibValues, Estimate, InitReport};

use crate::config::RunConfig;
use crate::launcher;
use crate::plot::convergence::{write_convergence, ConvergencePlot, Series};

/// Arguments of `shoal calibrate`.
#[derive(clap::Args, Debug)]
pub struct CalibrateArgs {
    /// Dataset folder: any layout `run` reads, AprilGrid detections
    /// (`cam0/<t_ns>.csv`, `imu0.csv`, `config.yaml`) or a GoPro clip.
    #[arg(long)]
    pub dataset: PathBuf,
    /// Starting values: Kalibr's `camchain-imucam.yaml` (`.yaml`) or the project's
    /// calibration file (`.toml`), over the dataset's own.
    #[arg(long, value_name = "FILE")]
    pub init: Option<PathBuf>,
    /// A calibration to compare with (same formats as `--init`): the table gives the
    /// differences and the plot draws its values. Never used by the estimator.
    #[arg(long, value_name = "FILE")]
    pub reference: Option<PathBuf>,
    /// Output folder (the run's outputs, the calibration files, the plot).
    #[arg(long)]
    pub out: PathBuf,
    /// Configuration file of the run (`shoal config --print`).
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Set one configuration key, e.g. `tracker.calib.focal_sigma_px=15` (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub sets: Vec<String>,
    /// Real-time replay at this speed factor (default: lock-step, deterministic).
    #[arg(long)]
    pub rate: Option<f64>,
    /// Replay at most this many frames.
    #[arg(long)]
    pub max_frames: Option<usize>,
    /// iceoryx2 resource prefix (isolates concurrent runs).
    #[arg(long)]
    pub ipc_prefix: Option<String>,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

/// Runs `shoal calibrate`.
pub fn run(args: &CalibrateArgs) -> anyhow::Result<()> {
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let ds = datasets::open(&args.dataset)?;
    let start = starting_file(&ds, args.init.as_deref())?;
    let init_path = args.out.join("start.toml");
    start.write(&init_path)?;
    let reference = args
        .reference
        .as_deref()
        .map(|p| read_any(&ds, p))
        .transpose()?;
    // A dataset without camera-IMU extrinsics and no --init: the tracker starts from the
    // dataset itself, so that it knows R_cb is not given and estimates it (`calib::init`).
    let new_device = args.init.is_none() && !ds.camera.t_bs_given;
    let cfg = run_config(args, (!new_device).then_some(init_path.as_path()))?;
    let rep = launcher::run(&cfg)?;
    let calib = rep
        .clients
        .first()
        .and_then(|c| c.calib.clone())
        .context("the tracker gave no calibration report")?;
    let Some(est) = calib.estimate.as_ref() else {
        anyhow::bail!(
            "the calibration filter never started ({} frames before it): {}",
            calib.frames_before_start,
            calib
                .last_refusal
                .as_deref()
                .unwrap_or("not enough IMU before the frames")
        );
    };
    let result = result_file(&start, est, &calib, &args.dataset);
    result.write(&args.out.join("calibration.toml"))?;
    datasets::kalibr::write(&result, &args.out)?;
    if datasets::kalibr::camera_of(&result).line_delay.is_none() && result.camera.readout_ns > 0.0 {
        eprintln!(
            "note: Kalibr's layout reads rows top to bottom only; camchain-imucam.yaml has this \
             {} camera's middle-line t_d and no line_delay (calibration.toml has t_r)",
            result
                .camera
                .readout_direction
                .as_deref()
                .unwrap_or("top-to-bottom")
        );
    }
    let log = cfg.out.join("calib_c0.csv");
    let plot = convergence_plot(&log, &args.dataset, reference.as_ref())?;
    write_convergence(&plot, &args.out.join("convergence.png"))?;
    print_table(&start, &result, &calib, reference.as_ref());
    println!(
        "wrote {0}/calibration.toml (shoal run --calib), {0}/camchain-imucam.yaml, {0}/imu.yaml, \
         {0}/convergence.png",
        args.out.display()
    );
    Ok(())
}

/// The run: the dataset in the calibration mode, starting from `init` (none: the dataset's
/// own values, extrinsics not given).
fn run_config(args: &CalibrateArgs, init: Option<&Path>) -> anyhow::Result<RunConfig> {
    let mut cfg = RunConfig::resolve(args.config.as_deref(), &args.sets)?;
    cfg.datasets = vec![args.dataset.clone()];
    cfg.calib = init.map(Path::to_path_buf).into_iter().collect();
    cfg.tracker.mode = tracker::ClientMode::Calib;
    cfg.out = args.out.clone();
    cfg.mode = shoal_runtime::ReplayMode::Lockstep;
    if let Some(r) = args.rate {
        anyhow::ensure!(r > 0.0, "--rate must be positive");
        cfg.mode = shoal_runtime::ReplayMode::Realtime;
        cfg.rate = r;
    }
    cfg.max_frames = args.max_frames.or(cfg.max_frames);
    if let Some(p) = &args.ipc_prefix {
        cfg.ipc_prefix = p.clone();
    }
    cfg.progress &= !args.quiet;
    cfg.validate()?;
    Ok(cfg)
}

/// The dataset's own calibration (camera, and its IMU file when it has one).
fn dataset_file(ds: &datasets::Dataset) -> anyhow::Result<CalibrationFile> {
    let imu = launcher::modes::dataset_imu(ds).transpose()?;
    Ok(CalibrationFile::from_dataset(
        &ds.camera,
        imu.as_ref().map(|(y, _)| y),
    ))
}

/// A calibration in either format over the dataset's own: Kalibr's camchain (`.yaml`,
/// `.yml`) fills the camera part, the project's file replaces everything.
fn read_any(ds: &datasets::Dataset, path: &Path) -> anyhow::Result<CalibrationFile> {
    let yaml = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("yaml") || e.eq_ignore_ascii_case("yml"));
    if yaml {
        let mut base = dataset_file(ds)?;
        datasets::kalibr::read_camchain_into(path, &mut base)?;
        Ok(base)
    } else {
        Ok(CalibrationFile::read(path)?)
    }
}

/// The starting calibration: `--init` over the dataset's own.
fn starting_file(ds: &datasets::Dataset, init: Option<&Path>) -> anyhow::Result<CalibrationFile> {
    let mut f = match init {
        Some(p) => read_any(ds, p)?,
        None => dataset_file(ds)?,
    };
    f.sigma = None;
    f.comment = Some(format!(
        "starting values of shoal calibrate on {} ({})",
        ds.root.display(),
        init.map_or("the dataset's own".to_string(), |p| p.display().to_string())
    ));
    Ok(f)
}

fn values<const N: usize>(e: &[Estimate; N]) -> [f64; N] {
    std::array::from_fn(|k| e[k].value)
}

fn sigmas<const N: usize>(e: &[Estimate; N]) -> [f64; N] {
    std::array::from_fn(|k| e[k].sigma)
}

fn rows<T: Copy + Default>(a: [T; 9]) -> [[T; 3]; 3] {
    std::array::from_fn(|r| std::array::from_fn(|c| a[3 * r + c]))
}

/// The estimate as a calibration file: `start` with every estimated value put in, their
/// 1σ, and the parameters that did not converge.
fn result_file(
    start: &CalibrationFile,
    e: &CalibValues,
    rep: &CalibReport,
    dataset: &Path,
) -> CalibrationFile {
    let mut f = start.clone();
    let c = &mut f.camera;
    c.intrinsics = values(&e.intrinsics);
    c.distortion = values(&e.distortion);
    c.time_offset_ns = e.t_d_ns.value;
    c.readout_ns = e.t_r_ns.value.max(0.0);
    c.t_bs = e.t_bs;
    let i = &mut f.imu;
    i.t_g = rows(values(&e.t_g));
    i.t_s = rows(values(&e.t_s));
    i.t_a = rows(values(&e.t_a));
    i.gyro_bias = values(&e.gyro_bias);
    i.accel_bias = values(&e.accel_bias);
    f.sigma = Some(SigmaSection {
        intrinsics: Some(sigmas(&e.intrinsics)),
        distortion: Some(sigmas(&e.distortion)),
        readout_ns: Some(e.t_r_ns.sigma),
        time_offset_ns: Some(e.t_d_ns.sigma),
        p_cb_m: Some(sigmas(&e.p_cb_m)),
        t_g: Some(rows(sigmas(&e.t_g))),
        t_s: Some(rows(sigmas(&e.t_s))),
        t_a: Some(rows(sigmas(&e.t_a))),
        gyro_bias: Some(sigmas(&e.gyro_bias)),
        accel_bias: Some(sigmas(&e.accel_bias)),
        not_converged: rep.not_converged.clone(),
    });
    keep_starting_values(&mut f, start, rep);
    f.comment = Some(format!(
        "shoal calibrate on {}: {} frames updated ({} start), {:.0} features per frame",
        dataset.display(),
        rep.frames_updated,
        rep.start.as_deref().unwrap_or("-"),
        rep.features_per_frame
    ));
    f
}

/// The parameters that did not converge get their starting values back (the file's
/// contract, `SigmaSection::not_converged`: a value the run did not determine is no
/// estimate). The start of `t_d` is the initialisation's when it ran; `R_cb` stays the
/// run's (from the initialisation, held fixed by the filter).
fn keep_starting_values(f: &mut CalibrationFile, start: &CalibrationFile, rep: &CalibReport) {
    let nc = |n: &str| rep.not_converged.iter().any(|x| x == n);
    for (k, n) in ["fx", "fy", "cx", "cy"].iter().enumerate() {
        if nc(n) {
            f.camera.intrinsics[k] = start.camera.intrinsics[k];
        }
    }
    for (k, n) in ["k1", "k2", "p1", "p2"].iter().enumerate() {
        if nc(n) {
            f.camera.distortion[k] = start.camera.distortion[k];
        }
    }
    if nc("t_d") {
        let init_ms = rep.init.as_ref().and_then(|i| i.t_d_ms).unwrap_or(0.0);
        f.camera.time_offset_ns = start.camera.time_offset_ns + init_ms * 1e6;
    }
    if nc("t_r") {
        f.camera.readout_ns = start.camera.readout_ns;
    }
    let (p0, mut p) = (p_cb(start), p_cb(f));
    for (k, n) in ["p_cb.x", "p_cb.y", "p_cb.z"].iter().enumerate() {
        if nc(n) {
            p[k] = p0[k];
        }
    }
    if let Ok(t) = datasets::calibration::isometry(&f.camera.t_bs) {
        let t_bs = -(t.rotation * nalgebra::Vector3::from(p));
        for (r, row) in f.camera.t_bs.iter_mut().enumerate().take(3) {
            row[3] = t_bs[r];
        }
    }
    for (n, m, m0) in [
        ("T_g", &mut f.imu.t_g, start.imu.t_g),
        ("T_s", &mut f.imu.t_s, start.imu.t_s),
        ("T_a", &mut f.imu.t_a, start.imu.t_a),
    ] {
        if nc(n) {
            *m = m0;
        }
    }
}

/// The lever arm `p_cb` (body origin in the camera) of a file's `T_BS`.
fn p_cb(f: &CalibrationFile) -> [f64; 3] {
    match datasets::calibration::isometry(&f.camera.t_bs) {
        Ok(t) => slam_core::calib::lever_arm_of_t_bs(&t).into(),
        Err(_) => [f64::NAN; 3],
    }
}

/// `(name [unit], value)` of every printed parameter of a file.
fn table_values(f: &CalibrationFile) -> Vec<(String, f64)> {
    let c = &f.camera;
    let p = p_cb(f);
    let mut v: Vec<(String, f64)> = [
        ("fx [px]", c.intrinsics[0]),
        ("fy [px]", c.intrinsics[1]),
        ("cx [px]", c.intrinsics[2]),
        ("cy [px]", c.intrinsics[3]),
        ("k1", c.distortion[0]),
        ("k2", c.distortion[1]),
        ("p1", c.distortion[2]),
        ("p2", c.distortion[3]),
        ("t_d [ms]", c.time_offset_ns * 1e-6),
        ("t_r [ms]", c.readout_ns * 1e-6),
        ("p_cb.x [mm]", p[0] * 1e3),
        ("p_cb.y [mm]", p[1] * 1e3),
        ("p_cb.z [mm]", p[2] * 1e3),
    ]
    .map(|(n, x)| (n.to_string(), x))
    .to_vec();
    let i = &f.imu;
    for (name, m) in [("T_g", &i.t_g), ("T_a", &i.t_a)] {
        for (k, axis) in ["xx", "yy", "zz"].iter().enumerate() {
            v.push((format!("{name}.{axis}"), m[k][k]));
        }
    }
    v
}

/// The 1σ of the printed parameters, in the table's units and order.
fn table_sigmas(e: &CalibValues) -> Vec<f64> {
    let mut s: Vec<f64> = sigmas(&e.intrinsics).to_vec();
    s.extend(sigmas(&e.distortion));
    s.push(e.t_d_ns.sigma * 1e-6);
    s.push(e.t_r_ns.sigma * 1e-6);
    s.extend(sigmas(&e.p_cb_m).map(|x| x * 1e3));
    s.extend([e.t_g[0], e.t_g[4], e.t_g[8], e.t_a[0], e.t_a[4], e.t_a[8]].map(|x| x.sigma));
    s
}

/// Prints start, estimate ± 1σ (and the reference and difference), marking the parameters
/// that did not converge.
fn print_table(
    start: &CalibrationFile,
    result: &CalibrationFile,
    rep: &CalibReport,
    reference: Option<&CalibrationFile>,
) {
    let (s, r) = (table_values(start), table_values(result));
    let sig = rep.estimate.as_ref().map(table_sigmas).unwrap_or_default();
    let refv = reference.map(table_values);
    println!(
        "{:<12} {:>13} {:>13} {:>10} {:>13} {:>10}",
        "parameter", "start", "estimate", "1σ", "reference", "est - ref"
    );
    for (k, ((name, start_v), (_, est))) in s.iter().zip(&r).enumerate() {
        let base = name.split(' ').next().unwrap_or(name);
        let base = base.trim_end_matches(".xx").trim_end_matches(".yy");
        let nc = rep
            .not_converged
            .iter()
            .any(|n| n == base.trim_end_matches(".zz"));
        let (rv, diff) = refv.as_ref().map_or((String::new(), String::new()), |v| {
            (format!("{:.4}", v[k].1), format!("{:+.4}", est - v[k].1))
        });
        println!(
            "{name:<12} {start_v:>13.4} {est:>13.4} {:>10.4} {rv:>13} {diff:>10}{}",
            sig.get(k).copied().unwrap_or(f64::NAN),
            if nc { "  not converged" } else { "" }
        );
    }
    let [p50, p99, max] = rep.update_ms;
    println!(
        "{} frames updated, {} refused, {} before the start ({}); {:.0} features per frame, \
         {:.0} used ({} gated, {} not triangulated, {} used with the depth prior in all), {} \
         updates not applied (no step lowered the cost); update p50 {p50:.1} ms, p99 \
         {p99:.1} ms, max {max:.1} ms",
        rep.frames_updated,
        rep.frames_refused,
        rep.frames_before_start,
        rep.start.as_deref().unwrap_or("-"),
        rep.features_per_frame,
        rep.features_used_per_frame,
        rep.features_gated,
        rep.features_failed,
        rep.features_low_parallax,
        rep.updates_refused
    );
    if !rep.implausible.is_empty() {
        println!(
            "implausible (moved more than {} prior σ from the start: the start, the prior or \
             the estimate is wrong, whatever its σ): {}",
            tracker::core::IMPLAUSIBLE_PRIOR_SIGMAS,
            rep.implausible.join(", ")
        );
    }
    if !rep.not_converged.is_empty() {
        println!(
            "not converged (σ did not shrink below half the prior's: this run's motion does not \
             determine them, the values above are the starting ones): {}",
            rep.not_converged.join(", ")
        );
    }
    if let Some(i) = &rep.init {
        print_init(i);
    }
}

/// The initialisation's line: `t_d` and `R_cb`, and how `R_cb` was found.
fn print_init(i: &InitReport) {
    if let Some(e) = &i.error {
        println!(
            "initialisation failed after {} tries: {e}; R_cb is the starting one (t_d, t_r, p_cb \
             are estimated with it)",
            i.tries
        );
        return;
    }
    let how = match (i.r_cb_estimated, i.r_cb_snapped_deg) {
        (false, _) => "given".to_string(),
        (true, Some([s, a])) => format!(
            "not observable (fit 1σ {s:.1}°): snapped to the nearest axis permutation, {a:.1}° \
             from the fit"
        ),
        (true, None) => format!("estimated, 1σ {:.2}°", i.r_cb_sigma_deg.unwrap_or(f64::NAN)),
    };
    println!(
        "initialisation ({} tries, {} / {} visual rotations): t_d {:+.2} ms (correlation peak \
         {:.3}); R_cb {how}: {:.3?}",
        i.tries,
        i.rotations[1],
        i.rotations[0],
        i.t_d_ms.unwrap_or(f64::NAN),
        i.t_d_peak.unwrap_or(f64::NAN),
        i.r_cb.unwrap_or_default()
    );
}

/// The convergence plot from the per-frame log `log` (columns of
/// [`tracker::core::LOG_NAMES`] with their σ), with the reference's values.
fn convergence_plot(
    log: &Path,
    dataset: &Path,
    reference: Option<&CalibrationFile>,
) -> anyhow::Result<ConvergencePlot> {
    let text =
        std::fs::read_to_string(log).with_context(|| format!("reading {}", log.display()))?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap_or_default().split(',').collect();
    let n = (header.len() - 1) / 2;
    let mut series: Vec<Series> = (0..n)
        .map(|k| Series {
            name: header[1 + 2 * k].to_string(),
            ..Series::default()
        })
        .collect();
    let t0 = lines
        .clone()
        .next()
        .and_then(|l| l.split(',').next()?.parse::<f64>().ok());
    for line in lines {
        let cells: Vec<f64> = line.split(',').filter_map(|c| c.parse().ok()).collect();
        if cells.len() != 1 + 2 * n {
            continue;
        }
        for (k, s) in series.iter_mut().enumerate() {
            let t = cells[0] - t0.unwrap_or(0.0);
            s.points.push((t, cells[1 + 2 * k], cells[2 + 2 * k]));
        }
    }
    if let Some(r) = reference {
        let v = table_values(r);
        for (s, (_, x)) in series.iter_mut().zip(v) {
            s.reference = Some(x);
        }
        // The log's t_d, t_r are ms and p_cb m: put the reference in the log's units.
        for s in &mut series {
            if s.name.starts_with("p_cb") {
                s.reference = s.reference.map(|x| x * 1e-3);
            }
        }
    }
    let groups = [4usize, 4, 2, 3, 6];
    let mut rows = vec![];
    let mut it = series.into_iter();
    for g in groups {
        rows.push(it.by_ref().take(g).collect());
    }
    Ok(ConvergencePlot {
        title: format!("shoal calibrate: {} (estimate, ±3σ)", dataset.display()),
        rows,
    })
}
