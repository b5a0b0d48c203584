//! What every shoal service process shares: the status report it keeps on disk (so the
//! launcher can aggregate counters even of a SIGKILLed process, and a restarted service can
//! resume), error records, the readiness line and the exit codes.
#![deny(missing_docs)]

pub mod config;
mod error_kind;
pub mod journal;
mod per_client;
pub mod wire;

pub use error_kind::ErrorKind;
pub use per_client::PerClient;

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

/// Line a service prints on stdout once its services are open and it is ready for data.
pub const READY_LINE: &str = "SHOAL_READY";

/// Exit code of a service that cannot run with its configuration (missing dataset, bad
/// arguments): the launcher does not restart it.
pub const EXIT_CONFIG: i32 = 3;

/// Most error records a status keeps verbatim (all are counted).
pub const MAX_ERROR_RECORDS: usize = 200;

/// One error met by a service: where and what. Bad input is counted, not fatal.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ErrorRecord {
    /// Service that met it, e.g. `camera_ingest:0`.
    pub service: String,
    /// Machine-friendly kind, e.g. `corrupt_image`, `malformed_line`, `schema_version`.
    pub kind: ErrorKind,
    /// Human-readable detail naming the file/line or the message.
    pub detail: String,
}

/// The on-disk status of one service: counters, errors, whether it finished, and its
/// crash-recovery state. A service keeps its counters as its own struct (the one list of
/// their names, [`Status::put_counters`]) and its crash-recovery state as another, with a
/// format version ([`Status::set_resume`]); readers take the counters back with the same
/// struct ([`Status::counters_as`]).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Status {
    /// Service name with client index, e.g. `tracker:0`.
    pub service: String,
    /// Process id of the writer.
    pub pid: u32,
    /// How many times this service was started (1 = never restarted).
    pub starts: u64,
    /// True once the service reached the end of its input and stopped by itself.
    pub finished: bool,
    /// The counters by name (frames_published, keyframes_acked, ...), as the service's
    /// counters struct put them ([`Status::put_counters`]).
    pub counters: BTreeMap<String, u64>,
    /// Named gauges that are not counters and are not read back (scale ratio, queue length
    /// at the stop, ...).
    pub values: BTreeMap<String, f64>,
    /// Error counts per kind (all errors, also those not kept in `errors`).
    pub error_counts: BTreeMap<ErrorKind, u64>,
    /// The first [`MAX_ERROR_RECORDS`] errors.
    pub errors: Vec<ErrorRecord>,
    /// The service's crash-recovery state ([`Status::set_resume`]), typed and versioned by
    /// the service, written atomically with the counters so that the two always agree.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub resume: Option<serde_json::Value>,
    /// The service's own report section beyond counters (the tracker's visual-inertial
    /// state, ...): its typed struct ([`Status::set_details`]), read back with the same type
    /// ([`Status::details_as`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub details: Option<serde_json::Value>,
}

/// A crash-recovery state as kept in the status file: the service's own struct with its
/// format version.
#[derive(Debug, Serialize, Deserialize)]
struct Versioned<T> {
    version: u32,
    state: T,
}

impl Status {
    /// A fresh status for `service`.
    pub fn new(service: &str) -> Self {
        Self {
            service: service.to_string(),
            pid: std::process::id(),
            starts: 1,
            ..Self::default()
        }
    }

    /// Sets value `name`.
    pub fn set_value(&mut self, name: &str, v: f64) {
        self.values.insert(name.to_string(), v);
    }

    /// Sets the typed counters `c` (a struct of `u64` fields, `Option`s left out when
    /// `None`): the service's one list of counter names, which the launcher reads back with
    /// [`Status::counters_as`].
    pub fn put_counters<C: Serialize>(&mut self, c: &C) {
        if let Ok(serde_json::Value::Object(m)) = serde_json::to_value(c) {
            for (k, v) in m {
                if let Some(v) = v.as_u64() {
                    self.counters.insert(k, v);
                }
            }
        }
    }

