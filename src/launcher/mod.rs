//! The launcher: the one place that knows the whole topology ([`topology`]: per client
//! camera_ingest, imu_ingest, tracker; per host mapper, loop_closer, each with its role). It
//! writes each service's section of the run's [`RunConfig`] to `OUT/config/` and starts
//! every service as a child process with it (`--config FILE`), consumers before producers,
//! waits until they are ready, reaps and restarts crashed ones with back-off after cleaning
//! their stale iceoryx2 resources, injects faults, records poses and latencies, stops
//! everything in the reverse order at the end of the data or on Ctrl-C, writes
//! `OUT/report.json` (with its [`provenance`]) and leaves nothing of the run in shared
//! memory.
pub mod child;
pub mod faults;
pub mod map_file;
pub mod modes;
pub mod provenance;
pub mod record;
pub mod recorder;
pub mod report;
pub mod serve;
pub mod sessions;
pub mod summary;
pub mod topology;
pub mod view;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::Context;
use iceoryx2::node::NodeView;
use iceoryx2::prelude::*;
use shm_schema::time::monotonic_ns;
use shm_schema::topics::{self, Ipc};
use shoal_runtime::{ErrorKind, ErrorRecord, ReplayMode};
use tracker::ClientMode;

use child::{describe_exit, Phase, Supervised};
use recorder::Recorder;

pub use crate::config::RunConfig;

/// Removes the stale resources of dead nodes on `prefix`; returns how many were removed.
pub fn cleanup_dead_nodes(prefix: &str) -> anyhow::Result<usize> {
    let config = topics::config_with_prefix(prefix)?;
    let mut removed = 0;
    Node::<Ipc>::list(&config, |state| {
        if let NodeState::Dead(view) = state {
            if view.try_remove_stale_resources().is_ok() {
                removed += 1;
            }
        }
        CallbackProgression::Continue
    })
    .map_err(|e| anyhow::anyhow!("listing iceoryx2 nodes: {e:?}"))?;
    Ok(removed)
}

/// Names of live shoal nodes on `prefix` that are not ours (another run is active).
fn foreign_live_nodes(prefix: &str) -> anyhow::Result<Vec<String>> {
    let config = topics::config_with_prefix(prefix)?;
    let me = std::process::id();
    let mut names = Vec::new();
    Node::<Ipc>::list(&config, |state| {
        if let NodeState::Alive(view) = state {
            if let Some(d) = view.details().as_ref() {
                if d.process_id().value() as u32 != me {
                    names.push(format!(
                        "{} (pid {})",
                        d.name().as_str(),
                        d.process_id().value()
                    ));
                }
            }
        }
        CallbackProgression::Continue
    })
    .map_err(|e| anyhow::anyhow!("listing iceoryx2 nodes: {e:?}"))?;
    Ok(names)
}

/// The mapper's journal in the output folder (replayed by a restarted mapper).
pub const MAPPER_JOURNAL: &str = "mapper_journal.bin";

/// Folder of the trackers' keyframe spools (`c{i}/` each), in the output folder.
pub const TRACKER_SPOOL: &str = "spool";

/// How long the mapper may take at the end to finish its handlers' queues.
const MAPPER_STOP_TIMEOUT: Duration = Duration::from_secs(60);

/// Folder of the services' configuration files, in the output folder.
pub const CONFIG_DIR: &str = "config";

/// The IMU ingest's lock-step look-ahead for a client in the calibration mode, ms: the filter
/// waits for the samples past a frame's last row at its current t_d.
const CALIB_IMU_LOOKAHEAD_MS: u64 = 400;

/// The configuration file of service `desc` in `out` (`tracker_c0.toml`, `mapper.toml`, ...;
/// the ingests of all clients share one).
pub fn service_config_path(out: &Path, desc: &topology::ServiceDesc) -> PathBuf {
    use topology::Kind;
    let name = match (desc.kind, desc.client) {
        (Kind::Tracker, Some(c)) => format!("tracker_c{c}.toml"),
        (kind, _) => format!("{}.toml", kind.name()),
    };
    out.join(CONFIG_DIR).join(name)
}

