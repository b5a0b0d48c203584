//! `OUT/report.json`: what a run did, aggregated from the services' status files and the
//! recorder; and the progress bar.
use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;

use serde::Serialize;
use shoal_runtime::{ErrorRecord, Status};

use super::child::Supervised;
use super::recorder::{write_tum, Percentiles, Recorder};
use super::RunConfig;

/// Per-client figures.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ClientReport {
    /// Dataset folder.
    pub dataset: String,
    /// Frames in the dataset (after `--max-frames`).
    pub frames_total: u64,
    /// Frames the camera ingest published (re-sends not counted).
    pub frames_published: u64,
    /// Distinct frames the tracker handled (a pose left the tracker for them), counted by the
    /// launcher's recorder: exact across tracker restarts, when the killed tracker's own
    /// counters lag its last status write.
    pub frames_received: u64,
    /// Frames with a valid pose when they were tracked.
    pub frames_tracked: u64,
    /// Frames seen while the VO initialised, given a pose once the map existed: between the
    /// two-view reference and the initialising frame, and before the reference (tracked
    /// backwards against the initial map).
    pub frames_backfilled: u64,
    /// Distinct frames with a valid pose (tracked or backfilled), what evaluation tools count.
    pub frames_posed: u64,
    /// The replayed frames without a pose, by reason: `frames_posed + frames_unposed.total`
    /// is every frame the camera went through.
    pub frames_unposed: FramesUnposed,
    /// Frames of the replayed part of the dataset that got no pose, corrupt images (errors,
    /// never published) not counted: frames published while the tracker was down or that it
    /// never took (real time: a killed tracker drops the frames published until its restart
    /// is ready), frames the camera ingest missed while it was down (real time), and a frame
    /// acknowledged by a tracker killed before it published the pose. In lock-step the ingest
    /// waits for each frame's acknowledgement and re-sends to a restarted tracker, so kills
    /// of any service drop nothing there.
    pub frames_dropped: u64,
    /// Of the dropped frames: the ones the camera ingest skipped because they were due while
    /// it was down (real time).
    pub frames_skipped_late: u64,
    /// Corrupt images (reported as errors, not published).
    pub frames_corrupt: u64,
    /// Frames re-sent in lock-step because no ack came (consumer restarted).
    pub frames_resent: u64,
    /// IMU samples published.
    pub imu_samples_published: u64,
    /// IMU samples the tracker took.
    pub imu_samples_received: u64,
    /// IMU samples lost between ingest and tracker.
    pub imu_samples_dropped: u64,
    /// Keyframe messages the tracker sent (re-sends not counted).
    pub keyframes_sent: u64,
    /// Keyframes the tracker saw acknowledged by the mapper.
    pub keyframes_acked: u64,
    /// Keyframes sent by a tracker that was killed before it saw their acknowledgement (the
    /// mapper still applied them; `keyframes_acked + keyframes_unacked_at_crash ==
    /// keyframes_sent`).
    pub keyframes_unacked_at_crash: u64,
    /// Keyframes a killed tracker had created and not sent yet (its VO window), sent by its
    /// successor from the keyframe spool (included in `keyframes_sent`).
    pub keyframes_recovered: u64,
    /// Keyframes the mapper applied: distinct keyframes of the client in the mapper's
    /// journal (a keyframe is journaled before it is acknowledged; the mapper's own counter
    /// lags its last status write when it is killed).
    pub keyframes_applied: u64,
    /// Keyframe messages the mapper received (re-sends included).
    pub keyframes_received: u64,
    /// Keyframes the client's handler inserted in a server map (before culling).
    pub keyframes_kept: u64,
    /// Keyframes in the client's server maps at the end (after culling).
    pub server_keyframes: u64,
    /// Server maps of the client (one per VO session that reached two keyframes).
    pub server_maps: u64,
    /// Keyframes the mapper forwarded to the loop closer.
    pub keyframes_forwarded: u64,
    /// Forwarded keyframes the loop closer received.
    pub loop_keyframes_received: u64,
    /// CPU time (user + system), s, of the client's processes summed over their restarts
    /// (`tracker`, `camera_ingest`, `imu_ingest`), and `mapper_handler`: the time the
    /// mapper's handler thread of this client spent handling its keyframes and idle steps
    /// (wall time of a compute-bound thread).
    pub cpu_s: BTreeMap<String, f64>,
    /// Keyframe message bytes the mapper received per second of data.
    pub keyframe_bytes_per_s: f64,
    /// Frames published with a pose in the server map (from the mapper's feedback).
    pub frames_server_pose: u64,
    /// Of those, frames whose pose is in another map than the client's final one (a map
    /// merged later, an older session's map): not in `trajectory_server_c{i}.txt` nor in
    /// `ate_server_frames`.
    pub frames_server_pose_other_maps: u64,
    /// ATE of the client VO's keyframes as the mapper received them (`keyframes_client_c{i}.txt`).
    pub ate_client_keyframes: Option<AteReport>,
    /// ATE of the server keyframes of the client's current server map
    /// (`keyframes_server_c{i}.txt`).
    pub ate_server_keyframes: Option<AteReport>,
    /// ATE of the per-frame poses in the client's final server map
    /// (`trajectory_server_c{i}.txt`): each frame relative to its session's keyframes' final
    /// server poses (`sessions.frames_server_from_keyframes`), else as reported live.
    pub ate_server_frames: Option<AteReport>,
    /// The client's VO sessions: which were re-expressed into one frame in
    /// `trajectory_c{i}.txt`, which could not be, and why.
    pub sessions: super::sessions::SessionsReport,
    /// Where the client VO's local mapping ran: `"thread"` (its own thread, the default) or
    /// `"inline"` (in the tracking thread, `tracker.local_mapping = "inline"`); `"none"` when
    /// the tracker ran no VO.
    pub local_mapping: String,
    /// Lock-step synchronisation was on (lock-step replay with `tracker.lockstep_sync`):
    /// the tracker waited for its local-mapping thread before each frame used the map and
    /// for the server's handling of each keyframe it sent, so the run is reproducible.
    pub lockstep_sync: bool,
    /// Waits of that synchronisation that timed out (tracker: local mapping, server
    /// handling, gyro samples); 0 in a reproducible run.
    pub lockstep_sync_timeouts: u64,
    /// Trajectory file written, if any.
    pub trajectory: Option<String>,
    /// Accuracy of the trajectory against the dataset's ground truth, if both exist.
    pub ate: Option<AteReport>,
    /// Frame publish → pose publish of this client's frames, ms.
    pub latency_ms_publish_to_pose: Percentiles,
    /// The client's output files in the output folder (`*_c{i}.*`), names only.
    pub files: Vec<String>,
}

