//! The IMU ingest's core: the replay position, the counters and the crash-recovery state,
//! and every decision of the replay, with typed inputs and outputs and no IPC, file or clock
//! access of its own (host times come in as `now_ns`), so that it is tested in-process
//! (`core/tests.rs`).
//!
//! The ports hand it the frame acknowledgements received ([`ImuReplayCore::on_ack`]), ask it
//! what to do now ([`ImuReplayCore::step`]) and carry out the [`ImuStep`] it returns: wait,
//! publish a sample (then [`ImuReplayCore::on_sent`]), publish the end of stream, or stop.
//!
//! Pacing: lock-step publishes the samples up to `t(last acknowledged frame) + lookahead`
//! (a gap in the samples simply waits for the acknowledgement that moves the horizon past
//! it); real time publishes each sample at its due time on the [`ReplayClock`], and a
//! restarted ingest skips (and counts) the samples due more than 50 ms before now. A dataset
//! without frames is replayed in real time in both modes. Malformed or non-monotonic lines
//! never reach the core: the dataset reader skipped them, and the ports report them
//! ([`shoal_runtime::report_input_issues`]) on a first start.
use serde::{Deserialize, Serialize};
use shm_schema::{FrameAck, ImuMsg, MsgMeta, FLAG_END_OF_STREAM, FLAG_IMU_REPLAY};
use shoal_runtime::{ReplayClock, ReplayMode, Status};

#[cfg(test)]
mod tests;

/// Counters of the IMU ingest (the status file's `counters`), carried on over restarts.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ImuCounters {
    /// Samples published (a restarted ingest publishes the samples after its predecessor's
    /// last status write again).
    pub imu_samples_published: u64,
    /// Real time: samples due while this service was down, skipped.
    pub imu_samples_skipped_late: u64,
    /// Lock-step: samples published again at a restarted tracker's request (the samples its
    /// killed predecessor took since its session's newest keyframe; in
    /// `imu_samples_published` too).
    pub imu_samples_replayed: u64,
    /// Those requests.
    pub imu_replays: u64,
}

/// Format version of [`ImuResume`].
pub const RESUME_VERSION: u32 = 1;

/// What a restarted IMU ingest needs of its killed predecessor besides the counters.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ImuResume {
    /// Index of the next sample to replay.
    pub next_index: u64,
}

/// Lock-step: how often the ports look for a frame acknowledgement, ns.
pub const ACK_POLL_NS: u64 = 100_000;
/// Real time, after a restart: a sample late by more than this was missed while the service
/// was down, ns.
pub const LATE_NS: i64 = 50_000_000;

/// What stays fixed over a replay.
#[derive(Debug, Clone)]
pub struct ImuReplayPlan<'a> {
    /// Client index (the messages' `client_id`).
    pub client: u32,
    /// Real time or lock-step (lock-step needs frames: `first_frame_t_ns`).
    pub mode: ReplayMode,
    /// Sensor time to host time (real time).
    pub clock: ReplayClock,
    /// Lock-step: samples up to this far past the last acknowledged frame, ns.
    pub lookahead_ns: i64,
    /// Time of the dataset's first frame (`None`: no frames, real-time pacing).
    pub first_frame_t_ns: Option<i64>,
    /// The samples to replay (those before the first frame not replayed).
    pub samples: &'a [datasets::ImuSample],
}

/// What the ports are to do next.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ImuStep {
    /// Wait this long (for time to pass or acknowledgements to come; a signal stops the
    /// replay), then step again.
    Wait {
        /// How long, ns.
        for_ns: u64,
    },
    /// Publish this sample (stamped when sent), then call [`ImuReplayCore::on_sent`].
    Publish(ImuMsg),
    /// Publish the end of stream (stamped when sent) and step again.
    PublishEndOfStream(ImuMsg),
    /// A sample is done (skipped late): step again.
    Continue,
    /// The replay is over.
    Done,
}

/// The IMU replay's state and decisions.
#[derive(Debug)]
pub struct ImuReplayCore<'a> {
    plan: ImuReplayPlan<'a>,
    status: Status,
    counters: ImuCounters,
    /// Index of the next sample.
    next: usize,
    session_id: u32,
    /// Lock-step (the mode is lock-step and the dataset has frames).
    lockstep: bool,
    /// Lock-step horizon: samples with `t <= horizon` may be published.
    horizon_ns: i64,
    /// A restarted ingest: samples due while it was down are skipped (and counted).
    restarted: bool,
    /// Real time: sample `next` waited for, to be published.
    due: bool,
    /// The end of stream was published.
    ended: bool,
}