/// Writes the whole run's configuration (`OUT/config/run.toml`, which `shoal run --config`
/// takes back) and every service's section (`OUT/config/<service>.toml`, see
/// [`service_config_path`]), which each service is started with.
/// A tracker's section is the run's `[tracker]` with its client's mode and IMU calibration
/// (`setups`, [`modes::client_setup`]).
fn write_configs(
    cfg: &RunConfig,
    topology: &[topology::ServiceDesc],
    setups: &[modes::ClientSetup],
) -> anyhow::Result<()> {
    let dir = cfg.out.join(CONFIG_DIR);
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let write = |path: PathBuf, text: String| {
        std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))
    };
    write(dir.join("run.toml"), cfg.to_toml_with_header()?)?;
    for desc in topology {
        let setup = desc.client.and_then(|c| setups.get(c as usize));
        let text = match (desc.kind, setup) {
            (topology::Kind::Tracker, Some(s)) => {
                let mut one = cfg.clone();
                one.tracker.mode = s.mode;
                one.tracker.imu = s.imu.clone();
                one.tracker.readout_direction = s.readout;
                // A monocular client localises in the loaded map before its VO initialises.
                if s.mode == ClientMode::Mono && one.tracker.prior_map.is_none() {
                    one.tracker.prior_map = cfg.load_map.clone();
                }
                // A recording or a live viewer draws the tracked features on the images.
                one.tracker.publish_features |= cfg.record.is_some() || cfg.viz.is_some();
                // A remote server is not lock-stepped with its clients (it serves several,
                // each at its own pace): the tracker does not wait for it to finish each
                // keyframe.
                one.tracker.lockstep_sync &= cfg.connect.is_none();
                // A remote server may be away for a while: the tracker waits for it after its
                // stream, and its spool holds every keyframe until the mapper acknowledged it.
                if cfg.connect.is_some() {
                    let wait = one.tracker.end_wait_s;
                    one.tracker.end_wait_s = wait.or(Some(::tracker::config::REMOTE_END_WAIT_S));
                    one.tracker.spool_until_ack = true;
                }
                if s.mode == ClientMode::Calib && one.tracker.calib.log.is_none() {
                    one.tracker.calib.log = Some(cfg.out.join("calib_c{c}.csv"));
                }
                one.service_toml(desc)?
            }
            (topology::Kind::ImuIngest, Some(s)) if s.mode == ClientMode::Calib => {
                // The calibration filter needs the IMU past a frame's last row at its t_d.
                let mut one = cfg.clone();
                let l = &mut one.imu_ingest.lookahead_ms;
                *l = (*l).max(CALIB_IMU_LOOKAHEAD_MS);
                one.service_toml(desc)?
            }
            (topology::Kind::Bridge, _) => continue,
            _ => cfg.service_toml(desc)?,
        };
        write(service_config_path(&cfg.out, desc), text)?;
    }
    Ok(())
}

/// The command-line arguments of `desc` after `shoal service`: the launcher's wiring and
/// the service's configuration file (`--status` is added by [`Supervised::spawn`]).
fn service_args(cfg: &RunConfig, desc: &topology::ServiceDesc) -> Vec<String> {
    use topology::Kind;
    let out = &cfg.out;
    // Every service knows the replay mode: in lock-step the tracker, mapper and loop closer
    // synchronise so that a run is reproducible.
    let mode = match cfg.mode {
        ReplayMode::Lockstep => "lockstep",
        ReplayMode::Realtime => "realtime",
    };
    let mut args = vec![desc.kind.subcommand().to_string()];
    let c = desc.client.unwrap_or(0).to_string();
    match desc.kind {
        Kind::Mapper => {
            // A server of remote clients has a slot for each client it takes.
            let clients = match cfg.listen {
                Some(_) => cfg.server_clients as usize,
                None => cfg.datasets.len(),
            };
            args.extend(["--clients".to_string(), clients.to_string()]);
            args.extend(["--journal".to_string(), path_arg(&out.join(MAPPER_JOURNAL))]);
            args.extend(["--out".to_string(), path_arg(out)]);
            if let Some(p) = &cfg.load_map {
                args.extend(["--load-map".to_string(), path_arg(p)]);
            }
            // A recording takes the server map's points from a saved map.
            let for_record = || record::map_file(cfg).filter(|_| !cfg.localize_only);
            let save = cfg.save_map.clone().or_else(for_record);
            if let Some(p) = &save {
                args.extend(["--save-map".to_string(), path_arg(p)]);
            }
            if cfg.localize_only {
                args.push("--localize-only".to_string());
            }
        }
        Kind::LoopCloser => {
            if let Some(p) = &cfg.load_map {
                args.extend(["--load-map".to_string(), path_arg(p)]);
            }
            if cfg.localize_only {
                args.push("--localize-only".to_string());
            }
        }
        Kind::Tracker => {
            let spool = out.join(TRACKER_SPOOL).join(format!("c{c}"));
            args.extend(["--client".to_string(), c.clone()]);
            args.extend(["--spool".to_string(), path_arg(&spool)]);
        }
        Kind::ImuIngest | Kind::CameraIngest => {
            let client = desc.client.unwrap_or(0) as usize;
            args.extend(["--client".to_string(), c.clone()]);
            args.extend(["--dataset".to_string(), path_arg(&cfg.datasets[client])]);
            if let Some(calib) = cfg.calib_of(client) {
                args.extend(["--calib".to_string(), path_arg(calib)]);
            }
            if let Some(t) = &cfg.image_topic {
                args.extend(["--image-topic".to_string(), t.clone()]);
            }
            if let Some(t) = &cfg.imu_topic {
                args.extend(["--imu-topic".to_string(), t.clone()]);
            }
            args.extend(["--rate".to_string(), cfg.rate.to_string()]);
            if let Some(m) = cfg.max_frames {
                args.extend(["--max-frames".to_string(), m.to_string()]);
            }
            if let Some(f) = cfg.fps {
                args.extend(["--fps".to_string(), f.to_string()]);
            }
            if let Some(r) = cfg.frames_of(client) {
                args.extend(["--frames".to_string(), r.to_string()]);
            }
        }
        // The bridge takes no configuration file nor replay mode.
        Kind::Bridge => return bridge_args(cfg, desc),
    }
    args.extend(["--mode".to_string(), mode.to_string()]);
    let config = service_config_path(out, desc);
    args.extend(["--config".to_string(), path_arg(&config)]);
    args
}

