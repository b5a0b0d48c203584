//! `shoal sim`: writes a synthetic EuRoC-layout dataset (see `datasets::sim`).

use std::path::PathBuf;

use anyhow::Context;
use datasets::sim::{generate, Scenario, SimParams};
use slam_core::imu::ImuNoise;

/// Arguments of `shoal sim`.
#[derive(clap::Args, Debug, Clone)]
pub struct SimArgs {
    /// Scenario: `loop` (one camera, two laps), `two-agents` (two overlapping cameras,
    /// written to OUT/agent0 and OUT/agent1), `fast-rs` (fast rotation, rolling shutter),
    /// `drone` (EuRoC-like aggressive 6-DoF flight, global shutter), `blackout` (`loop`
    /// with 2 s of black frames in the middle) or `phone` (hand-held walk, 30 Hz rolling
    /// shutter t_r 25 ms, phone-grade IMU with biases and T_g/T_s/T_a, t_d 40 ms).
    #[arg(long, value_parser = parse_scenario)]
    pub scenario: Scenario,
    /// Output folder (created; holds `mav0/` and `groundtruth_cam0.txt`).
    #[arg(long)]
    pub out: PathBuf,
    /// Seed of textures, IMU noise and pixel noise (same seed, same bytes).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Number of frames per agent (default: the scenario's full length).
    #[arg(long)]
    pub frames: Option<usize>,
    /// Rolling-shutter readout time in ms (default: 30 for fast-rs, 25 for phone, else 0).
    #[arg(long)]
    pub readout_ms: Option<f64>,
    /// Camera-IMU time offset t_d in ms (true capture time = frame stamp + t_d; default: 40
    /// for phone, else 0).
    #[arg(long, allow_hyphen_values = true)]
    pub time_offset_ms: Option<f64>,
    /// Standard deviation of the per-pixel image noise, grey levels (0 = none).
    #[arg(long, default_value_t = 1.5)]
    pub pixel_noise: f32,
    /// Exact IMU measurements: no white noise, no bias random walk, zero biases.
    #[arg(long)]
    pub no_imu_noise: bool,
}

fn parse_scenario(s: &str) -> Result<Scenario, String> {
    s.parse()
}

impl SimArgs {
    /// The generator parameters these arguments describe.
    pub fn params(&self) -> SimParams {
        let mut p = SimParams::new(self.scenario);
        p.seed = self.seed;
        p.frames = self.frames;
        p.readout_ms = self.readout_ms;
        if let Some(t_d) = self.time_offset_ms {
            p.time_offset_ms = t_d;
        }
        p.pixel_noise_sigma = self.pixel_noise;
        if self.no_imu_noise {
            p.noise = ImuNoise::zero();
            p.initial_biases = Default::default();
        }
        p
    }
}

/// Runs `shoal sim`: generates the dataset and prints a summary.
pub fn run(args: &SimArgs) -> anyhow::Result<()> {
    let params = args.params();
    params.validate().context("invalid simulation parameters")?;
    println!(
        "shoal sim: scenario {} seed {} -> {} ({} frame(s) per agent, readout {:.1} ms, t_d {:.3} ms)",
        params.scenario,
        params.seed,
        args.out.display(),
        params.n_frames(),
        params.readout_ns() as f64 * 1e-6,
        params.time_offset_ms,
    );
    let summary = generate(&params, &args.out)
        .with_context(|| format!("generating {} into {}", params.scenario, args.out.display()))?;
    for (i, a) in summary.agents.iter().enumerate() {
        println!(
            "  agent {i}: {} frames, {:.2} s, camera path {:.2} m, {} IMU samples -> {}",
            a.frames,
            a.duration_s,
            a.path_length_m,
            a.imu_samples,
            a.dir.display()
        );
    }
    println!(
        "  rendered at {:.1} frames/s (one thread); total {:.1} s including textures, PNG and CSV",
        summary.render_fps, summary.total_s
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        sim: SimArgs,
    }

    #[test]
    fn parses_flags_and_writes_a_tiny_dataset() {
        let tmp = tempfile::tempdir().expect("tmp");
        let out = tmp.path().join("sim");
        let cli = Cli::try_parse_from([
            "shoal",
            "--scenario",
            "fast-rs",
            "--out",
            out.to_str().expect("utf8"),
            "--frames",
            "2",
            "--seed",
            "3",
            "--readout-ms",
            "20",
            "--time-offset-ms",
            "-1.5",
        ])
        .expect("parse");
        let p = cli.sim.params();
        assert_eq!(
            (p.scenario, p.seed, p.frames),
            (Scenario::FastRs, 3, Some(2))
        );
        assert_eq!(p.readout_ns(), 20_000_000);
        assert_eq!(p.time_offset_ns(), -1_500_000);
        run(&cli.sim).expect("run");
        assert!(out.join("mav0/cam0/data.csv").is_file());
        assert!(Cli::try_parse_from(["shoal", "--scenario", "nope", "--out", "x"]).is_err());
    }
}
