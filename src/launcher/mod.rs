//! The launcher: the one place that knows the whole topology. It starts every service as a
//! child process (per client: camera_ingest, imu_ingest, tracker; per host: mapper,
//! loop_closer), waits until they are ready, reaps and restarts crashed ones with back-off
//! after cleaning their stale iceoryx2 resources, records poses and latencies, stops
//! everything cleanly at the end of the data or on Ctrl-C, and writes `OUT/report.json`.
pub mod child;
pub mod faults;
pub mod recorder;
pub mod report;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::Context;
use iceoryx2::node::NodeView;
use iceoryx2::prelude::*;
use shm_schema::time::monotonic_ns;
use shm_schema::topics::{self, Ipc};
use shoal_runtime::{ErrorRecord, ReplayMode};

use child::{describe_exit, Phase, Supervised};
use recorder::Recorder;

/// Everything a run needs.
#[derive(Debug, Clone)]
pub struct RunConfig {
    /// One dataset per client.
    pub datasets: Vec<PathBuf>,
    /// Replay mode.
    pub mode: ReplayMode,
    /// Speed factor in real time.
    pub rate: f64,
    /// Output folder.
    pub out: PathBuf,
    /// iceoryx2 resource prefix of the run.
    pub ipc_prefix: String,
    /// Show a progress bar (on a terminal).
    pub progress: bool,
    /// Replay at most this many frames per client.
    pub max_frames: Option<usize>,
    /// Extra arguments for every tracker (e.g. `--frame-log`), `{c}` replaced by the client.
    pub tracker_args: Vec<String>,
    /// Extra arguments for the mapper.
    pub mapper_args: Vec<String>,
    /// Extra arguments for the loop closer.
    pub loop_closer_args: Vec<String>,
    /// Give up (stop everything, report) after this long.
    pub max_duration: Option<Duration>,
    /// Most restarts of a crash-looping service before it is given up: crashes in a row,
    /// each within `child::STABLE_AFTER` of being ready (a service that runs a while between
    /// kills, e.g. under `--chaos`, is always restarted).
    pub max_restarts: u32,
    /// Kill schedule (`--kill SERVICE@SECONDS`).
    pub kills: Vec<faults::KillSpec>,
    /// Chaos (`--chaos SEED:PERIOD`).
    pub chaos: Option<faults::ChaosSpec>,
}

impl RunConfig {
    /// Defaults for `datasets` written to `out`.
    pub fn new(datasets: Vec<PathBuf>, out: PathBuf) -> Self {
        Self {
            datasets,
            mode: ReplayMode::Lockstep,
            rate: 1.0,
            out,
            ipc_prefix: topics::prefix_from_env(),
            progress: true,
            max_frames: None,
            tracker_args: Vec::new(),
            mapper_args: Vec::new(),
            loop_closer_args: Vec::new(),
            max_duration: None,
            max_restarts: 20,
            kills: Vec::new(),
            chaos: None,
        }
    }
}

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

fn services_for(cfg: &RunConfig, t0_mono_ns: i64) -> Vec<Supervised> {
    let n = cfg.datasets.len() as u32;
    let out = &cfg.out;
    let s = |v: &str| v.to_string();
    // Every service knows the replay mode: in lock-step the tracker, mapper and loop closer
    // synchronise so that a run is reproducible.
    let mode = s(match cfg.mode {
        ReplayMode::Lockstep => "lockstep",
        ReplayMode::Realtime => "realtime",
    });
    let mut list = vec![
        Supervised::new(
            "mapper",
            [
                s("mapper"),
                s("--clients"),
                n.to_string(),
                s("--journal"),
                out.join(MAPPER_JOURNAL).display().to_string(),
                s("--out"),
                out.display().to_string(),
                s("--mode"),
                mode.clone(),
            ]
            .into_iter()
            .chain(cfg.mapper_args.iter().cloned())
            .collect(),
            out,
            false,
        ),
        Supervised::new(
            "loop_closer",
            [s("loop-closer"), s("--mode"), mode.clone()]
                .into_iter()
                .chain(cfg.loop_closer_args.iter().cloned())
                .collect(),
            out,
            false,
        ),
    ];
    for (c, ds) in cfg.datasets.iter().enumerate() {
        let mut targs = vec![
            s("tracker"),
            s("--client"),
            c.to_string(),
            s("--mode"),
            mode.clone(),
            s("--spool"),
            out.join(TRACKER_SPOOL)
                .join(format!("c{c}"))
                .display()
                .to_string(),
        ];
        targs.extend(
            cfg.tracker_args
                .iter()
                .map(|a| a.replace("{c}", &c.to_string())),
        );
        list.push(Supervised::new(&format!("tracker:{c}"), targs, out, true));
        for (svc, cli) in [
            ("imu_ingest", "imu-ingest"),
            ("camera_ingest", "camera-ingest"),
        ] {
            let mut args = vec![
                s(cli),
                s("--client"),
                c.to_string(),
                s("--dataset"),
                ds.display().to_string(),
                s("--mode"),
                mode.clone(),
                s("--rate"),
                cfg.rate.to_string(),
                s("--t0-mono-ns"),
                t0_mono_ns.to_string(),
            ];
            if let Some(m) = cfg.max_frames {
                args.extend([s("--max-frames"), m.to_string()]);
            }
            list.push(Supervised::new(&format!("{svc}:{c}"), args, out, true));
        }
    }
    for sv in list.iter_mut() {
        sv.env
            .push((topics::ENV_IPC_PREFIX.to_string(), cfg.ipc_prefix.clone()));
    }
    list
}

