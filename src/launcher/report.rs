//! `OUT/report.json`: what a run did, aggregated from the services' status files and the
//! recorder; and the progress bar.
use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;

use camera_ingest::CameraCounters;
use imu_ingest::ImuCounters;
use loop_closer::LoopCloserCounters;
use mapper::{MapperClientCounters, MapperCounters};
use serde::de::DeserializeOwned;
use serde::Serialize;
use shoal_runtime::{ErrorKind, ErrorRecord, Status};
use slam_core::metrics::Alignment;
use tracker::core::TrackerCounters;

mod accuracy;

pub use accuracy::AteReport;
use accuracy::{
    evaluate_client, evaluate_file, evaluate_file_aligned, evaluate_poses, split_wire, PlotSpec,
};

use super::child::Supervised;
use super::recorder::{write_tum, Percentiles, Recorder};
use super::RunConfig;

/// A client's localisation in a saved map before its VO initialised (issue 20).
#[derive(Debug, Clone, Default, Serialize, PartialEq)]
pub struct PriorMapReport {
    /// Keyframes and points of the map it tried (the file's largest).
    pub keyframes: u64,
    /// See `keyframes`.
    pub points: u64,
    /// Frames tried against it (until one relocalised, or the VO initialised first).
    pub frames_tried: u64,
    /// Time of the frame that relocalised in it, s (`None`: none did; the VO initialised
    /// on its own and the loop closer had to find the map).
    pub relocalised_t_s: Option<f64>,
    /// The server took the session into the loaded map at its first keyframe, by the
    /// map's points it names (mapper `sessions_joined`); `None` for a client of a remote
    /// server (the server's report says it).
    pub joined_by_server: Option<bool>,
}

impl PriorMapReport {
    /// From the tracker's and the mapper's counters of the client (the mapper's when it is
    /// `local`); `None` without a prior.
    fn of(t: &TrackerCounters, m: &MapperClientCounters, local: bool) -> Option<Self> {
        (t.prior_map_keyframes > 0).then(|| Self {
            keyframes: t.prior_map_keyframes,
            points: t.prior_map_points,
            frames_tried: t.prior_map_frames_tried,
            relocalised_t_s: (t.prior_map_relocalised > 0)
                .then_some(t.prior_map_relocalised_t_ns as f64 * 1e-9),
            joined_by_server: local.then_some(m.sessions_joined > 0),
        })
    }
}

