//! Tracker service of one client: where frames are consumed and poses leave.
//!
//! It takes every frame from shared memory in place (the VO reads the pixels inside the
//! sample, no copy), checks its schema version and sequence number (gaps = frames dropped
//! upstream), runs the client VO of `slam_core::vo` (seed §3.3) on it, acknowledges it
//! (lock-step pacing) and publishes one `TrackedPose` per frame (pose, state, latency
//! stamps, per-stage timings). Keyframes leaving the client map are sent to the mapper and
//! kept in an [`outbox::Outbox`] until acknowledged. It drains and checks the IMU stream and
//! keeps its counters in a status file.
//!
//! Rolling shutter: when the IMU stream is live, the mean gyro rate over each frame's readout
//! ([`imu::ImuInput::camera_rate`]) rotates every keypoint to the mid-row time; without it
//! the VO uses its motion model. The frames seen while the VO initialises get their poses
//! once the map exists; they are published afterwards flagged `FLAG_BACKFILL`.
//!
//! Layout: [`core::TrackerCore`] decides everything (typed inputs, [`core::Out`] messages
//! out, no IPC or files, tested in-process); [`ports`] is the service around it (iceoryx2
//! ports, spool, frame log, status file, the event loop).
//!
//! With `--frame-log` it writes, per frame, sequence number, dataset index,
//! timestamps, size and an FNV-1a checksum of the pixels it read from shared memory (and per
//! IMU sample its time), which the end-to-end tests compare with the dataset.
#![deny(missing_docs)]

use std::path::PathBuf;

use shoal_runtime::ReplayMode;

/// Parameters of the tracker service.
#[derive(Debug, Clone, clap::Parser)]
#[command(name = "tracker", about = "Client tracker service")]
pub struct Params {
    /// Client index.
    #[arg(long, default_value_t = 0)]
    pub client: u32,
    /// Status file (JSON).
    #[arg(long)]
    pub status: Option<PathBuf>,
    /// iceoryx2 resource prefix (default: $SHOAL_IPC_PREFIX or "shoal_").
    #[arg(long)]
    pub ipc_prefix: Option<String>,
    /// Write a per-frame / per-IMU-sample log (tests).
    #[arg(long)]
    pub frame_log: Option<PathBuf>,
    /// Sleep this many ms per frame (to simulate a slow consumer in tests).
    #[arg(long, default_value_t = 0)]
    pub work_ms: u64,
    /// Do not run the VO (transport only: replay and IPC tests).
    #[arg(long)]
    pub no_vo: bool,
    /// Turn rolling-shutter compensation off (for comparison).
    #[arg(long)]
    pub no_rs: bool,
    /// Keyframe spool folder: keyframes created and not yet sent are kept there, so that a
    /// restarted tracker sends its killed predecessor's VO window (none: not kept).
    #[arg(long)]
    pub spool: Option<PathBuf>,
    /// Most keyframes in the client map (seed: N = 100).
    #[arg(long, default_value_t = 100)]
    pub window: usize,
    /// ORB features per frame.
    #[arg(long, default_value_t = 1000)]
    pub features: usize,
    /// Wait at most this long (ms) for the gyro samples up to a frame's last row.
    #[arg(long, default_value_t = 40)]
    pub imu_wait_ms: u64,
    /// Local mapping inline in the tracking thread (after each new keyframe) instead of its
    /// own thread: slower per keyframe, but a lock-step replay then takes the same
    /// decisions on every run and machine.
    #[arg(long)]
    pub inline_mapping: bool,
    /// Replay mode of the run (the launcher passes it): in lock-step the tracker
    /// synchronises with its local-mapping thread and with the server (see
    /// [`Params::lockstep_sync`]).
    #[arg(long, default_value = "realtime")]
    pub mode: ReplayMode,
    /// In lock-step, do not synchronise (free-running threads and server, as in real time:
    /// faster, but not reproducible; for benchmarks).
    #[arg(long)]
    pub no_lockstep_sync: bool,
}

impl Params {
    /// Lock-step synchronisation: each frame waits for local mapping to finish before it
    /// uses the map (its ORB extraction overlaps the mapping), and a frame that sent
    /// keyframes waits, before its pose is published and acknowledged, until the server has
    /// finished them ([`shm_schema::FLAG_HANDLED`]); the gyro wait has no short deadline.
    /// So no decision depends on thread timing: a lock-step replay is reproducible.
    pub fn lockstep_sync(&self) -> bool {
        self.mode == ReplayMode::Lockstep && !self.no_lockstep_sync
    }
}

pub mod core;
pub mod imu;
pub mod outbox;
pub mod ports;
pub mod spool;

pub use ports::run;

/// The service's name in reports.
pub fn service_name(client: u32) -> String {
    format!("tracker:{client}")
}

/// Runs the service; returns the process exit code.
pub fn main_with(params: Params) -> i32 {
    shoal_runtime::exit_code(&service_name(params.client), run(&params))
}

/// FNV-1a 64-bit hash of `bytes` (pixel checksums in frame logs).
pub fn fnv1a(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}