/// Absolute trajectory error after Sim(3) alignment (as `shoal eval --align sim3`).
#[derive(Debug, Clone, Default, Serialize)]
pub struct AteReport {
    /// Associated poses.
    pub n: usize,
    /// RMSE of the position error, m.
    pub rmse_m: f64,
    /// Largest position error, m.
    pub max_m: f64,
    /// Ground-truth path length over the associated poses, m.
    pub path_length_m: f64,
    /// RMSE in % of the path length.
    pub rmse_percent: f64,
    /// Scale of the alignment (monocular scale).
    pub scale: f64,
    /// RPE (translation part, between consecutive associated poses, after the alignment),
    /// RMSE, m: the figure of `shoal eval --align sim3`.
    pub rpe_rmse_m: Option<f64>,
    /// Top-view plot written.
    pub plot: Option<String>,
}

/// A plot written beside an evaluation: its file, the first title line, and the run's loop
/// closures and merges (marked where they touch `client`'s keyframes).
struct PlotSpec<'a> {
    path: std::path::PathBuf,
    title: String,
    client: u32,
    events: &'a [crate::plot::events::CorrectionEvent],
}

impl<'a> PlotSpec<'a> {
    /// `OUT/{name}_c{client}.png`, titled with the dataset, client and `name`.
    fn new(
        out: &Path,
        ds: &datasets::Dataset,
        name: &str,
        client: usize,
        events: &'a [crate::plot::events::CorrectionEvent],
    ) -> Self {
        let dataset = ds.root.file_name().map_or_else(
            || ds.root.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        );
        Self {
            path: out.join(format!("{name}_c{client}.png")),
            title: format!("{dataset} / client {client} / {name}"),
            client: client as u32,
            events,
        }
    }
}