/// Per-client figures.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ClientReport {
    /// Dataset folder.
    pub dataset: String,
    /// What the client ran: `mono` or `vio` (`shoal run --mode`, `tracker.mode`).
    pub client_mode: String,
    /// Why: asked, or what the dataset has (an IMU stream and camera-IMU extrinsics).
    pub client_mode_reason: String,
    /// Where the visual-inertial client's IMU calibration came from (`vio` only).
    pub imu_calibration: Option<String>,
    /// The visual-inertial client's state: inertial initialisation (when, scale, biases) or
    /// why it did not initialise (`vio` only).
    pub vio: Option<tracker::VioReport>,
    /// The calibration mode's estimate with 1σ, its figures, and the parameters that did
    /// not converge (`calib` only).
    pub calib: Option<tracker::core::CalibReport>,
    /// The saved map the monocular client localised in before its VO initialised
    /// (`--load-map`, `tracker.prior_map`); `None` without one.
    pub prior_map: Option<PriorMapReport>,
    /// Posed frames (as tracked, backfilled ones not included) by where the pose came from:
    /// `visual` (monocular, up to scale), `visual_inertial`, `inertial` (IMU alone through
    /// a visual dropout).
    pub frames_by_source: BTreeMap<String, u64>,
    /// Frames with only a gyro-propagated orientation (no pose), written to
    /// `orientation_c{i}.txt` with their state.
    pub frames_orientation_only: u64,
    /// World moves of the visual-inertial client (inertial initialisation and
    /// refinements): every earlier pose of the moved session was re-expressed.
    pub world_moves: u64,
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
    /// Mean bytes of a keyframe message the mapper received (header and payload: keypoint
    /// and IMU records; re-sends included).
    pub keyframe_bytes_mean: f64,
    /// Keyframes the mapper applied per second of data.
    pub keyframes_per_s: f64,
    /// Keyframes the mapper applied with an IMU segment (issue 19): distinct keyframes of
    /// the client in the mapper's journal with IMU records, as `keyframes_applied` (the
    /// mapper's own count of the messages it received lags its last status write when it
    /// is killed).
    pub keyframes_with_imu: u64,
    /// IMU samples in those segments (each keyframe's once).
    pub keyframe_imu_samples: u64,
    /// Keyframes the mapper applied visual-only because their IMU segment did not hold.
    pub imu_segments_refused: u64,
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
    /// The same with a rigid (SE(3)) alignment, no scale: the figure of a metric map (a
    /// visual-inertial client's, `maps[].metric`); a monocular map's is not metric.
    pub ate_server_keyframes_se3: Option<AteReport>,
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
    /// Accuracy of the trajectory against the dataset's ground truth, if both exist, after a
    /// Sim(3) alignment (plotted: `trajectory_c{i}.png`).
    pub ate: Option<AteReport>,
    /// The same trajectory after an SE(3) alignment, no scale correction: the figure a
    /// metric (visual-inertial) run is judged by. A monocular run's scale is arbitrary, so
    /// there it is large and means nothing. Not plotted.
    pub ate_se3: Option<AteReport>,
    /// The same trajectory after a 4-DoF alignment (yaw about z + translation, no scale),
    /// with the tilt (roll/pitch) error: for gravity-aligned visual-inertial runs (world z
    /// up). A monocular run's scale and vertical are arbitrary, so there its figures are
    /// large and mean nothing. Not plotted.
    pub ate_4dof: Option<AteReport>,
    /// Frame publish → pose publish of this client's frames, ms.
    pub latency_ms_publish_to_pose: Percentiles,
    /// Per tracked frame with a live server-map pose, the distance between the camera
    /// centre as tracked and in the server map, mm: a visual-inertial client anchored to
    /// its metric server map tracks in the map's frame (`slam_core::vio::anchor`), so the
    /// two agree up to the drift since the last feedback.
    pub live_server_gap_mm: Percentiles,
    /// The client's output files in the output folder (`*_c{i}.*`), names only.
    pub files: Vec<String>,
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
    /// The server maps at the end: id, clients, keyframes, points, and whether each is
    /// metric and gravity-aligned (a visual-inertial client's).
    pub maps: Vec<mapper::MapSummary>,
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
    /// The saved-map file the server started from (`--load-map`).
    pub map_loaded: Option<super::map_file::MapLoadReport>,
    /// The saved-map file written at the end (`--save-map`).
    pub map_saved: Option<super::map_file::MapSaveReport>,
    /// The recording of each client (`--record`).
    pub record: Vec<super::record::RecordReport>,
    /// `shoal serve`: the remote clients by slot, and what the mapper did with their
    /// keyframes.
    pub remote_clients: Vec<super::serve::RemoteClient>,
    /// `shoal serve` / `shoal client`: the bridges' counters.
    pub bridges: BTreeMap<String, ::bridge::BridgeCounters>,
    /// Status values of the mapper and loop closer about saved maps (`map_*`), read at
    /// the end (for [`RunReport::add_map_files`]).
    #[serde(skip)]
    map_values: BTreeMap<String, BTreeMap<String, f64>>,
}

/// What a report is made of besides the recorder, read from disk and the system once the
/// run is over; the client outputs (trajectories, plots, evaluations) are written here.
struct Gathered {
    statuses: Statuses,
    /// Distinct keyframes per client in the mapper journal, if it could be read.
    journaled: Option<Vec<Journaled>>,
    outputs: Vec<ClientOutputs>,
    /// Per client, its files in the output folder.
    files: Vec<Vec<String>>,
    launcher_cpu_s: f64,
}

