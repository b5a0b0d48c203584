//! `slam_core::metrics` against the `evo` tool on generated TUM files. Runs only when
//! `evo_ape` / `evo_rpe` are on PATH (`python3 -m pip install evo`); otherwise prints
//! "SKIP: evo not installed" and passes.

use std::path::Path;
use std::process::Command;

use datasets::trajectory::{read_tum, write_tum};
use datasets::StampedPose;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use slam_core::metrics::{evaluate, Alignment, ErrorStats, EvalParams};

fn on_path(tool: &str) -> bool {
    std::env::var_os("PATH")
        .is_some_and(|p| std::env::split_paths(&p).any(|d| d.join(tool).is_file()))
}

/// Deterministic uniform noise in [-1, 1).
struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    }
}

fn gt_pose(t: f64) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(
            3.0 * (0.4 * t).cos(),
            2.0 * (0.4 * t).sin(),
            0.5 * (0.9 * t).sin(),
        ),
        UnitQuaternion::from_scaled_axis(Vector3::new(0.3 * t.sin(), 0.1, 0.4 * t)),
    )
}

/// Ground truth at 20 Hz; estimate at 15 Hz with jitter, drops, a similarity and noise.
fn generate(dir: &Path) -> (std::path::PathBuf, std::path::PathBuf) {
    let t0 = 1_403_715_273_000_000_000i64;
    let gt: Vec<StampedPose> = (0..300)
        .map(|i| StampedPose {
            t_ns: t0 + i * 50_000_000,
            pose: gt_pose(i as f64 * 0.05),
        })
        .collect();
    let mut rng = Lcg(42);
    let sim = Isometry3::new(Vector3::new(1.0, -2.0, 0.5), Vector3::new(0.2, -0.4, 0.9));
    let mut est = Vec::new();
    for i in 0..220 {
        let jitter_ns = (rng.next() * 4e6) as i64;
        if rng.next() > 0.8 {
            continue;
        }
        let t_ns = t0 + 300_000_000 + i * 66_666_667 + jitter_ns;
        let p = gt_pose((t_ns - t0) as f64 * 1e-9);
        let noisy_t =
            p.translation.vector + Vector3::new(rng.next(), rng.next(), rng.next()) * 0.05;
        let noisy_r = p.rotation
            * UnitQuaternion::from_scaled_axis(
                Vector3::new(rng.next(), rng.next(), rng.next()) * 0.02,
            );
        let moved = sim * Isometry3::from_parts(Translation3::from(noisy_t * 0.4), noisy_r);
        est.push(StampedPose { t_ns, pose: moved });
    }
    let (g, e) = (dir.join("gt.txt"), dir.join("est.txt"));
    write_tum(&g, &gt).expect("write gt");
    write_tum(&e, &est).expect("write est");
    (g, e)
}

/// Runs an evo tool and returns the statistics of its saved results.
fn evo_stats(tool: &str, gt: &Path, est: &Path, flags: &[&str], dir: &Path) -> Vec<(String, f64)> {
    let zip = dir.join(format!("{tool}{}.zip", flags.join("")));
    let mut cmd = Command::new(tool);
    cmd.arg("tum")
        .arg(gt)
        .arg(est)
        .args(flags)
        .arg("--save_results")
        .arg(&zip)
        .arg("--no_warnings");
    if tool == "evo_rpe" {
        cmd.args(["--delta", "1", "--delta_unit", "f"]);
    }
    let out = cmd.output().expect("run evo");
    assert!(
        out.status.success(),
        "{tool} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json = Command::new("python3")
        .args([
            "-c",
            "import sys,zipfile;print(zipfile.ZipFile(sys.argv[1]).read('stats.json').decode())",
        ])
        .arg(&zip)
        .output()
        .expect("python3");
    let text = String::from_utf8_lossy(&json.stdout).to_string();
    // A flat object of numbers: {"rmse": 0.1, "mean": ...}.
    text.trim()
        .trim_matches(['{', '}'])
        .split(',')
        .filter_map(|kv| {
            let (k, v) = kv.split_once(':')?;
            Some((
                k.trim().trim_matches('"').to_string(),
                v.trim().parse().ok()?,
            ))
        })
        .collect()
}

fn stat(s: &ErrorStats, name: &str) -> f64 {
    match name {
        "rmse" => s.rmse,
        "mean" => s.mean,
        "median" => s.median,
        "std" => s.std,
        "min" => s.min,
        "max" => s.max,
        "sse" => s.sse,
        _ => f64::NAN,
    }
}

#[test]
fn metrics_agree_with_evo() {
    if !on_path("evo_ape") || !on_path("evo_rpe") {
        println!("SKIP: evo not installed");
        return;
    }
    let dir = tempfile::tempdir().expect("tmp");
    let (gt_path, est_path) = generate(dir.path());
    let gt = read_tum(&gt_path).expect("gt");
    let est = read_tum(&est_path).expect("est");
    let split = |t: &[StampedPose]| -> (Vec<i64>, Vec<Isometry3<f64>>) {
        t.iter().map(|p| (p.t_ns, p.pose)).unzip()
    };
    let (gt_t, gt_p) = split(&gt.poses);
    let (est_t, est_p) = split(&est.poses);
    let mut worst = 0.0f64;
    for (alignment, flags) in [
        (Alignment::None, vec![]),
        (Alignment::Se3, vec!["-a"]),
        (Alignment::Sim3, vec!["-as"]),
    ] {
        let params = EvalParams {
            alignment,
            ..Default::default()
        };
        let ours = evaluate(&gt_t, &gt_p, &est_t, &est_p, &params).expect("evaluate");
        let rpe = ours.rpe.expect("rpe");
        for (tool, mine) in [("evo_ape", &ours.ape), ("evo_rpe", &rpe)] {
            let theirs = evo_stats(tool, &gt_path, &est_path, &flags, dir.path());
            assert_eq!(theirs.len(), 7, "{tool}: {theirs:?}");
            for (name, v) in theirs {
                let m = stat(mine, &name);
                let rel = (m - v).abs() / v.abs().max(m.abs()).max(1e-12);
                worst = worst.max(rel);
                assert!(
                    rel < 1e-6,
                    "{tool} {alignment:?} {name}: evo {v} vs ours {m} (rel {rel:e})"
                );
            }
        }
    }
    println!("evo agreement: max relative difference {worst:e}");
}
