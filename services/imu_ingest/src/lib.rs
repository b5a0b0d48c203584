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

use std::time::Duration;

use shm_schema::time::monotonic_ns;
use shm_schema::topics;
use shm_schema::{FrameAck, ImuMsg, MsgMeta, FLAG_END_OF_STREAM};
use shoal_runtime::{ReplayArgs, ReplayClock, ReplayMode, Status, StatusFile};

/// Parameters of the IMU ingest.
#[derive(Debug, Clone, clap::Parser)]
#[command(
    name = "imu_ingest",
    about = "Replay a dataset's IMU samples through iceoryx2"
)]
pub struct Params {
    /// Dataset, client, pacing, status and IPC prefix.
    #[command(flatten)]
    pub replay: ReplayArgs,
    /// Lock-step: publish samples up to this many ms past the last acknowledged frame.
    #[arg(long, default_value_t = 100)]
    pub lookahead_ms: u64,
}

/// The service's name in reports.
pub fn service_name(client: u32) -> String {
    format!("imu_ingest:{client}")
}

/// Runs the service; returns the process exit code (0 at the end of the data).
pub fn main_with(params: Params) -> i32 {
    shoal_runtime::exit_code(&service_name(params.replay.client), run(&params))
}

/// Replays the IMU samples; returns the final status. Stops early on SIGINT/SIGTERM.
pub fn run(params: &Params) -> anyhow::Result<Status> {
    let name = service_name(params.replay.client);
    let mut file = StatusFile::new(params.replay.status.clone());
    let mut status = shoal_runtime::resume_status(&file, &name);
    let dataset = datasets::open(&params.replay.dataset)?;
    if status.starts == 1 {
        for issue in dataset
            .issues
            .iter()
            .filter(|i| shoal_runtime::is_imu_file(&i.path))
        {
            status.error(
                &issue.kind,
                format!("{}:{}: {}", issue.path.display(), issue.line, issue.detail),
            );
        }
    }
    let prefix = params
        .replay
        .ipc_prefix
        .clone()
        .unwrap_or_else(topics::prefix_from_env);
    topics::check_foreign_versions(&prefix)?;
    let node = topics::create_node(&format!("imu_ingest_c{}", params.replay.client), &prefix)?;
    let imu_service = topics::imu_service(&node, params.replay.client)?;
    let publisher = topics::publisher(&imu_service)?;
    let acks = topics::frame_ack_service(&node, params.replay.client)?;
    let ack_sub = topics::subscriber(&acks)?;
    shoal_runtime::signal_ready();

    // Samples after the last frame replayed are not needed.
    let t_end = match params.replay.max_frames {
        Some(n) if n < dataset.frames.len() => dataset.frames[n].t_ns,
        _ => i64::MAX,
    };
    let n = dataset.imu.partition_point(|s| s.t_ns < t_end);
    let clock = ReplayClock {
        t0_mono_ns: params.replay.t0_mono_ns.unwrap_or_else(monotonic_ns),
        t_origin_ns: shoal_runtime::replay_origin_ns(&dataset),
        rate: params.replay.rate,
    };
    let lockstep = params.replay.mode == ReplayMode::Lockstep && !dataset.frames.is_empty();
    let first_frame_t = dataset.frames.first().map_or(i64::MIN, |f| f.t_ns);
    let lookahead = params.lookahead_ms as i64 * 1_000_000;
    let session_id = status.starts as u32;
    let mut next = status.values.get("next_index").copied().unwrap_or(0.0) as usize;
    // Lock-step horizon: samples with t <= horizon may be published.
    let mut horizon = first_frame_t.saturating_add(lookahead);
    let mut stopped = false;

    while next < n {
        let s = dataset.imu[next];
        if lockstep {
            while s.t_ns > horizon {
                while let Some(a) = ack_sub.receive()? {
                    let a: FrameAck = *a.payload();
                    if a.meta.check().is_ok() {
                        horizon = horizon.max(a.frame_t_ns.saturating_add(lookahead));
                    }
                }
                if s.t_ns <= horizon {
                    break;
                }
                if node.wait(Duration::from_micros(100)).is_err() {
                    stopped = true;
                    break;
                }
            }
        } else {
            let due = clock.due_mono_ns(s.t_ns);
            let now = monotonic_ns();
            if status.starts > 1 && now > due + 50_000_000 {
                status.add("imu_samples_skipped_late", 1);
                next += 1;
                status.set_value("next_index", next as f64);
                continue;
            }
            if due > now && node.wait(Duration::from_nanos((due - now) as u64)).is_err() {
                stopped = true;
            }
        }
        if stopped {
            break;
        }
        let msg = ImuMsg {
            meta: MsgMeta::new(
                params.replay.client,
                session_id,
                next as u64,
                monotonic_ns(),
            ),
            t_ns: s.t_ns,
            gyro: s.gyro,
            accel: s.accel,
        };
        publisher.send_copy(msg)?;
        status.add("imu_samples_published", 1);
        next += 1;
        status.set_value("next_index", next as f64);
        let _ = file.write_every(&status, Duration::from_millis(200));
    }
    if next >= n {
        let mut meta = MsgMeta::new(params.replay.client, session_id, n as u64, monotonic_ns());
        meta.flags = FLAG_END_OF_STREAM;
        publisher.send_copy(ImuMsg {
            meta,
            ..ImuMsg::default()
        })?;
        status.finished = true;
    }
    file.write(&status)?;
    Ok(status)
}
