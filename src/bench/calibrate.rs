//! `shoal bench calibrate`: Monte-Carlo runs of the online calibration filter
//! (`slam_core::calib`, issue 18) on the synthetic `calib` (seed Fig. 4.4) or `phone`
//! scenario: RMSE of every calibration group at 60 s and at the end against the issue's
//! targets, average NEES of the calibration block against its 95 % band, the fraction of
//! (entry, epoch) pairs within ±3σ, and the update time.
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use serde::Serialize;
use slam_core::calib::sim::{
    run_trial, MotionKind, TrialConfig, TrialTrace, CALIB_DIM, CALIB_FIRST,
};
use slam_core::calib::{IDX_DIST, IDX_INTR, IDX_PCB, IDX_TA, IDX_TD, IDX_TG, IDX_TR, IDX_TS};

/// Arguments of `shoal bench calibrate`.
#[derive(clap::Args, Debug)]
pub struct CalibrateArgs {
    /// Monte-Carlo runs.
    #[arg(long, default_value_t = 50)]
    pub runs: usize,
    /// Simulated seconds per run.
    #[arg(long, default_value_t = 120.0)]
    pub seconds: f64,
    /// `calib` (seed Fig. 4.4, ≥ 1 rad/s about every axis) or `phone` (walking).
    #[arg(long, value_enum, default_value = "calib")]
    pub scenario: ScenarioArg,
    /// Base seed: run `i` uses `seed · 2³² + i`.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Worker threads.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Spacing of the recorded epochs, s.
    #[arg(long, default_value_t = 0.5)]
    pub epoch_s: f64,
    /// Print (and write) the summary of the runs finished so far every this many runs
    /// (0: only at the end).
    #[arg(long, default_value_t = 0)]
    pub interim: usize,
    /// Folder for `calibrate_<scenario>.json` (summary) and `calibrate_<scenario>.csv`
    /// (RMSE, NEES over time).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// The scenario of `--scenario`.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum ScenarioArg {
    /// Seed Fig. 4.4: rotations ≥ 1 rad/s about every axis, landmarks on a box.
    Calib,
    /// Hand-held phone carried at walking pace on a circle in a room.
    Phone,
}

impl ScenarioArg {
    fn kind(self) -> MotionKind {
        match self {
            Self::Calib => MotionKind::Calib,
            Self::Phone => MotionKind::Phone,
        }
    }

    fn name(self) -> &'static str {
        match self {
            Self::Calib => "calib",
            Self::Phone => "phone",
        }
    }
}

/// A group of calibration entries with the RMSE target (per entry).
struct Group {
    name: &'static str,
    /// Error-state index of the first entry.
    at: usize,
    n: usize,
    /// Target on every entry's RMSE at 60 s, state units (`None`: reported only).
    target: Option<f64>,
    /// Display scale and unit.
    scale: f64,
    unit: &'static str,
}

const GROUPS: [Group; 10] = [
    Group {
        name: "t_d",
        at: IDX_TD,
        n: 1,
        target: Some(0.5e-3),
        scale: 1e3,
        unit: "ms",
    },
    Group {
        name: "t_r",
        at: IDX_TR,
        n: 1,
        target: Some(0.5e-3),
        scale: 1e3,
        unit: "ms",
    },
    Group {
        name: "fx fy",
        at: IDX_INTR,
        n: 2,
        target: Some(1.0),
        scale: 1.0,
        unit: "px",
    },
    Group {
        name: "cx cy",
        at: IDX_INTR + 2,
        n: 2,
        target: Some(1.5),
        scale: 1.0,
        unit: "px",
    },
    Group {
        name: "k1 k2",
        at: IDX_DIST,
        n: 2,
        target: Some(0.005),
        scale: 1.0,
        unit: "",
    },
    Group {
        name: "p1 p2",
        at: IDX_DIST + 2,
        n: 2,
        target: None,
        scale: 1.0,
        unit: "",
    },
    Group {
        name: "p_cb",
        at: IDX_PCB,
        n: 3,
        target: Some(5e-3),
        scale: 1e3,
        unit: "mm",
    },
    Group {
        name: "T_g",
        at: IDX_TG,
        n: 9,
        target: Some(1e-3),
        scale: 1.0,
        unit: "",
    },
    Group {
        name: "T_s",
        at: IDX_TS,
        n: 9,
        target: Some(5e-4),
        scale: 1.0,
        unit: "",
    },
    Group {
        name: "T_a",
        at: IDX_TA,
        n: 9,
        target: Some(1e-3),
        scale: 1.0,
        unit: "",
    },
];

