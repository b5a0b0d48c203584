//! The camera ingest's core: the replay position, the counters and the crash-recovery state,
//! and every decision of the replay, with typed inputs and outputs and no IPC, file or clock
//! access of its own (host times come in as `now_ns`), so that it is tested in-process
//! (`core/tests.rs`).
//!
//! The ports drive it: they hand it the acknowledgements received ([`CameraReplayCore::on_ack`]),
//! ask it what to do now ([`CameraReplayCore::step`]) and carry out the [`CameraStep`] it
//! returns: wait, decode a frame straight into a loaned sample and publish it (then
//! [`CameraReplayCore::on_sent`] or, for an undecodable image,
//! [`CameraReplayCore::on_corrupt`]), publish the end of stream, or stop. Decoding stays in the
//! ports (zero-copy into the sample). Counters and errors go to the core's [`Status`].
//!
//! Pacing: real time on the [`ReplayClock`] (a frame due long before now, e.g. after a
//! restart, is skipped and counted in `frames_skipped_late`), or lock-step (after frame k,
//! wait for its [`FrameAck`], re-send it with [`FLAG_RESEND`] every `resend_ms`, give up after
//! `ack_timeout_ms` with an [`ErrorKind::AckTimeout`] and `frames_unacked`). The end of
//! stream is re-sent every 250 ms until acknowledged, for at most `ack_timeout_ms`.
use serde::{Deserialize, Serialize};
use shm_schema::{
    FrameAck, FrameHeader, MsgMeta, FLAG_END_OF_STREAM, FLAG_IMU_REPLAY, FLAG_RESEND,
};
use shoal_runtime::{ErrorKind, ReplayClock, ReplayMode, Status};

use crate::CameraIngestConfig;

#[cfg(test)]
mod tests;

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

/// Lock-step: how often the ports look for an acknowledgement, ns.
pub const ACK_POLL_NS: u64 = 50_000;
/// Real time: a frame late by more than this (or a frame period, if longer) was missed while
/// the service was down (a restart resumes "now"), not a scheduling hiccup of a loaded
/// machine: counted and skipped, never silently.
pub const LATE_MIN_NS: i64 = 250_000_000;
/// Re-send period of the end of stream until it is acknowledged, ms.
pub const EOS_RESEND_MS: u64 = 250;

/// What stays fixed over a replay: the pacing, the header template and the frames.
#[derive(Debug, Clone)]
pub struct CameraReplayPlan<'a> {
    /// Client index (the messages' `client_id`).
    pub client: u32,
    /// Real time or lock-step.
    pub mode: ReplayMode,
    /// Sensor time to host time (real time).
    pub clock: ReplayClock,
    /// Nominal frame period, ns (real time: part of the lateness bound).
    pub period_ns: i64,
    /// Re-send period and ack timeout (lock-step, end of stream).
    pub cfg: CameraIngestConfig,
    /// Header fields shared by every frame (intrinsics, `T_BS`, size).
    pub template: FrameHeader,
    /// The frames to replay (at most `--max-frames`), by dataset index.
    pub frames: &'a [datasets::FrameRecord],
}

/// What the ports are to do next.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CameraStep {
    /// Wait this long (for time to pass or acknowledgements to come; a signal stops the
    /// replay), then step again.
    Wait {
        /// How long, ns.
        for_ns: u64,
    },
    /// Decode frame `index` into a loaned sample and publish it with `header` (stamped when
    /// sent), then call [`CameraReplayCore::on_sent`] or [`CameraReplayCore::on_corrupt`].
    Publish {
        /// Dataset index of the frame.
        index: usize,
        /// Its header (`FLAG_RESEND` set on a re-send).
        header: FrameHeader,
    },
    /// Publish the end of stream, an empty sample with `header` (stamped when sent), then
    /// call [`CameraReplayCore::on_sent`].
    PublishEndOfStream {
        /// Its header.
        header: FrameHeader,
    },
    /// A frame is done (skipped late): step again.
    Continue,
    /// The replay is over.
    Done,
}

/// An acknowledgement awaited since `since_ns`, last sent at `last_send_ns`.
#[derive(Debug, Clone, Copy)]
struct AckWait {
    since_ns: i64,
    last_send_ns: i64,
    resent: u64,
}

impl AckWait {
    fn new(now_ns: i64) -> Self {
        Self {
            since_ns: now_ns,
            last_send_ns: now_ns,
            resent: 0,
        }
    }
}

