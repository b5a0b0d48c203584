//! IMU ingest service: replays the IMU samples of one dataset into the client's `imu`
//! service, one [`ImuMsg`](shm_schema::ImuMsg) per sample, with safe overflow (a dead consumer never blocks it).
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
//!
//! Core and ports: every decision above is [`ImuReplayCore`]'s (`core.rs`, typed inputs and
//! outputs, host time as a value, tested in-process); this file keeps the ports (the
//! iceoryx2 node, publisher and subscriber, the clock, signals, the status file) and the
//! loop that carries out the core's [`ImuStep`]s.
#![deny(missing_docs)]

pub mod config;
pub mod core;

pub use config::{ImuIngestConfig, ImuIngestFlags};
pub use core::{ImuCounters, ImuReplayCore, ImuReplayPlan, ImuResume, ImuStep, RESUME_VERSION};

use std::path::PathBuf;
use std::time::Duration;

use iceoryx2::node::Node;
use shm_schema::time::monotonic_ns;
use shm_schema::topics::{self, Ipc};
use shm_schema::FrameAck;
use shoal_runtime::{ReplayArgs, ReplayClock, Status};

/// How often the status file is written during the replay.
const STATUS_PERIOD: Duration = Duration::from_millis(200);

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

type AckSub = iceoryx2::port::subscriber::Subscriber<Ipc, FrameAck, ()>;

/// The replay's fixed part for `params` and `dataset`: pacing and the samples to replay.
fn plan<'a>(
    params: &Params,
    cfg: &ImuIngestConfig,
    dataset: &'a datasets::Dataset,
) -> ImuReplayPlan<'a> {
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
    ImuReplayPlan {
        client: params.replay.client,
        mode: params.replay.mode,
        clock,
        lookahead_ns: cfg.lookahead_ms as i64 * 1_000_000,
        first_frame_t_ns: dataset.frames.first().map(|f| f.t_ns),
        samples: &dataset.imu[..n],
    }
}

/// Hands the frame acknowledgements received to `core`.
fn receive_acks(acks: &AckSub, core: &mut ImuReplayCore) -> anyhow::Result<()> {
    while let Some(a) = acks.receive()? {
        core.on_ack(a.payload());
    }
    Ok(())
}

/// Replays the IMU samples; returns the final status. Stops early on SIGINT/SIGTERM.
pub fn run(params: &Params) -> anyhow::Result<Status> {
    let cfg = params.config()?;
    let c = params.replay.client;
    let start = params.replay.start(&service_name(c), "imu_ingest")?;
    let (mut file, node): (_, Node<Ipc>) = (start.file, start.node);
    let dataset = params.replay.open_dataset()?;
    let mut core = ImuReplayCore::new(plan(params, &cfg, &dataset), start.status);
    shoal_runtime::report_dataset_issues(core.status_mut(), &dataset, true);
    let publisher = topics::publisher(&topics::imu_service(&node, c)?)?;
    let acks = topics::subscriber(&topics::frame_ack_service(&node, c)?)?;
    shoal_runtime::signal_ready();
    loop {
        receive_acks(&acks, &mut core)?;
        let next = core.next_index();
        match core.step(monotonic_ns()) {
            ImuStep::Wait { for_ns } => {
                if node.wait(Duration::from_nanos(for_ns)).is_err() {
                    break;
                }
            }
            ImuStep::Publish(mut m) => {
                m.meta.publish_mono_ns = monotonic_ns();
                publisher.send_copy(m)?;
                core.on_sent();
            }
            ImuStep::PublishEndOfStream(mut m) => {
                m.meta.publish_mono_ns = monotonic_ns();
                publisher.send_copy(m)?;
            }
            ImuStep::Continue => {}
            ImuStep::Done => break,
        }
        if core.next_index() != next && file.due(STATUS_PERIOD) {
            let _ = file.write(core.status());
        }
    }
    let status = core.into_status();
    file.write(&status)?;
    Ok(status)
}