impl Gathered {
    /// Reads the status files and the journal, writes each client's outputs and lists them.
    fn read(
        cfg: &RunConfig,
        datasets: &[datasets::Dataset],
        services: &[Supervised],
        recorder: &Recorder,
    ) -> anyhow::Result<Self> {
        let statuses = Statuses::load(services);
        let journal = cfg.out.join(super::MAPPER_JOURNAL);
        let journaled = journal_keyframes(&journal, datasets.len());
        let events = crate::plot::events::corrections_from_journal(&journal);
        let mut outputs = Vec::with_capacity(datasets.len());
        for (c, ds) in datasets.iter().enumerate() {
            let rec = &recorder.clients[c];
            outputs.push(ClientOutputs::write(
                &cfg.out, ds, c, rec, &statuses, &events,
            )?);
        }
        let files = (0..datasets.len())
            .map(|c| client_files(&cfg.out, c))
            .collect();
        Ok(Self {
            statuses,
            journaled,
            outputs,
            files,
            launcher_cpu_s: self_cpu_s(),
        })
    }
}

/// A client's keyframes in the mapper's journal, each distinct keyframe once.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(super) struct Journaled {
    /// Distinct keyframes (session, id).
    pub(super) applied: u64,
    /// Of those, the ones with IMU records.
    with_imu: u64,
    /// Their IMU records.
    imu_samples: u64,
}

