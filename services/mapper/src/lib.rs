//! Mapper service: owns the server maps (one process for all clients).
//!
//! **Status: plumbing.** Keyframe handlers, server maps, scale-ratio tracking and pose
//! feedback (seed §3.4.1) come with the mapper issue. Until then this service does the
//! message work for real: it takes every client's keyframe messages from shared memory,
//! checks their schema version, journals what it applied (append-only, one line per
//! keyframe, in the run's output folder), acknowledges each applied keyframe on the
//! client's feedback service (the tracker's re-send logic relies on these acks), forwards
//! it to the loop closer, and keeps counters per client in its status file. A restarted
//! mapper re-reads its journal, so keyframes applied before the crash stay applied and are
//! not counted twice.
#![deny(missing_docs)]

use std::collections::HashSet;
use std::io::{BufRead, Write};
use std::path::PathBuf;
use std::time::Duration;

use shm_schema::time::monotonic_ns;
use shm_schema::topics;
use shm_schema::{Feedback, MsgMeta};
use shoal_runtime::{Status, StatusFile};

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
    /// Append-only journal of applied keyframes.
    #[arg(long)]
    pub journal: Option<PathBuf>,
    /// iceoryx2 resource prefix (default: $SHOAL_IPC_PREFIX or "shoal_").
    #[arg(long)]
    pub ipc_prefix: Option<String>,
}

/// The service's name in reports.
pub const SERVICE_NAME: &str = "mapper";

/// Runs the service; returns the process exit code.
pub fn main_with(params: Params) -> i32 {
    shoal_runtime::exit_code(SERVICE_NAME, run(&params))
}

/// A journal line: `client session keyframe_id t_ns n_keypoints`.
fn parse_journal_line(line: &str) -> Option<(u32, u32, u64)> {
    let mut it = line.split_whitespace();
    Some((
        it.next()?.parse().ok()?,
        it.next()?.parse().ok()?,
        it.next()?.parse().ok()?,
    ))
}

/// Serves keyframes until SIGINT/SIGTERM.
pub fn run(params: &Params) -> anyhow::Result<Status> {
    let mut file = StatusFile::new(params.status.clone());
    let mut status = shoal_runtime::resume_status(&file, SERVICE_NAME);
    // Rebuild what was applied from the journal (a torn last line is ignored and reported).
    let mut applied: HashSet<(u32, u32, u64)> = HashSet::new();
    if let Some(path) = &params.journal {
        if let Ok(f) = std::fs::File::open(path) {
            for (i, line) in std::io::BufReader::new(f).lines().enumerate() {
                match line.ok().as_deref().and_then(parse_journal_line) {
                    Some(k) => {
                        applied.insert(k);
                    }
                    None => status.error(
                        "journal",
                        format!(
                            "{}:{}: unreadable journal line skipped",
                            path.display(),
                            i + 1
                        ),
                    ),
                }
            }
        }
    }
    status.set_value("journal_keyframes_on_start", applied.len() as f64);
    let mut journal = match &params.journal {
        Some(p) => Some(
            std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(p)?,
        ),
        None => None,
    };
    let prefix = params
        .ipc_prefix
        .clone()
        .unwrap_or_else(topics::prefix_from_env);
    topics::check_foreign_versions(&prefix)?;
    let node = topics::create_node("mapper", &prefix)?;
    let mut clients = Vec::new();
    for c in 0..params.clients {
        let sub = topics::keyframe_subscriber(&topics::keyframes_service(&node, c)?)?;
        let fb = topics::publisher(&topics::feedback_service(&node, c)?)?;
        clients.push((c, sub, fb, 0u64));
    }
    let loop_pub = topics::keyframe_publisher(&topics::loop_keyframes_service(&node)?)?;
    shoal_runtime::signal_ready();

    loop {
        let mut idle = true;
        for (c, sub, fb, fb_seq) in clients.iter_mut() {
            while let Some(kf) = sub.receive()? {
                idle = false;
                let h = *kf.user_header();
                if let Err(e) = h.meta.check() {
                    status.error("schema_version", format!("keyframe of client {c}: {e}"));
                    continue;
                }
                let key = (*c, h.meta.session_id, h.keyframe_id);
                status.add(&format!("c{c}.keyframes_received"), 1);
                if applied.insert(key) {
                    if let Some(j) = journal.as_mut() {
                        writeln!(
                            j,
                            "{} {} {} {} {}",
                            c, h.meta.session_id, h.keyframe_id, h.t_ns, h.n_keypoints
                        )?;
                        j.flush()?;
                    }
                    status.add(&format!("c{c}.keyframes_applied"), 1);
                    let records = kf.payload();
                    let mut out = loop_pub.loan_slice_uninit(records.len())?;
                    *out.user_header_mut() = h;
                    out.write_from_slice(records).send()?;
                } else {
                    status.add(&format!("c{c}.keyframes_duplicate"), 1);
                }
                let ack = Feedback {
                    meta: MsgMeta::new(*c, h.meta.session_id, *fb_seq, monotonic_ns()),
                    acked_keyframe_id: h.keyframe_id,
                    acked_session_id: h.meta.session_id,
                    has_pose: 0,
                    scale_ratio: 1.0,
                    ..Feedback::default()
                };
                fb.send_copy(ack)?;
                *fb_seq += 1;
                status.add(&format!("c{c}.keyframes_acked"), 1);
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