/// The bridge's arguments: beside a client's tracker, the server to connect to and the
/// client's name; beside the server's mapper, the endpoint, the capacity and the clients'
/// table (kept in the output folder across restarts).
fn bridge_args(cfg: &RunConfig, desc: &topology::ServiceDesc) -> Vec<String> {
    let mut args = vec!["bridge".to_string()];
    match desc.client {
        Some(c) => {
            let endpoint = cfg.connect.clone().unwrap_or_default();
            args.extend(["--side", "client", "--endpoint", &endpoint].map(String::from));
            args.extend(["--name".to_string(), client_name(cfg, c as usize)]);
            args.extend(["--client".to_string(), c.to_string()]);
            args.extend(["--run".to_string(), run_id().to_string()]);
            let files = [("--auth", &cfg.auth), ("--tls-ca", &cfg.tls_ca)];
            for (flag, f) in files {
                if let Some(f) = f {
                    args.extend([flag.to_string(), path_arg(f)]);
                }
            }
        }
        None => {
            let endpoint = cfg.listen.clone().unwrap_or_default();
            args.extend(["--side", "server", "--endpoint", &endpoint].map(String::from));
            args.extend(["--capacity".to_string(), cfg.server_clients.to_string()]);
            let rate = cfg.server_max_keyframe_rate.to_string();
            args.extend(["--max-keyframe-rate".to_string(), rate]);
            let table = cfg.out.join(REMOTE_CLIENTS);
            args.extend(["--clients-file".to_string(), path_arg(&table)]);
            let files = [
                ("--auth", &cfg.auth),
                ("--tls-cert", &cfg.tls_cert),
                ("--tls-key", &cfg.tls_key),
            ];
            for (flag, f) in files {
                if let Some(f) = f {
                    args.extend([flag.to_string(), path_arg(f)]);
                }
            }
        }
    }
    args
}

/// This run's id, the same for every start of its bridges: the server keeps the ids of a
/// client's runs apart by it (`bridge::run_ids`). The wall clock's nanoseconds and the
/// launcher's pid: two runs of one client differ in either.
fn run_id() -> u64 {
    static ID: std::sync::OnceLock<u64> = std::sync::OnceLock::new();
    *ID.get_or_init(|| {
        let ns = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64);
        // Never 0 (the bridge's default when started by hand).
        (ns ^ (u64::from(std::process::id()) << 44)).max(1)
    })
}

/// The server's table of remote clients' slots, in its output folder.
pub const REMOTE_CLIENTS: &str = "remote_clients.txt";

/// Remote client `c`'s name: `client_name` (with `-c{c}` for the second client on),
/// else the host name and the dataset's folder name.
fn client_name(cfg: &RunConfig, c: usize) -> String {
    let clean = |s: String| -> String {
        s.chars()
            .map(|ch| {
                if ch.is_ascii_alphanumeric() || "-_.".contains(ch) {
                    ch
                } else {
                    '_'
                }
            })
            .collect()
    };
    if let Some(n) = &cfg.client_name {
        return clean(if c == 0 {
            n.clone()
        } else {
            format!("{n}-c{c}")
        });
    }
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_string())
        .unwrap_or_else(|_| "host".into());
    let data = (cfg.datasets.get(c))
        .and_then(|d| d.file_name())
        .map_or("data".into(), |n| n.to_string_lossy().to_string());
    clean(format!("{host}-{data}"))
}