/// The keyframes of each client in the mapper journal at `path`.
pub(super) fn journal_keyframes(path: &Path, clients: usize) -> Option<Vec<Journaled>> {
    let contents = shoal_runtime::journal::read_journal(path).ok()?;
    let mut seen: Vec<std::collections::HashMap<(u32, u64), u64>> =
        vec![Default::default(); clients];
    for e in &contents.entries {
        if let shoal_runtime::journal::Entry::Keyframe { client, header, .. } = e {
            if let Some(s) = seen.get_mut(*client as usize) {
                let key = (header.meta.session_id, header.keyframe_id);
                s.insert(key, u64::from(header.n_imu));
            }
        }
    }
    let count = |s: &std::collections::HashMap<(u32, u64), u64>| Journaled {
        applied: s.len() as u64,
        with_imu: s.values().filter(|n| **n > 0).count() as u64,
        imu_samples: s.values().sum(),
    };
    Some(seen.iter().map(count).collect())
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

/// One service as the run left it: the launcher's supervision figures and the status file
/// the service kept.
struct ServiceFacts {
    name: String,
    restarts: u32,
    /// Final phase (`done`, `stopped`, `failed`).
    outcome: &'static str,
    recovery_s: Vec<f64>,
    /// CPU time of all its processes (the reaped ones and the running one so far), s.
    cpu_s: f64,
    status: Status,
}

impl ServiceFacts {
    /// Reads `sv`'s status file and CPU time.
    fn read(sv: &Supervised) -> Self {
        let outcome = match sv.phase {
            super::child::Phase::Done => "done",
            super::child::Phase::Failed => "failed",
            _ => "stopped",
        };
        Self {
            name: sv.name.clone(),
            restarts: sv.restarts,
            outcome,
            recovery_s: sv.recoveries_s.clone(),
            cpu_s: sv.cpu_s + sv.running_cpu_s(),
            status: load_status(&sv.status),
        }
    }
}

/// Every service's facts, in start order, read once; the report's figures come from them
/// through the services' own counter types ([`Status::counters_as`]).
struct Statuses {
    services: Vec<ServiceFacts>,
}

impl Statuses {
    /// Reads every service's status file and CPU time.
    fn load(services: &[Supervised]) -> Self {
        Self {
            services: services.iter().map(ServiceFacts::read).collect(),
        }
    }

    fn facts(&self, svc: &str) -> Option<&ServiceFacts> {
        self.services.iter().find(|s| s.name == svc)
    }

    /// Service `svc`'s counters as its type `C` (zeros when it left no status).
    fn counters<C: DeserializeOwned + Default>(&self, svc: &str) -> C {
        self.facts(svc)
            .map(|s| s.status.counters_as())
            .unwrap_or_default()
    }

    /// Errors of `kind` met by service `svc`.
    fn details_of<D: DeserializeOwned>(&self, svc: &str) -> Option<D> {
        self.facts(svc)?.status.details_as()
    }

    fn errors_of(&self, svc: &str, kind: ErrorKind) -> u64 {
        self.facts(svc).map_or(0, |s| s.status.errors_of(kind))
    }

    /// CPU time of service `svc` over all its starts, s.
    fn cpu_of(&self, svc: &str) -> f64 {
        self.facts(svc).map_or(0.0, |s| s.cpu_s)
    }
}

/// What a run wrote for one client, and the evaluations of it against ground truth.
struct ClientOutputs {
    /// `trajectory_c{i}.txt`, when the tracker posed frames.
    trajectory: Option<String>,
    ate: Option<AteReport>,
    ate_se3: Option<AteReport>,
    ate_4dof: Option<AteReport>,
    ate_client_keyframes: Option<AteReport>,
    ate_server_keyframes: Option<AteReport>,
    ate_server_keyframes_se3: Option<AteReport>,
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
        let mut one = super::sessions::one_frame(out, c, &rec.trajectory, &rec.trajectory_sessions);
        let mapper: MapperCounters = st.counters(mapper::SERVICE_NAME);
        let final_map = mapper.client(c as u32).map_id;
        // A client that relocalised into a loaded map (`--load-map`: the merge keeps the
        // loaded map's frame) has every frame of its linked sessions, before the merge too,
        // written in that map's frame: the frame of the session that saved it.
        if let (true, Some(server)) = (in_loaded_map(final_map), one.server.as_ref()) {
            one.trajectory = server.clone();
            one.report.in_loaded_map = true;
        }
        let (mut trajectory, mut ate) = (None, [None, None, None]);
        if !one.trajectory.is_empty() {
            let (est_t, est_p) = split_wire(&one.trajectory);
            let plot = plot_spec("trajectory");
            // Only the Sim(3) figure is plotted (one PNG per trajectory).
            ate = [
                (Alignment::Sim3, Some(&plot)),
                (Alignment::Se3, None),
                (Alignment::FourDof, None),
            ]
            .map(|(a, plot)| evaluate_poses(ds, &est_t, &est_p, a, plot));
            let path = out.join(format!("trajectory_c{c}.txt"));
            write_tum(&path, &one.trajectory)?;
            trajectory = Some(path.display().to_string());
        }
        if !rec.orientations.is_empty() {
            let path = out.join(format!("orientation_c{c}.txt"));
            write_orientations(&path, &rec.orientations)?;
        }
        let (live, other_maps) = live_server_poses(rec, final_map);
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
        let [ate, ate_se3, ate_4dof] = ate;
        Ok(Self {
            trajectory,
            ate,
            ate_se3,
            ate_4dof,
            ate_client_keyframes: ate_file("keyframes_client"),
            ate_server_keyframes: ate_file("keyframes_server"),
            ate_server_keyframes_se3: evaluate_file_aligned(
                ds,
                &out.join(format!("keyframes_server_c{c}.txt")),
                Alignment::Se3,
                None,
            ),
            ate_server_frames: evaluate_client(ds, &server_traj, &plot_spec("trajectory_server")),
            server_frames_other_maps: other_maps,
            sessions: one.report,
        })
    }
}