/// Evaluates `traj` against the ground truth of `ds` (Sim(3) alignment) and plots it.
fn evaluate_client(
    ds: &datasets::Dataset,
    traj: &[(i64, shm_schema::Pose)],
    plot: &PlotSpec,
) -> Option<AteReport> {
    let est_t: Vec<i64> = traj.iter().map(|(t, _)| *t).collect();
    let est_p: Vec<_> = traj
        .iter()
        .map(|(_, p)| super::sessions::to_iso(p))
        .collect();
    evaluate_poses(ds, &est_t, &est_p, plot)
}

/// Evaluates the TUM trajectory file `path` like [`evaluate_client`].
fn evaluate_file(ds: &datasets::Dataset, path: &Path, plot: &PlotSpec) -> Option<AteReport> {
    let traj = datasets::trajectory::read_tum(path).ok()?;
    let est_t: Vec<i64> = traj.poses.iter().map(|p| p.t_ns).collect();
    let est_p: Vec<_> = traj.poses.iter().map(|p| p.pose).collect();
    evaluate_poses(ds, &est_t, &est_p, plot)
}

/// Evaluates poses (camera → map) against the ground truth of `ds` (Sim(3)) and plots them.
fn evaluate_poses(
    ds: &datasets::Dataset,
    est_t: &[i64],
    est_p: &[nalgebra::Isometry3<f64>],
    plot: &PlotSpec,
) -> Option<AteReport> {
    let gt = ds.ground_truth.as_ref()?;
    if est_t.len() < 3 {
        return None;
    }
    let gt_t: Vec<i64> = gt.iter().map(|g| g.t_ns).collect();
    let gt_p: Vec<_> = gt.iter().map(|g| g.pose).collect();
    let params = slam_core::metrics::EvalParams {
        alignment: slam_core::metrics::Alignment::Sim3,
        ..Default::default()
    };
    let r = slam_core::metrics::evaluate(&gt_t, &gt_p, est_t, est_p, &params).ok()?;
    let aligned: Vec<_> = r
        .pairs
        .iter()
        .map(|(_, j)| r.alignment.transform_point(&est_p[*j].translation.vector))
        .collect();
    let gt_pts: Vec<_> = gt_p.iter().map(|g| g.translation.vector).collect();
    let mut ate = AteReport {
        n: r.pairs.len(),
        rmse_m: r.ape.rmse,
        max_m: r.ape.max,
        path_length_m: r.ref_path_length_m,
        rmse_percent: 100.0 * r.ape.rmse / r.ref_path_length_m.max(1e-12),
        scale: r.alignment.scale,
        rpe_rmse_m: r.rpe.map(|e| e.rmse),
        plot: None,
    };
    let mut timed: Vec<(i64, nalgebra::Vector3<f64>)> = r
        .pairs
        .iter()
        .zip(&aligned)
        .map(|((_, j), p)| (est_t[*j], *p))
        .collect();
    timed.sort_by_key(|p| p.0);
    let spec = crate::plot::TrajectoryPlot {
        title: plot.title.clone(),
        subtitle: format!(
            "ATE {:.3} m ({:.2}% of {:.1} m), {} poses, Sim(3) aligned, scale {:.2}",
            ate.rmse_m, ate.rmse_percent, ate.path_length_m, ate.n, ate.scale
        ),
        est: &aligned,
        gt: &gt_pts,
        marks: crate::plot::events::marks_for_client(plot.events, plot.client, &timed),
    };
    ate.plot = crate::plot::write_trajectory(&spec, &plot.path)
        .ok()
        .map(|_| plot.path.display().to_string());
    Some(ate)
}

/// Why frames of a client got no pose.
#[derive(Debug, Clone, Default, Serialize, PartialEq, Eq)]
pub struct FramesUnposed {
    /// Sum of the reasons below.
    pub total: u64,
    /// Handled before the VO session's map existed (two-view initialisation not reached, or
    /// not tracked backwards from it).
    pub before_init: u64,
    /// Handled while tracking was lost (relocalisation failed, before a new session).
    pub lost: u64,
    /// Corrupt images (reported as errors, never published).
    pub corrupt: u64,
    /// Never handled by a tracker (`frames_dropped`).
    pub dropped: u64,
}