    /// The counters as the service's typed struct (fields not in the file: their default).
    pub fn counters_as<C: DeserializeOwned + Default>(&self) -> C {
        let m: serde_json::Map<String, serde_json::Value> = self
            .counters
            .iter()
            .map(|(k, v)| (k.clone(), serde_json::Value::from(*v)))
            .collect();
        serde_json::from_value(serde_json::Value::Object(m)).unwrap_or_default()
    }

    /// Keeps `d` as the service's report section.
    pub fn set_details<T: Serialize>(&mut self, d: &T) {
        self.details = serde_json::to_value(d).ok();
    }

    /// The service's report section as its typed struct (`None` when absent or of another
    /// shape).
    pub fn details_as<T: DeserializeOwned>(&self) -> Option<T> {
        serde_json::from_value(self.details.clone()?).ok()
    }

    /// Keeps `state`, format `version`, as the crash-recovery state.
    pub fn set_resume<T: Serialize>(&mut self, version: u32, state: &T) {
        self.resume = serde_json::to_value(Versioned { version, state }).ok();
    }

    /// Takes the crash-recovery state a predecessor left, if it is of format `version`
    /// (none left: `None`, no error). One of another version or unreadable is an error
    /// ([`ErrorKind::ResumeState`], counted and named in the log) and the service starts
    /// afresh.
    pub fn take_resume<T: DeserializeOwned>(&mut self, version: u32) -> Option<T> {
        let v = self.resume.take()?;
        let version_of = |v: &serde_json::Value| v.get("version").and_then(|n| n.as_u64());
        match version_of(&v) {
            Some(found) if found != u64::from(version) => {
                let detail =
                    format!("state of format {found}, this build reads {version}: starting afresh");
                self.error(ErrorKind::ResumeState, detail);
                return None;
            }
            _ => {}
        }
        match serde_json::from_value::<Versioned<T>>(v) {
            Ok(r) => Some(r.state),
            Err(e) => {
                let detail = format!("unreadable ({e}): starting afresh");
                self.error(ErrorKind::ResumeState, detail);
                None
            }
        }
    }

    /// Errors of `kind` counted so far.
    pub fn errors_of(&self, kind: ErrorKind) -> u64 {
        self.error_counts.get(&kind).copied().unwrap_or(0)
    }

    /// Records an error: counted by kind, kept verbatim up to [`MAX_ERROR_RECORDS`], and
    /// printed on stderr (the service's log).
    pub fn error(&mut self, kind: ErrorKind, detail: impl Into<String>) {
        let detail = detail.into();
        eprintln!("[{}] error {kind}: {detail}", self.service);
        *self.error_counts.entry(kind).or_insert(0) += 1;
        if self.errors.len() < MAX_ERROR_RECORDS {
            self.errors.push(ErrorRecord {
                service: self.service.clone(),
                kind,
                detail,
            });
        }
    }
}

/// Keeps a [`Status`] in a JSON file, written atomically (temp file + rename).
#[derive(Debug)]
pub struct StatusFile {
    path: Option<PathBuf>,
    last_write: std::time::Instant,
}

impl StatusFile {
    /// A status file at `path` (`None`: keep nothing on disk).
    pub fn new(path: Option<PathBuf>) -> Self {
        Self {
            path,
            last_write: std::time::Instant::now(),
        }
    }

    /// Loads the status a previous run of this service left (after a crash), if any.
    pub fn load_previous(&self) -> Option<Status> {
        let path = self.path.as_ref()?;
        let text = std::fs::read_to_string(path).ok()?;
        serde_json::from_str(&text).ok()
    }