impl<'a> ImuReplayCore<'a> {
    /// A core resuming what a killed predecessor left in `status` (a fresh start, or a resume
    /// state of another format: from the first sample; the counters carry on).
    pub fn new(plan: ImuReplayPlan<'a>, mut status: Status) -> Self {
        let counters = status.counters_as();
        let resume: ImuResume = status.take_resume(RESUME_VERSION).unwrap_or_default();
        let first_frame_t = plan.first_frame_t_ns.unwrap_or(i64::MIN);
        Self {
            lockstep: plan.mode == ReplayMode::Lockstep && plan.first_frame_t_ns.is_some(),
            horizon_ns: first_frame_t.saturating_add(plan.lookahead_ns),
            restarted: status.starts > 1,
            session_id: status.starts as u32,
            plan,
            status,
            counters,
            next: resume.next_index as usize,
            due: false,
            ended: false,
        }
    }

    /// Index of the next sample (the resume position): when it moves, a sample is done and
    /// the status may be written.
    pub fn next_index(&self) -> usize {
        self.next
    }

    /// The counters so far.
    pub fn counters(&self) -> &ImuCounters {
        &self.counters
    }

    /// Lock-step horizon: samples up to this time may be published, ns.
    pub fn horizon_ns(&self) -> i64 {
        self.horizon_ns
    }

    /// The status (to report errors into).
    pub fn status_mut(&mut self) -> &mut Status {
        &mut self.status
    }

    /// The status as of now (counters and resume position put in), to write.
    pub fn status(&mut self) -> &Status {
        self.status.put_counters(&self.counters);
        let resume = ImuResume {
            next_index: self.next as u64,
        };
        self.status.set_resume(RESUME_VERSION, &resume);
        &self.status
    }

    /// The final status: finished when every sample was replayed (the end of stream sent).
    pub fn into_status(mut self) -> Status {
        self.status();
        self.status.finished = self.next >= self.plan.samples.len();
        self.status
    }

    /// A frame acknowledgement received: lock-step, it moves the horizon (one of another
    /// schema version is ignored). A replay request ([`FLAG_IMU_REPLAY`]) moves the replay
    /// back instead ([`Self::replay_from`]).
    pub fn on_ack(&mut self, ack: &FrameAck) {
        if ack.meta.check().is_err() {
            return;
        }
        if ack.meta.flags & FLAG_IMU_REPLAY != 0 {
            self.replay_from(ack.frame_t_ns);
            return;
        }
        let h = ack.frame_t_ns.saturating_add(self.plan.lookahead_ns);
        self.horizon_ns = self.horizon_ns.max(h);
    }

    /// Lock-step: the samples from the one at or before `t_ns` on are published again (up
    /// to the horizon, then on as acknowledgements move it), followed by the end of stream
    /// again if it was sent: a restarted tracker lost them with its killed predecessor. In
    /// real time nothing is replayed (the frames that tracker missed are dropped too).
    fn replay_from(&mut self, t_ns: i64) {
        if !self.lockstep {
            return;
        }
        let from = self
            .plan
            .samples
            .partition_point(|s| s.t_ns <= t_ns)
            .saturating_sub(1);
        if from < self.next {
            self.counters.imu_replays += 1;
            self.counters.imu_samples_replayed += (self.next - from) as u64;
            self.next = from;
            self.ended = false;
        }
    }

    /// What to do at host time `now_ns`.
    pub fn step(&mut self, now_ns: i64) -> ImuStep {
        let n = self.plan.samples.len();
        let Some(s) = self.plan.samples.get(self.next) else {
            if self.ended {
                return ImuStep::Done;
            }
            self.ended = true;
            let mut meta = MsgMeta::new(self.plan.client, self.session_id, n as u64, 0);
            meta.flags = FLAG_END_OF_STREAM;
            let eos = ImuMsg {
                meta,
                ..ImuMsg::default()
            };
            return ImuStep::PublishEndOfStream(eos);
        };
        if self.lockstep {
            if s.t_ns > self.horizon_ns {
                return ImuStep::Wait {
                    for_ns: ACK_POLL_NS,
                };
            }
        } else if !self.due {
            let due = self.plan.clock.due_mono_ns(s.t_ns);
            if self.restarted && now_ns > due + LATE_NS {
                self.counters.imu_samples_skipped_late += 1;
                self.advance();
                return ImuStep::Continue;
            }
            if due > now_ns {
                self.due = true;
                let for_ns = (due - now_ns) as u64;
                return ImuStep::Wait { for_ns };
            }
        }
        ImuStep::Publish(ImuMsg {
            meta: MsgMeta::new(self.plan.client, self.session_id, self.next as u64, 0),
            t_ns: s.t_ns,
            gyro: s.gyro,
            accel: s.accel,
        })
    }

    /// The sample of the last [`ImuStep::Publish`] was sent.
    pub fn on_sent(&mut self) {
        self.counters.imu_samples_published += 1;
        self.advance();
    }

    fn advance(&mut self) {
        self.next += 1;
        self.due = false;
    }
}