/// Whether server map `map_id` is one loaded by `--load-map` (its id names a saved client,
/// [`map_store::remap::SAVED_CLIENT_BASE`] and up; a live map merged into it takes its id).
fn in_loaded_map(map_id: Option<u64>) -> bool {
    map_id.is_some_and(|m| {
        slam_core::ids::MapId::from_raw(m).client().raw() >= map_store::remap::SAVED_CLIENT_BASE
    })
}

/// Writes `orientation_c{i}.txt`: `t qx qy qz qw state` per frame with only a
/// gyro-propagated orientation (camera-to-world, in its VO session's world as last moved;
/// t in seconds), by time.
fn write_orientations(path: &Path, rows: &[(i64, [f64; 4], u32, u32)]) -> std::io::Result<()> {
    use std::fmt::Write as _;
    let mut sorted = rows.to_vec();
    sorted.sort_by_key(|r| r.0);
    let mut text =
        String::from("# t qx qy qz qw state (camera-to-world orientation only, shoal)\n");
    for (t_ns, q, state, _) in &sorted {
        let state = shm_schema::TrackState::from_u32(*state).map_or("unknown", |s| s.name());
        let _ = writeln!(
            text,
            "{:.9} {:.9} {:.9} {:.9} {:.9} {state}",
            *t_ns as f64 * 1e-9,
            q[0],
            q[1],
            q[2],
            q[3]
        );
    }
    std::fs::write(path, text)
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
    journaled: Option<Journaled>,
    o: ClientOutputs,
) -> ClientReport {
    let journaled_applied = journaled.map(|j| j.applied);
    let ci = c as u32;
    let (cam, imu, trk) = (
        camera_ingest::service_name(ci),
        imu_ingest::service_name(ci),
        tracker::service_name(ci),
    );
    let cam_n: CameraCounters = st.counters(&cam);
    let imu_n: ImuCounters = st.counters(&imu);
    let t: TrackerCounters = st.counters(&trk);
    let m = st
        .counters::<MapperCounters>(mapper::SERVICE_NAME)
        .client(ci);
    let lc: LoopCloserCounters = st.counters(loop_closer::SERVICE_NAME);
    let total = cfg.max_frames.unwrap_or(usize::MAX).min(ds.frames.len()) as u64;
    let received = rec.frames_posed;
    let (posed, before_init, lost) = rec.fate_counts();
    // Frames the camera went through (published, skipped late, or corrupt): all of them
    // unless the run was stopped early.
    let offered = cam_n.frames_offered.min(total);
    let corrupt = st.errors_of(&cam, ErrorKind::CorruptImage);
    let dropped = offered.saturating_sub(received + corrupt);
    ClientReport {
        dataset: ds.root.display().to_string(),
        vio: st.details_of::<tracker::VioReport>(&trk),
        calib: st.details_of::<tracker::core::CalibReport>(&trk),
        prior_map: PriorMapReport::of(&t, &m, cfg.connect.is_none()),
        frames_by_source: frames_by_source(rec),
        frames_orientation_only: rec.orientations.len() as u64,
        world_moves: rec.world_moves,
        // Set by the launcher, which decided the mode.
        client_mode: String::new(),
        client_mode_reason: String::new(),
        imu_calibration: None,
        frames_total: total,
        frames_published: cam_n.frames_published,
        frames_received: received,
        frames_tracked: rec.tracked,
        frames_backfilled: rec.backfilled,
        frames_posed: posed,
        frames_unposed: FramesUnposed::new(before_init, lost, corrupt, dropped),
        frames_dropped: dropped,
        frames_skipped_late: cam_n.frames_skipped_late,
        frames_corrupt: corrupt,
        frames_resent: cam_n.frames_resent,
        imu_samples_published: imu_n.imu_samples_published,
        imu_samples_received: t.imu_samples_received,
        imu_samples_dropped: t.imu_samples_dropped + imu_n.imu_samples_skipped_late,
        keyframes_sent: t.keyframes_sent,
        keyframes_acked: t.keyframes_acked_seen,
        keyframes_unacked_at_crash: t.keyframes_unacked_at_crash,
        keyframes_recovered: t.keyframes_recovered,
        keyframes_applied: journaled_applied.unwrap_or(m.keyframes_applied),
        keyframes_received: m.keyframes_received,
        keyframes_kept: m.keyframes_kept,
        server_keyframes: m.server_keyframes,
        server_maps: m.maps,
        keyframes_forwarded: m.keyframes_forwarded,
        loop_keyframes_received: lc.client(ci).keyframes_received,
        cpu_s: client_cpu_s(st, [&trk, &cam, &imu], &m),
        keyframe_bytes_per_s: keyframe_rate(ds, total, m.keyframe_bytes),
        keyframe_bytes_mean: m.keyframe_bytes as f64 / m.keyframes_received.max(1) as f64,
        keyframes_per_s: keyframe_rate(ds, total, journaled_applied.unwrap_or(m.keyframes_applied)),
        keyframes_with_imu: journaled.map_or(m.keyframes_with_imu, |j| j.with_imu),
        keyframe_imu_samples: journaled.map_or(m.imu_samples_received, |j| j.imu_samples),
        imu_segments_refused: m.imu_segments_refused,
        frames_server_pose: rec.tracked_server,
        frames_server_pose_other_maps: o.server_frames_other_maps,
        ate_client_keyframes: o.ate_client_keyframes,
        ate_server_keyframes: o.ate_server_keyframes,
        ate_server_keyframes_se3: o.ate_server_keyframes_se3,
        ate_server_frames: o.ate_server_frames,
        sessions: o.sessions,
        local_mapping: local_mapping(&t).to_string(),
        lockstep_sync: t.lockstep_sync > 0,
        lockstep_sync_timeouts: t.local_mapping_sync_timeouts
            + t.lockstep_server_timeouts
            + t.lockstep_imu_timeouts,
        trajectory: o.trajectory,
        ate: o.ate,
        ate_se3: o.ate_se3,
        ate_4dof: o.ate_4dof,
        latency_ms_publish_to_pose: rec.publish_to_pose.percentiles(),
        live_server_gap_mm: rec.live_server_gap.percentiles(),
        files: Vec::new(),
    }
}

