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
#![deny(missing_docs)]

pub mod config;

pub use config::{CameraIngestConfig, CameraIngestFlags};

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use iceoryx2::prelude::*;
use serde::{Deserialize, Serialize};
use shm_schema::time::monotonic_ns;
use shm_schema::topics::{self, Ipc};
use shm_schema::FLAG_RESEND;
use shm_schema::{FrameAck, FrameHeader, MsgMeta, PixelFormat, FLAG_END_OF_STREAM};
use shoal_runtime::{ErrorKind, ReplayArgs, ReplayClock, ReplayMode, Status, StatusFile};

/// Counters of the camera ingest (the status file's `counters`), carried on over restarts.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct CameraCounters {
    /// Frames published (first sends; a restarted ingest publishes the frames after its
    /// predecessor's last status write again).
    pub frames_published: u64,
    /// Frames the replay went through: published, skipped late or corrupt.
    pub frames_offered: u64,
    /// Real time: frames missed while this service was down (due long before it was back).
    pub frames_skipped_late: u64,
    /// Lock-step: re-sends of a frame whose acknowledgement did not come (consumer restarted).
    pub frames_resent: u64,
    /// Lock-step: frames never acknowledged within the ack timeout.
    pub frames_unacked: u64,
}

/// Format version of [`CameraResume`].
pub const RESUME_VERSION: u32 = 1;

/// What a restarted camera ingest needs of its killed predecessor besides the counters.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraResume {
    /// Dataset index of the next frame to replay.
    pub next_index: u64,
}

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

/// The replay of one dataset's frames: what stays fixed over the run.
struct Replay<'a> {
    params: &'a Params,
    cfg: CameraIngestConfig,
    dataset: datasets::Dataset,
    n_frames: usize,
    /// Header fields shared by every frame (intrinsics, `T_BS`, size).
    template: FrameHeader,
    clock: ReplayClock,
    period_ns: i64,
    node: Node<Ipc>,
    publisher: iceoryx2::port::publisher::Publisher<Ipc, [u8], FrameHeader>,
    acks: iceoryx2::port::subscriber::Subscriber<Ipc, FrameAck, ()>,
}

/// What the pacing says of the next frame.
enum Pace {
    /// Publish it now.
    Go,
    /// Missed (real time, far too late): counted and skipped.
    Skip,
    /// SIGINT/SIGTERM while waiting.
    Stop,
}

impl Replay<'_> {
    fn frame_bytes(&self) -> usize {
        (self.template.width as usize * self.template.height as usize).max(1)
    }

    /// Real time: waits until frame `k` is due; lock-step: at once.
    fn pace(&self, k: usize, counters: &mut CameraCounters) -> Pace {
        if self.params.replay.mode != ReplayMode::Realtime {
            return Pace::Go;
        }
        let due = self.clock.due_mono_ns(self.dataset.frames[k].t_ns);
        let now = monotonic_ns();
        // Late by more than a frame period and 250 ms: missed while this service was down (a
        // restart resumes "now"), not a scheduling hiccup of a loaded machine. Counted,
        // never silently skipped.
        if now > due + self.period_ns.max(250_000_000) {
            counters.frames_skipped_late += 1;
            return Pace::Skip;
        }
        if due > now
            && self
                .node
                .wait(Duration::from_nanos((due - now) as u64))
                .is_err()
        {
            return Pace::Stop;
        }
        Pace::Go
    }

    /// The header of frame `k` (publish stamp and flags set when sent).
    fn header(&self, k: usize, session_id: u32) -> FrameHeader {
        let rec = &self.dataset.frames[k];
        FrameHeader {
            meta: MsgMeta::new(self.params.replay.client, session_id, k as u64, 0),
            dataset_index: k as u64,
            t_mid_ns: rec.t_ns,
            readout_ns: rec.readout_ns,
            exposure_ns: rec.exposure_ns,
            ..self.template
        }
    }

    /// Decodes frame `k` straight into a loaned sample and publishes it with `header`
    /// (stamped now). A corrupt image is an error to count, not to stop on.
    fn send(&self, k: usize, mut header: FrameHeader) -> anyhow::Result<Result<(), String>> {
        let (w, h) = (self.template.width, self.template.height);
        let mut sample = self
            .publisher
            .loan_slice(self.frame_bytes())
            .context("loan frame sample")?;
        let path = &self.dataset.frames[k].path;
        if let Err(e) = datasets::decode_gray_into(path, sample.payload_mut(), w, h) {
            return Ok(Err(e.to_string()));
        }
        header.meta.publish_mono_ns = monotonic_ns();
        *sample.user_header_mut() = header;
        sample.send().context("send frame")?;
        Ok(Ok(()))
    }

    /// Lock-step: waits for the tracker's acknowledgement of frame `k`, re-sending it when
    /// none comes (a restarted tracker). Returns `false` on SIGINT/SIGTERM.
    fn lockstep_ack(
        &self,
        k: usize,
        header: FrameHeader,
        acked: &mut Option<u64>,
        p: &mut Progress,
    ) -> anyhow::Result<bool> {
        let resend = || {
            let mut h = header;
            h.meta.flags |= FLAG_RESEND;
            self.send(k, h)?.map_err(anyhow::Error::msg)
        };
        match wait_for_ack(&self.node, &self.acks, k as u64, acked, &self.cfg, resend)? {
            AckWait::Acked => {}
            AckWait::Resent(n) => p.counters.frames_resent += n,
            AckWait::TimedOut => {
                let ms = self.cfg.ack_timeout_ms;
                p.status.error(
                    ErrorKind::AckTimeout,
                    format!("no consumer took frame {k} within {ms} ms"),
                );
                p.counters.frames_unacked += 1;
            }
            AckWait::Stopped => return Ok(false),
        }
        Ok(true)
    }
}

