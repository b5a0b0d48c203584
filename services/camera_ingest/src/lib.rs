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

use std::time::Duration;

use anyhow::Context;
use iceoryx2::prelude::*;
use shm_schema::time::monotonic_ns;
use shm_schema::topics::{self, Ipc};
use shm_schema::FLAG_RESEND;
use shm_schema::{
    FrameAck, FrameHeader, Intrinsics, MsgMeta, PixelFormat, Pose, FLAG_END_OF_STREAM,
};
use shoal_runtime::{ReplayArgs, ReplayClock, ReplayMode, Status, StatusFile};

/// Parameters of the camera ingest.
#[derive(Debug, Clone, clap::Parser)]
#[command(
    name = "camera_ingest",
    about = "Replay a dataset's camera frames through iceoryx2"
)]
pub struct Params {
    /// Dataset, client, pacing, status and IPC prefix.
    #[command(flatten)]
    pub replay: ReplayArgs,
    /// Lock-step: re-send a frame when its ack has not come after this many ms.
    #[arg(long, default_value_t = 1000)]
    pub resend_ms: u64,
    /// Lock-step: give up waiting for an ack (and count the frame as dropped) after this
    /// many ms.
    #[arg(long, default_value_t = 60_000)]
    pub ack_timeout_ms: u64,
}

/// The service's name in reports.
pub fn service_name(client: u32) -> String {
    format!("camera_ingest:{client}")
}

/// Runs the service; returns the process exit code (0 at the end of the data).
pub fn main_with(params: Params) -> i32 {
    shoal_runtime::exit_code(&service_name(params.replay.client), run(&params))
}