    /// Writes `status` now, with the process's heap in use ([`heap_in_use_bytes`]) beside
    /// it (`heap_in_use_bytes` in the file; memory figures of long runs).
    pub fn write(&mut self, status: &Status) -> std::io::Result<()> {
        self.last_write = std::time::Instant::now();
        let Some(path) = &self.path else {
            return Ok(());
        };
        #[derive(Serialize)]
        struct OnDisk<'a> {
            #[serde(flatten)]
            status: &'a Status,
            #[serde(skip_serializing_if = "Option::is_none")]
            heap_in_use_bytes: Option<u64>,
        }
        write_json_atomic(
            path,
            &OnDisk {
                status,
                heap_in_use_bytes: heap_in_use_bytes(),
            },
        )
    }

    /// The last write is older than `period` (a periodic write is due).
    pub fn due(&self, period: std::time::Duration) -> bool {
        self.last_write.elapsed() >= period
    }

    /// Writes `status` if the last write is older than `period`.
    pub fn write_every(
        &mut self,
        status: &Status,
        period: std::time::Duration,
    ) -> std::io::Result<()> {
        if self.due(period) {
            self.write(status)
        } else {
            Ok(())
        }
    }
}

/// Writes `value` as pretty JSON to `path` atomically.
pub fn write_json_atomic<T: Serialize>(path: &Path, value: &T) -> std::io::Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    let tmp = path.with_extension(format!("json.tmp{}", std::process::id()));
    {
        let mut f = std::fs::File::create(&tmp)?;
        serde_json::to_writer_pretty(&mut f, value).map_err(std::io::Error::other)?;
        f.write_all(b"\n")?;
    }
    std::fs::rename(&tmp, path)
}

/// Bytes of heap the process has allocated and not freed (glibc `mallinfo2`: `uordblks`
/// plus `hblkhd`), `None` where unavailable. Beside the resident size it separates memory the
/// program holds from memory the allocator keeps (fragmentation, free lists).
pub fn heap_in_use_bytes() -> Option<u64> {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: mallinfo2 only reads the allocator's statistics; no arguments.
        let m = unsafe { libc::mallinfo2() };
        Some((m.uordblks + m.hblkhd) as u64)
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        None
    }
}

/// Gives free heap memory back to the system now and then (glibc `malloc_trim`: releases
/// the free pages of every arena). Services with worker threads that allocate and free
/// large transient buffers (keyframe messages, BA problems) otherwise keep resident memory
/// the program no longer holds: on a 20-minute run the mapper's resident size grew 3× more
/// than its heap in use (BENCHMARKS.md, "Long run").
#[derive(Debug)]
pub struct HeapTrimmer {
    period: std::time::Duration,
    last: std::time::Instant,
}

impl HeapTrimmer {
    /// Trims at most once per `period`.
    pub fn new(period: std::time::Duration) -> Self {
        Self {
            period,
            last: std::time::Instant::now(),
        }
    }

    /// Trims if the last trim is older than the period; returns whether it trimmed.
    pub fn maybe_trim(&mut self) -> bool {
        if self.last.elapsed() < self.period {
            return false;
        }
        self.last = std::time::Instant::now();
        #[cfg(all(target_os = "linux", target_env = "gnu"))]
        // SAFETY: malloc_trim only returns free memory of the allocator's arenas.
        unsafe {
            libc::malloc_trim(0);
        }
        true
    }
}

/// Tells the launcher this service is ready.
pub fn signal_ready() {
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{READY_LINE}");
    let _ = out.flush();
}

/// Loads a status left by a previous start of this service and counts this start; a fresh
/// status when there is none.
pub fn resume_status(file: &StatusFile, service: &str) -> Status {
    match file.load_previous() {
        Some(mut prev) if prev.service == service => {
            prev.starts += 1;
            prev.pid = std::process::id();
            prev.finished = false;
            prev
        }
        _ => Status::new(service),
    }
}