/// CPU time of a client's tracker, camera and IMU ingest (`services`, in that order) and of
/// its mapper handler, s.
fn client_cpu_s(
    st: &Statuses,
    services: [&str; 3],
    m: &mapper::MapperClientCounters,
) -> BTreeMap<String, f64> {
    let [trk, cam, imu] = services;
    BTreeMap::from([
        ("tracker".to_string(), st.cpu_of(trk)),
        ("camera_ingest".to_string(), st.cpu_of(cam)),
        ("imu_ingest".to_string(), st.cpu_of(imu)),
        (
            "mapper_handler".to_string(),
            (m.handle_us + m.idle_us) as f64 * 1e-6,
        ),
    ])
}

/// Posed frames by source (the sources that posed any).
fn frames_by_source(rec: &super::recorder::ClientRecord) -> BTreeMap<String, u64> {
    use shm_schema::PoseSource as S;
    [S::Visual, S::VisualInertial, S::Inertial]
        .into_iter()
        .filter(|s| rec.pose_sources[*s as usize] > 0)
        .map(|s| (s.name().to_string(), rec.pose_sources[s as usize]))
        .collect()
}

/// Keyframe bytes (or keyframes) per second of data over the first `total` frames.
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
fn local_mapping(t: &TrackerCounters) -> &'static str {
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

    /// Writes each client's trajectories and plots ([`ClientOutputs::write`]), reads the
    /// services' status files and the mapper journal ([`Gathered::read`]), then aggregates
    /// them with the recorder ([`RunReport::aggregate`]).
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
        let gathered = Gathered::read(cfg, datasets, services, recorder)?;
        let mut rep = Self::aggregate(cfg, datasets, recorder, gathered, launcher_errors, wall);
        rep.interrupted = interrupted;
        rep.timed_out = timed_out;
        Ok(rep)
    }

    /// The report of what was gathered (pure: no file, process or clock is read).
    fn aggregate(
        cfg: &RunConfig,
        datasets: &[datasets::Dataset],
        recorder: &Recorder,
        g: Gathered,
        launcher_errors: Vec<ErrorRecord>,
        wall: Duration,
    ) -> Self {
        let mut rep = Self::failed(cfg, launcher_errors, wall);
        let st = &g.statuses;
        let clients = datasets.iter().zip(g.outputs).zip(g.files).enumerate();
        for (c, ((ds, o), files)) in clients {
            let applied = g.journaled.as_ref().map(|j| j[c]);
            let mut cl = client_report(cfg, ds, c, &recorder.clients[c], st, applied, o);
            cl.files = files;
            rep.clients.push(cl);
        }
        rep.add_server(st);
        rep.launcher_cpu_s = g.launcher_cpu_s;
        rep.latency_ms = LatencyReport {
            publish_to_pose: recorder.publish_to_pose.percentiles(),
            publish_to_receive: recorder.publish_to_receive.percentiles(),
            tracker_total: recorder.tracker_total.percentiles(),
        };
        rep.add_services(st);
        rep
    }

    /// The mapper's and loop closer's figures.
    fn add_server(&mut self, st: &Statuses) {
        let m: MapperCounters = st.counters(mapper::SERVICE_NAME);
        let l: LoopCloserCounters = st.counters(loop_closer::SERVICE_NAME);
        self.mapper = MapperReport {
            maps: m.maps,
            keyframes: m.keyframes,
            points: m.points,
        };
        self.loops = l.loops;
        self.merges = l.merges;
        self.maps = st
            .details_of::<mapper::MapperDetails>(mapper::SERVICE_NAME)
            .map(|d| d.maps)
            .unwrap_or_default();
        self.corrections_applied = m.corrections_applied();
        for svc in [mapper::SERVICE_NAME, loop_closer::SERVICE_NAME] {
            if let Some(f) = st.facts(svc) {
                let v = &f.status.values;
                let map_values = v.iter().filter(|(k, _)| k.starts_with("map_"));
                let map_values = map_values.map(|(k, x)| (k.clone(), *x)).collect();
                self.map_values.insert(svc.to_string(), map_values);
            }
        }
    }

    /// Completes `map_loaded` with the services' load figures and sets `map_saved` from
    /// the mapper's status.
    pub fn add_map_files(&mut self, cfg: &RunConfig) {
        let empty = BTreeMap::new();
        let m = self.map_values.get(mapper::SERVICE_NAME).unwrap_or(&empty);
        let l = self
            .map_values
            .get(loop_closer::SERVICE_NAME)
            .unwrap_or(&empty);
        if let Some(r) = self.map_loaded.as_mut() {
            r.mapper_load_ms = m.get("map_load_ms").copied();
            r.loop_closer_keyframes = l.get("map_loaded_keyframes").map(|v| *v as u64);
            r.loop_closer_load_ms = l.get("map_load_ms").copied();
            let from_file = l.get("map_loaded_vectors_from_file");
            r.loop_closer_vectors_from_file = from_file.map(|v| *v > 0.0);
            r.localize_only = cfg.localize_only;
            let unchanged = m.get("map_localize_only_unchanged");
            r.maps_unchanged = unchanged.map(|v| *v > 0.0);
        }
        self.map_saved = cfg
            .save_map
            .as_deref()
            .map(|p| super::map_file::saved(p, m));
    }

    /// Every service's errors, restarts, outcome, CPU time and counters.
    fn add_services(&mut self, st: &Statuses) {
        for sv in &st.services {
            self.errors.extend(sv.status.errors.iter().cloned());
            for (kind, n) in &sv.status.error_counts {
                *self
                    .error_counts
                    .entry(format!("{}/{kind}", sv.name))
                    .or_insert(0) += n;
            }
            let service = ServiceReport {
                restarts: sv.restarts,
                outcome: sv.outcome.to_string(),
                recovery_s: sv.recovery_s.clone(),
                cpu_s: sv.cpu_s,
                counters: sv.status.counters.clone(),
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

#[cfg(test)]
mod tests {
    use super::*;

    fn facts(name: &str, status: Status) -> ServiceFacts {
        ServiceFacts {
            name: name.to_string(),
            restarts: 1,
            outcome: "done",
            recovery_s: vec![0.5],
            cpu_s: 2.0,
            status,
        }
    }

    /// The server figures, error counts and per-service sections come from the services'
    /// typed counters and error kinds, under the names report.json has always had.
    #[test]
    fn server_figures_and_services_from_typed_counters() {
        let mut m = MapperCounters {
            maps: 1,
            keyframes: 30,
            points: 900,
            corrections_applied_merge: 1,
            corrections_applied_pose_graph: 2,
            ..MapperCounters::default()
        };
        m.clients.of(0).keyframes_received = 31;
        let mut ms = Status::new(mapper::SERVICE_NAME);
        ms.put_counters(&m);
        ms.set_details(&mapper::MapperDetails {
            maps: vec![mapper::MapSummary {
                id: 1 << 32,
                clients: vec![0, 1],
                keyframes: 30,
                points: 900,
                metric: true,
                gravity_aligned: true,
            }],
        });
        let l = LoopCloserCounters {
            loops: 2,
            merges: 1,
            ..LoopCloserCounters::default()
        };
        let mut ls = Status::new(loop_closer::SERVICE_NAME);
        ls.put_counters(&l);
        let cam = camera_ingest::service_name(0);
        let mut cs = Status::new(&cam);
        cs.error(ErrorKind::CorruptImage, "f.png: bad");
        cs.put_counters(&CameraCounters {
            frames_published: 9,
            ..CameraCounters::default()
        });
        let st = Statuses {
            services: vec![
                facts(mapper::SERVICE_NAME, ms),
                facts(loop_closer::SERVICE_NAME, ls),
                facts(&cam, cs),
            ],
        };
        assert_eq!(st.counters::<CameraCounters>(&cam).frames_published, 9);
        assert_eq!(st.errors_of(&cam, ErrorKind::CorruptImage), 1);
        assert_eq!(
            st.counters::<TrackerCounters>("tracker:0"),
            Default::default()
        );
        let mut rep = RunReport::default();
        rep.add_server(&st);
        rep.add_services(&st);
        let mr = &rep.mapper;
        assert_eq!((mr.maps, mr.keyframes, mr.points), (1, 30, 900));
        assert_eq!((rep.loops, rep.merges, rep.corrections_applied), (2, 1, 3));
        assert_eq!(rep.error_total(), 1);
        let json = serde_json::to_value(&rep).unwrap();
        assert_eq!(json["error_counts"]["camera_ingest:0/corrupt_image"], 1);
        assert_eq!(json["errors"][0]["kind"], "corrupt_image");
        let services = &json["services"];
        assert_eq!(services["mapper"]["counters"]["c0.keyframes_received"], 31);
        assert_eq!(services["loop_closer"]["counters"]["merges"], 1);
        assert_eq!(
            services["camera_ingest:0"]["counters"]["frames_published"],
            9
        );
        assert_eq!(services["mapper"]["outcome"], "done");
        assert_eq!(services["mapper"]["cpu_s"], 2.0);
        let map = &json["maps"][0];
        assert_eq!(map["clients"], serde_json::json!([0, 1]));
        assert_eq!(
            (map["keyframes"].as_u64(), map["metric"].as_bool()),
            (Some(30), Some(true))
        );
        assert_eq!(map["gravity_aligned"], true);
    }
}
