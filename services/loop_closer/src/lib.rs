//! Loop closer service: place recognition, Sim(3) loops, map merging and pose-graph
//! optimisation over all clients' server maps.
//!
//! **Status: plumbing.** The algorithms (seed §3.4.2-3.4.3) come with the loop-closer issue.
//! Until then this service subscribes to the keyframes the mapper forwards, checks their
//! schema version and counts them per client in its status file; it sends no corrections.
#![deny(missing_docs)]

use std::path::PathBuf;
use std::time::Duration;

use shm_schema::topics;
use shoal_runtime::{Status, StatusFile};

/// Parameters of the loop closer service.
#[derive(Debug, Clone, clap::Parser)]
#[command(name = "loop_closer", about = "Loop closer service")]
pub struct Params {
    /// Status file (JSON).
    #[arg(long)]
    pub status: Option<PathBuf>,
    /// iceoryx2 resource prefix (default: $SHOAL_IPC_PREFIX or "shoal_").
    #[arg(long)]
    pub ipc_prefix: Option<String>,
}

/// The service's name in reports.
pub const SERVICE_NAME: &str = "loop_closer";

/// Runs the service; returns the process exit code.
pub fn main_with(params: Params) -> i32 {
    shoal_runtime::exit_code(SERVICE_NAME, run(&params))
}

/// Receives keyframes until SIGINT/SIGTERM.
pub fn run(params: &Params) -> anyhow::Result<Status> {
    let mut file = StatusFile::new(params.status.clone());
    let mut status = shoal_runtime::resume_status(&file, SERVICE_NAME);
    let prefix = params
        .ipc_prefix
        .clone()
        .unwrap_or_else(topics::prefix_from_env);
    topics::check_foreign_versions(&prefix)?;
    let node = topics::create_node("loop_closer", &prefix)?;
    let sub = topics::keyframe_subscriber(&topics::loop_keyframes_service(&node)?)?;
    shoal_runtime::signal_ready();
    loop {
        let mut idle = true;
        while let Some(kf) = sub.receive()? {
            idle = false;
            let h = kf.user_header();
            match h.meta.check() {
                Ok(()) => status.add(&format!("c{}.keyframes_received", h.meta.client_id), 1),
                Err(e) => status.error("schema_version", format!("loop keyframe: {e}")),
            }
        }
        let _ = file.write_every(&status, Duration::from_millis(200));
        if idle && node.wait(Duration::from_millis(1)).is_err() {
            break;
        }
    }
    status.finished = true;
    file.write(&status)?;
    Ok(status)
}