/// The standard normal's 97.5 % quantile.
const Z_975: f64 = 1.959_963_985;

/// Quantile of χ² with `dof` degrees of freedom at the standard-normal quantile `z`
/// (Wilson-Hilferty: `(χ²/k)^⅓` is nearly normal with mean `1 - 2/(9k)`, variance `2/(9k)`).
pub fn chi2_quantile_wh(dof: f64, z: f64) -> f64 {
    let a = 2.0 / (9.0 * dof);
    dof * (1.0 - a + z * a.sqrt()).max(0.0).powi(3)
}

/// The two-sided 95 % band of the average of `runs` independent NEES values of dimension
/// `dim`: `χ²(runs · dim)` at 2.5 % and 97.5 %, divided by `runs`.
pub fn nees_band_95(runs: usize, dim: usize) -> (f64, f64) {
    let k = (runs * dim) as f64;
    let n = runs as f64;
    (
        chi2_quantile_wh(k, -Z_975) / n,
        chi2_quantile_wh(k, Z_975) / n,
    )
}

/// One group's figures at one epoch.
#[derive(Serialize, Clone, Copy, Debug)]
struct GroupAt {
    /// Largest per-entry RMSE over the runs (the one compared with the target).
    rmse_worst: f64,
    /// RMSE pooled over the runs and the group's entries.
    rmse_pooled: f64,
    /// RMS of the filter's 1σ over runs and entries.
    sigma_rms: f64,
    /// Mean of `(e/σ)²` over runs and entries (1 for a consistent filter).
    nees_per_dof: f64,
}

#[derive(Serialize)]
struct GroupReport {
    name: &'static str,
    unit: &'static str,
    /// Target in display units.
    target: Option<f64>,
    /// At the epoch closest to 60 s, display units (`nees_per_dof` unitless).
    at_60s: GroupAt,
    /// At the last epoch.
    at_end: GroupAt,
    pass_60s: Option<bool>,
    /// Fraction of (run, entry, epoch) within ±3σ.
    within_3sigma: f64,
}

#[derive(Serialize)]
struct Summary {
    scenario: &'static str,
    runs: usize,
    runs_failed: usize,
    seconds: f64,
    seed: u64,
    threads: usize,
    wall_s: f64,
    /// Time of the epoch used as "60 s" (the last one in shorter runs), s.
    t_60s_s: f64,
    /// Time of the last epoch, s.
    t_end_s: f64,
    /// Dimension of the NEES block (`T_g .. t_r`).
    nees_dim: usize,
    nees_band_lo: f64,
    nees_band_hi: f64,
    /// Fraction of epochs whose run-averaged NEES is inside the band.
    nees_epochs_in_band: f64,
    /// Run-averaged NEES averaged over the epochs.
    nees_mean: f64,
    /// Fraction of (run, entry, epoch) within ±3σ over the whole block.
    within_3sigma: f64,
    /// The worst entry's fraction.
    within_3sigma_worst_entry: f64,
    update_p50_ms: f64,
    update_p99_ms: f64,
    features_used_per_run: f64,
    features_gated_per_run: f64,
    covariance_positive_all: bool,
    groups: Vec<GroupReport>,
}

/// Runs the benchmark.
pub fn run(args: &CalibrateArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.runs > 0 && args.seconds > 0.0,
        "need runs > 0 and seconds > 0"
    );
    let t0 = Instant::now();
    let (traces, failed) = run_all(args, t0);
    anyhow::ensure!(!traces.is_empty(), "every run failed");
    report(args, &traces, failed, t0.elapsed().as_secs_f64())
}

/// Prints the summary of `traces` and writes the files of `--out`.
fn report(
    args: &CalibrateArgs,
    traces: &[TrialTrace],
    failed: usize,
    wall_s: f64,
) -> anyhow::Result<()> {
    let n_epochs = traces.iter().map(|t| t.epochs.len()).min().unwrap_or(0);
    anyhow::ensure!(n_epochs > 0, "no epoch recorded: --seconds below --epoch-s");
    let summary = summarise(args, traces, failed, n_epochs, wall_s);
    print_text(&summary, traces, n_epochs);
    if let Some(dir) = &args.out {
        std::fs::create_dir_all(dir)?;
        let stem = format!("calibrate_{}", args.scenario.name());
        let json = dir.join(format!("{stem}.json"));
        std::fs::write(&json, serde_json::to_string_pretty(&summary)?)?;
        let csv = dir.join(format!("{stem}.csv"));
        std::fs::write(&csv, time_series_csv(traces, n_epochs))?;
        println!("wrote {} and {}", json.display(), csv.display());
    }
    Ok(())
}

