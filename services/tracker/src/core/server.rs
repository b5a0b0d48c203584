//! What the tracker knows from the server's feedback: the last usable pose feedback (for
//! frames' server-map poses, seed eq. 3.1, 3.4), a visual-inertial session's anchor to its
//! metric server map (`slam_core::vio::anchor`: what it asks the client to move, and the
//! un-anchoring of what the tracker sends) and, in lock-step, which keyframes the server
//! has finished.
use std::collections::HashSet;

use nalgebra::Isometry3;
use shm_schema::{Feedback, Pose, FLAG_HANDLED, FLAG_INERTIAL_MAP};
use shoal_runtime::{ErrorKind, Status};
use slam_core::ids::MapId;
use slam_core::lie::Sim3;
use slam_core::vio::anchor::{AnchorParams, AnchorRequest, SessionAnchor};

use super::counters::{TrackerCounters, TrackerResume};
use crate::outbox::Outbox;

/// A keyframe as the tracker and the server name it: (VO session, keyframe id).
pub type KeyframeKey = (u32, u64);

/// The last usable pose feedback: keyframe `j`'s client pose as sent, its server pose and
/// the scale ratio (seed eq. 3.1, 3.4), for frames of the same VO session.
#[derive(Debug, Clone)]
pub struct ServerRef {
    /// VO session of keyframe `j`.
    pub session: u32,
    /// Server map the keyframe is in.
    pub map_id: MapId,
    /// Keyframe `j` (client id).
    pub kf_id: u64,
    t_cj: Isometry3<f64>,
    t_sj: Isometry3<f64>,
    lambda: f64,
    /// A metric keyframe in a metric, gravity-aligned map ([`FLAG_INERTIAL_MAP`]).
    metric: bool,
}

impl ServerRef {
    /// From a feedback message with a pose, if the keyframe is one this tracker sent and
    /// the values are valid.
    fn from_feedback(f: &Feedback, outbox: &Outbox) -> Option<Self> {
        let t_cj = outbox.sent_pose(f.acked_session_id, f.acked_keyframe_id)?;
        if !(f.scale_ratio.is_finite() && f.scale_ratio > 0.0) {
            return None;
        }
        let t_sj = shoal_runtime::wire::iso_from_wire(&f.server_pose)?;
        Some(Self {
            session: f.acked_session_id,
            map_id: MapId::from_raw(f.server_map_id),
            kf_id: f.acked_keyframe_id,
            t_cj,
            t_sj,
            lambda: f.scale_ratio,
            metric: f.meta.flags & FLAG_INERTIAL_MAP != 0,
        })
    }

    /// The server-map pose (wire, camera → server map) of a frame with client pose `t_cf`.
    pub fn frame_pose(&self, t_cf: &Isometry3<f64>) -> Pose {
        shoal_runtime::wire::wire_from_iso(&slam_core::server::frame_pose_in_server_map(
            &self.t_cj,
            &self.t_sj,
            self.lambda,
            t_cf,
        ))
    }
}

/// The server's side as the tracker sees it.
#[derive(Debug, Default)]
pub struct ServerState {
    /// Client index.
    client: u32,
    /// Lock-step synchronisation on (else `handled` stays empty).
    sync: bool,
    /// The last usable pose feedback.
    pub server_ref: Option<ServerRef>,
    /// Lock-step: keyframes the server has finished and no frame waited for yet.
    handled: HashSet<KeyframeKey>,
    anchor_params: AnchorParams,
    /// The anchor of the newest session that had a metric feedback.
    anchor: Option<SessionAnchor>,
    /// The anchor move asked of the client and not applied yet.
    requested: Option<AnchorRequest>,
}

impl ServerState {
    /// Nothing heard from the server yet.
    pub fn new(client: u32, sync: bool, anchor_params: AnchorParams) -> Self {
        Self {
            client,
            sync,
            anchor_params,
            ..Self::default()
        }
    }

    /// Takes one feedback message: acknowledgement (outbox), pose feedback and, in
    /// lock-step, the keyframe the server has finished.
    pub fn on_feedback(
        &mut self,
        f: &Feedback,
        outbox: &mut Outbox,
        status: &mut Status,
        counters: &mut TrackerCounters,
    ) {
        if f.meta.check().is_err() {
            let c = self.client;
            status.error(ErrorKind::SchemaVersion, format!("feedback of client {c}"));
            return;
        }
        counters.feedback_received += 1;
        outbox.ack(f.acked_session_id, f.acked_keyframe_id);
        if f.has_pose != 0 {
            match ServerRef::from_feedback(f, outbox) {
                // Lock-step's "finished" answer on a keyframe can come after the pose
                // feedback on a newer one: the reference only moves forward.
                Some(r) if self.is_older(&r) => counters.pose_feedback_older += 1,
                Some(r) => {
                    outbox.forget_sent_before(f.acked_session_id, f.acked_keyframe_id);
                    self.server_ref = Some(r);
                    counters.pose_feedback_used += 1;
                }
                None => counters.pose_feedback_unusable += 1,
            }
        }
        if self.sync && f.meta.flags & FLAG_HANDLED != 0 {
            self.handled
                .insert((f.acked_session_id, f.acked_keyframe_id));
        }
    }