fn path_arg(p: &Path) -> String {
    p.display().to_string()
}

/// The supervised processes of the run, one per descriptor of `topology`, in its order.
fn services_for(cfg: &RunConfig, topology: &[topology::ServiceDesc]) -> Vec<Supervised> {
    topology
        .iter()
        .map(|desc| {
            let ends_by_itself = desc.role() != topology::Role::Server;
            let args = service_args(cfg, desc);
            let mut sv = Supervised::new(&desc.name(), args, &cfg.out, ends_by_itself);
            sv.env
                .push((topics::ENV_IPC_PREFIX.to_string(), cfg.ipc_prefix.clone()));
            sv
        })
        .collect()
}

/// Each client's mode and why, its IMU calibration's source, and only the mode's own report
/// (`vio` or `calib`; the other is a status detail of the wrong shape).
fn put_client_modes(rep: &mut report::RunReport, setups: &[modes::ClientSetup]) {
    for (cl, s) in rep.clients.iter_mut().zip(setups) {
        cl.client_mode = s.mode.name().to_string();
        cl.client_mode_reason = s.reason.clone();
        if matches!(s.mode, ClientMode::Vio | ClientMode::Calib) {
            cl.imu_calibration = Some(s.imu.source.clone());
        }
        if s.mode != ClientMode::Vio {
            cl.vio = None;
        }
        if s.mode != ClientMode::Calib {
            cl.calib = None;
        }
    }
}

/// Runs the pipeline; returns the report (also written to `OUT/report.json`).
pub fn run(cfg: &RunConfig) -> anyhow::Result<report::RunReport> {
    let started = Instant::now();
    let loaded = map_file::check_inputs(cfg)?;
    // Hashing the datasets overlaps the start-up.
    let checksums = {
        let paths = cfg.datasets.clone();
        std::thread::spawn(move || provenance::dataset_checksums(&paths))
    };
    prepare_out_dir(&cfg.out)?;
    map_file::check_outputs(cfg)?;
    let datasets = match open_datasets(cfg) {
        Ok(d) => d,
        Err((e, errors)) => {
            let mut rep = report::RunReport::failed(cfg, errors, started.elapsed());
            rep.provenance = provenance_of(cfg, checksums);
            rep.write(&cfg.out.join("report.json"))?;
            anyhow::bail!("{e}");
        }
    };
    let exe = std::env::current_exe().context("locating the shoal binary")?;
    claim_prefix(&cfg.ipc_prefix)?;
    // Dropped last (after the node and the recorder's ports): removes what the run leaves in
    // shared memory once no node of the prefix is left.
    let _ipc_cleanup = IpcCleanup(cfg.ipc_prefix.clone());
    let node = topics::create_node("launcher", &cfg.ipc_prefix)?;
    let mut recorder = Recorder::new(&node, cfg.datasets.len() as u32)?;

    let topology = topology_of(cfg);
    let setups: Vec<modes::ClientSetup> = datasets
        .iter()
        .enumerate()
        .map(|(c, ds)| modes::client_setup(cfg.mode_of(c), ds, cfg.calib_of(c)))
        .collect();
    write_configs(cfg, &topology, &setups)?;
    // Subscribed before any service publishes.
    let taps = Taps::start(cfg, &datasets)?;
    let mut services = services_for(cfg, &topology);
    start_services(&mut services, &topology, &exe)?;
    tracing::info!("all {} services ready", services.len());

    let mut watch = Watch {
        services,
        injector: faults::FaultInjector::new(cfg.kills.clone(), cfg.chaos.clone()),
        errors: setups
            .iter()
            .filter_map(|s| s.calibration_error.clone())
            .map(|detail| ErrorRecord {
                service: "launcher".into(),
                kind: ErrorKind::ImuCalibration,
                detail,
            })
            .collect(),
        ready_at: Instant::now(),
    };
    let progress = report::Progress::new(cfg.progress, &datasets, cfg.max_frames);
    let end = watch.until_done(cfg, &exe, &node, &mut recorder, &progress, started)?;
    // The trackers are done and the mapper has acknowledged every keyframe, but the loop
    // closer may still be querying the last ones and a correction may be on its way: stop
    // the server side only once it is quiet, so that a loop found at the very end is applied.
    if end == RunEnd::Done {
        wait_server_quiet(&watch.services, SERVER_QUIET_TIMEOUT);
    }
    stop_services(&mut watch.services, &topology, &mut recorder)?;
    let records = taps.finish(cfg);
    progress.finish();
    let elapsed_s = watch.ready_at.elapsed().as_secs_f64();
    let unfired = watch.injector.unfired(elapsed_s, &recorder.frames_posed());
    watch.injector.note_recoveries(&watch.services);
    for s in &unfired {
        watch.errors.push(ErrorRecord {
            service: "launcher".into(),
            kind: ErrorKind::KillUnfired,
            detail: format!("{}: {}", s.spec, s.reason),
        });
    }
    let mut rep = report::RunReport::collect(
        cfg,
        &datasets,
        &watch.services,
        &recorder,
        watch.errors,
        started.elapsed(),
        end == RunEnd::Interrupted,
        end == RunEnd::TimedOut,
    )?;
    put_client_modes(&mut rep, &setups);
    rep.faults_summary = faults::FaultsSummary::of(&watch.injector.events);
    rep.faults_summary.unfired = unfired.len();
    rep.faults = watch.injector.events;
    rep.faults_unfired = unfired;
    rep.provenance = provenance_of(cfg, checksums);
    rep.map_loaded = loaded;
    rep.add_map_files(cfg);
    rep.record = records;
    rep.bridges = serve::bridges(&watch.services);
    rep.write(&cfg.out.join("report.json"))?;
    Ok(rep)
}