/// The runs on `--threads` workers; the traces in run order and the number that failed.
/// Every `--interim` finished runs, the summary of those so far is printed (and written).
fn run_all(args: &CalibrateArgs, start: Instant) -> (Vec<TrialTrace>, usize) {
    let next = AtomicUsize::new(0);
    let slots: Mutex<Vec<Option<TrialTrace>>> = Mutex::new(vec![None; args.runs]);
    let (failed, finished) = (AtomicUsize::new(0), AtomicUsize::new(0));
    std::thread::scope(|s| {
        for _ in 0..args.threads.max(1) {
            s.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                if i >= args.runs {
                    break;
                }
                let mut cfg = TrialConfig::new(
                    args.scenario.kind(),
                    args.seconds,
                    (args.seed << 32) + i as u64,
                );
                cfg.epoch_period_s = args.epoch_s;
                let clock = Instant::now();
                match run_trial(&cfg, || clock.elapsed().as_nanos() as u64) {
                    Ok(tr) => slots.lock().expect("slots")[i] = Some(tr),
                    Err(e) => {
                        failed.fetch_add(1, Ordering::Relaxed);
                        eprintln!("run {i}: {e}");
                    }
                }
                let done = finished.fetch_add(1, Ordering::Relaxed) + 1;
                eprintln!("run {i} done ({:.0} s)", start.elapsed().as_secs_f64());
                if args.interim > 0 && done % args.interim == 0 && done < args.runs {
                    let so_far: Vec<TrialTrace> = slots
                        .lock()
                        .expect("slots")
                        .iter()
                        .flatten()
                        .cloned()
                        .collect();
                    println!("--- interim: {done} of {} runs finished", args.runs);
                    let wall_s = start.elapsed().as_secs_f64();
                    if let Err(e) = report(args, &so_far, failed.load(Ordering::Relaxed), wall_s) {
                        eprintln!("interim report: {e}");
                    }
                }
            });
        }
    });
    let traces = slots
        .into_inner()
        .expect("slots")
        .into_iter()
        .flatten()
        .collect();
    (traces, failed.into_inner())
}

/// The epoch index closest to `t_s`.
fn epoch_at(trace: &TrialTrace, n_epochs: usize, t_s: f64) -> usize {
    (0..n_epochs)
        .min_by(|&a, &b| {
            let d = |i: usize| (trace.epochs[i].t_s - t_s).abs();
            d(a).total_cmp(&d(b))
        })
        .unwrap_or(0)
}

/// A group's figures at epoch `e`, display units.
fn group_at(traces: &[TrialTrace], g: &Group, e: usize) -> GroupAt {
    let n_runs = traces.len() as f64;
    let (mut worst, mut pooled, mut sig, mut nees) = (0.0f64, 0.0, 0.0, 0.0);
    for j in g.at - CALIB_FIRST..g.at - CALIB_FIRST + g.n {
        let (mut se, mut ss) = (0.0, 0.0);
        for t in traces {
            let (err, sigma) = (t.epochs[e].err[j], t.epochs[e].sigma[j]);
            se += err * err;
            ss += sigma * sigma;
            nees += (err / sigma).powi(2);
        }
        worst = worst.max((se / n_runs).sqrt());
        pooled += se;
        sig += ss;
    }
    let m = n_runs * g.n as f64;
    GroupAt {
        rmse_worst: worst * g.scale,
        rmse_pooled: (pooled / m).sqrt() * g.scale,
        sigma_rms: (sig / m).sqrt() * g.scale,
        nees_per_dof: nees / m,
    }
}

/// Fraction of (run, entry, epoch) with |error| ≤ 3σ over the entries `entries`.
fn within_3sigma(traces: &[TrialTrace], n_epochs: usize, entries: std::ops::Range<usize>) -> f64 {
    let (mut inside, mut all) = (0usize, 0usize);
    for t in traces {
        for ep in &t.epochs[..n_epochs] {
            for j in entries.clone() {
                inside += usize::from(ep.err[j].abs() <= 3.0 * ep.sigma[j]);
                all += 1;
            }
        }
    }
    inside as f64 / all.max(1) as f64
}

/// The run-averaged NEES of the calibration block at every epoch.
fn average_nees(traces: &[TrialTrace], n_epochs: usize) -> Vec<f64> {
    (0..n_epochs)
        .map(|e| traces.iter().map(|t| t.epochs[e].nees).sum::<f64>() / traces.len() as f64)
        .collect()
}

