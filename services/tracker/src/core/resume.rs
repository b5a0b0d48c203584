//! A visual-inertial tracker's successor resumes its killed predecessor's session from the
//! keyframe spool instead of initialising again (issue 17).
//!
//! At start ([`TrackerCore::recover_spool`]) the spooled keyframes of the predecessor's
//! newest session are held back when the session was initialised inertially (its newest
//! keyframe carries velocity and biases) and its files hold the point positions; every
//! other spooled keyframe is sent at once, as before. At the first frame (which brings the
//! camera and `T_BS`) the held keyframes are rebuilt into the VO's client map
//! ([`slam_core::vo::restore_map`]) and the visual-inertial client continues the session
//! ([`VioTracker::resume`], with the refinements the predecessor reported, none left
//! when it did not say): same wire session id, so the mapper appends to the same server
//! map and the recorder keeps one world; keyframe ids continue the session's; new map points
//! are numbered from this start's range ([`ClientPointId`]). The held keyframes are the
//! VO's window again: they are sent when they leave it, their files stay in the spool
//! until then (and are rewritten with this process's map).
//!
//! Not resumed, with the reason in the report's `vio.resume_refused` (and a `vio_resume`
//! error when something was wrong with the spool): a session that was not initialised
//! inertially (expected before the initialisation), spool files of an older tracker
//! without point positions, keyframes of another camera or newer than the first frame, a
//! map that does not rebuild. The held keyframes are then sent as before, ahead of the
//! first frame's own keyframes, and the client starts a new session.
use nalgebra::Vector3;
use shm_schema::{FrameAck, FrameHeader, MsgMeta, FLAG_IMU_REPLAY, NO_MAP_POINT};
use shoal_runtime::wire::{
    camera_from_intrinsics, iso_from_wire, keyframe_imu_from_wire, wire_keypoint,
};
use shoal_runtime::ErrorKind;
use slam_core::features::OrbFeatures;
use slam_core::ids::ClientPointId;
use slam_core::imu::ImuBiases;
use slam_core::vio::{VioParams, VioTracker};
use slam_core::vo::{Keyframe, KeyframeInertial, RestoredMap, StoredPoint};

use super::{Out, TrackerCore, VioReport};
use crate::outbox::KeyframeMsg;
use crate::spool::Recovered;

/// The resume's bookkeeping over one start of the tracker.
#[derive(Default)]
pub(super) struct SpoolResume {
    /// Host time the spool was read (this start), ns.
    started_ns: i64,
    /// The keyframes of the session to resume, in id order, until the first frame.
    held: Vec<Recovered>,
    /// The session resumed: what was rebuilt, and when vision posed a frame again.
    pub(super) facts: Option<ResumeFacts>,
    /// Why this start did not resume its predecessor's session.
    pub(super) refused: Option<String>,
}

/// What a resume rebuilt and how soon the client tracked again (the report's `vio`).
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct ResumeFacts {
    /// Keyframes and points rebuilt into the client map.
    pub keyframes: u64,
    /// Map points rebuilt.
    pub points: u64,
    /// Frames handled since the resume.
    pub frames: u64,
    /// Frames handled until vision posed one, host ms from the spool read to that frame,
    /// and its gap to the keyframe resumed from (s, sensor time).
    pub anchored: Option<(u64, f64, f64)>,
}

/// A held keyframe as the message it was spooled as.
fn message(k: Recovered) -> KeyframeMsg {
    KeyframeMsg {
        header: k.header,
        records: k.records.into(),
        imu: k.imu.into(),
        imu_cut: 0,
    }
}

impl TrackerCore {
    /// What a killed predecessor left in the spool (its VO window), at host time `now_ns`:
    /// the keyframes of a session to resume are held (module docs), the others sent now,
    /// before this start's own keyframes.
    pub fn recover_spool(&mut self, keyframes: Vec<Recovered>, now_ns: i64) -> Vec<Out> {
        self.spool_resume.started_ns = now_ns;
        let send = self.hold_resumable(keyframes);
        let mut out: Vec<Out> = self.imu_replay_request(now_ns).into_iter().collect();
        for k in send {
            out.extend(self.recover_keyframe(message(k), now_ns));
        }
        out
    }

    /// Sends the held keyframes (the session is not resumed after all, or the stream ended
    /// before any frame).
    pub fn release_held(&mut self, now_ns: i64) -> Vec<Out> {
        let mut out = vec![];
        for k in std::mem::take(&mut self.spool_resume.held) {
            out.extend(self.recover_keyframe(message(k), now_ns));
        }
        out
    }

