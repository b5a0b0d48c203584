//! `shoal serve` and the remote side of `shoal client` (issue 22): the server of clients on
//! other hosts. It runs the mapper, the loop closer and the server's bridge
//! ([`::bridge`], zenoh) under the launcher's supervision until SIGINT/SIGTERM, then writes
//! `OUT/report.json` with each remote client's keyframes and maps.
//!
//! A restarted server resumes: the output folder keeps the mapper's journal (its maps come
//! back as they were), the services' status files (their counters go on) and the clients'
//! slots ([`super::REMOTE_CLIENTS`]), so a client that reconnects rejoins its map; the
//! keyframes it sent while the server was away come again from its tracker, which keeps
//! every keyframe until the mapper acknowledges it.
use std::net::ToSocketAddrs;
use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::Context;
use serde::Serialize;
use shm_schema::topics;

use super::{report, supervise, topology, RunConfig, Supervised};

/// One remote client in the server's report.
#[derive(Debug, Clone, Default, Serialize)]
pub struct RemoteClient {
    /// Its name.
    pub name: String,
    /// Its slot (the client index of the server's mapper and loop closer).
    pub slot: u32,
    /// Keyframes the mapper received from it.
    pub keyframes_received: u64,
    /// Keyframes the mapper applied (end to end: the feedback acknowledges these).
    pub keyframes_applied: u64,
    /// Server maps holding its keyframes at the end.
    pub maps: u64,
}

/// Refuses an endpoint that is not on a loopback address: without authentication the
/// server must not be reachable from other hosts.
pub fn check_loopback(endpoint: &str) -> anyhow::Result<()> {
    let addr = (endpoint.strip_prefix("tcp/"))
        .or_else(|| endpoint.strip_prefix(::bridge::tls::SCHEME))
        .with_context(|| format!("--listen {endpoint}: expected tcp/HOST:PORT or tls/HOST:PORT"))?;
    let resolved: Vec<_> = (addr.to_socket_addrs())
        .with_context(|| format!("--listen {endpoint}: cannot resolve {addr}"))?
        .collect();
    if resolved.is_empty() || resolved.iter().any(|a| !a.ip().is_loopback()) {
        anyhow::bail!(
            "--listen {endpoint}: without authentication the server listens on loopback \
             addresses only (127.0.0.1, ::1); give the known clients with --auth FILE"
        );
    }
    Ok(())
}

/// Runs the server until SIGINT/SIGTERM; its report.
pub fn serve(cfg: &RunConfig) -> anyhow::Result<report::RunReport> {
    let started = Instant::now();
    let listen = cfg.listen.clone().context("shoal serve needs --listen")?;
    let rate = cfg.server_max_keyframe_rate;
    anyhow::ensure!(
        rate >= 0.0 && rate.is_finite(),
        "server_max_keyframe_rate must be 0 (no limit) or positive (got {rate})"
    );
    let tls = [
        ("--tls-cert", cfg.tls_cert.as_deref(), "CERTIFICATE"),
        ("--tls-key", cfg.tls_key.as_deref(), "PRIVATE KEY"),
    ];
    ::bridge::tls::check("--listen", &listen, &tls)?;
    let loaded = super::map_file::check_inputs(cfg)?;
    let known = match &cfg.auth {
        Some(file) => ::bridge::auth::read_credentials(file)?.len(),
        None => {
            check_loopback(&listen)?;
            0
        }
    };
    std::fs::create_dir_all(&cfg.out)
        .with_context(|| format!("creating output folder {}", cfg.out.display()))?;
    let _ = std::fs::remove_dir_all(cfg.out.join(super::CONFIG_DIR));
    let exe = std::env::current_exe().context("locating the shoal binary")?;
    super::claim_prefix(&cfg.ipc_prefix)?;
    let _ipc_cleanup = super::IpcCleanup(cfg.ipc_prefix.clone());
    let node = topics::create_node("launcher", &cfg.ipc_prefix)?;
    let recorder = super::Recorder::new(&node, 0)?;
    let topology = topology::server_topology();
    super::write_configs(cfg, &topology, &[])?;
    let mut services = super::services_for(cfg, &topology);
    super::start_services(&mut services, &topology, &exe)?;
    let who = match known {
        0 => "loopback only, no authentication".to_string(),
        n => format!("only the clients of --auth, {n} known"),
    };
    let wire = match cfg.tls_cert {
        Some(_) => "encrypted (TLS)",
        None => "not encrypted",
    };
    eprintln!(
        "shoal serve: listening on {listen} ({who}; {wire}) for up to {} clients; Ctrl-C stops",
        cfg.server_clients
    );
    let mut errors = Vec::new();
    loop {
        supervise(&mut services, &exe, cfg, &mut errors)?;
        if node.wait(Duration::from_millis(20)).is_err() {
            break;
        }
    }
    // Work already received is finished first: the loop closer may still be querying the
    // last keyframes, and a merge found then is applied and counted.
    super::wait_server_quiet(&services, super::SERVER_QUIET_TIMEOUT);
    let mut recorder = recorder;
    super::stop_services(&mut services, &topology, &mut recorder)?;
    let mut rep = report::RunReport::collect(
        cfg,
        &[],
        &services,
        &recorder,
        errors,
        started.elapsed(),
        true,
        false,
    )?;
    rep.map_loaded = loaded;
    rep.remote_clients = remote_clients(&cfg.out, &services, &rep.maps);
    rep.bridges = bridges(&services);
    rep.add_map_files(cfg);
    rep.write(&cfg.out.join("report.json"))?;
    Ok(rep)
}

/// The remote clients of the clients' table, with the mapper's counters of their slots.
fn remote_clients(
    out: &Path,
    services: &[Supervised],
    maps: &[::mapper::MapSummary],
) -> Vec<RemoteClient> {
    // The bridge's own reader (a table it never wrote reads as empty here; the bridge
    // itself refuses to start on a malformed one).
    let table = bridge::slots::Slots::open(Some(&out.join(super::REMOTE_CLIENTS)), u32::MAX)
        .unwrap_or_default();
    let table = table.by_slot();
    let mapper = services.iter().find(|s| s.name == "mapper");
    let counters: ::mapper::MapperCounters = mapper
        .map(|m| report::load_status(&m.status).counters_as())
        .unwrap_or_default();
    // Applied keyframes from the journal, as `shoal run` counts them: a keyframe is
    // journaled before it is acknowledged, and a SIGKILLed server's status file may lag.
    let slots = table
        .iter()
        .map(|(s, _)| *s as usize + 1)
        .max()
        .unwrap_or(0);
    let journaled = report::journal_keyframes(&out.join(super::MAPPER_JOURNAL), slots);
    table
        .into_iter()
        .map(|(slot, name)| {
            let c = counters.client(slot);
            RemoteClient {
                name: name.to_string(),
                slot,
                keyframes_received: c.keyframes_received,
                keyframes_applied: (journaled.as_ref())
                    .and_then(|j| j.get(slot as usize))
                    .map_or(c.keyframes_applied, |j| j.applied),
                maps: maps.iter().filter(|m| m.clients.contains(&slot)).count() as u64,
            }
        })
        .collect()
}

/// Every bridge's counters by service name.
pub fn bridges(
    services: &[Supervised],
) -> std::collections::BTreeMap<String, ::bridge::BridgeCounters> {
    (services.iter())
        .filter(|s| s.name.starts_with("bridge"))
        .map(|s| (s.name.clone(), report::load_status(&s.status).counters_as()))
        .collect()
}