impl FramesUnposed {
    fn new(before_init: u64, lost: u64, corrupt: u64, dropped: u64) -> Self {
        Self {
            total: before_init + lost + corrupt + dropped,
            before_init,
            lost,
            corrupt,
            dropped,
        }
    }
}

/// Per-service figures.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ServiceReport {
    /// Restarts by the launcher.
    pub restarts: u32,
    /// Final phase (`done`, `stopped`, `failed`).
    pub outcome: String,
    /// Recovery times in s (crash seen → ready again).
    pub recovery_s: Vec<f64>,
    /// CPU time (user + system) of all its processes (every start), s.
    pub cpu_s: f64,
    /// The service's own counters.
    pub counters: BTreeMap<String, u64>,
}

/// Server map figures at the end of the run (all clients).
#[derive(Debug, Clone, Default, Serialize)]
pub struct MapperReport {
    /// Server maps.
    pub maps: u64,
    /// Keyframes in them.
    pub keyframes: u64,
    /// Points in them.
    pub points: u64,
}

/// Latency figures of the run.
#[derive(Debug, Clone, Default, Serialize)]
pub struct LatencyReport {
    /// Frame publish (ingest) → pose publish (tracker).
    pub publish_to_pose: Percentiles,
    /// Frame publish → the tracker holds the frame.
    pub publish_to_receive: Percentiles,
    /// The tracking step inside the tracker.
    pub tracker_total: Percentiles,
}

/// The whole report.
#[derive(Debug, Clone, Default, Serialize)]
pub struct RunReport {
    /// shoal version.
    pub shoal_version: String,
    /// Message schema version.
    pub schema_version: u32,
    /// `lockstep` or `realtime`.
    pub mode: String,
    /// Speed factor (real time).
    pub rate: f64,
    /// Wall time of the run, s.
    pub wall_time_s: f64,
    /// True when the run was stopped by SIGINT/SIGTERM.
    pub interrupted: bool,
    /// True when `--max-seconds` stopped the run.
    pub timed_out: bool,
    /// Per client.
    pub clients: Vec<ClientReport>,
    /// Latencies, ms.
    pub latency_ms: LatencyReport,
    /// The server maps.
    pub mapper: MapperReport,
    /// Per service.
    pub services: BTreeMap<String, ServiceReport>,
    /// Errors (bad input, schema mismatches, crashes given up), at most 200 per service.
    pub errors: Vec<ErrorRecord>,
    /// Error counts per `service/kind`, including those not listed in `errors`.
    pub error_counts: BTreeMap<String, u64>,
    /// Loops the loop closer closed within one map (pose graph corrections sent).
    pub loops: u64,
    /// Map merges the loop closer found (loops between two maps).
    pub merges: u64,
    /// Corrections (merges and pose graph corrections) the mapper applied.
    pub corrections_applied: u64,
    /// CPU time of the launcher process itself (supervision, recorder), s.
    pub launcher_cpu_s: f64,
    /// Kills injected (`--kill`, `--chaos`): service, time, recovery time.
    pub faults: Vec<super::faults::FaultEvent>,
    /// Kills per service and recovery times (p50 / max).
    pub faults_summary: super::faults::FaultsSummary,
    /// `--kill` entries and `--chaos` that killed nothing, quoted as given, with the reason
    /// (the run ended before they were due, their service was not running or does not exist).
    pub faults_unfired: Vec<super::faults::UnfiredFault>,
    /// What produced the run: command line, version and commit, configuration, dataset
    /// checksums.
    pub provenance: super::provenance::Provenance,
}

/// Distinct keyframes (session, id) per client in the mapper journal at `path`.
fn journal_keyframes(path: &Path, clients: usize) -> Option<Vec<u64>> {
    let bytes = std::fs::read(path).ok()?;
    let contents = shoal_runtime::journal::parse(&bytes);
    let mut seen: Vec<std::collections::HashSet<(u32, u64)>> = vec![Default::default(); clients];
    for e in &contents.entries {
        if let shoal_runtime::journal::Entry::Keyframe { client, header, .. } = e {
            if let Some(s) = seen.get_mut(*client as usize) {
                s.insert((header.meta.session_id, header.keyframe_id));
            }
        }
    }
    Some(seen.iter().map(|s| s.len() as u64).collect())
}