    /// Keeps the newest session's keyframes when they can be resumed; returns the others.
    fn hold_resumable(&mut self, mut keyframes: Vec<Recovered>) -> Vec<Recovered> {
        let vio = self.cfg.mode == crate::ClientMode::Vio && !self.cfg.no_vo;
        let Some(newest) = keyframes.iter().map(|k| k.header.meta.session_id).max() else {
            return keyframes;
        };
        if !vio {
            return keyframes;
        }
        let split = keyframes.partition_point(|k| k.header.meta.session_id < newest);
        let session = keyframes.split_off(split);
        let refused = if session.last().is_some_and(|k| k.header.inertial == 0) {
            Some("the killed tracker's session was not initialised inertially".to_string())
        } else if session.iter().any(|k| k.points.is_none()) {
            let why = "spool files without point positions (an older tracker's)";
            self.status.error(ErrorKind::VioResume, why);
            Some(why.to_string())
        } else {
            None
        };
        match refused {
            Some(why) => {
                self.spool_resume.refused = Some(why);
                keyframes.extend(session);
            }
            None => self.spool_resume.held = session,
        }
        keyframes
    }

    /// For a held session: the request to the IMU ingest to publish again the samples from
    /// the session's newest keyframe on ([`FLAG_IMU_REPLAY`]; lock-step): the predecessor
    /// took them, and the next keyframe's IMU segment starts at that keyframe, so that the
    /// session's keyframes stay linked on the server across the kill. The samples are kept
    /// until the client exists, and the first frame waits for its samples as any frame.
    fn imu_replay_request(&mut self, now_ns: i64) -> Option<Out> {
        let newest = self.spool_resume.held.last()?;
        let t_ns = newest.header.imu_t1_ns;
        if newest.header.has_imu == 0 {
            return None;
        }
        self.pending_imu_from_ns = Some(t_ns);
        self.imu_wait_waived = false;
        let mut meta = MsgMeta::new(self.cfg.client, self.session_id(), self.ack_seq, now_ns);
        meta.flags |= FLAG_IMU_REPLAY;
        self.ack_seq += 1;
        self.counters.imu_replays_asked += 1;
        Some(Out::Ack(FrameAck {
            meta,
            frame_seq: 0,
            frame_t_ns: t_ns,
        }))
    }

    /// Whether keyframes are held for a resume.
    pub(super) fn holds_session(&self) -> bool {
        !self.spool_resume.held.is_empty()
    }

    /// The visual-inertial client continuing the held session for frames like `h`, or why
    /// not (then the held keyframes are still held: [`TrackerCore::release_held`]).
    pub(super) fn resume_client(
        &mut self,
        h: &FrameHeader,
        params: VioParams,
    ) -> Result<VioTracker, String> {
        let held = &self.spool_resume.held;
        let session = held.first().map_or(0, |k| k.header.meta.session_id);
        let (keyframes, points) = stored_session(held, h, self.cfg.readout)?;
        let first_point = ClientPointId::first_of_start(self.ids.start()).raw();
        let restored = slam_core::vo::restore_map(1, keyframes, &points, first_point)
            .map_err(|e| e.to_string())?;
        let facts = facts_of(&restored);
        let mut vo = self.new_vo(h).map_err(|e| e.to_string())?;
        vo.resume_session(restored.map).map_err(|e| e.to_string())?;
        let done = self
            .predecessor_vio
            .as_ref()
            .map_or(2, |p| p.refinements as usize);
        let client = VioTracker::resume(vo, params, done).map_err(|e| e.to_string())?;
        self.ids.resume_session(session);
        self.counters.vio_resumes += 1;
        self.counters.keyframes_resumed += facts.keyframes;
        self.spool_resume.held.clear();
        self.spool_resume.facts = Some(facts);
        Ok(client)
    }

    /// A frame of the resumed session was handled at host time `now_ns`: counts it, and
    /// notes the first one vision posed.
    pub(super) fn note_resumed_frame(&mut self, now_ns: i64) {
        let Some(from) = self
            .client
            .as_ref()
            .and_then(|c| c.vio())
            .and_then(|v| v.resumed().copied())
        else {
            return;
        };
        let started = self.spool_resume.started_ns;
        let Some(f) = self.spool_resume.facts.as_mut() else {
            return;
        };
        if f.anchored.is_some() {
            return;
        }
        f.frames += 1;
        if let Some(t) = from.anchored_t_ns {
            let ms = (now_ns - started) as f64 * 1e-6;
            f.anchored = Some((f.frames, ms, (t - from.keyframe_t_ns) as f64 * 1e-9));
        }
    }
}