/// Replays the dataset; returns the final status. Stops early (without error) on
/// SIGINT/SIGTERM.
pub fn run(params: &Params) -> anyhow::Result<Status> {
    let name = service_name(params.replay.client);
    let mut file = StatusFile::new(params.replay.status.clone());
    let mut status = shoal_runtime::resume_status(&file, &name);
    let dataset = datasets::open(&params.replay.dataset)?;
    if status.starts == 1 {
        // Problems the reader met and skipped (the IMU ingest reports the IMU files').
        for issue in dataset
            .issues
            .iter()
            .filter(|i| !shoal_runtime::is_imu_file(&i.path))
        {
            status.error(
                &issue.kind,
                format!("{}:{}: {}", issue.path.display(), issue.line, issue.detail),
            );
        }
    }
    let cam = &dataset.camera;
    let (width, height) = (cam.model.width, cam.model.height);
    let n_frames = params
        .replay
        .max_frames
        .unwrap_or(usize::MAX)
        .min(dataset.frames.len());
    status.set_value("frames_total", n_frames as f64);
    let prefix = params
        .replay
        .ipc_prefix
        .clone()
        .unwrap_or_else(topics::prefix_from_env);
    topics::check_foreign_versions(&prefix)?;
    let node = topics::create_node(&format!("camera_ingest_c{}", params.replay.client), &prefix)?;
    let frames = topics::frames_service(&node, params.replay.client)?;
    let frame_bytes = (width as usize * height as usize).max(1);
    let publisher = topics::frame_publisher(&frames, frame_bytes, params.replay.client)?;
    let acks = topics::frame_ack_service(&node, params.replay.client)?;
    let ack_sub = topics::subscriber(&acks)?;
    shoal_runtime::signal_ready();

    let intrinsics = Intrinsics {
        pinhole: [cam.model.fx, cam.model.fy, cam.model.cx, cam.model.cy],
        distortion: [
            cam.model.k1,
            cam.model.k2,
            cam.model.p1,
            cam.model.p2,
            cam.model.k3,
        ],
    };
    let t_bs = {
        let q = cam.t_bs.rotation.quaternion();
        let t = cam.t_bs.translation.vector;
        Pose {
            t: [t.x, t.y, t.z],
            q: [q.i, q.j, q.k, q.w],
        }
    };
    let t_origin = shoal_runtime::replay_origin_ns(&dataset);
    let clock = ReplayClock {
        t0_mono_ns: params.replay.t0_mono_ns.unwrap_or_else(monotonic_ns),
        t_origin_ns: t_origin,
        rate: params.replay.rate,
    };
    let period_ns = if cam.rate_hz > 0.0 {
        (1e9 / cam.rate_hz) as i64
    } else {
        100_000_000
    };
    let session_id = status.starts as u32;
    let mut next = status.values.get("next_index").copied().unwrap_or(0.0) as usize;
    let mut acked: Option<u64> = None;

    while next < n_frames {
        let rec = &dataset.frames[next];
        if params.replay.mode == ReplayMode::Realtime {
            let due = clock.due_mono_ns(rec.t_ns);
            let now = monotonic_ns();
            // Late by more than a frame period and 250 ms: missed while this service was
            // down (a restart resumes "now"), not a scheduling hiccup of a loaded machine.
            if now > due + period_ns.max(250_000_000) {
                // Missed while this service was down (or hopelessly late): counted, never
                // silently skipped.
                status.add("frames_skipped_late", 1);
                next += 1;
                status.set_value("next_index", next as f64);
                continue;
            }
            if due > now && node.wait(Duration::from_nanos((due - now) as u64)).is_err() {
                break;
            }
        }
        let mut header = FrameHeader {
            meta: MsgMeta::new(params.replay.client, session_id, next as u64, 0),
            width,
            height,
            stride: width,
            pixel_format: PixelFormat::Gray8 as u32,
            dataset_index: next as u64,
            t_mid_ns: rec.t_ns,
            readout_ns: rec.readout_ns,
            exposure_ns: rec.exposure_ns,
            time_offset_ns: cam.time_offset_ns,
            intrinsics,
            t_bs,
        };
        let mut sample = publisher
            .loan_slice(frame_bytes)
            .context("loan frame sample")?;
        if let Err(e) = datasets::decode_gray_into(&rec.path, sample.payload_mut(), width, height) {
            status.error("corrupt_image", e.to_string());
            next += 1;
            status.set_value("next_index", next as f64);
            continue;
        }
        header.meta.publish_mono_ns = monotonic_ns();
        *sample.user_header_mut() = header;
        sample.send().context("send frame")?;
        status.add("frames_published", 1);

        if params.replay.mode == ReplayMode::Lockstep {
            match wait_for_ack(&node, &ack_sub, next as u64, &mut acked, params, || {
                let mut s = publisher.loan_slice(frame_bytes)?;
                datasets::decode_gray_into(&rec.path, s.payload_mut(), width, height)
                    .map_err(anyhow::Error::from)?;
                let mut h = header;
                h.meta.flags |= FLAG_RESEND;
                h.meta.publish_mono_ns = monotonic_ns();
                *s.user_header_mut() = h;
                s.send()?;
                Ok(())
            })? {
                AckWait::Acked => {}
                AckWait::Resent(n) => status.add("frames_resent", n),
                AckWait::TimedOut => {
                    status.error(
                        "ack_timeout",
                        format!(
                            "no consumer took frame {next} within {} ms",
                            params.ack_timeout_ms
                        ),
                    );
                    status.add("frames_unacked", 1);
                }
                AckWait::Stopped => break,
            }
        }
        next += 1;
        status.set_value("next_index", next as f64);
        let _ = file.write_every(&status, Duration::from_millis(200));
    }

    if next >= n_frames {
        send_end_of_stream(
            &node,
            &publisher,
            &ack_sub,
            params,
            n_frames as u64,
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
    params: &Params,
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
        if now - start > params.ack_timeout_ms as i64 * 1_000_000 {
            return Ok(AckWait::TimedOut);
        }
        if now - last_send > params.resend_ms as i64 * 1_000_000 {
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
    params: &Params,
    seq: u64,
    session_id: u32,
) -> anyhow::Result<()> {
    let send = || -> anyhow::Result<()> {
        let mut s = publisher.loan_slice(0)?;
        let mut meta = MsgMeta::new(params.replay.client, session_id, seq, monotonic_ns());
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
    let eos_params = Params {
        resend_ms: 250,
        ack_timeout_ms: params.ack_timeout_ms,
        ..params.clone()
    };
    let _ = wait_for_ack(node, acks, seq, &mut acked, &eos_params, send)?;
    Ok(())
}