/// On a service's first start, the problems the dataset reader met and skipped (file and
/// line), as errors: the IMU files' (`imu`) or the others' (the camera ingest's), so each
/// is reported once.
pub fn report_dataset_issues(status: &mut Status, dataset: &datasets::Dataset, imu: bool) {
    report_input_issues(status, &dataset.issues, imu);
}

/// [`report_dataset_issues`] of a reader's `issues` (those of the IMU files when `imu`, the
/// others otherwise), on a first start only.
pub fn report_input_issues(status: &mut Status, issues: &[datasets::InputIssue], imu: bool) {
    if status.starts != 1 {
        return;
    }
    for i in issues.iter().filter(|i| is_imu_file(&i.path) == imu) {
        let detail = format!("{}:{}: {}", i.path.display(), i.line, i.detail);
        status.error(i.kind.into(), detail);
    }
}

/// The start of every service process, in the one order they share: resume the status a
/// killed predecessor left (counting this start), refuse to run beside services of another
/// schema version on the same IPC prefix, open the iceoryx2 node. The service then opens its
/// ports, calls [`signal_ready`], runs its event loop and writes its final status.
pub struct ServiceStart {
    /// The status file.
    pub file: StatusFile,
    /// The status resumed (or a fresh one).
    pub status: Status,
    /// The IPC prefix in use.
    pub prefix: String,
    /// The service's iceoryx2 node.
    pub node: iceoryx2::node::Node<shm_schema::topics::Ipc>,
}

impl ServiceStart {
    /// Resumes service `service` from `status_path`, checks the prefix (`ipc_prefix`, else
    /// `$SHOAL_IPC_PREFIX` or the default) and creates node `node_name`.
    pub fn open(
        service: &str,
        node_name: &str,
        status_path: Option<PathBuf>,
        ipc_prefix: Option<String>,
    ) -> anyhow::Result<Self> {
        let file = StatusFile::new(status_path);
        let status = resume_status(&file, service);
        let prefix = ipc_prefix.unwrap_or_else(shm_schema::topics::prefix_from_env);
        shm_schema::topics::check_foreign_versions(&prefix)?;
        let node = shm_schema::topics::create_node(node_name, &prefix)?;
        Ok(Self {
            file,
            status,
            prefix,
            node,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn status_round_trip_and_resume() {
        let dir = std::env::temp_dir().join(format!("shoal_rt_{}", std::process::id()));
        let path = dir.join("s.json");
        let mut f = StatusFile::new(Some(path.clone()));
        let mut s = Status::new("tracker:0");
        s.put_counters(&Counts {
            frames: 3,
            flag: None,
        });
        s.error(ErrorKind::CorruptImage, "x.png: bad");
        f.write(&s).unwrap();
        let r = resume_status(&f, "tracker:0");
        assert_eq!(r.counters_as::<Counts>().frames, 3);
        assert_eq!(r.starts, 2);
        assert_eq!(r.errors_of(ErrorKind::CorruptImage), 1);
        let other = resume_status(&f, "tracker:1");
        assert_eq!(other.starts, 1);
        let json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        assert_eq!(json["error_counts"]["corrupt_image"], 1, "{json}");
        assert_eq!(json["errors"][0]["kind"], "corrupt_image", "{json}");
        if cfg!(all(target_os = "linux", target_env = "gnu")) {
            assert!(json["heap_in_use_bytes"].as_u64().unwrap() > 0, "{json}");
        }
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[derive(Debug, Default, PartialEq, Serialize, Deserialize)]
    #[serde(default)]
    struct Counts {
        frames: u64,
        flag: Option<u64>,
    }

    #[derive(Debug, PartialEq, Serialize, Deserialize)]
    struct State {
        next: u64,
    }

    /// Typed counters go through the status's map by name; the resume state comes back only
    /// in its own format version, else it is an error and the service starts afresh.
    #[test]
    fn typed_counters_and_versioned_resume_state() {
        let mut s = Status::new("x:0");
        s.put_counters(&Counts {
            frames: 4,
            flag: None,
        });
        assert_eq!(s.counters.len(), 1, "a None is left out");
        assert_eq!(
            s.counters_as::<Counts>(),
            Counts {
                frames: 4,
                flag: None
            }
        );
        s.set_resume(2, &State { next: 9 });
        let text = serde_json::to_string(&s).unwrap();
        let mut back: Status = serde_json::from_str(&text).unwrap();
        assert_eq!(back.take_resume::<State>(2), Some(State { next: 9 }));
        assert!(back.resume.is_none(), "taken");
        let mut old: Status = serde_json::from_str(&text).unwrap();
        assert_eq!(old.take_resume::<State>(3), None);
        assert_eq!(old.errors_of(ErrorKind::ResumeState), 1);
        assert!(old.errors[0]
            .detail
            .contains("format 2, this build reads 3"));
    }

    /// No resume section (a first start, or a predecessor that never wrote one): nothing to
    /// resume and no error; a section of the right version that does not parse as the
    /// state: an error and a fresh start, never a panic.
    #[test]
    fn missing_or_unreadable_resume_state() {
        let mut s = Status::new("x:0");
        assert_eq!(s.take_resume::<State>(1), None);
        assert!(s.error_counts.is_empty());
        let mut text = serde_json::to_value(&s).unwrap();
        assert!(text.get("resume").is_none(), "no section written: {text}");
        text["resume"] = serde_json::json!({"version": 1, "state": {"nxt": 4}});
        let mut bad: Status = serde_json::from_value(text).unwrap();
        assert_eq!(bad.take_resume::<State>(1), None);
        assert_eq!(bad.errors_of(ErrorKind::ResumeState), 1);
        assert!(
            bad.errors[0].detail.contains("unreadable"),
            "{:?}",
            bad.errors
        );
    }

    // The heap statistics and the trimmer are tested in their own process
    // (`tests/heap_trimmer.rs`): they read process-wide figures.
}

/// How the ingests pace a replay.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ReplayMode {
    /// On the dataset's clock (× a speed factor); a slow consumer loses frames.
    Realtime,
    /// Wait until the consumer took the previous frame: nothing dropped, deterministic.
    Lockstep,
}

impl std::str::FromStr for ReplayMode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "realtime" => Ok(Self::Realtime),
            "lockstep" => Ok(Self::Lockstep),
            other => Err(format!(
                "unknown replay mode '{other}' (realtime | lockstep)"
            )),
        }
    }
}