/// Quantile `q` of the sorted `v`.
fn quantile(v: &[f64], q: f64) -> f64 {
    v.get(((v.len() as f64 * q) as usize).min(v.len().saturating_sub(1)))
        .copied()
        .unwrap_or(f64::NAN)
}

fn summarise(
    args: &CalibrateArgs,
    traces: &[TrialTrace],
    failed: usize,
    n_epochs: usize,
    wall_s: f64,
) -> Summary {
    let e60 = epoch_at(&traces[0], n_epochs, 60.0);
    let groups = GROUPS
        .iter()
        .map(|g| {
            let at_60s = group_at(traces, g, e60);
            let rel = g.at - CALIB_FIRST;
            GroupReport {
                name: g.name,
                unit: g.unit,
                target: g.target.map(|t| t * g.scale),
                at_60s,
                at_end: group_at(traces, g, n_epochs - 1),
                pass_60s: g.target.map(|t| at_60s.rmse_worst <= t * g.scale),
                within_3sigma: within_3sigma(traces, n_epochs, rel..rel + g.n),
            }
        })
        .collect();
    let (lo, hi) = nees_band_95(traces.len(), CALIB_DIM);
    let nees = average_nees(traces, n_epochs);
    let worst_entry = (0..CALIB_DIM)
        .map(|j| within_3sigma(traces, n_epochs, j..j + 1))
        .fold(1.0, f64::min);
    let mut ms: Vec<f64> = traces
        .iter()
        .flat_map(|t| t.update_ms.iter().copied())
        .collect();
    ms.sort_by(f64::total_cmp);
    let runs = traces.len() as f64;
    Summary {
        scenario: args.scenario.name(),
        runs: traces.len(),
        runs_failed: failed,
        seconds: args.seconds,
        seed: args.seed,
        threads: args.threads,
        wall_s,
        t_60s_s: traces[0].epochs[e60].t_s,
        t_end_s: traces[0].epochs[n_epochs - 1].t_s,
        nees_dim: CALIB_DIM,
        nees_band_lo: lo,
        nees_band_hi: hi,
        nees_epochs_in_band: nees.iter().filter(|&&v| (lo..=hi).contains(&v)).count() as f64
            / n_epochs as f64,
        nees_mean: nees.iter().sum::<f64>() / n_epochs as f64,
        within_3sigma: within_3sigma(traces, n_epochs, 0..CALIB_DIM),
        within_3sigma_worst_entry: worst_entry,
        update_p50_ms: quantile(&ms, 0.5),
        update_p99_ms: quantile(&ms, 0.99),
        features_used_per_run: traces.iter().map(|t| t.used as f64).sum::<f64>() / runs,
        features_gated_per_run: traces.iter().map(|t| t.gated as f64).sum::<f64>() / runs,
        covariance_positive_all: traces.iter().all(|t| t.positive),
        groups,
    }
}

fn print_text(s: &Summary, traces: &[TrialTrace], n_epochs: usize) {
    println!(
        "scenario {}: {} runs x {} s ({} failed), seed {}, {} threads, wall {:.0} s",
        s.scenario, s.runs, s.seconds, s.runs_failed, s.seed, s.threads, s.wall_s
    );
    println!(
        "{:<6} {:>9} | {:>10} {:>10} {:>10} {:>6} | {:>10} {:>10} | {:>6} {:>7}",
        "group",
        "target",
        format!("RMSE@{:.0}s", s.t_60s_s),
        "pooled",
        "σ rms",
        "pass",
        format!("RMSE@{:.0}s", s.t_end_s),
        "σ rms",
        "NEES/1",
        "in 3σ"
    );
    for g in &s.groups {
        let target = g.target.map_or("-".into(), |t| format!("{t:.3e}"));
        let pass = g.pass_60s.map_or("-", |p| if p { "yes" } else { "NO" });
        println!(
            "{:<6} {:>9} | {:>10.3e} {:>10.3e} {:>10.3e} {:>6} | {:>10.3e} {:>10.3e} | {:>6.2} {:>7.3}  {}",
            g.name, target, g.at_60s.rmse_worst, g.at_60s.rmse_pooled, g.at_60s.sigma_rms, pass,
            g.at_end.rmse_worst, g.at_end.sigma_rms, g.at_60s.nees_per_dof, g.within_3sigma, g.unit
        );
    }
    println!(
        "NEES of the {}-entry block, average of {} runs: 95 % band [{:.2}, {:.2}]; in band at {:.1} % of epochs; mean over epochs {:.2}",
        s.nees_dim, s.runs, s.nees_band_lo, s.nees_band_hi, 100.0 * s.nees_epochs_in_band, s.nees_mean
    );
    print_nees_over_time(s, traces, n_epochs);
    println!(
        "within ±3σ: {:.2} % of (run, entry, epoch), worst entry {:.2} %",
        100.0 * s.within_3sigma,
        100.0 * s.within_3sigma_worst_entry
    );
    println!(
        "update (add_frame) p50 {:.2} ms, p99 {:.2} ms; features used {:.0}, gated {:.0} per run; P positive in every run: {}",
        s.update_p50_ms, s.update_p99_ms, s.features_used_per_run, s.features_gated_per_run,
        s.covariance_positive_all
    );
}

