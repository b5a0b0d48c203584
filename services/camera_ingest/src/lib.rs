//! Camera ingest service: replays the frames of one dataset (EuRoC ASL, KITTI, phone, or a
//! `shoal sim` output) into the client's `frames` service.
//!
//! This is where a frame enters shoal. Each image is decoded straight into a loaned
//! shared-memory sample ([`datasets::decode_gray_into`] writes into the sample's slice), so no
//! pixel byte is copied between processes. The [`FrameHeader`] carries the mid-row time
//! (t_d applied), the rolling-shutter readout time t_r, exposure, intrinsics and the host
//! publish stamp.
//!
//! Pacing: real time (× a speed factor) on a [`ReplayClock`] shared with the IMU ingest, or
//! lock-step (publish frame k, wait for the tracker's [`FrameAck`] of k, re-send k when no ack
//! comes, e.g. because the tracker was restarted). A corrupt image is reported (file named),
//! counted and skipped; the stream goes on. After a crash the launcher restarts this service,
//! which resumes from its status file: in lock-step at the first unacknowledged frame, in
//! real time at the frame due now, counting the frames it missed as dropped.
//!
//! Core and ports: every decision above is [`CameraReplayCore`]'s (`core.rs`, typed inputs
//! and outputs, host time as a value, tested in-process); this file keeps the ports (the
//! iceoryx2 node, the loaned samples the images are decoded into, the clock, signals, the
//! status file) and the loop that carries out the core's [`CameraStep`]s.
#![deny(missing_docs)]

pub mod config;
pub mod core;

pub use config::{CameraIngestConfig, CameraIngestFlags};
pub use core::{
    CameraCounters, CameraReplayCore, CameraReplayPlan, CameraResume, CameraStep, RESUME_VERSION,
};

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use iceoryx2::prelude::*;
use shm_schema::time::monotonic_ns;
use shm_schema::topics::{self, Ipc};
use shm_schema::{FeatureRecord, FrameAck, FrameHeader, PixelFormat};
use shoal_runtime::{ReplayArgs, ReplayClock, Status};

/// How often the status file is written during the replay.
const STATUS_PERIOD: Duration = Duration::from_millis(200);

/// The camera ingest's command line: the run's replay (dataset, client, pacing, status,
/// IPC prefix) and the configuration ([`CameraIngestConfig`]: a `--config` file, which the
/// launcher writes, and flags overriding it).
#[derive(Debug, Clone, clap::Parser)]
#[command(
    name = "camera_ingest",
    about = "Replay a dataset's camera frames through iceoryx2"
)]
pub struct Params {
    /// Dataset, client, pacing, status and IPC prefix.
    #[command(flatten)]
    pub replay: ReplayArgs,
    /// Configuration file (TOML, the keys of `[camera_ingest]` in `shoal config --print`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Options overriding the configuration file.
    #[command(flatten)]
    pub options: CameraIngestFlags,
}

impl Params {
    /// The configuration: the `--config` file (else the defaults) and the flags over it.
    pub fn config(&self) -> Result<CameraIngestConfig, shoal_runtime::config::ConfigError> {
        shoal_runtime::config::resolve(self.config.as_ref(), |c: &mut CameraIngestConfig| {
            self.options.apply(c)
        })
    }
}

/// The service's name in reports.
pub fn service_name(client: u32) -> String {
    format!("camera_ingest:{client}")
}

/// Runs the service; returns the process exit code (0 at the end of the data).
pub fn main_with(params: Params) -> i32 {
    shoal_runtime::exit_code(&service_name(params.replay.client), run(&params))
}

/// The ports: the iceoryx2 node, the frame publisher and the acknowledgement subscriber.
struct Ports {
    node: Node<Ipc>,
    publisher: iceoryx2::port::publisher::Publisher<Ipc, [u8], FrameHeader>,
    acks: iceoryx2::port::subscriber::Subscriber<Ipc, FrameAck, ()>,
    /// Malformed lines of the feature frames sent since the loop last took them.
    issues: std::cell::RefCell<Vec<datasets::InputIssue>>,
    /// Reads the frames' pixels (image files, or messages of an MCAP recording on demand).
    frames: std::cell::RefCell<datasets::FrameReader>,
}