/// Maps sensor time to host `CLOCK_MONOTONIC` time in real-time replay:
/// `mono = t0_mono + (t - t_origin) / rate`. Both ingests of a client use the same origin
/// (the dataset's first frame time) and the launcher's `t0_mono`, so a restarted ingest
/// knows where "now" is in the stream.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReplayClock {
    /// Host time of the stream origin, ns.
    pub t0_mono_ns: i64,
    /// Sensor time of the stream origin, ns.
    pub t_origin_ns: i64,
    /// Speed factor (2.0 = twice real time).
    pub rate: f64,
}

impl ReplayClock {
    /// Host time at which sensor time `t_ns` is due.
    pub fn due_mono_ns(&self, t_ns: i64) -> i64 {
        self.t0_mono_ns + ((t_ns - self.t_origin_ns) as f64 / self.rate.max(1e-9)) as i64
    }
}

/// True for the IMU files of the supported layouts (`imu0/...`, `gyro_accel.csv`): the IMU
/// ingest reports reader problems of these files, the camera ingest all others.
pub fn is_imu_file(path: &Path) -> bool {
    path.components().any(|c| c.as_os_str() == "imu0")
        || path.file_name().is_some_and(|n| n == "gyro_accel.csv")
}

/// Sensor time both ingests of a client map to the replay start: the earliest frame or IMU
/// sample of the dataset.
pub fn replay_origin_ns(dataset: &datasets::Dataset) -> i64 {
    let f = dataset.frames.first().map(|f| f.t_ns);
    let i = dataset.imu.first().map(|s| s.t_ns);
    match (f, i) {
        (Some(a), Some(b)) => a.min(b),
        (Some(a), None) | (None, Some(a)) => a,
        (None, None) => 0,
    }
}