/// Average NEES and the `t_d`, `t_r` per-dof NEES at a few epochs.
fn print_nees_over_time(s: &Summary, traces: &[TrialTrace], n_epochs: usize) {
    let nees = average_nees(traces, n_epochs);
    let last_t = traces[0].epochs[n_epochs - 1].t_s;
    let mut line = String::from("  t [s] / avg NEES / t_d, t_r (e/σ)²:");
    for t in [
        0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 30.0, 60.0, 90.0, 120.0, 300.0,
    ] {
        if t > last_t + 1e-6 {
            break;
        }
        let e = epoch_at(&traces[0], n_epochs, t);
        let td = group_at(traces, &GROUPS[0], e).nees_per_dof;
        let tr = group_at(traces, &GROUPS[1], e).nees_per_dof;
        let flag = if (s.nees_band_lo..=s.nees_band_hi).contains(&nees[e]) {
            ""
        } else {
            "*"
        };
        line += &format!("  {t}: {:.1}{flag} / {td:.1}, {tr:.1}", nees[e]);
    }
    println!("{line}   (* outside the band)");
}

/// One row per epoch: time, the run-averaged NEES and its band, the fraction within ±3σ,
/// then per group the worst-entry RMSE (display units) and the per-dof NEES.
fn time_series_csv(traces: &[TrialTrace], n_epochs: usize) -> String {
    let (lo, hi) = nees_band_95(traces.len(), CALIB_DIM);
    let nees = average_nees(traces, n_epochs);
    let mut out = String::from("t_s,nees_avg,nees_band_lo,nees_band_hi,within_3sigma");
    for g in &GROUPS {
        let name = g.name.replace(' ', "_");
        out += &format!(
            ",{name}_rmse_{},{name}_nees_per_dof",
            if g.unit.is_empty() { "1" } else { g.unit }
        );
    }
    out.push('\n');
    for (e, nees_e) in nees.iter().enumerate() {
        let inside = traces
            .iter()
            .flat_map(|t| (0..CALIB_DIM).map(move |j| (t, j)))
            .filter(|(t, j)| t.epochs[e].err[*j].abs() <= 3.0 * t.epochs[e].sigma[*j])
            .count() as f64
            / (traces.len() * CALIB_DIM) as f64;
        out += &format!(
            "{:.3},{nees_e:.4},{lo:.4},{hi:.4},{inside:.4}",
            traces[0].epochs[e].t_s
        );
        for g in &GROUPS {
            let a = group_at(traces, g, e);
            out += &format!(",{:.6e},{:.4}", a.rmse_worst, a.nees_per_dof);
        }
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Wilson-Hilferty against tabulated χ² quantiles (to 1 % at 10 dof, 0.1 % at ≥ 100).
    #[test]
    fn chi2_quantiles_match_the_tables() {
        let cases = [
            (10.0, -Z_975, 3.247, 0.01),
            (10.0, Z_975, 20.483, 0.01),
            (100.0, -Z_975, 74.222, 1e-3),
            (100.0, Z_975, 129.561, 1e-3),
            (1000.0, -Z_975, 914.257, 1e-3),
            (1000.0, Z_975, 1089.531, 1e-3),
            (40.0, 1.644_853_6, 55.758, 2e-3),
        ];
        for (k, z, want, tol) in cases {
            let got = chi2_quantile_wh(k, z);
            assert!(
                (got / want - 1.0).abs() < tol,
                "χ²({k}) at z {z}: {got} vs {want}"
            );
        }
    }

    /// The band of an average of N NEES values narrows around the dimension as N grows.
    #[test]
    fn nees_band_is_chi2_of_n_dim_over_n() {
        let (lo, hi) = nees_band_95(1, 10);
        assert!((lo - 3.247).abs() < 0.05 && (hi - 20.483).abs() < 0.2);
        let (lo, hi) = nees_band_95(25, 40);
        assert!((lo - 914.257 / 25.0).abs() < 0.05 && (hi - 1089.531 / 25.0).abs() < 0.05);
        assert!(lo < 40.0 && hi > 40.0);
    }
}