/// CPU time (user + system) of the calling process, s.
fn self_cpu_s() -> f64 {
    // SAFETY: an all-zero rusage is valid; getrusage fills it.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: valid out-pointer.
    if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) } != 0 {
        return 0.0;
    }
    let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    tv(u.ru_utime) + tv(u.ru_stime)
}

/// Names of the files of client `c` in the output folder `out` (`*_c{c}.*`), sorted.
fn client_files(out: &Path, c: usize) -> Vec<String> {
    let suffix = format!("_c{c}");
    let mut names: Vec<String> = std::fs::read_dir(out)
        .into_iter()
        .flatten()
        .flatten()
        .filter(|e| e.file_type().is_ok_and(|t| t.is_file()))
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| {
            Path::new(n)
                .file_stem()
                .is_some_and(|s| s.to_string_lossy().ends_with(&suffix))
        })
        .collect();
    names.sort();
    names
}

/// The status file at `path` (default when missing or unreadable).
pub fn load_status(path: &Path) -> Status {
    std::fs::read_to_string(path)
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok())
        .unwrap_or_default()
}

/// The services' status files, by service name, with the launcher's CPU figures.
struct Statuses<'a> {
    map: BTreeMap<String, Status>,
    services: &'a [Supervised],
}

impl<'a> Statuses<'a> {
    fn load(services: &'a [Supervised]) -> Self {
        let map = services
            .iter()
            .map(|s| (s.name.clone(), load_status(&s.status)))
            .collect();
        Self { map, services }
    }

    /// Counter `key` of service `svc` (0 when absent).
    fn get(&self, svc: &str, key: &str) -> u64 {
        self.map.get(svc).map_or(0, |s| s.get(key))
    }

    /// Value `key` of service `svc` (0 when absent).
    fn value(&self, svc: &str, key: &str) -> f64 {
        let v = self.map.get(svc).and_then(|s| s.values.get(key).copied());
        v.unwrap_or(0.0)
    }

    /// Errors of `kind` met by service `svc`.
    fn errors_of(&self, svc: &str, kind: &str) -> u64 {
        let n = self
            .map
            .get(svc)
            .and_then(|s| s.error_counts.get(kind).copied());
        n.unwrap_or(0)
    }

    /// CPU time of service `svc` over all its starts, s.
    fn cpu_of(&self, svc: &str) -> f64 {
        let sv = self.services.iter().find(|s| s.name == svc);
        sv.map_or(0.0, |s| s.cpu_s + s.running_cpu_s())
    }

    /// The mapper's per-client counter `c{c}.{key}`.
    fn mapper_client(&self, c: usize, key: &str) -> u64 {
        self.get("mapper", &format!("c{c}.{key}"))
    }
}

/// What a run wrote for one client, and the evaluations of it against ground truth.
struct ClientOutputs {
    /// `trajectory_c{i}.txt`, when the tracker posed frames.
    trajectory: Option<String>,
    ate: Option<AteReport>,
    ate_client_keyframes: Option<AteReport>,
    ate_server_keyframes: Option<AteReport>,
    ate_server_frames: Option<AteReport>,
    /// Live server poses left out because they are in a map later merged into another.
    server_frames_other_maps: u64,
    sessions: super::sessions::SessionsReport,
}

