//! `shoal`: the one binary users run. Subcommands: `demo`, `run`, `sim`, `eval`, `pgo`, `bench`;
//! `service` (hidden) is how the launcher starts each service as its own process.
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod bench;
mod demo;
mod eval;
mod launcher;
mod pgo_cmd;
mod plot;
mod sim_cmd;
mod vocab_cmd;

/// shoal: zero-copy, multi-process collaborative SLAM on one host.
#[derive(Parser)]
#[command(name = "shoal", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the whole pipeline on a built-in synthetic scene (no download) and summarise.
    Demo(demo::DemoArgs),
    /// Run the pipeline on one or more datasets (one client each).
    Run(RunArgs),
    /// Generate a synthetic sequence (EuRoC ASL layout + ground truth).
    Sim(sim_cmd::SimArgs),
    /// Trajectory error (ATE, RPE) of an estimate against ground truth, as evo computes it.
    Eval(eval::EvalArgs),
    /// Pose graph optimisation of a g2o-like file (Sim(3): stepwise / direct; SE(3): LM).
    Pgo(pgo_cmd::PgoArgs),
    /// Bag-of-words vocabulary of the loop closer (`vocab train`).
    #[command(subcommand)]
    Vocab(vocab_cmd::VocabCommand),
    /// Benchmarks (IPC hand-off, ...).
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// Run one service in this process (used by the launcher).
    #[command(subcommand, hide = true)]
    Service(ServiceCommand),
}

/// Arguments of `shoal run`.
#[derive(clap::Args, Debug)]
struct RunArgs {
    /// Dataset folder (EuRoC ASL, KITTI odometry, phone logger; auto-detected). Repeat for
    /// more clients.
    #[arg(long = "dataset", required = true)]
    datasets: Vec<PathBuf>,
    /// Lock-step replay: nothing dropped, deterministic (the default).
    #[arg(long, conflicts_with = "rate")]
    lockstep: bool,
    /// Real-time replay at this speed factor (1.0 = the dataset's clock).
    #[arg(long)]
    rate: Option<f64>,
    /// Output folder (report.json, trajectories, logs, status).
    #[arg(long, default_value = "out")]
    out: PathBuf,
    /// Replay at most this many frames per client.
    #[arg(long)]
    max_frames: Option<usize>,
    /// Stop the run after this many seconds.
    #[arg(long)]
    max_seconds: Option<f64>,
    /// iceoryx2 resource prefix (isolates concurrent runs; default $SHOAL_IPC_PREFIX or shoal_).
    #[arg(long)]
    ipc_prefix: Option<String>,
    /// Extra argument for every tracker, `{c}` = client index (repeatable).
    #[arg(long = "tracker-arg", allow_hyphen_values = true)]
    tracker_args: Vec<String>,
    /// Extra argument for the mapper (repeatable).
    #[arg(long = "mapper-arg", allow_hyphen_values = true)]
    mapper_args: Vec<String>,
    /// Extra argument for the loop closer (repeatable), e.g. `--loop-closer-arg=--detect-only`.
    #[arg(long = "loop-closer-arg", allow_hyphen_values = true)]
    loop_closer_args: Vec<String>,
    /// SIGKILL a service at a time after start-up, e.g. `tracker:0@3.5` or `mapper@10`
    /// (repeatable). The service is restarted like after any crash.
    #[arg(long = "kill", value_name = "SERVICE@SECONDS")]
    kills: Vec<launcher::faults::KillSpec>,
    /// SIGKILL a random running service every PERIOD seconds on average (exponential
    /// gaps), reproducible from SEED, e.g. `7:2.0`.
    #[arg(long, value_name = "SEED:PERIOD")]
    chaos: Option<launcher::faults::ChaosSpec>,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

#[derive(Subcommand)]
enum ServiceCommand {
    /// Camera ingest.
    CameraIngest(camera_ingest::Params),
    /// IMU ingest.
    ImuIngest(imu_ingest::Params),
    /// Tracker.
    Tracker(tracker::Params),
    /// Mapper.
    Mapper(mapper::Params),
    /// Loop closer.
    LoopCloser(loop_closer::Params),
}

fn init_tracing() {
    let filter = tracing_subscriber::EnvFilter::try_from_env("SHOAL_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

fn run_cmd(args: RunArgs) -> anyhow::Result<()> {
    let mut cfg = launcher::RunConfig::new(args.datasets, args.out);
    if let Some(r) = args.rate {
        anyhow::ensure!(r > 0.0, "--rate must be positive");
        cfg.mode = shoal_runtime::ReplayMode::Realtime;
        cfg.rate = r;
    }
    if let Some(p) = args.ipc_prefix {
        cfg.ipc_prefix = p;
    }
    cfg.max_frames = args.max_frames;
    cfg.max_duration = args.max_seconds.map(std::time::Duration::from_secs_f64);
    cfg.tracker_args = args.tracker_args;
    cfg.mapper_args = args.mapper_args;
    cfg.loop_closer_args = args.loop_closer_args;
    cfg.kills = args.kills;
    cfg.chaos = args.chaos;
    cfg.progress = !args.quiet;
    let rep = launcher::run(&cfg)?;
    launcher::summary::print(&rep, &cfg.out);
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let code = match cli.command {
        Command::Service(s) => match s {
            ServiceCommand::CameraIngest(p) => camera_ingest::main_with(p),
            ServiceCommand::ImuIngest(p) => imu_ingest::main_with(p),
            ServiceCommand::Tracker(p) => tracker::main_with(p),
            ServiceCommand::Mapper(p) => mapper::main_with(p),
            ServiceCommand::LoopCloser(p) => loop_closer::main_with(p),
        },
        command => {
            init_tracing();
            let result = match command {
                Command::Demo(a) => demo::run(a),
                Command::Run(a) => run_cmd(a),
                Command::Sim(a) => sim_cmd::run(&a),
                Command::Eval(a) => eval::run(&a).map(|r| eval::print(&r, a.json)),
                Command::Pgo(a) => pgo_cmd::run(&a),
                Command::Vocab(v) => vocab_cmd::run(&v),
                Command::Bench(b) => bench::run(b),
                Command::Service(_) => Ok(()),
            };
            match result {
                Ok(()) => 0,
                Err(e) => {
                    eprintln!("error: {e:#}");
                    1
                }
            }
        }
    };
    ExitCode::from(code.clamp(0, 255) as u8)
}
