//! `shoal`: the one binary users run. Subcommands: `demo`, `run`, `calibrate`, `config`, `sim`, `eval`,
//! `pgo`, `vocab`, `bench`, `convert`, `map`;
//! `service` (hidden) is how the launcher starts each service as its own process.
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod bench;
mod calibrate_cmd;
mod config;
mod convert_cmd;
mod demo;
mod eval;
mod launcher;
mod map_cmd;
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
    Run(Box<RunArgs>),
    /// Run clients whose server is on another host (`shoal serve`): the ingests and the
    /// tracker here, the keyframes and the feedback through a bridge (zenoh). The options
    /// of `run`, with `--connect tcp/HOST:PORT`.
    Client(Box<RunArgs>),
    /// The server of clients on other hosts: the mapper, the loop closer and a bridge
    /// listening for `shoal client`s, until Ctrl-C; `OUT/report.json` at the end.
    Serve(ServeArgs),
    /// The run configuration: `config --print` shows every key with its default.
    Config(ConfigArgs),
    /// Online camera-IMU calibration of a dataset (t_d, t_r, intrinsics, lever arm, IMU
    /// errors): writes the project's calibration file and Kalibr's YAML.
    Calibrate(calibrate_cmd::CalibrateArgs),
    /// Generate a synthetic sequence (EuRoC ASL layout + ground truth).
    Sim(sim_cmd::SimArgs),
    /// Trajectory error (ATE, RPE) of an estimate against ground truth, as evo computes it.
    Eval(eval::EvalArgs),
    /// Pose graph optimisation of a g2o-like file (Sim(3): stepwise / direct; SE(3): LM).
    Pgo(pgo_cmd::PgoArgs),
    /// Bag-of-words vocabulary of the loop closer (`vocab train`).
    #[command(subcommand)]
    Vocab(vocab_cmd::VocabCommand),
    /// Saved-map files (`run --save-map`): `map info FILE`, `map export FILE --ply OUT`.
    #[command(subcommand)]
    Map(map_cmd::MapCommand),
    /// Convert a dataset (any format `run` reads) to another format: `--to mcap`.
    Convert(convert_cmd::ConvertArgs),
    /// Benchmarks (IPC hand-off, ...).
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// Run one service in this process (used by the launcher).
    #[command(subcommand, hide = true)]
    Service(ServiceCommand),
}

