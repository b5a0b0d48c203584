//! `shoal demo`: generates a synthetic scene on the fly (no download) and runs the whole
//! multi-process pipeline on it, then prints a short summary.
use std::path::PathBuf;

use crate::launcher;

/// Arguments of `shoal demo`.
#[derive(clap::Args, Debug)]
pub struct DemoArgs {
    /// Output folder (scene, report.json, trajectories, logs).
    #[arg(long, default_value = "out/demo")]
    pub out: PathBuf,
    /// Scenario of the built-in scene: loop | two-agents | fast-rs.
    #[arg(long, default_value = "loop")]
    pub scenario: String,
    /// Frames per camera (default: 400, the first lap and a bit).
    #[arg(long, default_value_t = 400)]
    pub frames: usize,
    /// Seed of the scene.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    /// Real-time replay at this speed factor instead of lock-step.
    #[arg(long)]
    pub rate: Option<f64>,
    /// iceoryx2 resource prefix.
    #[arg(long)]
    pub ipc_prefix: Option<String>,
}

/// Runs the demo.
pub fn run(args: DemoArgs) -> anyhow::Result<()> {
    let scenario: datasets::sim::Scenario = args
        .scenario
        .parse()
        .map_err(|e: String| anyhow::anyhow!(e))?;
    let mut params = datasets::sim::SimParams::new(scenario);
    params.seed = args.seed;
    params.frames = Some(args.frames);
    let scene_dir = args.out.join("scene");
    eprintln!(
        "generating the '{}' scene ({} frames per camera) ...",
        scenario.name(),
        args.frames
    );
    let summary = datasets::sim::generate(&params, &scene_dir)?;
    eprintln!(
        "  rendered at {:.0} frames/s; {} camera(s), path {:.1} m over {:.1} s",
        summary.render_fps,
        summary.agents.len(),
        summary.agents.iter().map(|a| a.path_length_m).sum::<f64>(),
        summary.agents.first().map_or(0.0, |a| a.duration_s),
    );
    let dirs: Vec<PathBuf> = summary.agents.iter().map(|a| a.dir.clone()).collect();
    let mut cfg = launcher::RunConfig::new(dirs, args.out.clone());
    if let Some(r) = args.rate {
        cfg.mode = shoal_runtime::ReplayMode::Realtime;
        cfg.rate = r;
    }
    if let Some(p) = args.ipc_prefix {
        cfg.ipc_prefix = p;
    }
    let rep = launcher::run(&cfg)?;
    launcher::summary::print(&rep, &args.out);
    Ok(())
}
