//! IMU ingest service: replays the IMU samples of one dataset into the client's `imu`
//! service, one [`ImuMsg`] per sample, with safe overflow (a dead consumer never blocks it).
//!
//! Pacing follows the camera so that a consumer has the IMU data of a frame when the frame
//! arrives:
//! - real time: each sample at its due time on the [`ReplayClock`] shared with the camera
//!   ingest (same origin, same `t0_mono`);
//! - lock-step: samples up to `t(last acknowledged frame) + lookahead`, read from the
//!   tracker's frame acknowledgements; everything once the camera stream has ended. A dataset
//!   without frames is replayed in real time × rate in both modes.
//!
//! Malformed or non-monotonic lines of the IMU file were skipped by the reader; they are
//! reported here (file and line) and counted. After a restart the service resumes at the
//! sample after the last one it published; in real time samples due while it was down are
//! counted as dropped.
#![deny(missing_docs)]

pub mod config;

pub use config::{ImuIngestConfig, ImuIngestFlags};

use std::path::PathBuf;
use std::time::Duration;

use iceoryx2::node::Node;
use serde::{Deserialize, Serialize};
use shm_schema::time::monotonic_ns;
use shm_schema::topics::{self, Ipc};
use shm_schema::{FrameAck, ImuMsg, MsgMeta, FLAG_END_OF_STREAM};
use shoal_runtime::{ReplayArgs, ReplayClock, ReplayMode, Status};

/// Counters of the IMU ingest (the status file's `counters`), carried on over restarts.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ImuCounters {
    /// Samples published (a restarted ingest publishes the samples after its predecessor's
    /// last status write again).
    pub imu_samples_published: u64,
    /// Real time: samples due while this service was down, skipped.
    pub imu_samples_skipped_late: u64,
}

/// Format version of [`ImuResume`].
pub const RESUME_VERSION: u32 = 1;

/// What a restarted IMU ingest needs of its killed predecessor besides the counters.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ImuResume {
    /// Index of the next sample to replay.
    pub next_index: u64,
}

/// How often the status file is written during the replay.
const STATUS_PERIOD: Duration = Duration::from_millis(200);

/// The counters and the index of the next sample a killed predecessor left in `status` (a
/// fresh start, or a resume state of another format: zeros).
fn resume(status: &mut Status) -> (ImuCounters, usize) {
    let counters = status.counters_as();
    let resume: ImuResume = status.take_resume(RESUME_VERSION).unwrap_or_default();
    (counters, resume.next_index as usize)
}

/// The status with `counters` and the resume position `next` put in.
fn put_state(status: &mut Status, counters: &ImuCounters, next: usize) {
    status.put_counters(counters);
    let resume = ImuResume {
        next_index: next as u64,
    };
    status.set_resume(RESUME_VERSION, &resume);
}

/// The IMU ingest's command line: the run's replay (dataset, client, pacing, status, IPC
/// prefix) and the configuration ([`ImuIngestConfig`]: a `--config` file, which the
/// launcher writes, and flags overriding it).
#[derive(Debug, Clone, clap::Parser)]
#[command(
    name = "imu_ingest",
    about = "Replay a dataset's IMU samples through iceoryx2"
)]
pub struct Params {
    /// Dataset, client, pacing, status and IPC prefix.
    #[command(flatten)]
    pub replay: ReplayArgs,
    /// Configuration file (TOML, the keys of `[imu_ingest]` in `shoal config --print`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Options overriding the configuration file.
    #[command(flatten)]
    pub options: ImuIngestFlags,
}

impl Params {
    /// The configuration: the `--config` file (else the defaults) and the flags over it.
    pub fn config(&self) -> Result<ImuIngestConfig, shoal_runtime::config::ConfigError> {
        shoal_runtime::config::resolve(self.config.as_ref(), |c: &mut ImuIngestConfig| {
            self.options.apply(c)
        })
    }
}