impl ClientOutputs {
    /// Writes client `c`'s per-frame trajectories (every VO session in one frame; the
    /// server-map poses) and evaluates them and the mapper's keyframe files, with plots.
    fn write(
        out: &Path,
        ds: &datasets::Dataset,
        c: usize,
        rec: &super::recorder::ClientRecord,
        st: &Statuses,
        events: &[crate::plot::events::CorrectionEvent],
    ) -> anyhow::Result<Self> {
        let plot_spec = |name: &str| PlotSpec::new(out, ds, name, c, events);
        // Backfilled poses arrive after later frames: ordered by time, every VO session in
        // one frame (the server's merges tie them), and in the server map.
        let one = super::sessions::one_frame(out, c, &rec.trajectory, &rec.trajectory_sessions);
        let (mut trajectory, mut ate) = (None, None);
        if !one.trajectory.is_empty() {
            ate = evaluate_client(ds, &one.trajectory, &plot_spec("trajectory"));
            let path = out.join(format!("trajectory_c{c}.txt"));
            write_tum(&path, &one.trajectory)?;
            trajectory = Some(path.display().to_string());
        }
        let final_map = st
            .map
            .get("mapper")
            .and_then(|s| s.counters.get(&format!("c{c}.map_id")));
        let (live, other_maps) = live_server_poses(rec, final_map.copied());
        // Every frame relative to its session's keyframes' final server poses when the
        // server map has them (the live poses cover only frames tracked after feedback).
        let server_traj = one.server.unwrap_or(live);
        if !server_traj.is_empty() {
            write_tum(
                &out.join(format!("trajectory_server_c{c}.txt")),
                &server_traj,
            )?;
        }
        let ate_file =
            |name: &str| evaluate_file(ds, &out.join(format!("{name}_c{c}.txt")), &plot_spec(name));
        Ok(Self {
            trajectory,
            ate,
            ate_client_keyframes: ate_file("keyframes_client"),
            ate_server_keyframes: ate_file("keyframes_server"),
            ate_server_frames: evaluate_client(ds, &server_traj, &plot_spec("trajectory_server")),
            server_frames_other_maps: other_maps,
            sessions: one.report,
        })
    }
}

/// The per-frame server poses reported live in the client's final map (poses reported in a
/// map later merged into another are in a different frame), by time; and how many were in
/// other maps.
fn live_server_poses(
    rec: &super::recorder::ClientRecord,
    final_map: Option<u64>,
) -> (Vec<(i64, shm_schema::Pose)>, u64) {
    let mut traj: Vec<(i64, shm_schema::Pose)> = rec
        .server_trajectory
        .iter()
        .filter(|p| final_map.is_none_or(|m| p.2 == m))
        .map(|p| (p.0, p.1))
        .collect();
    let other_maps = (rec.server_trajectory.len() - traj.len()) as u64;
    traj.sort_by_key(|p| p.0);
    traj.dedup_by_key(|p| p.0);
    (traj, other_maps)
}

/// Client `c`'s figures from the status files, the recorder and what was written (pure).
fn client_report(
    cfg: &RunConfig,
    ds: &datasets::Dataset,
    c: usize,
    rec: &super::recorder::ClientRecord,
    st: &Statuses,
    journaled_applied: Option<u64>,
    o: ClientOutputs,
) -> ClientReport {
    let (cam, imu, trk) = (
        format!("camera_ingest:{c}"),
        format!("imu_ingest:{c}"),
        format!("tracker:{c}"),
    );
    let total = cfg.max_frames.unwrap_or(usize::MAX).min(ds.frames.len()) as u64;
    let received = rec.frames_posed;
    let (posed, before_init, lost) = rec.fate_counts();
    // Frames the camera went through (published, skipped late, or corrupt): all of them
    // unless the run was stopped early.
    let offered = (st.value(&cam, "next_index") as u64).min(total);
    let corrupt = st.errors_of(&cam, "corrupt_image");
    let dropped = offered.saturating_sub(received + corrupt);
    let m = |k: &str| st.mapper_client(c, k);
    let t: tracker::core::TrackerCounters = st
        .map
        .get(&trk)
        .map(|s| s.counters_as())
        .unwrap_or_default();
    ClientReport {
        dataset: ds.root.display().to_string(),
        frames_total: total,
        frames_published: st.get(&cam, "frames_published"),
        frames_received: received,
        frames_tracked: rec.tracked,
        frames_backfilled: rec.backfilled,
        frames_posed: posed,
        frames_unposed: FramesUnposed::new(before_init, lost, corrupt, dropped),
        frames_dropped: dropped,
        frames_skipped_late: st.get(&cam, "frames_skipped_late"),
        frames_corrupt: corrupt,
        frames_resent: st.get(&cam, "frames_resent"),
        imu_samples_published: st.get(&imu, "imu_samples_published"),
        imu_samples_received: t.imu_samples_received,
        imu_samples_dropped: t.imu_samples_dropped + st.get(&imu, "imu_samples_skipped_late"),
        keyframes_sent: t.keyframes_sent,
        keyframes_acked: t.keyframes_acked_seen,
        keyframes_unacked_at_crash: t.keyframes_unacked_at_crash,
        keyframes_recovered: t.keyframes_recovered,
        keyframes_applied: journaled_applied.unwrap_or_else(|| m("keyframes_applied")),
        keyframes_received: m("keyframes_received"),
        keyframes_kept: m("keyframes_kept"),
        server_keyframes: m("server_keyframes"),
        server_maps: m("maps"),
        keyframes_forwarded: m("keyframes_forwarded"),
        loop_keyframes_received: st.get("loop_closer", &format!("c{c}.keyframes_received")),
        cpu_s: BTreeMap::from([
            ("tracker".to_string(), st.cpu_of(&trk)),
            ("camera_ingest".to_string(), st.cpu_of(&cam)),
            ("imu_ingest".to_string(), st.cpu_of(&imu)),
            (
                "mapper_handler".to_string(),
                (m("handle_us") + m("idle_us")) as f64 * 1e-6,
            ),
        ]),
        keyframe_bytes_per_s: keyframe_rate(ds, total, m("keyframe_bytes")),
        frames_server_pose: rec.tracked_server,
        frames_server_pose_other_maps: o.server_frames_other_maps,
        ate_client_keyframes: o.ate_client_keyframes,
        ate_server_keyframes: o.ate_server_keyframes,
        ate_server_frames: o.ate_server_frames,
        sessions: o.sessions,
        local_mapping: local_mapping(&t).to_string(),
        lockstep_sync: t.lockstep_sync > 0,
        lockstep_sync_timeouts: t.local_mapping_sync_timeouts
            + t.lockstep_server_timeouts
            + t.lockstep_imu_timeouts,
        trajectory: o.trajectory,
        ate: o.ate,
        latency_ms_publish_to_pose: rec.publish_to_pose.percentiles(),
        files: Vec::new(),
    }
}