#[derive(Debug, Clone, Copy)]
enum Phase {
    /// Frame `next`: to be paced.
    Pace,
    /// Frame `next`: waited for, to be published.
    Due,
    /// Frame `next`: being published.
    Sending,
    /// Frame `next`: published, lock-step: its acknowledgement awaited.
    AwaitAck(AckWait),
    /// The end of stream: being published.
    EndSending,
    /// The end of stream: published, its acknowledgement awaited.
    AwaitEndAck(AckWait),
    Done,
}

/// The camera replay's state and decisions.
#[derive(Debug)]
pub struct CameraReplayCore<'a> {
    plan: CameraReplayPlan<'a>,
    status: Status,
    counters: CameraCounters,
    /// Dataset index of the next frame.
    next: usize,
    session_id: u32,
    /// Highest frame sequence number acknowledged (since the end of stream: of it).
    acked: Option<u64>,
    phase: Phase,
}

impl<'a> CameraReplayCore<'a> {
    /// A core resuming what a killed predecessor left in `status` (a fresh start, or a resume
    /// state of another format: from the first frame; the counters carry on).
    pub fn new(plan: CameraReplayPlan<'a>, mut status: Status) -> Self {
        let counters = status.counters_as();
        let resume: CameraResume = status.take_resume(RESUME_VERSION).unwrap_or_default();
        status.set_value("frames_total", plan.frames.len() as f64);
        Self {
            plan,
            session_id: status.starts as u32,
            status,
            counters,
            next: resume.next_index as usize,
            acked: None,
            phase: Phase::Pace,
        }
    }

    /// Dataset index of the next frame (the resume position): when it moves, a frame is done
    /// and the status may be written.
    pub fn next_index(&self) -> usize {
        self.next
    }

    /// The counters so far.
    pub fn counters(&self) -> &CameraCounters {
        &self.counters
    }

    /// The messages' session id (this start's number).
    pub fn session_id(&self) -> u32 {
        self.session_id
    }

    /// The status (to report errors into).
    pub fn status_mut(&mut self) -> &mut Status {
        &mut self.status
    }

    /// The status as of now (counters and resume position put in), to write.
    pub fn status(&mut self) -> &Status {
        self.status.put_counters(&self.counters);
        let resume = CameraResume {
            next_index: self.next as u64,
        };
        self.status.set_resume(RESUME_VERSION, &resume);
        &self.status
    }

    /// The final status: finished when every frame was replayed (the end of stream sent).
    pub fn into_status(mut self) -> Status {
        self.status();
        self.status.finished = self.next >= self.plan.frames.len();
        self.status
    }

    /// A frame acknowledgement received (one of another schema version, or an IMU replay
    /// request, which acknowledges no frame, is ignored).
    pub fn on_ack(&mut self, ack: &FrameAck) {
        if ack.meta.check().is_ok() && ack.meta.flags & FLAG_IMU_REPLAY == 0 {
            let seq = ack.frame_seq;
            self.acked = Some(self.acked.map_or(seq, |a| a.max(seq)));
        }
    }

    /// What to do at host time `now_ns`.
    pub fn step(&mut self, now_ns: i64) -> CameraStep {
        match self.phase {
            Phase::Pace => self.pace(now_ns),
            Phase::Due | Phase::Sending => self.publish(),
            Phase::AwaitAck(w) => self.await_ack(w, now_ns),
            Phase::EndSending => self.end_of_stream(),
            Phase::AwaitEndAck(w) => self.await_end_ack(w, now_ns),
            Phase::Done => CameraStep::Done,
        }
    }

    /// The frame or end of stream of the last [`CameraStep::Publish`] /
    /// [`CameraStep::PublishEndOfStream`] was sent at `now_ns`.
    pub fn on_sent(&mut self, now_ns: i64) {
        match self.phase {
            Phase::Sending => {
                self.counters.frames_published += 1;
                if self.plan.mode == ReplayMode::Lockstep {
                    self.phase = Phase::AwaitAck(AckWait::new(now_ns));
                } else {
                    self.advance();
                }
            }
            Phase::EndSending => self.phase = Phase::AwaitEndAck(AckWait::new(now_ns)),
            // A re-send: nothing changes.
            _ => {}
        }
    }

    /// The frame of the last [`CameraStep::Publish`] could not be decoded (`detail` names
    /// the file): counted and skipped. A re-send that fails (the image changed on disk since
    /// its first send) is an error the service stops on (`Err`).
    pub fn on_corrupt(&mut self, detail: String) -> Result<(), String> {
        match self.phase {
            Phase::Sending => {
                self.status.error(ErrorKind::CorruptImage, detail);
                self.advance();
                Ok(())
            }
            _ => Err(detail),
        }
    }