/// The process exit code of a service's `run` result: 0 on success; on error the message is
/// printed (the service's log) and [`EXIT_CONFIG`] is returned for dataset/configuration
/// errors (the launcher does not restart those), 1 otherwise.
pub fn exit_code<T>(service: &str, result: anyhow::Result<T>) -> i32 {
    match result {
        Ok(_) => 0,
        Err(e) => {
            eprintln!("[{service}] fatal: {e:#}");
            if e.downcast_ref::<datasets::DatasetError>().is_some()
                || e.downcast_ref::<config::ConfigError>().is_some()
            {
                EXIT_CONFIG
            } else {
                1
            }
        }
    }
}

/// Arguments both ingest services take (flattened into their `Params`).
#[derive(Debug, Clone, clap::Args)]
pub struct ReplayArgs {
    /// Client index.
    #[arg(long, default_value_t = 0)]
    pub client: u32,
    /// Dataset folder (format auto-detected).
    #[arg(long)]
    pub dataset: PathBuf,
    /// Calibration file put in place of the dataset's own (`shoal run --calib`).
    #[arg(long)]
    pub calib: Option<PathBuf>,
    /// Image topic of an MCAP / ROS 2 bag dataset (default: found by message type).
    #[arg(long)]
    pub image_topic: Option<String>,
    /// IMU topic of an MCAP / ROS 2 bag dataset (default: found by message type).
    #[arg(long)]
    pub imu_topic: Option<String>,
    /// Replay mode: realtime | lockstep.
    #[arg(long, default_value = "lockstep")]
    pub mode: ReplayMode,
    /// Speed factor in real-time mode.
    #[arg(long, default_value_t = 1.0)]
    pub rate: f64,
    /// Host CLOCK_MONOTONIC ns of the stream origin (real time; default: now).
    #[arg(long)]
    pub t0_mono_ns: Option<i64>,
    /// Status file (JSON), also used to resume after a restart.
    #[arg(long)]
    pub status: Option<PathBuf>,
    /// iceoryx2 resource prefix (default: $SHOAL_IPC_PREFIX or "shoal_").
    #[arg(long)]
    pub ipc_prefix: Option<String>,
    /// Replay at most this many frames (the IMU: samples up to that frame's time).
    #[arg(long)]
    pub max_frames: Option<usize>,
    /// Frame rate of a dataset without timestamps (an image folder), Hz.
    #[arg(long)]
    pub fps: Option<f64>,
    /// Only frames A to B-1 of the dataset (`A..B`, or `A..` to the end), at their own times.
    #[arg(long)]
    pub frames: Option<datasets::FrameRange>,
}

impl ReplayArgs {
    /// The dataset as the arguments say: the calibration file, the MCAP topics, the frame
    /// rate and the frame range ([`datasets::open_with`]).
    pub fn open_dataset(&self) -> Result<datasets::Dataset, datasets::DatasetError> {
        let options = datasets::OpenOptions {
            calib: self.calib.clone(),
            topics: datasets::mcap_bag::Topics {
                image: self.image_topic.clone(),
                imu: self.imu_topic.clone(),
            },
            fps: self.fps,
            frames: self.frames,
        };
        datasets::open_with(&self.dataset, &options)
    }

    /// The [`ServiceStart`] of ingest service `service` (node `{node}_c{client}`).
    pub fn start(&self, service: &str, node: &str) -> anyhow::Result<ServiceStart> {
        let node_name = format!("{node}_c{}", self.client);
        ServiceStart::open(
            service,
            &node_name,
            self.status.clone(),
            self.ipc_prefix.clone(),
        )
    }
}