/// The services of the run: the whole pipeline, or (`--connect`) the clients' side with a
/// bridge to their remote server.
fn topology_of(cfg: &RunConfig) -> Vec<topology::ServiceDesc> {
    let n_clients = cfg.datasets.len() as u32;
    match cfg.connect {
        Some(_) => topology::client_topology(n_clients),
        None => topology::topology(n_clients),
    }
}

/// What the launcher takes off shared memory for a file (`--record`) and live viewers
/// (`--viz`).
struct Taps {
    live: Option<std::sync::Arc<view::Live>>,
    recording: Option<record::Recording>,
}

impl Taps {
    /// Starts the viewer's server and the recording threads (before any service
    /// publishes).
    fn start(cfg: &RunConfig, datasets: &[datasets::Dataset]) -> anyhow::Result<Self> {
        let live = start_viz(cfg)?;
        let recording = (cfg.record.is_some() || live.is_some())
            .then(|| start_recording(cfg, live.clone(), datasets))
            .transpose()?;
        Ok(Self { live, recording })
    }

    /// Ends them once the services have stopped: the files' reports (none without
    /// `--record`).
    fn finish(self, cfg: &RunConfig) -> Vec<record::RecordReport> {
        let map_file = record::map_file(cfg);
        let records = (self.recording.map(|r| r.finish(map_file.as_deref()))).unwrap_or_default();
        if let Some(l) = &self.live {
            l.stop();
        }
        records
            .into_iter()
            .filter(|_| cfg.record.is_some())
            .collect()
    }
}

/// Starts `--viz`'s server, and waits `viz_wait_s` for a viewer.
fn start_viz(cfg: &RunConfig) -> anyhow::Result<Option<std::sync::Arc<view::Live>>> {
    let Some(addr) = &cfg.viz else {
        return Ok(None);
    };
    let (host, port) = (addr.rsplit_once(':'))
        .and_then(|(h, p)| Some((h, p.parse::<u16>().ok()?)))
        .with_context(|| format!("--viz {addr}: expected HOST:PORT"))?;
    let live = view::Live::start(host, port)?;
    eprintln!(
        "viz: serving the run on ws://{} (Foxglove: Open connection)",
        live.addr
    );
    let until = Instant::now() + Duration::from_secs_f64(cfg.viz_wait_s.max(0.0));
    if cfg.viz_wait_s > 0.0 {
        eprintln!("viz: waiting up to {} s for a viewer", cfg.viz_wait_s);
    }
    while live.clients() == 0 && Instant::now() < until {
        std::thread::sleep(Duration::from_millis(20));
    }
    Ok(Some(live))
}

/// Starts `--record path` and/or `--viz`: every client's calibration record and ground
/// truth, then the recording threads.
fn start_recording(
    cfg: &RunConfig,
    live: Option<std::sync::Arc<view::Live>>,
    datasets: &[datasets::Dataset],
) -> anyhow::Result<record::Recording> {
    let metas = (datasets.iter().enumerate())
        .map(|(c, ds)| record::meta_of(ds, cfg.calib_of(c)))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let truth = (datasets.iter())
        .map(|ds| ds.ground_truth.clone().unwrap_or_default())
        .collect();
    record::Recording::start(cfg.record.as_deref(), live, &cfg.ipc_prefix, metas, truth)
}