/// Keyframe bytes sent per second of data over the first `total` frames.
fn keyframe_rate(ds: &datasets::Dataset, total: u64, bytes: u64) -> f64 {
    let frames = &ds.frames[..(total as usize).min(ds.frames.len())];
    let data_s = match (frames.first(), frames.last()) {
        (Some(a), Some(b)) if b.t_ns > a.t_ns => (b.t_ns - a.t_ns) as f64 * 1e-9,
        _ => 0.0,
    };
    if data_s > 0.0 {
        bytes as f64 / data_s
    } else {
        0.0
    }
}

/// How the tracker ran local mapping: `thread`, `inline`, or `none` (no VO ran).
fn local_mapping(t: &tracker::core::TrackerCounters) -> &'static str {
    let thread = t.local_mapping_thread;
    thread.map_or("none", |t| if t > 0 { "thread" } else { "inline" })
}

impl RunReport {
    /// A report for a run that could not start.
    pub fn failed(cfg: &RunConfig, errors: Vec<ErrorRecord>, wall: Duration) -> Self {
        let mut error_counts = BTreeMap::new();
        for e in &errors {
            *error_counts
                .entry(format!("{}/{}", e.service, e.kind))
                .or_insert(0) += 1;
        }
        Self {
            shoal_version: env!("CARGO_PKG_VERSION").to_string(),
            schema_version: shm_schema::SCHEMA_VERSION,
            mode: format!("{:?}", cfg.mode).to_lowercase(),
            rate: cfg.rate,
            wall_time_s: wall.as_secs_f64(),
            errors,
            error_counts,
            ..Self::default()
        }
    }

