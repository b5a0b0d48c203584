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

pub mod config;
pub mod convert;
pub mod core;
pub mod counters;
pub mod lockstep;
pub mod ports;
pub mod saved;
pub mod worker;

use std::path::PathBuf;

use shoal_runtime::ReplayMode;

pub use config::{MapperConfig, MapperFlags};
pub use counters::{MapSummary, MapperClientCounters, MapperCounters, MapperDetails};
pub use ports::run;

/// The mapper service's command line: the launcher's wiring (clients, status, journal,
/// output folder, IPC prefix, replay mode) and the configuration ([`MapperConfig`]: a
/// `--config` file, which the launcher writes, and flags overriding it).
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
    /// Replay mode of the run (the launcher passes it). In lock-step the mapper runs the
    /// idle step after every keyframe and tells the tracker when a keyframe is finished
    /// ([`lockstep`]; unless `lockstep_sync = false`), so the server maps are the same on
    /// every run.
    #[arg(long, default_value = "realtime")]
    pub mode: ReplayMode,
    /// A saved-map file to start from ([`map_store`]; the launcher has checked it): its
    /// maps are hosted with their clients renamed to the saved-clients range.
    #[arg(long)]
    pub load_map: Option<PathBuf>,
    /// Localise in the loaded maps without adding to them (`--localize-only`): they are
    /// frozen; a client's map that matches one is dropped and the client's keyframes are
    /// localised in it, never inserted.
    #[arg(long)]
    pub localize_only: bool,
    /// Where to save the server's maps at the end of the run (atomically).
    #[arg(long)]
    pub save_map: Option<PathBuf>,
    /// Configuration file (TOML, the keys of `[mapper]` in `shoal config --print`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Options overriding the configuration file.
    #[command(flatten)]
    pub options: MapperFlags,
}

impl Params {
    /// The configuration: the `--config` file (else the defaults) and the flags over it.
    pub fn config(&self) -> Result<MapperConfig, shoal_runtime::config::ConfigError> {
        shoal_runtime::config::resolve(self.config.as_ref(), |c: &mut MapperConfig| {
            self.options.apply(c)
        })
    }
}

/// The service's name in reports.
pub const SERVICE_NAME: &str = "mapper";

/// Runs the service; returns the process exit code.
pub fn main_with(params: Params) -> i32 {
    shoal_runtime::exit_code(SERVICE_NAME, run(&params))
}