/// The service's name in reports.
pub fn service_name(client: u32) -> String {
    format!("imu_ingest:{client}")
}

/// Runs the service; returns the process exit code (0 at the end of the data).
pub fn main_with(params: Params) -> i32 {
    shoal_runtime::exit_code(&service_name(params.replay.client), run(&params))
}

/// The pacing of the samples: lock-step on the tracker's frame acknowledgements, else the
/// replay clock.
struct Pacer {
    lockstep: bool,
    clock: ReplayClock,
    lookahead_ns: i64,
    /// Lock-step horizon: samples with `t <= horizon` may be published.
    horizon_ns: i64,
    /// A restarted ingest: samples due while it was down are skipped (and counted).
    restarted: bool,
}

/// What the pacing says of the next sample.
enum Pace {
    Go,
    Skip,
    Stop,
}

impl Pacer {
    /// Waits until the sample at `t_ns` may be published.
    fn wait(&mut self, t_ns: i64, node: &Node<Ipc>, acks: &AckSub) -> anyhow::Result<Pace> {
        if self.lockstep {
            return self.wait_for_ack(t_ns, node, acks);
        }
        let due = self.clock.due_mono_ns(t_ns);
        let now = monotonic_ns();
        if self.restarted && now > due + 50_000_000 {
            return Ok(Pace::Skip);
        }
        if due > now && node.wait(Duration::from_nanos((due - now) as u64)).is_err() {
            return Ok(Pace::Stop);
        }
        Ok(Pace::Go)
    }

    /// Lock-step: until a frame acknowledgement moves the horizon past `t_ns`.
    fn wait_for_ack(&mut self, t_ns: i64, node: &Node<Ipc>, acks: &AckSub) -> anyhow::Result<Pace> {
        while t_ns > self.horizon_ns {
            while let Some(a) = acks.receive()? {
                let a: FrameAck = *a.payload();
                if a.meta.check().is_ok() {
                    let h = a.frame_t_ns.saturating_add(self.lookahead_ns);
                    self.horizon_ns = self.horizon_ns.max(h);
                }
            }
            if t_ns <= self.horizon_ns {
                break;
            }
            if node.wait(Duration::from_micros(100)).is_err() {
                return Ok(Pace::Stop);
            }
        }
        Ok(Pace::Go)
    }
}

type AckSub = iceoryx2::port::subscriber::Subscriber<Ipc, FrameAck, ()>;

/// The pacing of `dataset` for `params`, and how many samples to replay.
fn pacer(
    params: &Params,
    cfg: &ImuIngestConfig,
    dataset: &datasets::Dataset,
    status: &Status,
) -> (Pacer, usize) {
    // Samples after the last frame replayed are not needed.
    let t_end = match params.replay.max_frames {
        Some(n) if n < dataset.frames.len() => dataset.frames[n].t_ns,
        _ => i64::MAX,
    };
    let n = dataset.imu.partition_point(|s| s.t_ns < t_end);
    let clock = ReplayClock {
        t0_mono_ns: params.replay.t0_mono_ns.unwrap_or_else(monotonic_ns),
        t_origin_ns: shoal_runtime::replay_origin_ns(dataset),
        rate: params.replay.rate,
    };
    let first_frame_t = dataset.frames.first().map_or(i64::MIN, |f| f.t_ns);
    let lookahead_ns = cfg.lookahead_ms as i64 * 1_000_000;
    let pacer = Pacer {
        lockstep: params.replay.mode == ReplayMode::Lockstep && !dataset.frames.is_empty(),
        clock,
        lookahead_ns,
        horizon_ns: first_frame_t.saturating_add(lookahead_ns),
        restarted: status.starts > 1,
    };
    (pacer, n)
}

