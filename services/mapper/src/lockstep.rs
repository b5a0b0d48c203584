//! The mapper's side of the lock-step synchronisation (lock-step replay, `--mode lockstep`).
//!
//! In lock-step the tracker sends a keyframe and waits until the server has *finished* it
//! before its frame goes on ([`shm_schema::FLAG_HANDLED`] feedback). A keyframe is finished
//! when its handler has handled it (with its idle step), and, if it was forwarded to the
//! loop closer, when the loop closer has searched it ([`shm_schema::CORRECTION_DONE`],
//! sent after any correction it found, on the same topic) and every correction received
//! before that has been applied. So corrections land at the same point of the keyframe
//! stream and the tracker sees the server's answers at the same frame on every run.
//!
//! A dead loop closer must not stall the pipeline: a keyframe that waits longer than the
//! timeout is released anyway (counted), and a restarted loop closer's resynchronisation
//! request releases every wait on it (it gets those keyframes in its snapshot).
use std::collections::VecDeque;
use std::time::{Duration, Instant};

use slam_core::server::FeedbackPose;

/// Longest a handled keyframe waits for the loop closer before it is released anyway.
pub const LOOP_SYNC_TIMEOUT: Duration = Duration::from_secs(10);

/// A handled keyframe waiting to be reported finished.
#[derive(Debug, Clone)]
pub struct Settling {
    /// Client index.
    pub client: u32,
    /// VO session of the keyframe.
    pub session: u32,
    /// Client keyframe id.
    pub kf_id: u64,
    /// Pose feedback after it (the client's last keyframe).
    pub pose: Option<FeedbackPose>,
    /// Sequence number of the last loop keyframe message forwarded for it, if any.
    pub loop_seq: Option<u64>,
    /// When it was handled.
    pub since: Instant,
}

/// Keyframes handled and not yet reported finished, oldest first, and what they wait for.
#[derive(Debug)]
pub struct LockstepSync {
    queue: VecDeque<Settling>,
    /// Loop keyframe messages up to this sequence number are searched (or given up on).
    loop_done: Option<u64>,
    /// Corrections sent to a worker and not applied yet.
    corrections_in_flight: usize,
    timeout: Duration,
}

impl LockstepSync {
    /// Nothing waiting; a keyframe waits at most `timeout` for the loop closer.
    pub fn new(timeout: Duration) -> Self {
        Self {
            queue: VecDeque::new(),
            loop_done: None,
            corrections_in_flight: 0,
            timeout,
        }
    }

    /// A keyframe was handled.
    pub fn push(&mut self, s: Settling) {
        self.queue.push_back(s);
    }

    /// The loop closer has finished loop keyframe message `seq` (and all before it: it
    /// takes them in order).
    pub fn loop_done(&mut self, seq: u64) {
        self.loop_done = Some(self.loop_done.map_or(seq, |d| d.max(seq)));
    }

    /// A restarted loop closer asked for a snapshot of all maps: every loop keyframe sent
    /// before (sequence numbers below `next_seq`) is in it, nothing more will come for them.
    pub fn loop_closer_restarted(&mut self, next_seq: u64) {
        if let Some(last) = next_seq.checked_sub(1) {
            self.loop_done(last);
        }
    }

    /// A correction was sent to a worker.
    pub fn correction_dispatched(&mut self) {
        self.corrections_in_flight += 1;
    }

    /// A worker applied (or refused) a correction.
    pub fn correction_finished(&mut self) {
        self.corrections_in_flight = self.corrections_in_flight.saturating_sub(1);
    }

    /// Keyframes waiting.
    pub fn len(&self) -> usize {
        self.queue.len()
    }

    /// Nothing waiting.
    pub fn is_empty(&self) -> bool {
        self.queue.is_empty()
    }

    /// Takes the keyframes that are finished at `now`, oldest first (in order: a keyframe
    /// is never reported before an older one), each with whether it was released by the
    /// timeout instead.
    pub fn take_finished(&mut self, now: Instant) -> Vec<(Settling, bool)> {
        let mut out = Vec::new();
        while let Some(front) = self.queue.front() {
            let searched = front
                .loop_seq
                .is_none_or(|s| self.loop_done.is_some_and(|d| d >= s));
            let finished = searched && self.corrections_in_flight == 0;
            let timed_out = now.saturating_duration_since(front.since) > self.timeout;
            if !(finished || timed_out) {
                break;
            }
            if let Some(s) = self.queue.pop_front() {
                out.push((s, !finished));
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kf(id: u64, loop_seq: Option<u64>, since: Instant) -> Settling {
        Settling {
            client: 0,
            session: 1,
            kf_id: id,
            pose: None,
            loop_seq,
            since,
        }
    }

    fn ids(v: &[(Settling, bool)]) -> Vec<(u64, bool)> {
        v.iter().map(|(s, t)| (s.kf_id, *t)).collect()
    }

    #[test]
    fn keyframe_waits_for_loop_closer_and_corrections() {
        let t0 = Instant::now();
        let mut s = LockstepSync::new(Duration::from_secs(10));
        s.push(kf(1, None, t0));
        s.push(kf(2, Some(0), t0));
        s.push(kf(3, None, t0));
        // 1 was not forwarded: finished at once; 2 waits for the loop closer, 3 behind it.
        assert_eq!(ids(&s.take_finished(t0)), vec![(1, false)]);
        // The loop closer found a loop with 2: the correction is sent before the marker.
        s.correction_dispatched();
        s.loop_done(0);
        assert!(s.take_finished(t0).is_empty(), "correction not applied yet");
        s.correction_finished();
        assert_eq!(ids(&s.take_finished(t0)), vec![(2, false), (3, false)]);
        assert!(s.is_empty());
    }

    #[test]
    fn dead_loop_closer_releases_by_timeout_or_resync() {
        let t0 = Instant::now();
        let mut s = LockstepSync::new(Duration::from_secs(10));
        s.push(kf(1, Some(4), t0));
        s.push(kf(2, Some(5), t0 + Duration::from_secs(5)));
        assert!(s.take_finished(t0 + Duration::from_secs(9)).is_empty());
        // 1 waited too long: released and flagged; 2 still waits.
        assert_eq!(
            ids(&s.take_finished(t0 + Duration::from_secs(11))),
            vec![(1, true)]
        );
        assert_eq!(s.len(), 1);
        // A restarted loop closer resynchronises from the maps: 2 is in its snapshot.
        s.loop_closer_restarted(6);
        assert_eq!(
            ids(&s.take_finished(t0 + Duration::from_secs(11))),
            vec![(2, false)]
        );
        // A marker older than the newest done does not move it back.
        s.loop_done(3);
        s.push(kf(3, Some(5), t0));
        assert_eq!(ids(&s.take_finished(t0)), vec![(3, false)]);
    }
}