/// Runs the pipeline; returns the report (also written to `OUT/report.json`).
pub fn run(cfg: &RunConfig) -> anyhow::Result<report::RunReport> {
    let started = Instant::now();
    std::fs::create_dir_all(&cfg.out)
        .with_context(|| format!("creating output folder {}", cfg.out.display()))?;
    // Fresh status files: a status left by an earlier run in the same folder must not be
    // taken for a crash of this one.
    let _ = std::fs::remove_dir_all(cfg.out.join("status"));
    let _ = std::fs::remove_file(cfg.out.join(MAPPER_JOURNAL));
    let _ = std::fs::remove_dir_all(cfg.out.join(TRACKER_SPOOL));
    // Server outputs of an earlier run in the same folder.
    if let Ok(rd) = std::fs::read_dir(&cfg.out) {
        for e in rd.flatten() {
            let name = e.file_name().to_string_lossy().to_string();
            if ["keyframes_server_c", "keyframes_client_c", "map_growth_c"]
                .iter()
                .any(|p| name.starts_with(p))
            {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
    let mut launcher_errors: Vec<ErrorRecord> = Vec::new();
    let mut datasets = Vec::new();
    for path in &cfg.datasets {
        match datasets::open(path) {
            Ok(d) => datasets.push(d),
            Err(e) => {
                launcher_errors.push(ErrorRecord {
                    service: "launcher".into(),
                    kind: "dataset".into(),
                    detail: e.to_string(),
                });
                let rep = report::RunReport::failed(cfg, launcher_errors, started.elapsed());
                rep.write(&cfg.out.join("report.json"))?;
                anyhow::bail!("{e}");
            }
        }
    }
    let exe = std::env::current_exe().context("locating the shoal binary")?;

    // Stale state of a run killed earlier must not stop this one.
    let cleaned = cleanup_dead_nodes(&cfg.ipc_prefix)?;
    if cleaned > 0 {
        tracing::info!("removed stale iceoryx2 resources of {cleaned} dead node(s)");
    }
    let others = foreign_live_nodes(&cfg.ipc_prefix)?;
    if !others.is_empty() {
        anyhow::bail!(
            "another shoal run is active on iceoryx2 prefix '{}' ({}); stop it or pass \
             --ipc-prefix",
            cfg.ipc_prefix,
            others.join(", ")
        );
    }
    topics::check_foreign_versions(&cfg.ipc_prefix)?;
    let node = topics::create_node("launcher", &cfg.ipc_prefix)?;
    let mut recorder = Recorder::new(&node, cfg.datasets.len() as u32)?;

    // Consumers first, then the sensors, all on one stream origin a little in the future.
    let t0 = monotonic_ns() + 2_000_000_000;
    let mut services = services_for(cfg, t0);
    let consumers = services
        .iter()
        .filter(|s| !s.name.contains("ingest"))
        .count();
    for sv in services.iter_mut().take(consumers) {
        sv.spawn(&exe)
            .with_context(|| format!("starting {}", sv.name))?;
    }
    wait_ready(&mut services[..consumers], Duration::from_secs(30))?;
    for sv in services.iter_mut().skip(consumers) {
        sv.spawn(&exe)
            .with_context(|| format!("starting {}", sv.name))?;
    }
    wait_ready(&mut services[consumers..], Duration::from_secs(30))?;
    tracing::info!("all {} services ready", services.len());

    let mut injector = faults::FaultInjector::new(cfg.kills.clone(), cfg.chaos);
    let ready_at = Instant::now();
    let progress = report::Progress::new(cfg.progress, &datasets, cfg.max_frames);
    let mut interrupted = false;
    let mut timed_out = false;
    loop {
        recorder.drain()?;
        progress.update(&recorder);
        supervise(&mut services, &exe, cfg, &mut launcher_errors)?;
        if !injector.is_empty() {
            injector.step(
                &mut services,
                ready_at.elapsed().as_secs_f64(),
                &recorder.frames_posed(),
            );
        }
        let clients_done = (0..cfg.datasets.len()).all(|c| {
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
        });
        if clients_done {
            break;
        }
        if cfg.max_duration.is_some_and(|d| started.elapsed() > d) {
            timed_out = true;
            launcher_errors.push(ErrorRecord {
                service: "launcher".into(),
                kind: "timeout".into(),
                detail: format!("run stopped after {:?}", started.elapsed()),
            });
            break;
        }
        if node.wait(Duration::from_millis(5)).is_err() {
            interrupted = true;
            break;
        }
    }
    // The trackers are done and the mapper has acknowledged every keyframe, but the loop
    // closer may still be querying the last ones and a correction may be on its way: stop
    // the server side only once it is quiet, so that a loop found at the very end is applied.
    if !interrupted && !timed_out {
        wait_server_quiet(&services, SERVER_QUIET_TIMEOUT);
    }
    // Stop in order: sensors, trackers, then the server side.
    for prefix in [
        "camera_ingest",
        "imu_ingest",
        "tracker",
        "mapper",
        "loop_closer",
    ] {
        for sv in services.iter_mut().filter(|s| s.name.starts_with(prefix)) {
            if sv.child.is_some() {
                let timeout = if sv.name == "mapper" {
                    MAPPER_STOP_TIMEOUT
                } else {
                    Duration::from_secs(5)
                };
                sv.stop(timeout);
            }
        }
        recorder.drain()?;
    }
    progress.finish();
    injector.note_recoveries(&services);
    for s in &injector.skipped {
        launcher_errors.push(ErrorRecord {
            service: "launcher".into(),
            kind: "kill_skipped".into(),
            detail: s.clone(),
        });
    }
    let mut rep = report::RunReport::collect(
        cfg,
        &datasets,
        &services,
        &recorder,
        launcher_errors,
        started.elapsed(),
        interrupted,
        timed_out,
    )?;
    rep.faults_summary = faults::FaultsSummary::of(&injector.events);
    rep.faults = injector.events;
    rep.write(&cfg.out.join("report.json"))?;
    Ok(rep)
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
        let m = report::load_status(&mapper).counters;
        let l = report::load_status(&closer).counters;
        let sum = |c: &std::collections::BTreeMap<String, u64>, suffix: &str| -> u64 {
            c.iter()
                .filter(|(k, _)| k.starts_with('c') && k.ends_with(suffix))
                .map(|(_, v)| *v)
                .sum()
        };
        let caught_up = sum(&l, ".keyframes_received") >= sum(&m, ".keyframes_forwarded")
            && m.get("corrections_received").copied().unwrap_or(0)
                >= l.get("corrections_sent").copied().unwrap_or(0);
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

fn wait_ready(services: &mut [Supervised], timeout: Duration) -> anyhow::Result<()> {
    let start = Instant::now();
    loop {
        let mut all = true;
        for sv in services.iter_mut() {
            sv.poll_ready();
            if sv.phase == Phase::Starting {
                if let Some(st) = sv.try_reap() {
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
            let late: Vec<_> = services
                .iter()
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
            let clean = st.success() && sv.ends_by_itself;
            if clean {
                sv.phase = Phase::Done;
                continue;
            }
            let what = describe_exit(&st);
            if st.code() == Some(shoal_runtime::EXIT_CONFIG) {
                errors.push(ErrorRecord {
                    service: sv.name.clone(),
                    kind: "config".into(),
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
                    kind: "gave_up".into(),
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