/// The provenance of the run of `cfg`, with the dataset checksums the thread computed.
fn provenance_of(
    cfg: &RunConfig,
    checksums: std::thread::JoinHandle<Vec<provenance::DatasetChecksum>>,
) -> provenance::Provenance {
    let config = serde_json::to_value(cfg).unwrap_or_else(|e| serde_json::json!(e.to_string()));
    provenance::Provenance::of(config, checksums.join().unwrap_or_default())
}

/// Creates the output folder and removes what an earlier run in it left that this run's
/// services would take for their own: status files (a crash of this run), the mapper
/// journal and tracker spools (replayed at a restart), server outputs and trajectories (a
/// run that writes none must not show an earlier run's).
fn prepare_out_dir(out: &Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(out)
        .with_context(|| format!("creating output folder {}", out.display()))?;
    let _ = std::fs::remove_dir_all(out.join("status"));
    let _ = std::fs::remove_file(out.join(MAPPER_JOURNAL));
    let _ = std::fs::remove_dir_all(out.join(TRACKER_SPOOL));
    let _ = std::fs::remove_dir_all(out.join(CONFIG_DIR));
    if let Ok(rd) = std::fs::read_dir(out) {
        for e in rd.flatten() {
            let name = e.file_name().to_string_lossy().to_string();
            if [
                "keyframes_server_c",
                "keyframes_client_c",
                "map_growth_c",
                "trajectory_c",
                "trajectory_server_c",
            ]
            .iter()
            .any(|p| name.starts_with(p))
            {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
    Ok(())
}

/// Opens every dataset; on failure the error and the launcher's error record.
fn open_datasets(
    cfg: &RunConfig,
) -> Result<Vec<datasets::Dataset>, (datasets::DatasetError, Vec<ErrorRecord>)> {
    cfg.datasets
        .iter()
        .enumerate()
        .map(|(c, path)| {
            datasets::open_with(path, &cfg.open_options(c)).map_err(|e| {
                let record = ErrorRecord {
                    service: "launcher".into(),
                    kind: ErrorKind::Dataset,
                    detail: e.to_string(),
                };
                (e, vec![record])
            })
        })
        .collect()
}

/// Makes the iceoryx2 prefix this run's: removes what dead nodes (a run killed earlier)
/// left, refuses to start beside a live run or a pipeline of another schema version.
fn claim_prefix(prefix: &str) -> anyhow::Result<()> {
    let cleaned = cleanup_dead_nodes(prefix)?;
    if cleaned > 0 {
        tracing::info!("removed stale iceoryx2 resources of {cleaned} dead node(s)");
    }
    let others = foreign_live_nodes(prefix)?;
    if !others.is_empty() {
        anyhow::bail!(
            "another shoal run is active on iceoryx2 prefix '{prefix}' ({}); stop it or pass \
             --ipc-prefix",
            others.join(", ")
        );
    }
    topics::check_foreign_versions(prefix)?;
    Ok(())
}

/// How far after the consumers are ready the sensors' stream origin lies: time for the
/// ingests to start (read the dataset's index, open their ports) before their first sample
/// is due.
const STREAM_LEAD_NS: i64 = 1_500_000_000;

/// Starts the services in the topology's phases (consumers, then producers), each phase
/// ready before the next starts. The producers (the ingests) share one stream origin
/// (`--t0-mono-ns`), set once the consumers are ready: however long the server and trackers
/// took to start on a loaded machine, the first frames are not already late.
fn start_services(
    services: &mut [Supervised],
    topology: &[topology::ServiceDesc],
    exe: &Path,
) -> anyhow::Result<()> {
    let [consumers, producers] = topology::start_phases(topology);
    for (k, phase) in [consumers, producers].into_iter().enumerate() {
        if k == 1 {
            let t0 = monotonic_ns() + STREAM_LEAD_NS;
            for &i in &phase {
                services[i]
                    .args
                    .extend(["--t0-mono-ns".to_string(), t0.to_string()]);
            }
        }
        for &i in &phase {
            let sv = &mut services[i];
            sv.spawn(exe)
                .with_context(|| format!("starting {}", sv.name))?;
        }
        wait_ready_among(services, &phase, Duration::from_secs(30))?;
    }
    Ok(())
}

/// Stops the services in the topology's stop order (producers first), taking the poses
/// that arrive meanwhile.
fn stop_services(
    services: &mut [Supervised],
    topology: &[topology::ServiceDesc],
    recorder: &mut Recorder,
) -> anyhow::Result<()> {
    for i in topology::stop_order(topology) {
        let sv = &mut services[i];
        if sv.child.is_some() {
            let timeout = if sv.name == "mapper" {
                MAPPER_STOP_TIMEOUT
            } else {
                Duration::from_secs(5)
            };
            sv.stop(timeout);
        }
        recorder.drain()?;
    }
    Ok(())
}

/// How the watched part of a run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum RunEnd {
    /// Every client's data went through.
    Done,
    /// SIGINT / SIGTERM.
    Interrupted,
    /// `--max-seconds`.
    TimedOut,
}

/// The running services, the fault injector and the launcher's own error records.
struct Watch {
    services: Vec<Supervised>,
    injector: faults::FaultInjector,
    errors: Vec<ErrorRecord>,
    /// When every service was ready (fault times count from here).
    ready_at: Instant,
}

impl Watch {
    /// Records poses, supervises and injects faults until every client is done, the run is
    /// interrupted, or `--max-seconds` is over.
    fn until_done(
        &mut self,
        cfg: &RunConfig,
        exe: &Path,
        node: &Node<Ipc>,
        recorder: &mut Recorder,
        progress: &report::Progress,
        started: Instant,
    ) -> anyhow::Result<RunEnd> {
        loop {
            recorder.drain()?;
            progress.update(recorder);
            supervise(&mut self.services, exe, cfg, &mut self.errors)?;
            if !self.injector.is_empty() {
                self.injector.step(
                    &mut self.services,
                    self.ready_at.elapsed().as_secs_f64(),
                    &recorder.frames_posed(),
                );
            }
            if (0..cfg.datasets.len()).all(|c| client_done(&self.services, c)) {
                return Ok(RunEnd::Done);
            }
            if cfg.max_duration().is_some_and(|d| started.elapsed() > d) {
                self.errors.push(ErrorRecord {
                    service: "launcher".into(),
                    kind: ErrorKind::Timeout,
                    detail: format!("run stopped after {:?}", started.elapsed()),
                });
                return Ok(RunEnd::TimedOut);
            }
            if node.wait(Duration::from_millis(5)).is_err() {
                return Ok(RunEnd::Interrupted);
            }
        }
    }
}

/// True when client `c`'s camera ingest and tracker have ended, or its camera ingest failed
/// for good.
fn client_done(services: &[Supervised], c: usize) -> bool {
    let finished = |svc: &str| {
        services
            .iter()
            .filter(|s| s.name == format!("{svc}:{c}"))
            .all(|s| matches!(s.phase, Phase::Done | Phase::Failed))
    };
    finished("camera_ingest") && finished("tracker")
        || services
            .iter()
            .any(|s| s.name == format!("camera_ingest:{c}") && s.phase == Phase::Failed)
}

/// Removes the iceoryx2 resources a run leaves in shared memory when dropped: the prefix's
/// node-id counter segment (`/dev/shm/{prefix}…node.{version}.global_mgmt`, 16 bytes, which
/// iceoryx2 creates with the first node and never removes), once no node of the prefix is
/// left, alive or dead. Nodes' own resources go with the nodes (or, after a SIGKILL, with
/// the next run's [`cleanup_dead_nodes`]).
struct IpcCleanup(String);

impl Drop for IpcCleanup {
    fn drop(&mut self) {
        match remove_prefix_leftovers(&self.0) {
            Ok(true) => tracing::debug!("removed the node counter segment of '{}'", self.0),
            Ok(false) => {}
            Err(e) => tracing::warn!("iceoryx2 clean-up of prefix '{}': {e:#}", self.0),
        }
    }
}

/// Removes the node-id counter segment of `prefix` when no node of the prefix exists; true
/// when it was removed.
pub fn remove_prefix_leftovers(prefix: &str) -> anyhow::Result<bool> {
    let config = topics::config_with_prefix(prefix)?;
    let mut nodes = 0;
    Node::<Ipc>::list(&config, |_| {
        nodes += 1;
        CallbackProgression::Continue
    })
    .map_err(|e| anyhow::anyhow!("listing iceoryx2 nodes: {e:?}"))?;
    if nodes > 0 {
        return Ok(false);
    }
    // SAFETY: no node of this prefix exists, so no process uses its counter segment; a node
    // created meanwhile by a run starting on the same prefix keeps its unique id (the id
    // also holds its process id and creation time) and opens a fresh segment next time.
    unsafe { iceoryx2::testing::remove_global_mgmt_segment::<Ipc>(&config) }
        .map_err(|e| anyhow::anyhow!("removing the node counter segment: {e:?}"))
}

/// How long the end of a run waits at most for the mapper and loop closer to be quiet.
const SERVER_QUIET_TIMEOUT: Duration = Duration::from_secs(30);

/// Waits until the loop closer has taken every keyframe the mapper forwarded, the mapper
/// every correction the loop closer sent, and neither status file's counters changed for
/// half a second (work in progress shows up as changing counters), or `timeout`.
fn wait_server_quiet(services: &[Supervised], timeout: Duration) {
    let path = |name: &str| {
        services
            .iter()
            .find(|s| s.name == name && s.child.is_some())
            .map(|s| s.status.clone())
    };
    let (Some(mapper), Some(closer)) = (path("mapper"), path("loop_closer")) else {
        return;
    };
    let start = Instant::now();
    let mut last = None;
    let mut same_since = Instant::now();
    while start.elapsed() < timeout {
        let m: ::mapper::MapperCounters = report::load_status(&mapper).counters_as();
        let l: ::loop_closer::LoopCloserCounters = report::load_status(&closer).counters_as();
        let received: u64 = l.clients.iter().map(|(_, c)| c.keyframes_received).sum();
        let forwarded: u64 = m.clients.iter().map(|(_, c)| c.keyframes_forwarded).sum();
        let caught_up = received >= forwarded && m.corrections_received >= l.corrections_sent;
        let now = Some((m, l));
        if now != last {
            last = now;
            same_since = Instant::now();
        } else if caught_up && same_since.elapsed() >= Duration::from_millis(500) {
            return;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    tracing::warn!("the mapper and loop closer were still busy after {timeout:?}; stopping them");
}

/// Waits until the services `among` (indices into `services`) are ready; fails when one
/// exits during start-up or `timeout` passes. One that ended cleanly
/// ([`Supervised::ended_cleanly`], possibly before its ready line was read) is done.
fn wait_ready_among(
    services: &mut [Supervised],
    among: &[usize],
    timeout: Duration,
) -> anyhow::Result<()> {
    let start = Instant::now();
    loop {
        let mut all = true;
        for &i in among {
            let sv = &mut services[i];
            sv.poll_ready();
            if sv.phase == Phase::Starting {
                if let Some(st) = sv.try_reap() {
                    if sv.ended_cleanly(&st) {
                        sv.phase = Phase::Done;
                        continue;
                    }
                    anyhow::bail!(
                        "{} exited during start-up ({}); see {}",
                        sv.name,
                        describe_exit(&st),
                        sv.log.display()
                    );
                }
                all = false;
            }
        }
        if all {
            return Ok(());
        }
        if start.elapsed() > timeout {
            let late: Vec<_> = among
                .iter()
                .map(|&i| &services[i])
                .filter(|s| s.phase == Phase::Starting)
                .map(|s| &s.name)
                .collect();
            anyhow::bail!("services not ready after {timeout:?}: {late:?}");
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// One supervision step: readiness, exits, restarts.
fn supervise(
    services: &mut [Supervised],
    exe: &Path,
    cfg: &RunConfig,
    errors: &mut Vec<ErrorRecord>,
) -> anyhow::Result<()> {
    for sv in services.iter_mut() {
        sv.poll_ready();
        if let Some(st) = sv.try_reap() {
            if sv.ended_cleanly(&st) {
                sv.phase = Phase::Done;
                continue;
            }
            let what = describe_exit(&st);
            if st.code() == Some(shoal_runtime::EXIT_CONFIG) {
                errors.push(ErrorRecord {
                    service: sv.name.clone(),
                    kind: ErrorKind::Config,
                    detail: format!(
                        "{what}: cannot run with its configuration, not restarted; see {}",
                        sv.log.display()
                    ),
                });
                sv.phase = Phase::Failed;
                continue;
            }
            let backoff = sv.note_crash();
            if sv.quick_crashes > cfg.max_restarts {
                errors.push(ErrorRecord {
                    service: sv.name.clone(),
                    kind: ErrorKind::GaveUp,
                    detail: format!(
                        "{what} after {} restarts ({} crashes in a row, each within {:?} of \
                         being ready)",
                        sv.restarts,
                        sv.quick_crashes,
                        child::STABLE_AFTER
                    ),
                });
                sv.phase = Phase::Failed;
                continue;
            }
            tracing::warn!("{} died ({what}); restarting in {backoff:?}", sv.name);
            sv.crashed_at = Some(Instant::now());
            sv.phase = Phase::WaitingRestart(Instant::now() + backoff);
        }
        if let Phase::WaitingRestart(at) = sv.phase {
            if Instant::now() >= at {
                // Clean what the dead process left in shared memory before it rejoins.
                let _ = cleanup_dead_nodes(&cfg.ipc_prefix);
                // What the new process will resume from (the dead one's last status write).
                let snapshot = report::load_status(&sv.status).counters;
                sv.restarts += 1;
                sv.spawn(exe)
                    .with_context(|| format!("restarting {}", sv.name))?;
                sv.restart_snapshots.push((Instant::now(), snapshot));
            }
        }
    }
    Ok(())
}
