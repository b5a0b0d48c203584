//! `shoal bench ...`: benchmarks whose figures go to BENCHMARKS.md (never asserted in tests).
pub mod calibrate;
pub mod ipc;
pub mod map;
pub mod read;
pub mod tracking;

/// Benchmarks.
#[derive(clap::Subcommand, Debug)]
pub enum BenchCommand {
    /// Frame hand-off latency between two processes: iceoryx2 (busy poll, WaitSet event) and
    /// a copying Unix-socket baseline.
    Ipc(ipc::IpcArgs),
    /// Latency of the tracking core on a dataset: per stage inside the tracker, and frame
    /// publish → pose publish through the pipeline.
    Tracking(tracking::TrackingArgs),
    /// Monte-Carlo runs of the online camera-IMU calibration (issue 18) on a synthetic
    /// scenario: RMSE vs the targets, NEES vs its 95 % band, ±3σ coverage.
    Calibrate(calibrate::CalibrateArgs),
    /// Frame read-and-decode throughput of a dataset (the camera ingest's work per frame),
    /// its opening time and the peak memory: an MCAP recording against its folder.
    Read(read::ReadArgs),
    /// Save and load times and size of a saved-map file, per 1,000 keyframes (`--copies`
    /// makes a large file of copies of a small one).
    Map(map::MapArgs),
    /// The subscriber side of `bench ipc` (started by it as a child process).
    #[command(hide = true)]
    IpcPeer(ipc::PeerArgs),
}

/// Runs a benchmark.
pub fn run(cmd: BenchCommand) -> anyhow::Result<()> {
    match cmd {
        BenchCommand::Calibrate(a) => calibrate::run(&a),
        BenchCommand::Ipc(a) => ipc::run(&a),
        BenchCommand::IpcPeer(a) => ipc::peer(&a),
        BenchCommand::Tracking(a) => tracking::run(&a),
        BenchCommand::Read(a) => read::run(&a),
        BenchCommand::Map(a) => map::run(&a),
    }
}
