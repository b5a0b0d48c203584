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
//! Configuration: [`TrackerConfig`] (`--config FILE`, written by the launcher; flags
//! override it). The client VO's local-mapping thread is this service's
//! ([`mapping_thread`]); `slam_core` keeps the steps.
//!
//! With `frame_log` it writes, per frame, sequence number, dataset index,
//! timestamps, size and an FNV-1a checksum of the pixels it read from shared memory (and per
//! IMU sample its time), which the end-to-end tests compare with the dataset.
#![deny(missing_docs)]

use std::path::PathBuf;

use shoal_runtime::ReplayMode;

/// The tracker service's command line: the launcher's wiring (client, status, IPC prefix,
/// spool, replay mode) and the configuration ([`TrackerConfig`]: a `--config` file, which
/// the launcher writes, and flags overriding it in a manual run).
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
    /// Keyframe spool folder: keyframes created and not yet sent are kept there, so that a
    /// restarted tracker sends its killed predecessor's VO window (none: not kept).
    #[arg(long)]
    pub spool: Option<PathBuf>,
    /// Replay mode of the run (the launcher passes it): in lock-step the tracker
    /// synchronises with its local-mapping thread and with the server (see
    /// [`TrackerConfig::lockstep_sync`]).
    #[arg(long, default_value = "realtime")]
    pub mode: ReplayMode,
    /// Configuration file (TOML, the keys of `[tracker]` in `shoal config --print`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Options overriding the configuration file.
    #[command(flatten)]
    pub options: TrackerFlags,
}

impl Params {
    /// The configuration: the `--config` file (else the defaults), the flags over it, and
    /// `SHOAL_DEBUG_INIT` (set: `debug_init = true`).
    pub fn config(&self) -> Result<TrackerConfig, shoal_runtime::config::ConfigError> {
        shoal_runtime::config::resolve(self.config.as_ref(), |c: &mut TrackerConfig| {
            self.options.apply(c);
            c.debug_init |= std::env::var_os("SHOAL_DEBUG_INIT").is_some();
        })
    }

    /// Lock-step synchronisation with configuration `cfg`: each frame waits for local
    /// mapping to finish before it uses the map (its ORB extraction overlaps the mapping),
    /// and a frame that sent keyframes waits, before its pose is published and
    /// acknowledged, until the server has finished them ([`shm_schema::FLAG_HANDLED`]); the
    /// gyro wait has no short deadline. So no decision depends on thread timing: a lock-step
    /// replay is reproducible.
    pub fn lockstep_sync(&self, cfg: &TrackerConfig) -> bool {
        self.mode == ReplayMode::Lockstep && cfg.lockstep_sync
    }
}

pub mod config;
pub mod core;
pub mod imu;
pub mod mapping_thread;
pub mod outbox;
pub mod ports;
pub mod spool;
#[cfg(any(test, feature = "testing"))]
pub mod testing;

pub use config::{
    CalibInit, CalibModeConfig, ClientMode, ImuCalibConfig, LocalMapping, TrackerConfig,
    TrackerFlags,
};
pub use core::VioReport;
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