impl Ports {
    /// Opens the ports of client `c` for frames of `frame_bytes` bytes.
    fn open(node: Node<Ipc>, c: u32, frame_bytes: usize) -> anyhow::Result<Self> {
        let frames = topics::frames_service(&node, c)?;
        let publisher = topics::frame_publisher(&frames, frame_bytes, c)?;
        let acks = topics::subscriber(&topics::frame_ack_service(&node, c)?)?;
        Ok(Self {
            node,
            publisher,
            acks,
            issues: Default::default(),
            frames: Default::default(),
        })
    }

    /// Hands the acknowledgements received to `core`.
    fn receive_acks(&self, core: &mut CameraReplayCore) -> anyhow::Result<()> {
        while let Some(s) = self.acks.receive()? {
            core.on_ack(s.payload());
        }
        Ok(())
    }

    /// Decodes `frame` (its image file, or its message of an MCAP recording) straight into a loaned sample of `frame_bytes` bytes and publishes it
    /// with `header` (stamped now). A corrupt image is an error to count (`Ok(Err)`), not to
    /// stop on.
    fn send(
        &self,
        frame: &datasets::FrameRecord,
        frame_bytes: usize,
        mut header: FrameHeader,
    ) -> anyhow::Result<Result<(), String>> {
        if header.pixel_format == PixelFormat::Features as u32 {
            return self.send_features(&frame.path, frame_bytes, header);
        }
        let mut sample = self
            .publisher
            .loan_slice(frame_bytes)
            .context("loan frame sample")?;
        let (w, h) = (header.width, header.height);
        let decoded = self
            .frames
            .borrow_mut()
            .read_gray_into(frame, sample.payload_mut(), w, h);
        if let Err(e) = decoded {
            return Ok(Err(e.to_string()));
        }
        header.meta.publish_mono_ns = monotonic_ns();
        *sample.user_header_mut() = header;
        sample.send().context("send frame")?;
        Ok(Ok(()))
    }

    /// Publishes the detections file `path` (AprilGrid corners) as a feature frame with
    /// `header` (`PixelFormat::Features`). A file that cannot be read is an error to
    /// count; malformed lines in it are skipped and kept in `issues` for the status (file and
    /// line; the tracker gets the corners that were read).
    fn send_features(
        &self,
        path: &std::path::Path,
        frame_bytes: usize,
        mut header: FrameHeader,
    ) -> anyhow::Result<Result<(), String>> {
        let t_ns = header.t_mid_ns - header.time_offset_ns;
        let mut issues = Vec::new();
        let frame = match datasets::april::read_frame(path, t_ns, &mut issues) {
            Ok(f) => f,
            Err(e) => return Ok(Err(e.to_string())),
        };
        self.issues.borrow_mut().extend(issues);
        let n = frame.observations.len();
        if n * FeatureRecord::BYTES > frame_bytes {
            return Ok(Err(format!(
                "{}: {n} detections, more than a frame sample holds",
                path.display()
            )));
        }
        let mut sample = self
            .publisher
            .loan_slice(n * FeatureRecord::BYTES)
            .context("loan feature sample")?;
        let payload = sample.payload_mut();
        for (o, out) in frame
            .observations
            .iter()
            .zip(payload.chunks_exact_mut(FeatureRecord::BYTES))
        {
            let rec = FeatureRecord {
                track: o.track.0,
                u: o.uv[0] as f32,
                v: o.uv[1] as f32,
            };
            rec.write(out);
        }
        header.meta.publish_mono_ns = monotonic_ns();
        *sample.user_header_mut() = header;
        sample.send().context("send feature frame")?;
        Ok(Ok(()))
    }