    /// Whether `r` is on an older keyframe than the present reference (same session).
    fn is_older(&self, r: &ServerRef) -> bool {
        self.server_ref
            .as_ref()
            .is_some_and(|now| now.session == r.session && r.kf_id < now.kf_id)
    }

    /// The move that anchors a metric client's session to its server map, after a metric
    /// pose feedback (`None`: anchoring off, no such feedback, or a change below the
    /// thresholds); kept until [`ServerState::anchor_applied`] or the next request.
    pub fn anchor_request(&mut self) -> Option<AnchorRequest> {
        self.requested = None;
        let r = self.server_ref.as_ref().filter(|r| r.metric)?;
        if !self.anchor_params.enabled {
            return None;
        }
        let a = match self.anchor {
            Some(a) if a.session == r.session => a,
            _ => *self.anchor.insert(SessionAnchor::new(r.session, r.map_id)),
        };
        self.requested = a.request(&r.t_cj, &r.t_sj, r.map_id, &self.anchor_params);
        self.requested
    }

    /// The client applied the anchor move asked for (of session `session`); returns it.
    pub fn anchor_applied(&mut self, session: u32) -> Option<AnchorRequest> {
        let r = self.requested.take().filter(|r| r.session == session)?;
        let a = self.anchor.as_mut().filter(|a| a.session == session)?;
        a.applied(&r);
        Some(r)
    }

    /// Session `session`'s world moved by `m` for another reason (a refinement, a gravity
    /// correction): its anchor follows ([`SessionAnchor::on_world_move`]).
    pub fn on_world_move(&mut self, session: u32, m: &Sim3) {
        if let Some(a) = self.anchor.as_mut().filter(|a| a.session == session) {
            a.on_world_move(m);
        }
        self.requested = None;
    }

    /// The rigid move from the client's present world of session `session` back to the
    /// session's own world, in which keyframes are sent and the server's predictions work
    /// (identity without an anchor).
    pub fn to_session(&self, session: u32) -> Isometry3<f64> {
        self.anchor
            .filter(|a| a.session == session)
            .map_or(Isometry3::identity(), |a| a.to_session())
    }

    /// Lock-step: whether the server has finished keyframe `key`; when it has, the record
    /// of finished keyframes starts afresh (feedback comes in handling order).
    pub fn take_handled(&mut self, key: KeyframeKey) -> bool {
        let done = self.handled.remove(&key);
        if done {
            self.handled.clear();
        }
        done
    }

    /// The server-map pose and map id of a frame of VO session `session` with client pose
    /// `t_cf` (camera → the client's present world), from the last feedback of the same
    /// session (eq. 3.1, 3.4, in the session's own world).
    pub fn frame_pose(&self, session: u32, t_cf: &Isometry3<f64>) -> Option<(Pose, MapId)> {
        let r = self.server_ref.as_ref().filter(|r| r.session == session)?;
        Some((r.frame_pose(&(self.to_session(session) * t_cf)), r.map_id))
    }
}

/// The keyframe counters, kept current: a SIGKILLed tracker must leave exact figures behind
/// (keyframes are few, so the status is written whenever one is sent or acknowledged).
/// Counters carry on from the previous start; the keyframes a killed tracker had sent
/// without seeing their acknowledgement are counted as `keyframes_unacked_at_crash` by its
/// successor (the mapper applied them; their acknowledgements went to a dead process), so
/// that `keyframes_acked_seen + keyframes_unacked_at_crash == keyframes_sent`.
#[derive(Debug)]
pub struct KeyframeCounts {
    sent_base: u64,
    resent_base: u64,
    acked_base: u64,
}

impl KeyframeCounts {
    /// The bases of a start that resumes `counters` and `resume` (a fresh one: zeros).
    pub fn resume(counters: &mut TrackerCounters, resume: &TrackerResume, restarted: bool) -> Self {
        if restarted {
            counters.keyframes_unacked_at_crash += resume.keyframes_unacked;
            // Queued behind the in-flight limit, never sent: lost with the process (as are
            // the keyframes still in its VO window).
            counters.keyframes_unsent_at_crash += resume.keyframes_queued;
        }
        Self {
            sent_base: counters.keyframes_sent,
            resent_base: counters.keyframes_resent,
            acked_base: counters.keyframes_acked_seen,
        }
    }

    /// Puts the outbox's counts into `counters` and `resume`.
    pub fn set(&self, outbox: &Outbox, counters: &mut TrackerCounters, resume: &mut TrackerResume) {
        counters.keyframes_sent = self.sent_base + outbox.sent;
        counters.keyframes_resent = self.resent_base + outbox.resent;
        counters.keyframes_acked_seen = self.acked_base + outbox.acked;
        let in_flight = outbox.in_flight();
        resume.keyframes_unacked = in_flight as u64;
        resume.keyframes_queued = (outbox.pending() - in_flight) as u64;
    }
}
