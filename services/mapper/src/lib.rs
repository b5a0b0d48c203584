//! Mapper service: owns the server maps of all clients (seed §3.4.1).
//!
//! The main thread takes every client's keyframe messages from shared memory, checks their
//! schema version, converts them ([`convert`]), journals them whole ([`shoal_runtime::journal`]) and only
//! then acknowledges them on the client's feedback service (the tracker keeps a keyframe
//! until it is acknowledged). Duplicates (re-sends) are acknowledged again but not re-applied.
//! Each client has its own [`slam_core::server::KeyframeHandler`] on its own thread
//! ([`worker`]), created when its first keyframe arrives. For every handled keyframe the
//! main thread publishes pose feedback (server pose of the keyframe, scale ratio, server map
//! id) and forwards the keyframes the handler kept to the loop closer (with their points in
//! their own frame and their covisible neighbours).
//!
//! Corrections from the loop closer (seed §3.4.2-3.4.3: map merges, pose-graph corrections)
//! are journaled and then applied by the worker hosting the map; a merge of maps hosted by
//! two workers first hands one worker's group over to the other, so merged clients share
//! one map. The mapper owns the maps; the loop closer only computes.
//!
//! A restarted mapper replays its journal through fresh handlers before it takes new
//! keyframes, following the journaled idle-step schedule, so it rebuilds the same maps.
//! Outputs: `OUT/keyframes_server_c{i}.txt` (and `keyframes_client_c{i}.txt`), written
//! periodically and at the end; figures in the status file (`maps`, `keyframes`, `points`,
//! per client `c{i}.keyframes_received`, `c{i}.keyframes_kept`, ...).
//!
//! Layout: [`core::Mapper`] holds the state and decisions and returns the messages to
//! publish ([`core::Out`]); [`ports`] is the service around it (iceoryx2 ports, the event
//! loop, the drain at the end).
#![deny(missing_docs)]

pub mod convert;
pub mod core;
pub mod counters;
pub mod lockstep;
pub mod ports;
pub mod worker;

use std::path::PathBuf;

use shoal_runtime::ReplayMode;
use slam_core::server::HandlerParams;

pub use counters::{MapperClientCounters, MapperCounters};
pub use ports::run;

/// Parameters of the mapper service.
#[derive(Debug, Clone, clap::Parser)]
#[command(name = "mapper", about = "Server mapper service")]
pub struct Params {
    /// Number of clients (client indices 0..N).
    #[arg(long, default_value_t = 1)]
    pub clients: u32,
    /// Status file (JSON).
    #[arg(long)]
    pub status: Option<PathBuf>,
    /// Append-only journal of applied keyframes (replayed on start).
    #[arg(long)]
    pub journal: Option<PathBuf>,
    /// Output folder for the server keyframe trajectories (default: the journal's folder).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// iceoryx2 resource prefix (default: $SHOAL_IPC_PREFIX or "shoal_").
    #[arg(long)]
    pub ipc_prefix: Option<String>,
    /// Keyframes near the predicted pose searched for a revisit (0: none, so that a revisit
    /// is left to loop closing; for ablations).
    #[arg(long, default_value_t = HandlerParams::default().spatial_keyframes)]
    pub spatial_keyframes: usize,
    /// Global BA when a kept keyframe re-observes at least this many points of a place
    /// seen more than 5 s before (a revisit; at most one per 5 s of data). 0: never (an
    /// ablation: the revisit then only links the keyframes locally).
    #[arg(long, default_value_t = HandlerParams::default().revisit_min_points)]
    pub revisit_points: usize,
    /// Forget a client point not referenced by the last this-many keyframe ids of its
    /// client session (must exceed the id span of the client VO's window; 0: never; memory
    /// on long runs, BENCHMARKS.md "Long run").
    #[arg(long, default_value_t = HandlerParams::default().assoc_horizon_kfs)]
    pub assoc_horizon: u64,
    /// At the end, wait at most this long (s) for the handlers to finish their queues.
    #[arg(long, default_value_t = 50.0)]
    pub drain_seconds: f64,
    /// Replay mode of the run (the launcher passes it). In lock-step the mapper runs the
    /// idle step after every keyframe and tells the tracker when a keyframe is finished
    /// ([`lockstep`]), so the server maps are the same on every run.
    #[arg(long, default_value = "realtime")]
    pub mode: ReplayMode,
    /// In lock-step, do not synchronise (as in real time; for benchmarks).
    #[arg(long)]
    pub no_lockstep_sync: bool,
}

/// The service's name in reports.
pub const SERVICE_NAME: &str = "mapper";

/// Runs the service; returns the process exit code.
pub fn main_with(params: Params) -> i32 {
    shoal_runtime::exit_code(SERVICE_NAME, run(&params))
}