    /// Publishes the end of stream (an empty sample) with `header`, stamped now.
    fn send_end_of_stream(&self, mut header: FrameHeader) -> anyhow::Result<()> {
        let mut s = self.publisher.loan_slice(0)?;
        header.meta.publish_mono_ns = monotonic_ns();
        *s.user_header_mut() = header;
        s.send()?;
        Ok(())
    }
}

/// The replay's fixed part for `params` and `dataset`: pacing, header template, frames.
fn plan<'a>(
    params: &Params,
    cfg: CameraIngestConfig,
    dataset: &'a datasets::Dataset,
) -> CameraReplayPlan<'a> {
    let cam = &dataset.camera;
    let n_frames = (params.replay.max_frames.unwrap_or(usize::MAX)).min(dataset.frames.len());
    let (width, height) = (cam.model.width, cam.model.height);
    let features = dataset.kind == datasets::DatasetKind::AprilTracks;
    let template = FrameHeader {
        width,
        height,
        stride: if features {
            FeatureRecord::BYTES as u32
        } else {
            width
        },
        pixel_format: if features {
            PixelFormat::Features as u32
        } else {
            PixelFormat::Gray8 as u32
        },
        time_offset_ns: cam.time_offset_ns,
        intrinsics: shoal_runtime::wire::intrinsics_from_camera(&cam.model).0,
        t_bs: shoal_runtime::wire::wire_from_iso(&cam.t_bs),
        ..FrameHeader::default()
    };
    let clock = ReplayClock {
        t0_mono_ns: params.replay.t0_mono_ns.unwrap_or_else(monotonic_ns),
        t_origin_ns: shoal_runtime::replay_origin_ns(dataset),
        rate: params.replay.rate,
    };
    let period_ns = if cam.rate_hz > 0.0 {
        (1e9 / cam.rate_hz) as i64
    } else {
        100_000_000
    };
    CameraReplayPlan {
        client: params.replay.client,
        mode: params.replay.mode,
        clock,
        period_ns,
        cfg,
        template,
        frames: &dataset.frames[..n_frames],
    }
}

/// Replays the dataset; returns the final status. Stops early (without error) on
/// SIGINT/SIGTERM.
pub fn run(params: &Params) -> anyhow::Result<Status> {
    let cfg = params.config()?;
    let c = params.replay.client;
    let start = params.replay.start(&service_name(c), "camera_ingest")?;
    let mut file = start.file;
    let dataset = params.replay.open_dataset()?;
    let mut core = CameraReplayCore::new(plan(params, cfg, &dataset), start.status);
    shoal_runtime::report_dataset_issues(core.status_mut(), &dataset, false);
    let cam = &dataset.camera.model;
    let frame_bytes = (cam.width as usize * cam.height as usize).max(1);
    let ports = Ports::open(start.node, c, frame_bytes)?;
    shoal_runtime::signal_ready();
    loop {
        ports.receive_acks(&mut core)?;
        let next = core.next_index();
        match core.step(monotonic_ns()) {
            CameraStep::Wait { for_ns } => {
                if ports.node.wait(Duration::from_nanos(for_ns)).is_err() {
                    break;
                }
            }
            CameraStep::Publish { index, header } => {
                match ports.send(&dataset.frames[index], frame_bytes, header)? {
                    Ok(()) => core.on_sent(monotonic_ns()),
                    Err(e) => core.on_corrupt(e).map_err(anyhow::Error::msg)?,
                }
                for i in ports.issues.take() {
                    let detail = format!("{}:{}: {}", i.path.display(), i.line, i.detail);
                    core.status_mut().error(i.kind.into(), detail);
                }
            }
            CameraStep::PublishEndOfStream { header } => {
                ports.send_end_of_stream(header)?;
                core.on_sent(monotonic_ns());
            }
            CameraStep::Continue => {}
            CameraStep::Done => break,
        }
        if core.next_index() != next && file.due(STATUS_PERIOD) {
            let _ = file.write(core.status());
        }
    }
    let status = core.into_status();
    file.write(&status)?;
    Ok(status)
}