impl TrackerCore {
    /// The resume's part of the visual-inertial report: how many sessions were resumed,
    /// why this start's was not; for a resumed session, its predecessor's initialisation
    /// (time, scale: as the predecessor reported them), the refinements so far, and where
    /// and how soon it resumed.
    pub(super) fn put_resume_report(&self, v: &VioTracker, r: &mut VioReport) {
        r.resumed = self.counters.vio_resumes;
        r.resume_refused = self.spool_resume.refused.clone();
        let (Some(from), Some(f)) = (v.resumed(), self.spool_resume.facts) else {
            return;
        };
        r.refinements = from.refinements as u64;
        if let Some(p) = &self.predecessor_vio {
            r.attempts += p.attempts;
            r.initialised_t_ns = p.initialised_t_ns;
            r.initialised_after_s = p.initialised_after_s;
            r.scale = p.scale;
            r.scale_sigma_percent = p.scale_sigma_percent;
        }
        r.resumed_from_keyframe = Some(from.keyframe_id);
        r.resumed_keyframes = Some(f.keyframes);
        r.resumed_points = Some(f.points);
        if let Some((frames, ms, gap_s)) = f.anchored {
            r.resumed_after_frames = Some(frames);
            r.resumed_after_ms = Some(ms);
            r.resumed_gap_s = Some(gap_s);
        }
    }
}

/// What the report says of a rebuilt map.
fn facts_of(r: &RestoredMap) -> ResumeFacts {
    ResumeFacts {
        keyframes: r.map.keyframes.len() as u64,
        points: r.map.points.len() as u64,
        ..ResumeFacts::default()
    }
}

/// The held keyframes as the VO's keyframes and the point positions (oldest keyframe's
/// first, so the newest's win), checked against the first frame `h` of this start: the
/// same camera, and older than it.
fn stored_session(
    held: &[Recovered],
    h: &FrameHeader,
    readout: slam_core::rolling_shutter::ReadoutDirection,
) -> Result<(Vec<Keyframe>, Vec<StoredPoint>), String> {
    let mut keyframes = Vec::with_capacity(held.len());
    let mut points = Vec::new();
    for k in held {
        let kh = &k.header;
        if kh.intrinsics != h.intrinsics || (kh.width, kh.height) != (h.width, h.height) {
            return Err(format!(
                "spooled keyframe {} is of another camera",
                kh.keyframe_id
            ));
        }
        if kh.t_ns >= h.t_mid_ns {
            return Err(format!(
                "spooled keyframe {} at {} ns is not before the first frame at {} ns",
                kh.keyframe_id, kh.t_ns, h.t_mid_ns
            ));
        }
        let mut kf = stored_keyframe(k, h.readout_ns)?;
        kf.camera.readout = readout;
        keyframes.push(kf);
        let spooled = k.points.iter().flatten();
        points.extend(spooled.map(|p| StoredPoint {
            id: p.id,
            p_w: Vector3::from(p.p_w),
        }));
    }
    Ok((keyframes, points))
}

/// A spooled keyframe message as the VO's keyframe (`readout_ns`: the frames'; the wire
/// does not carry it).
fn stored_keyframe(k: &Recovered, readout_ns: i64) -> Result<Keyframe, String> {
    let h = &k.header;
    let id = h.keyframe_id;
    if h.n_keypoints as usize != k.records.len() {
        return Err(format!("spooled keyframe {id}: keypoint count"));
    }
    let t_wc = iso_from_wire(&h.pose_ck).ok_or(format!("spooled keyframe {id}: invalid pose"))?;
    let mut features = OrbFeatures::with_capacity(k.records.len());
    let mut points = Vec::with_capacity(k.records.len());
    for r in &k.records {
        let kp = wire_keypoint(r.u, r.v, r.angle, r.response, r.octave);
        features.keypoints.push(kp);
        features.descriptors.push(r.descriptor);
        points.push((r.map_point_id != NO_MAP_POINT).then_some(r.map_point_id));
    }
    let inertial = (h.inertial != 0).then(|| KeyframeInertial {
        v_wb: Vector3::from(h.velocity_w),
        biases: ImuBiases {
            gyro: Vector3::from(h.gyro_bias),
            accel: Vector3::from(h.accel_bias),
        },
        // The predecessor's state (its window's or its navigator's): counted as refined,
        // so the successor's windows are anchored, not gauged (the session's scale and
        // gravity are corrected once, `slam_core::vo::vi_window` module docs).
        refined: 1,
    });
    // The segment it was spooled (and would have been sent) with, so that it goes to the
    // server again with the same samples when it leaves the window, and local mapping's
    // visual-inertial window links it to its neighbours (issue 19).
    let imu = (h.has_imu != 0)
        .then(|| keyframe_imu_from_wire(h, &k.imu))
        .transpose()
        .map_err(|e| format!("spooled keyframe {id}: IMU segment: {e}"))?;
    Ok(Keyframe {
        id,
        t_ns: h.t_ns,
        t_cw: t_wc.inverse(),
        camera: camera_from_intrinsics(&h.intrinsics, h.width, h.height),
        readout_ns,
        features,
        points,
        inertial,
        imu,
    })
}

#[cfg(test)]
mod tests;