/// Replays the IMU samples; returns the final status. Stops early on SIGINT/SIGTERM.
pub fn run(params: &Params) -> anyhow::Result<Status> {
    let cfg = params.config()?;
    let c = params.replay.client;
    let start = params.replay.start(&service_name(c), "imu_ingest")?;
    let (mut file, mut status, node) = (start.file, start.status, start.node);
    let dataset = datasets::open(&params.replay.dataset)?;
    shoal_runtime::report_dataset_issues(&mut status, &dataset, true);
    let publisher = topics::publisher(&topics::imu_service(&node, c)?)?;
    let acks = topics::subscriber(&topics::frame_ack_service(&node, c)?)?;
    shoal_runtime::signal_ready();
    let (mut pacer, n) = pacer(params, &cfg, &dataset, &status);
    let session_id = status.starts as u32;
    let (mut counters, mut next) = resume(&mut status);
    while next < n {
        let s = dataset.imu[next];
        match pacer.wait(s.t_ns, &node, &acks)? {
            Pace::Stop => break,
            Pace::Skip => counters.imu_samples_skipped_late += 1,
            Pace::Go => {
                let meta = MsgMeta::new(c, session_id, next as u64, monotonic_ns());
                let (t_ns, gyro, accel) = (s.t_ns, s.gyro, s.accel);
                publisher.send_copy(ImuMsg {
                    meta,
                    t_ns,
                    gyro,
                    accel,
                })?;
                counters.imu_samples_published += 1;
            }
        }
        next += 1;
        if file.due(STATUS_PERIOD) {
            put_state(&mut status, &counters, next);
            let _ = file.write(&status);
        }
    }
    put_state(&mut status, &counters, next);
    if next >= n {
        let mut meta = MsgMeta::new(c, session_id, n as u64, monotonic_ns());
        meta.flags = FLAG_END_OF_STREAM;
        let eos = ImuMsg {
            meta,
            ..ImuMsg::default()
        };
        publisher.send_copy(eos)?;
        status.finished = true;
    }
    file.write(&status)?;
    Ok(status)
}

#[cfg(test)]
mod tests {
    use super::*;
    use shoal_runtime::ErrorKind;

    fn left(counters: &ImuCounters, next: usize) -> Status {
        let mut s = Status::new(&service_name(0));
        put_state(&mut s, counters, next);
        let text = serde_json::to_string(&s).unwrap();
        let mut back: Status = serde_json::from_str(&text).unwrap();
        back.starts += 1;
        back
    }

    /// A restart resumes the counters and the position its predecessor wrote, under their
    /// names in the status file.
    #[test]
    fn the_resume_state_round_trips() {
        let c = ImuCounters {
            imu_samples_published: 40,
            imu_samples_skipped_late: 2,
        };
        let mut s = left(&c, 42);
        let json = serde_json::to_value(&s).unwrap();
        assert_eq!(json["counters"]["imu_samples_published"], 40);
        assert_eq!(json["resume"]["version"], RESUME_VERSION);
        assert_eq!(json["resume"]["state"]["next_index"], 42);
        assert!(s.values.is_empty(), "no position among the values");
        assert_eq!(resume(&mut s), (c, 42));
        assert!(s.error_counts.is_empty());
    }

    /// A resume state of another format: counted, named, and the replay starts over.
    #[test]
    fn a_resume_state_of_another_version_starts_afresh() {
        let c = ImuCounters {
            imu_samples_published: 40,
            ..ImuCounters::default()
        };
        let mut s = left(&c, 42);
        s.set_resume(RESUME_VERSION + 1, &ImuResume { next_index: 42 });
        assert_eq!(resume(&mut s), (c, 0));
        assert_eq!(s.errors_of(ErrorKind::ResumeState), 1);
    }

    /// No resume section (first start): from the first sample, no error.
    #[test]
    fn no_resume_section_starts_at_the_first_sample() {
        let mut s = Status::new(&service_name(0));
        assert_eq!(resume(&mut s), (ImuCounters::default(), 0));
        assert!(s.error_counts.is_empty());
    }
}