    /// Aggregates the services' status files and the recorder, after writing each client's
    /// trajectories and plots ([`ClientOutputs::write`]).
    #[allow(clippy::too_many_arguments)]
    pub fn collect(
        cfg: &RunConfig,
        datasets: &[datasets::Dataset],
        services: &[Supervised],
        recorder: &Recorder,
        launcher_errors: Vec<ErrorRecord>,
        wall: Duration,
        interrupted: bool,
        timed_out: bool,
    ) -> anyhow::Result<Self> {
        let st = Statuses::load(services);
        let journal = cfg.out.join(super::MAPPER_JOURNAL);
        let journaled = journal_keyframes(&journal, datasets.len());
        let events = crate::plot::events::corrections_from_journal(&journal);
        let mut outputs = Vec::with_capacity(datasets.len());
        for (c, ds) in datasets.iter().enumerate() {
            let rec = &recorder.clients[c];
            outputs.push(ClientOutputs::write(&cfg.out, ds, c, rec, &st, &events)?);
        }
        let mut rep = Self::failed(cfg, launcher_errors, wall);
        rep.interrupted = interrupted;
        rep.timed_out = timed_out;
        for (c, (ds, o)) in datasets.iter().zip(outputs).enumerate() {
            let applied = journaled.as_ref().map(|j| j[c]);
            let mut cl = client_report(cfg, ds, c, &recorder.clients[c], &st, applied, o);
            cl.files = client_files(&cfg.out, c);
            rep.clients.push(cl);
        }
        rep.add_server(&st);
        rep.launcher_cpu_s = self_cpu_s();
        rep.latency_ms = LatencyReport {
            publish_to_pose: recorder.publish_to_pose.percentiles(),
            publish_to_receive: recorder.publish_to_receive.percentiles(),
            tracker_total: recorder.tracker_total.percentiles(),
        };
        rep.add_services(services, &st);
        Ok(rep)
    }

    /// The mapper's and loop closer's figures.
    fn add_server(&mut self, st: &Statuses) {
        let g = |k: &str| st.get("mapper", k);
        self.mapper = MapperReport {
            maps: g("maps"),
            keyframes: g("keyframes"),
            points: g("points"),
        };
        self.loops = st.get("loop_closer", "loops");
        self.merges = st.get("loop_closer", "merges");
        self.corrections_applied =
            g("corrections_applied_merge") + g("corrections_applied_pose_graph");
    }

    /// Every service's errors, restarts, outcome, CPU time and counters.
    fn add_services(&mut self, services: &[Supervised], st: &Statuses) {
        for sv in services {
            let status = st.map.get(&sv.name).cloned().unwrap_or_default();
            self.errors.extend(status.errors.iter().cloned());
            for (kind, n) in &status.error_counts {
                *self
                    .error_counts
                    .entry(format!("{}/{kind}", sv.name))
                    .or_insert(0) += n;
            }
            let outcome = match sv.phase {
                super::child::Phase::Done => "done",
                super::child::Phase::Failed => "failed",
                _ => "stopped",
            };
            let service = ServiceReport {
                restarts: sv.restarts,
                outcome: outcome.to_string(),
                recovery_s: sv.recoveries_s.clone(),
                cpu_s: sv.cpu_s + sv.running_cpu_s(),
                counters: status.counters,
            };
            self.services.insert(sv.name.clone(), service);
        }
    }

    /// Total number of errors.
    pub fn error_total(&self) -> u64 {
        self.error_counts.values().sum()
    }

    /// Writes the report as pretty JSON.
    pub fn write(&self, path: &Path) -> anyhow::Result<()> {
        shoal_runtime::write_json_atomic(path, self)?;
        Ok(())
    }
}

/// Progress bars, one per client (hidden when stderr is not a terminal).
pub struct Progress {
    bars: Vec<indicatif::ProgressBar>,
    _multi: indicatif::MultiProgress,
}

impl Progress {
    /// Bars for the clients' frame counts.
    pub fn new(enabled: bool, datasets: &[datasets::Dataset], max_frames: Option<usize>) -> Self {
        let multi = if enabled {
            indicatif::MultiProgress::new()
        } else {
            indicatif::MultiProgress::with_draw_target(indicatif::ProgressDrawTarget::hidden())
        };
        let style = indicatif::ProgressStyle::with_template(
            "client {prefix} [{bar:40}] {pos}/{len} frames {per_sec} {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar());
        let bars = datasets
            .iter()
            .enumerate()
            .map(|(c, d)| {
                let n = max_frames.unwrap_or(usize::MAX).min(d.frames.len());
                let b = multi.add(indicatif::ProgressBar::new(n as u64));
                b.set_style(style.clone());
                b.set_prefix(c.to_string());
                b
            })
            .collect();
        Self {
            bars,
            _multi: multi,
        }
    }

    /// Shows the poses received so far.
    pub fn update(&self, rec: &Recorder) {
        for (b, c) in self.bars.iter().zip(&rec.clients) {
            b.set_position(c.poses);
            b.set_message(format!("tracked {}", c.tracked));
        }
    }

    /// Closes the bars.
    pub fn finish(&self) {
        for b in &self.bars {
            b.finish();
        }
    }
}