/// Opens the dataset and the ports; reports the reader's problems on a first start.
fn open<'a>(
    params: &'a Params,
    cfg: CameraIngestConfig,
    status: &mut Status,
    node: Node<Ipc>,
) -> anyhow::Result<Replay<'a>> {
    let dataset = datasets::open(&params.replay.dataset)?;
    shoal_runtime::report_dataset_issues(status, &dataset, false);
    let cam = &dataset.camera;
    let n_frames = (params.replay.max_frames.unwrap_or(usize::MAX)).min(dataset.frames.len());
    status.set_value("frames_total", n_frames as f64);
    let (width, height) = (cam.model.width, cam.model.height);
    let template = FrameHeader {
        width,
        height,
        stride: width,
        pixel_format: PixelFormat::Gray8 as u32,
        time_offset_ns: cam.time_offset_ns,
        intrinsics: shoal_runtime::wire::intrinsics_from_camera(&cam.model).0,
        t_bs: shoal_runtime::wire::wire_from_iso(&cam.t_bs),
        ..FrameHeader::default()
    };
    let clock = ReplayClock {
        t0_mono_ns: params.replay.t0_mono_ns.unwrap_or_else(monotonic_ns),
        t_origin_ns: shoal_runtime::replay_origin_ns(&dataset),
        rate: params.replay.rate,
    };
    let period_ns = if cam.rate_hz > 0.0 {
        (1e9 / cam.rate_hz) as i64
    } else {
        100_000_000
    };
    let c = params.replay.client;
    let frames = topics::frames_service(&node, c)?;
    let frame_bytes = (width as usize * height as usize).max(1);
    let publisher = topics::frame_publisher(&frames, frame_bytes, c)?;
    let acks = topics::subscriber(&topics::frame_ack_service(&node, c)?)?;
    Ok(Replay {
        params,
        cfg,
        dataset,
        n_frames,
        template,
        clock,
        period_ns,
        node,
        publisher,
        acks,
    })
}

/// The replay's state: the status (errors), the counters and the resume position, put
/// together into the status when it is written.
struct Progress {
    status: Status,
    counters: CameraCounters,
    /// Dataset index of the next frame.
    next: usize,
}

impl Progress {
    /// Resumes what a killed predecessor left in `status` (a fresh start: zeros).
    fn resume(mut status: Status) -> Self {
        let counters = status.counters_as();
        let resume: CameraResume = status.take_resume(RESUME_VERSION).unwrap_or_default();
        Self {
            status,
            counters,
            next: resume.next_index as usize,
        }
    }

    /// The status with the counters and the resume position put in.
    fn status(&mut self) -> &Status {
        self.status.put_counters(&self.counters);
        let resume = CameraResume {
            next_index: self.next as u64,
        };
        self.status.set_resume(RESUME_VERSION, &resume);
        &self.status
    }

    /// The final status (counters and resume position put in).
    fn into_status(mut self) -> Status {
        self.status();
        self.status
    }

    /// Writes the status if a periodic write is due.
    fn write_if_due(&mut self, file: &mut StatusFile) {
        if file.due(STATUS_PERIOD) {
            let _ = file.write(self.status());
        }
    }
}

/// Replays the dataset; returns the final status. Stops early (without error) on
/// SIGINT/SIGTERM.
pub fn run(params: &Params) -> anyhow::Result<Status> {
    let cfg = params.config()?;
    let c = params.replay.client;
    let start = params.replay.start(&service_name(c), "camera_ingest")?;
    let mut file = start.file;
    let mut p = Progress::resume(start.status);
    let replay = open(params, cfg, &mut p.status, start.node)?;
    shoal_runtime::signal_ready();
    let session_id = p.status.starts as u32;
    let mut acked: Option<u64> = None;
    while p.next < replay.n_frames {
        let next = p.next;
        match replay.pace(next, &mut p.counters) {
            Pace::Stop => break,
            Pace::Skip => {}
            Pace::Go => {
                let header = replay.header(next, session_id);
                match replay.send(next, header)? {
                    Err(e) => p.status.error(ErrorKind::CorruptImage, e),
                    Ok(()) => {
                        p.counters.frames_published += 1;
                        let lockstep = params.replay.mode == ReplayMode::Lockstep;
                        if lockstep && !replay.lockstep_ack(next, header, &mut acked, &mut p)? {
                            break;
                        }
                    }
                }
            }
        }
        p.next += 1;
        p.counters.frames_offered += 1;
        p.write_if_due(&mut file);
    }
    let next = p.next;
    let mut status = p.into_status();
    if next >= replay.n_frames {
        let r = &replay;
        send_end_of_stream(
            &r.node,
            &r.publisher,
            &r.acks,
            c,
            &r.cfg,
            next as u64,
            session_id,
        )?;
        status.finished = true;
    }
    file.write(&status)?;
    Ok(status)
}