    /// Frame `next` done (published, skipped or corrupt): on to the following one.
    fn advance(&mut self) {
        self.next += 1;
        self.counters.frames_offered += 1;
        self.phase = Phase::Pace;
    }

    /// Real time: waits until frame `next` is due (skips it when far too late); lock-step: at
    /// once. After the last frame: the end of stream.
    fn pace(&mut self, now_ns: i64) -> CameraStep {
        let Some(frame) = self.plan.frames.get(self.next) else {
            self.acked = None;
            return self.end_of_stream();
        };
        if self.plan.mode == ReplayMode::Realtime {
            let due = self.plan.clock.due_mono_ns(frame.t_ns);
            if now_ns > due + self.plan.period_ns.max(LATE_MIN_NS) {
                self.counters.frames_skipped_late += 1;
                self.advance();
                return CameraStep::Continue;
            }
            if due > now_ns {
                self.phase = Phase::Due;
                return CameraStep::Wait {
                    for_ns: (due - now_ns) as u64,
                };
            }
        }
        self.publish()
    }

    /// The first send of frame `next`.
    fn publish(&mut self) -> CameraStep {
        self.phase = Phase::Sending;
        CameraStep::Publish {
            index: self.next,
            header: self.header(self.next),
        }
    }

    /// The header of frame `k` (publish stamp and flags set when sent).
    fn header(&self, k: usize) -> FrameHeader {
        let rec = &self.plan.frames[k];
        let meta = MsgMeta::new(self.plan.client, self.session_id, k as u64, 0);
        FrameHeader {
            meta,
            dataset_index: k as u64,
            t_mid_ns: rec.t_ns,
            readout_ns: rec.readout_ns,
            exposure_ns: rec.exposure_ns,
            ..self.plan.template
        }
    }

    /// Lock-step: frame `next` acknowledged, timed out, to be re-sent, or still awaited.
    fn await_ack(&mut self, mut w: AckWait, now_ns: i64) -> CameraStep {
        let k = self.next;
        if self.acked.is_some_and(|a| a >= k as u64) {
            self.counters.frames_resent += w.resent;
            self.advance();
            return CameraStep::Continue;
        }
        let ms = self.plan.cfg.ack_timeout_ms;
        if now_ns - w.since_ns > ms as i64 * 1_000_000 {
            let detail = format!("no consumer took frame {k} within {ms} ms");
            self.status.error(ErrorKind::AckTimeout, detail);
            self.counters.frames_unacked += 1;
            self.advance();
            return CameraStep::Continue;
        }
        if now_ns - w.last_send_ns > self.plan.cfg.resend_ms as i64 * 1_000_000 {
            w.resent += 1;
            w.last_send_ns = now_ns;
            self.phase = Phase::AwaitAck(w);
            let mut header = self.header(k);
            header.meta.flags |= FLAG_RESEND;
            return CameraStep::Publish { index: k, header };
        }
        self.phase = Phase::AwaitAck(w);
        CameraStep::Wait {
            for_ns: ACK_POLL_NS,
        }
    }

    /// The end of stream (sequence number: the frame after the last).
    fn end_of_stream(&mut self) -> CameraStep {
        if !matches!(self.phase, Phase::AwaitEndAck(_)) {
            self.phase = Phase::EndSending;
        }
        let mut meta = MsgMeta::new(self.plan.client, self.session_id, self.next as u64, 0);
        meta.flags = FLAG_END_OF_STREAM;
        CameraStep::PublishEndOfStream {
            header: FrameHeader {
                meta,
                ..FrameHeader::default()
            },
        }
    }

    /// The end of stream must reach the consumer even if it restarts now: re-sent until it is
    /// acknowledged, for at most the ack timeout.
    fn await_end_ack(&mut self, mut w: AckWait, now_ns: i64) -> CameraStep {
        let acked = self.acked.is_some_and(|a| a >= self.next as u64);
        if acked || now_ns - w.since_ns > self.plan.cfg.ack_timeout_ms as i64 * 1_000_000 {
            self.phase = Phase::Done;
            return CameraStep::Done;
        }
        if now_ns - w.last_send_ns > EOS_RESEND_MS as i64 * 1_000_000 {
            w.last_send_ns = now_ns;
            self.phase = Phase::AwaitEndAck(w);
            return self.end_of_stream();
        }
        self.phase = Phase::AwaitEndAck(w);
        CameraStep::Wait {
            for_ns: ACK_POLL_NS,
        }
    }
}