/// Arguments of `shoal run`. The run's configuration is [`config::RunConfig`]: the
/// defaults, then `--config FILE`, then `--set KEY=VALUE`, then these flags.
#[derive(clap::Args, Debug)]
struct RunArgs {
    /// Configuration file (TOML; `shoal config --print` shows every key and its default).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Set one configuration key over the file, e.g. `tracker.window=10` (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    sets: Vec<String>,
    /// Dataset folder (EuRoC ASL, KITTI odometry, phone logger, ...), MCAP file or ROS 2
    /// bag folder; auto-detected. Repeat for more clients. Replaces the file's `datasets`.
    #[arg(long = "dataset")]
    datasets: Vec<PathBuf>,
    /// What each client runs: `auto` (visual-inertial when its dataset has an IMU stream
    /// and camera-IMU extrinsics, else monocular), `mono` or `vio`. Once: sets
    /// `tracker.mode` for every client; once per `--dataset`, in the same order: each
    /// client's own (mixed monocular and visual-inertial clients; `client_modes`).
    #[arg(long = "mode", value_enum)]
    client_mode: Vec<tracker::ClientMode>,
    /// Calibration file (`shoal calibrate`'s output) put in place of the dataset's own
    /// camera model, camera-IMU pose, t_d, t_r and IMU model. Once for every dataset, or once
    /// per `--dataset` in the same order. Replaces the file's `calib`.
    #[arg(long = "calib", value_name = "FILE")]
    calib: Vec<PathBuf>,
    /// Image topic of MCAP / ROS 2 / ROS 1 bag datasets (default: found by message type).
    #[arg(long, value_name = "TOPIC")]
    image_topic: Option<String>,
    /// IMU topic of MCAP / ROS 2 / ROS 1 bag datasets (default: found by message type).
    #[arg(long, value_name = "TOPIC")]
    imu_topic: Option<String>,
    /// Lock-step replay: nothing dropped, deterministic (the default).
    #[arg(long, conflicts_with = "rate")]
    lockstep: bool,
    /// Real-time replay at this speed factor (1.0 = the dataset's clock).
    #[arg(long)]
    rate: Option<f64>,
    /// Output folder (report.json, trajectories, logs, status; default `out`).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Replay at most this many frames per client.
    #[arg(long)]
    max_frames: Option<usize>,
    /// Frame rate of datasets without timestamps (an image folder: frame k at k / FPS s;
    /// default 20).
    #[arg(long)]
    fps: Option<f64>,
    /// Only frames A to B-1 of the datasets (`A..B`, 0-based; `A..` to the end), at their
    /// own times. Once for every dataset, or once per `--dataset` in the same order.
    #[arg(long = "frames", value_name = "A..B")]
    frames: Vec<datasets::FrameRange>,
    /// Stop the run after this many seconds.
    #[arg(long)]
    max_seconds: Option<f64>,
    /// iceoryx2 resource prefix (isolates concurrent runs; default $SHOAL_IPC_PREFIX or shoal_).
    #[arg(long)]
    ipc_prefix: Option<String>,
    /// Deprecated: a tracker flag, mapped onto `[tracker]` (e.g. `--window=10` sets
    /// `tracker.window`); `{c}` = client index (repeatable). Use `--set` or `--config`.
    #[arg(long = "tracker-arg", allow_hyphen_values = true)]
    tracker_args: Vec<String>,
    /// Deprecated: a mapper flag, mapped onto `[mapper]` (repeatable).
    #[arg(long = "mapper-arg", allow_hyphen_values = true)]
    mapper_args: Vec<String>,
    /// Deprecated: a loop closer flag, mapped onto `[loop_closer]` (repeatable).
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
    /// Start the server from this saved-map file (`shoal map info FILE` shows what it
    /// holds); a truncated, corrupted or other-version file is refused before any service
    /// starts. Monocular clients localise in it before their VO initialises
    /// (`tracker.prior_map`); with `shoal client` that is all it does (give the server the
    /// same file: `shoal serve --load-map`).
    #[arg(long, value_name = "FILE")]
    load_map: Option<PathBuf>,
    /// Save the server's maps to this file at the end of the run (atomically).
    #[arg(long, value_name = "FILE")]
    save_map: Option<PathBuf>,
    /// Localise in the `--load-map` map without adding to it: the server keeps it frozen,
    /// each client's keyframes are localised in it once the client's map matches it, and
    /// its poses are written in the map's frame.
    #[arg(long)]
    localize_only: bool,
    /// Record the frames, IMU samples and poses that cross shared memory, with the
    /// calibration, to this MCAP file (ROS 2 messages; `shoal run --dataset FILE` replays
    /// it); with several clients, one file each (`STEM_c{i}.mcap`).
    #[arg(long, value_name = "FILE.mcap")]
    record: Option<PathBuf>,
    /// Serve the run live to Foxglove (its WebSocket protocol; "Open connection" →
    /// `ws://HOST:PORT`): poses, paths, keyframes, image with tracked features, latency, and
    /// at the end the map and its loops. Loopback port 8765 when no address is given.
    #[arg(long, value_name = "HOST:PORT", num_args = 0..=1, default_missing_value = "127.0.0.1:8765")]
    viz: Option<String>,
    /// With `--viz`: wait up to this many seconds for a viewer to connect before the run
    /// starts.
    #[arg(long, value_name = "SECONDS")]
    viz_wait: Option<f64>,
    /// `shoal client`: the server's endpoint (`tcp/HOST:PORT`, or `tls/HOST:PORT` with
    /// `--tls-ca`).
    #[arg(long, value_name = "tcp/HOST:PORT")]
    connect: Option<String>,
    /// `shoal client`: this client's name, which keeps its slot (and map) on the server
    /// across reconnects (default: the host name and the dataset's folder name).
    #[arg(long)]
    name: Option<String>,
    /// `shoal client`: this client's credential, a file of one `NAME:PASSWORD` line, for a
    /// server started with `--auth` (the name is the client's).
    #[arg(long, value_name = "FILE")]
    auth: Option<PathBuf>,
    /// `shoal client` of a `tls/HOST:PORT` server: the CA certificate (PEM) its TLS
    /// certificate must chain to (the host connected to must be one of its names).
    #[arg(long, value_name = "FILE")]
    tls_ca: Option<PathBuf>,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

/// Arguments of `shoal serve`.
#[derive(clap::Args, Debug)]
struct ServeArgs {
    /// Configuration file (TOML; its `[mapper]` and `[loop_closer]` apply).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Set one configuration key over the file (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    sets: Vec<String>,
    /// Where to listen (`tcp/HOST:PORT`, or `tls/HOST:PORT` with `--tls-cert` and
    /// `--tls-key`; loopback addresses only without `--auth`).
    #[arg(long, default_value = "tcp/127.0.0.1:7447")]
    listen: String,
    /// With a `tls/` endpoint: the server's TLS certificate (chain), PEM. TLS encrypts what
    /// crosses; who may use the server is `--auth`'s.
    #[arg(long, value_name = "FILE")]
    tls_cert: Option<PathBuf>,
    /// With a `tls/` endpoint: the server's TLS private key, PEM.
    #[arg(long, value_name = "FILE")]
    tls_key: Option<PathBuf>,
    /// Only known clients: a file of `NAME:PASSWORD` lines; each client presents its own
    /// line (`shoal client --auth`) and may publish only under its name. A client's first
    /// slot (its index in the server's maps) is its line's rank, whatever the order of
    /// arrival. Without it the server listens on loopback addresses only.
    #[arg(long, value_name = "FILE")]
    auth: Option<PathBuf>,
    /// Output folder: the report, the maps' files, and what a restarted server resumes
    /// from (the mapper's journal, the clients' slots).
    #[arg(long, default_value = "out_server")]
    out: PathBuf,
    /// How many remote clients the server takes; more are refused.
    #[arg(long, default_value_t = 4)]
    clients: u32,
    /// The most keyframes a second the server takes, all clients together (0: no limit;
    /// default 20); more are refused and sent again by their clients.
    #[arg(long, value_name = "HZ")]
    max_keyframe_rate: Option<f64>,
    /// Save the server's maps to this file when it stops.
    #[arg(long, value_name = "FILE")]
    save_map: Option<PathBuf>,
    /// Start the server from this saved-map file (refused before anything starts when
    /// truncated, corrupted or of another version). A monocular `shoal client --load-map`
    /// of the same file localises in it before its own VO initialises, and the server takes
    /// its session into it at once.
    #[arg(long, value_name = "FILE")]
    load_map: Option<PathBuf>,
    /// Localise the clients in the `--load-map` map without adding to it.
    #[arg(long)]
    localize_only: bool,
    /// iceoryx2 resource prefix of the server's host.
    #[arg(long)]
    ipc_prefix: Option<String>,
}

/// Arguments of `shoal config`.
#[derive(clap::Args, Debug)]
struct ConfigArgs {
    /// Print the configuration as TOML: the defaults, or those of `--config FILE` and
    /// `--set` (what `shoal run` would use).
    #[arg(long)]
    print: bool,
    /// Configuration file to read (checked: an unknown key is an error).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Set one key, as `shoal run --set` (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    sets: Vec<String>,
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
    /// Bridge to another host.
    Bridge(bridge::Params),
}

fn init_tracing() {
    let filter = tracing_subscriber::EnvFilter::try_from_env("SHOAL_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

/// The run's configuration from `args`: file, `--set`, flags, then the deprecated
/// pass-through flags (one warning on stderr when they are used).
fn run_config(args: RunArgs) -> anyhow::Result<config::RunConfig> {
    let mut cfg = config::RunConfig::resolve(args.config.as_deref(), &args.sets)?;
    if !args.datasets.is_empty() {
        cfg.datasets = args.datasets;
    }
    match args.client_mode.as_slice() {
        [] => {}
        [m] => cfg.tracker.mode = *m,
        many => cfg.client_modes = many.to_vec(),
    }
    if !args.calib.is_empty() {
        cfg.calib = args.calib;
    }
    if args.image_topic.is_some() {
        cfg.image_topic = args.image_topic;
    }
    if args.imu_topic.is_some() {
        cfg.imu_topic = args.imu_topic;
    }
    if args.lockstep {
        cfg.mode = shoal_runtime::ReplayMode::Lockstep;
    }
    if let Some(r) = args.rate {
        anyhow::ensure!(r > 0.0, "--rate must be positive");
        cfg.mode = shoal_runtime::ReplayMode::Realtime;
        cfg.rate = r;
    }
    if let Some(o) = args.out {
        cfg.out = o;
    }
    if let Some(p) = args.ipc_prefix {
        cfg.ipc_prefix = p;
    }
    if args.max_frames.is_some() {
        cfg.max_frames = args.max_frames;
    }
    if args.max_seconds.is_some() {
        cfg.max_seconds = args.max_seconds;
    }
    if args.fps.is_some() {
        cfg.fps = args.fps;
    }
    if !args.frames.is_empty() {
        cfg.frames = args.frames;
    }
    if !args.kills.is_empty() {
        cfg.kills = args.kills;
    }
    if args.chaos.is_some() {
        cfg.chaos = args.chaos;
    }
    if args.load_map.is_some() {
        cfg.load_map = args.load_map;
    }
    if args.save_map.is_some() {
        cfg.save_map = args.save_map;
    }
    cfg.localize_only |= args.localize_only;
    if args.record.is_some() {
        cfg.record = args.record;
    }
    if args.viz.is_some() {
        cfg.viz = args.viz;
    }
    if let Some(s) = args.viz_wait {
        cfg.viz_wait_s = s;
    }
    if args.connect.is_some() {
        cfg.connect = args.connect;
    }
    if args.name.is_some() {
        cfg.client_name = args.name;
    }
    if args.auth.is_some() {
        cfg.auth = args.auth;
    }
    if args.tls_ca.is_some() {
        cfg.tls_ca = args.tls_ca;
    }
    if args.quiet {
        cfg.progress = false;
    }
    let deprecated = config::Deprecated {
        tracker: args.tracker_args,
        mapper: args.mapper_args,
        loop_closer: args.loop_closer_args,
    };
    if !deprecated.is_empty() {
        let set = deprecated.apply(&mut cfg)?;
        eprintln!("{}", config::Deprecated::warning(&set));
    }
    cfg.validate()?;
    Ok(cfg)
}

fn run_cmd(args: RunArgs) -> anyhow::Result<()> {
    let cfg = run_config(args)?;
    let rep = launcher::run(&cfg)?;
    launcher::summary::print(&rep, &cfg.out);
    Ok(())
}

fn client_cmd(args: RunArgs) -> anyhow::Result<()> {
    let mut cfg = run_config(args)?;
    anyhow::ensure!(
        cfg.connect.is_some(),
        "shoal client needs --connect tcp/HOST:PORT (the server's `shoal serve --listen`)"
    );
    if let Some(file) = &cfg.auth {
        // The credential names the client: the server lets it publish under that name only.
        let cred = bridge::auth::client_credential(file)?;
        if let Some(n) = cfg.client_name.as_ref().filter(|n| **n != cred.name) {
            anyhow::bail!(
                "--name {n:?}, but {} is {:?}'s credential",
                file.display(),
                cred.name
            );
        }
        anyhow::ensure!(
            cfg.datasets.len() == 1,
            "--auth: one credential is one client; run one `shoal client` per dataset"
        );
        cfg.client_name = Some(cred.name);
    }
    let connect = cfg.connect.as_deref().unwrap_or_default();
    let ca = [("--tls-ca", cfg.tls_ca.as_deref(), "CERTIFICATE")];
    bridge::tls::check("--connect", connect, &ca)?;
    let rep = launcher::run(&cfg)?;
    launcher::summary::print(&rep, &cfg.out);
    Ok(())
}

fn serve_cmd(args: ServeArgs) -> anyhow::Result<()> {
    let mut cfg = config::RunConfig::resolve(args.config.as_deref(), &args.sets)?;
    cfg.listen = Some(args.listen);
    if args.auth.is_some() {
        cfg.auth = args.auth;
    }
    if args.tls_cert.is_some() {
        cfg.tls_cert = args.tls_cert;
    }
    if args.tls_key.is_some() {
        cfg.tls_key = args.tls_key;
    }
    cfg.out = args.out;
    cfg.server_clients = args.clients;
    if let Some(r) = args.max_keyframe_rate {
        cfg.server_max_keyframe_rate = r;
    }
    cfg.mode = shoal_runtime::ReplayMode::Realtime;
    if args.save_map.is_some() {
        cfg.save_map = args.save_map;
    }
    if args.load_map.is_some() {
        cfg.load_map = args.load_map;
    }
    cfg.localize_only |= args.localize_only;
    if let Some(p) = args.ipc_prefix {
        cfg.ipc_prefix = p;
    }
    let rep = launcher::serve::serve(&cfg)?;
    for c in &rep.remote_clients {
        println!(
            "client {} (slot {}): {} keyframes received, {} applied, in {} map(s)",
            c.name, c.slot, c.keyframes_received, c.keyframes_applied, c.maps
        );
    }
    println!(
        "server: {} map(s), {} merge(s), {} loop(s); report: {}",
        rep.maps.len(),
        rep.merges,
        rep.loops,
        cfg.out.join("report.json").display()
    );
    Ok(())
}

fn config_cmd(args: &ConfigArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.print,
        "nothing to do: `shoal config --print [--config FILE] [--set KEY=VALUE ...]`"
    );
    let cfg = config::RunConfig::resolve(args.config.as_deref(), &args.sets)?;
    print!("{}", cfg.to_toml_with_header()?);
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
            ServiceCommand::Bridge(p) => bridge::main_with(p),
        },
        command => {
            init_tracing();
            let result = match command {
                Command::Demo(a) => demo::run(a),
                Command::Run(a) => run_cmd(*a),
                Command::Client(a) => client_cmd(*a),
                Command::Serve(a) => serve_cmd(a),
                Command::Calibrate(a) => calibrate_cmd::run(&a),
                Command::Config(a) => config_cmd(&a),
                Command::Sim(a) => sim_cmd::run(&a),
                Command::Eval(a) => eval::run(&a).map(|r| eval::print(&r, a.json)),
                Command::Pgo(a) => pgo_cmd::run(&a),
                Command::Vocab(v) => vocab_cmd::run(&v),
                Command::Bench(b) => bench::run(b),
                Command::Convert(a) => convert_cmd::run(&a),
                Command::Map(m) => map_cmd::run(&m),
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