enum AckWait {
    Acked,
    Resent(u64),
    TimedOut,
    Stopped,
}

fn wait_for_ack(
    node: &Node<Ipc>,
    acks: &iceoryx2::port::subscriber::Subscriber<Ipc, FrameAck, ()>,
    seq: u64,
    acked: &mut Option<u64>,
    cfg: &CameraIngestConfig,
    mut resend: impl FnMut() -> anyhow::Result<()>,
) -> anyhow::Result<AckWait> {
    let start = monotonic_ns();
    let mut last_send = start;
    let mut resent = 0;
    loop {
        while let Some(s) = acks.receive()? {
            let a = *s.payload();
            if a.meta.check().is_ok() {
                *acked = Some(acked.map_or(a.frame_seq, |x| x.max(a.frame_seq)));
            }
        }
        if acked.is_some_and(|a| a >= seq) {
            return Ok(if resent > 0 {
                AckWait::Resent(resent)
            } else {
                AckWait::Acked
            });
        }
        let now = monotonic_ns();
        if now - start > cfg.ack_timeout_ms as i64 * 1_000_000 {
            return Ok(AckWait::TimedOut);
        }
        if now - last_send > cfg.resend_ms as i64 * 1_000_000 {
            resend()?;
            resent += 1;
            last_send = now;
        }
        if node.wait(Duration::from_micros(50)).is_err() {
            return Ok(AckWait::Stopped);
        }
    }
}

fn send_end_of_stream(
    node: &Node<Ipc>,
    publisher: &iceoryx2::port::publisher::Publisher<Ipc, [u8], FrameHeader>,
    acks: &iceoryx2::port::subscriber::Subscriber<Ipc, FrameAck, ()>,
    client: u32,
    cfg: &CameraIngestConfig,
    seq: u64,
    session_id: u32,
) -> anyhow::Result<()> {
    let send = || -> anyhow::Result<()> {
        let mut s = publisher.loan_slice(0)?;
        let mut meta = MsgMeta::new(client, session_id, seq, monotonic_ns());
        meta.flags = FLAG_END_OF_STREAM;
        *s.user_header_mut() = FrameHeader {
            meta,
            ..FrameHeader::default()
        };
        s.send()?;
        Ok(())
    };
    send()?;
    // The end of stream must reach the consumer even if it restarts now: re-send until it is
    // acknowledged (bounded).
    let mut acked = None;
    let eos = CameraIngestConfig {
        resend_ms: 250,
        ..cfg.clone()
    };
    let _ = wait_for_ack(node, acks, seq, &mut acked, &eos, send)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn left(counters: &CameraCounters, next: usize) -> Status {
        let mut p = Progress::resume(Status::new(&service_name(0)));
        p.counters = counters.clone();
        p.next = next;
        let text = serde_json::to_string(p.status()).unwrap();
        let mut back: Status = serde_json::from_str(&text).unwrap();
        back.starts += 1;
        back
    }

    /// A restart resumes the counters and the position its predecessor wrote, under their
    /// names in the status file.
    #[test]
    fn the_resume_state_round_trips() {
        let c = CameraCounters {
            frames_published: 11,
            frames_offered: 12,
            frames_resent: 1,
            ..CameraCounters::default()
        };
        let s = left(&c, 12);
        let json = serde_json::to_value(&s).unwrap();
        assert_eq!(json["counters"]["frames_published"], 11);
        assert_eq!(json["resume"]["version"], RESUME_VERSION);
        assert_eq!(json["resume"]["state"]["next_index"], 12);
        let p = Progress::resume(s);
        assert_eq!((&p.counters, p.next), (&c, 12));
        assert!(p.status.error_counts.is_empty());
    }

    /// A resume state of another format: counted, named, and the replay starts over (the
    /// counters carry on).
    #[test]
    fn a_resume_state_of_another_version_starts_afresh() {
        let c = CameraCounters {
            frames_published: 11,
            ..CameraCounters::default()
        };
        let mut s = left(&c, 12);
        s.set_resume(RESUME_VERSION + 1, &CameraResume { next_index: 12 });
        let p = Progress::resume(s);
        assert_eq!((&p.counters, p.next), (&c, 0));
        assert_eq!(p.status.errors_of(ErrorKind::ResumeState), 1);
        assert!(p.status.errors[0].detail.contains("starting afresh"));
    }

    /// No resume section (first start): from the first frame, no error.
    #[test]
    fn no_resume_section_starts_at_the_first_frame() {
        let p = Progress::resume(Status::new(&service_name(0)));
        assert_eq!((&p.counters, p.next), (&CameraCounters::default(), 0));
        assert!(p.status.error_counts.is_empty());
    }
}
