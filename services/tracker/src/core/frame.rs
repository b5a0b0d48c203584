//! A frame through the tracker core: admission (schema, end of stream, duplicates, gaps),
//! the VO with the gyro over the readout (rolling shutter), the keyframes leaving the VO
//! window, and the frame's outputs (backfilled poses, acknowledgement, tracked pose with its
//! server-map pose, seed eq. 3.1, 3.4).
use nalgebra::{Isometry3, Vector3};
use shm_schema::{
    stage, FrameAck, FrameHeader, MsgMeta, Pose, PoseSource, TrackState, TrackedPose,
    FLAG_BACKFILL, FLAG_WORLD_MOVE,
};
use shoal_runtime::ErrorKind;
use slam_core::features::GrayImage;
use slam_core::lie::Sim3;
use slam_core::vo::VoFrame;

use super::{ClientOutput, KeyframeKey, Out, TrackerCore};
use crate::outbox::{keyframe_message, wire_pose};

/// One frame as the ports took it from shared memory.
pub struct FrameIn<'a> {
    /// Its header.
    pub header: FrameHeader,
    /// Its pixels, in place in the shared-memory sample.
    pub pixels: &'a [u8],
    /// When it was taken (CLOCK_MONOTONIC), ns.
    pub recv_ns: i64,
    /// Now, ns (keyframe send stamps).
    pub now_ns: i64,
}

/// What [`TrackerCore::track`] made of a frame.
// One per frame, moved once to the ports: boxing `Tracked` would allocate on every frame.
#[allow(clippy::large_enum_variant)]
pub enum FrameStep {
    /// Nothing more to do: a rejected frame, or a duplicate (its acknowledgement in here).
    Done(Vec<Out>),
    /// The end of stream: send [`TrackerCore::take_window`], then
    /// [`TrackerCore::end_of_stream`].
    EndOfStream(FrameHeader),
    /// A frame handled: carry out its outputs, in lock-step wait until the server finished
    /// [`Tracked::await_handled`], then [`TrackerCore::publish_frame`].
    Tracked(Tracked),
}

/// A frame tracked, its pose not published yet.
pub struct Tracked {
    /// Keyframes that left the VO window with this frame, to publish now.
    pub out: Vec<Out>,
    /// Lock-step: the last of them, whose feedback (pose) must be in before the frame's
    /// server pose is computed.
    pub await_handled: Option<KeyframeKey>,
    header: FrameHeader,
    recv_ns: i64,
    pub(super) state: TrackState,
    /// World-to-camera pose `T_cw` of a tracked frame.
    pub(super) t_cw: Option<Isometry3<f64>>,
    pub(super) tracked: u32,
    is_keyframe: bool,
    vo_session: u32,
    stage_ms: [f32; stage::COUNT],
    /// Poses of frames seen while initialising, `(t_ns, T_cw)`.
    backfill: Vec<(i64, Isometry3<f64>)>,
    /// Where the pose came from.
    pub(super) source: PoseSource,
    /// The pose is in a metric, gravity-aligned world.
    pub(super) metric: bool,
    /// Camera orientation `R_wc` of a frame with no pose (gyro-propagated).
    r_wc: Option<nalgebra::UnitQuaternion<f64>>,
    /// The VO session's world moved with this frame, earlier poses to be re-expressed
    /// (`x' = s R x + t`), published before its poses.
    world_move: Option<Sim3>,
}

impl Tracked {
    fn untracked(header: FrameHeader, recv_ns: i64, session: u32) -> Self {
        Self {
            out: vec![],
            await_handled: None,
            header,
            recv_ns,
            state: TrackState::NotInitialized,
            t_cw: None,
            tracked: 0,
            is_keyframe: false,
            vo_session: session,
            stage_ms: [0.0; stage::COUNT],
            backfill: vec![],
            source: PoseSource::None,
            metric: false,
            r_wc: None,
            world_move: None,
        }
    }

    /// A pose of an earlier frame (`t_ns`) found with this one, published before it.
    pub(super) fn add_backfill(&mut self, t_ns: i64, t_cw: Isometry3<f64>) {
        self.backfill.push((t_ns, t_cw));
    }

    /// The client's result for the frame (not its keyframes): a pose from vision, or the
    /// IMU's through a dropout (then `Tracking` too), or an orientation only.
    fn take_output(&mut self, c: &mut ClientOutput) {
        let o = &mut c.vo;
        self.state = shoal_runtime::wire::track_state_from_vo(o.state);
        self.t_cw = c.t_cw;
        self.source = c.source;
        if c.t_cw.is_some() {
            self.state = TrackState::Tracking;
        } else if self.state == TrackState::Tracking {
            self.state = TrackState::Lost;
        }
        self.r_wc = c.r_wc.filter(|_| c.source == PoseSource::OrientationOnly);
        self.metric = c.metric;
        self.world_move = c.world_move.map(|m| m.world);
        self.tracked = o.tracked as u32;
        self.is_keyframe = o.keyframe.is_some();
        let (t, s) = (&o.times, &mut self.stage_ms);
        s[stage::PYRAMID] = t.pyramid;
        s[stage::DETECT] = t.detect;
        s[stage::DESCRIBE] = t.describe;
        s[stage::MATCH] = t.matching;
        s[stage::POSE_OPT] = t.pose_opt;
        s[stage::LOCAL_MAP] = t.local_map;
        s[stage::KEYFRAME] = t.keyframe;
        self.backfill = std::mem::take(&mut o.backfill);
    }
}

impl TrackerCore {
    /// How long a frame may wait for the gyro samples up to its last row, ns.
    pub fn imu_wait_ns(&self, realtime_wait_ns: i64) -> i64 {
        if self.cfg.lockstep_sync {
            5_000_000_000
        } else {
            realtime_wait_ns
        }
    }

    /// The time up to which frame `h` (with `payload_len` bytes) needs gyro samples before
    /// it is tracked (its last row), or `None` when it will not use the gyro.
    pub fn imu_needed_ns(&self, h: &FrameHeader, payload_len: usize) -> Option<i64> {
        let admitted = h.meta.check().is_ok()
            && !h.meta.is_end_of_stream()
            && self.resume.last_frame_seq.is_none_or(|l| h.meta.seq > l);
        if self.cfg.mode == crate::ClientMode::Calib {
            // The calibration filter updates a frame once the IMU covers its last row.
            let need = self
                .calib
                .as_ref()
                .map_or(h.t_mid_ns + h.readout_ns / 2, |c| {
                    c.calibrator().imu_needed_ns(h.t_mid_ns)
                });
            return (admitted && !self.cfg.no_vo).then_some(need);
        }
        let rs = !self.cfg.no_rs && h.readout_ns != 0;
        // The visual-inertial client predicts every frame with the IMU.
        let vio = self.cfg.mode == crate::ClientMode::Vio;
        (admitted && (rs || vio) && self.trackable(h, payload_len))
            .then(|| h.t_mid_ns + h.readout_ns / 2)
    }

    /// Whether gyro samples up to `need_ns` are still to come (in lock-step also before the
    /// stream's first sample: whether it is in before the first frames would otherwise
    /// change the initialisation).
    /// In lock-step a restarted tracker's first frame waits for nothing: the samples up to
    /// it were published to its predecessor (up to the lock-step horizon of the last frame
    /// that one acknowledged) and are not published again.
    pub fn imu_missing(&self, need_ns: i64) -> bool {
        let short = self.imu.newest_ns().is_none_or(|t| t < need_ns);
        if self.cfg.lockstep_sync && !self.imu_never_came {
            short && !self.imu.ended && !self.imu_wait_waived
        } else {
            short && self.imu.live()
        }
    }

    fn trackable(&self, h: &FrameHeader, payload_len: usize) -> bool {
        !self.cfg.no_vo && payload_len >= h.payload_len() && h.width > 0
    }

    /// Takes a frame (after the ports waited for its gyro samples, see
    /// [`TrackerCore::imu_needed_ns`]): checks it and runs the VO on it.
    pub fn track(&mut self, f: FrameIn) -> anyhow::Result<FrameStep> {
        self.diagnostics.clear();
        let h = f.header;
        if let Some(step) = self.admit(&h, f.now_ns) {
            return Ok(step);
        }
        let features = h.pixel_format == shm_schema::PixelFormat::Features as u32;
        if !features && f.pixels.len() != h.payload_len() {
            let (seq, n, want) = (h.meta.seq, f.pixels.len(), h.payload_len());
            let detail = format!("frame {seq}: {n} bytes, header says {want}");
            self.status.error(ErrorKind::BadFrame, detail);
        }
        let mut t = Tracked::untracked(h, f.recv_ns, self.session_id());
        if self.cfg.mode == crate::ClientMode::Calib && !self.cfg.no_vo {
            self.run_calib(&f, &mut t);
        } else if self.trackable(&h, f.pixels.len()) {
            self.run_vo(&f, &mut t)?;
        }
        self.imu_wait_waived = false;
        Ok(FrameStep::Tracked(t))
    }

    /// Schema, end of stream, re-sends and gaps: `Some` when the frame goes no further.
    fn admit(&mut self, h: &FrameHeader, now_ns: i64) -> Option<FrameStep> {
        let c = self.cfg.client;
        if let Err(e) = h.meta.check() {
            let detail = format!("frame of client {c}: {e}");
            self.status.error(ErrorKind::SchemaVersion, detail);
            return Some(FrameStep::Done(vec![]));
        }
        if h.meta.is_end_of_stream() {
            return Some(FrameStep::EndOfStream(*h));
        }
        if self.resume.last_frame_seq.is_some_and(|l| h.meta.seq <= l) {
            // A re-send of a frame already handled (e.g. the camera restarted): ack again.
            self.counters.frames_duplicate += 1;
            let ack = self.ack(h, now_ns);
            return Some(FrameStep::Done(vec![ack]));
        }
        let expected = self.resume.last_frame_seq.map_or(0, |l| l + 1);
        if h.meta.seq > expected {
            let c = &mut self.counters;
            let gap = if self.first_after_restart {
                &mut c.frames_gap_at_restart
            } else {
                &mut c.frames_gap
            };
            *gap += h.meta.seq - expected;
        }
        self.first_after_restart = false;
        self.resume.last_frame_seq = Some(h.meta.seq);
        None
    }

    /// The acknowledgement of frame `h` (the next in this start's sequence).
    fn ack(&mut self, h: &FrameHeader, now_ns: i64) -> Out {
        let ack = FrameAck {
            meta: MsgMeta::new(self.cfg.client, self.session_id(), self.ack_seq, now_ns),
            frame_seq: h.meta.seq,
            frame_t_ns: h.t_mid_ns,
        };
        self.ack_seq += 1;
        Out::Ack(ack)
    }

    /// Rolling shutter: the camera's mean gyro rate over the frame's readout, from the
    /// samples in (lock-step: a frame that waited in vain is counted).
    fn gyro_rate(&mut self, h: &FrameHeader) -> Option<Vector3<f64>> {
        if self.cfg.no_rs || h.readout_ns == 0 {
            return None;
        }
        let need = h.t_mid_ns + h.readout_ns / 2;
        if self.cfg.lockstep_sync && self.imu_missing(need) {
            self.counters.lockstep_imu_timeouts += 1;
            // No IMU at all (e.g. its ingest keeps failing): wait no more for its start.
            self.imu_never_came |= self.imu.newest_ns().is_none();
        }
        let omega = self.imu.camera_rate(h);
        if omega.is_some() {
            self.counters.frames_gyro_rs += 1;
        }
        omega
    }

    /// Runs the VO on the frame and sends the keyframes that left its window.
    fn run_vo(&mut self, f: &FrameIn, t: &mut Tracked) -> anyhow::Result<()> {
        let h = &f.header;
        if self.client.is_none() {
            let (client, out) = self.new_client(h, f.now_ns)?;
            self.client = Some(client);
            t.out.extend(out);
            for m in std::mem::take(&mut self.pending_imu) {
                self.sample_to_client(m);
            }
        }
        let angular_velocity = self.gyro_rate(h);
        self.first_frame_ns.get_or_insert(h.t_mid_ns);
        if self.client.is_none() {
            return Ok(());
        }
        let (w, ht, stride) = (h.width as usize, h.height as usize, h.stride as usize);
        let result = GrayImage::new(f.pixels, w, ht, stride)
            .map_err(anyhow::Error::from)
            .and_then(|image| {
                let frame = VoFrame {
                    image,
                    t_ns: h.t_mid_ns,
                    readout_ns: h.readout_ns,
                    angular_velocity,
                };
                if let Some(o) = self.prior_step(&frame)? {
                    return Ok(o);
                }
                match self.client.as_mut() {
                    Some(v) => Ok(v.process(&frame)?),
                    None => Err(anyhow::anyhow!("no client")),
                }
            });
        let Some(v) = self.client.as_mut() else {
            return Ok(());
        };
        let mut o = match result {
            Ok(o) => o,
            Err(e) => {
                let detail = format!("frame {}: {e}", h.meta.seq);
                self.status.error(ErrorKind::Vo, detail);
                return Ok(());
            }
        };
        // Evicted keyframes belong to the session they were made in.
        let vo_session = v.vo().session_id();
        let sess = self
            .ids
            .session(vo_session.saturating_sub(o.vo.new_session as u32));
        t.vo_session = self.ids.session(vo_session);
        self.diagnostics = std::mem::take(&mut o.vo.diagnostics);
        t.take_output(&mut o);
        if o.world_move.is_some() {
            // The spooled keyframes of this session are in the old world: spool them again
            // (an anchor move alone leaves them: they are in the session's own world).
            self.spooled = None;
            self.counters.world_moves += 1;
        }
        self.follow_world_moves(&o, t);
        if let Some(nav) = o.nav {
            self.last_biases = Some(nav.biases);
        }
        let mut o = o.vo;
        if o.new_session {
            self.counters.vo_sessions_started += 1;
        }
        let client = self.cfg.client;
        let to_session = self.server.to_session(sess);
        self.counters.prior_keyframes_dropped += super::prior::drop_prior_keyframes(&mut o.evicted);
        for kf in &o.evicted {
            let msg = keyframe_message(client, kf, sess, &to_session);
            t.out.extend(self.send_keyframe(msg, f.now_ns));
        }
        // Lock-step: the server's answers to these keyframes (pose feedback) are in before
        // this frame's server pose.
        if self.cfg.lockstep_sync {
            t.await_handled = o.evicted.last().map(|k| (sess, k.id));
        }
        Ok(())
    }

    /// The anchor (`slam_core::vio::anchor`) follows the client's world moves of this
    /// frame: the anchor move it applied before the frame, then the frame's own world move.
    /// Both re-express the session's earlier poses (`FLAG_WORLD_MOVE`): the recorded
    /// trajectory stays the client's own, in the frame of its last anchor, and each live
    /// pose is in the server map's frame as it then was.
    fn follow_world_moves(&mut self, o: &ClientOutput, t: &mut Tracked) {
        let anchored = o
            .anchor
            .and_then(|_| self.server.anchor_applied(t.vo_session));
        if let Some(r) = anchored {
            self.anchors.count(&r);
            let a = Sim3::from_isometry(&r.delta, 1.0);
            t.world_move = Some(t.world_move.map_or(a, |m| m.compose(&a)));
        }
        if let Some(m) = o.world_move {
            self.server.on_world_move(t.vo_session, &m.world);
        }
    }

    /// The frame's outputs once the server had its say: new keyframes to the spool, the
    /// backfilled poses of frames seen while initialising, the acknowledgement and the
    /// tracked pose (with its server-map pose from the last feedback, eq. 3.1, 3.4).
    pub fn publish_frame(&mut self, t: Tracked, now_ns: i64) -> Vec<Out> {
        let mut out = vec![];
        if let Some(m) = t.world_move {
            out.push(Out::Pose(self.world_move_pose(&t, &m, now_ns)));
        }
        // Keyframes enter the VO map only with a frame that reports one (two at
        // initialisation): no map lock on the other frames.
        if self.cfg.spool && t.is_keyframe {
            self.spool_new_keyframes(t.vo_session, &mut out);
        }
        let (c, h) = (self.cfg.client, &t.header);
        let source = if t.source == PoseSource::VisualInertial {
            PoseSource::VisualInertial
        } else {
            PoseSource::Visual
        };
        for (t_ns, t_cw) in &t.backfill {
            let mut meta = MsgMeta::new(c, t.vo_session, h.meta.seq, now_ns);
            meta.flags = FLAG_BACKFILL;
            out.push(Out::Pose(TrackedPose {
                meta,
                t_ns: *t_ns,
                pose: wire_pose(t_cw),
                state: TrackState::Tracking as u32,
                source: source as u32,
                metric: t.metric as u32,
                ..TrackedPose::default()
            }));
            self.counters.frames_backfilled += 1;
        }
        out.push(self.ack(h, now_ns));
        out.push(Out::Pose(self.tracked_pose(&t, now_ns)));
        if self.cfg.publish_features {
            out.extend(self.tracked_features(&t, now_ns));
        }
        self.count_frame(&t);
        self.note_resumed_frame(now_ns);
        out
    }

    /// The frame's keypoints matched to map points (`publish_features`), when it was
    /// tracked.
    fn tracked_features(&self, t: &Tracked, now_ns: i64) -> Option<Out> {
        let h = &t.header;
        let (t_ns, matched) = self.client.as_ref()?.vo().last_matches()?;
        if t.state != TrackState::Tracking || t_ns != h.t_mid_ns {
            return None;
        }
        let features: Vec<_> = matched
            .take(shm_schema::topics::MAX_TRACKED_FEATURES)
            .map(|(p, u, v)| shm_schema::TrackedFeature {
                map_point_id: p,
                u,
                v,
            })
            .collect();
        let header = shm_schema::TrackedFeaturesHeader {
            meta: MsgMeta::new(self.cfg.client, t.vo_session, h.meta.seq, now_ns),
            t_ns,
            n_features: features.len() as u32,
            reserved: 0,
        };
        Some(Out::Features(header, features))
    }

    /// A backfilled, metric visual-inertial pose `t_cw` of the frame at `t_ns`, sent with
    /// the end of stream `h` (the calibration mode's last frames).
    pub(super) fn backfill_pose(
        &mut self,
        h: &FrameHeader,
        t_ns: i64,
        t_cw: &Isometry3<f64>,
        now_ns: i64,
    ) -> TrackedPose {
        let mut meta = MsgMeta::new(self.cfg.client, self.session_id(), h.meta.seq, now_ns);
        meta.flags = FLAG_BACKFILL;
        self.counters.frames_backfilled += 1;
        TrackedPose {
            meta,
            t_ns,
            pose: wire_pose(t_cw),
            state: TrackState::Tracking as u32,
            source: PoseSource::VisualInertial as u32,
            metric: 1,
            ..TrackedPose::default()
        }
    }

    /// The message that moves the world of the frame's VO session by `x' = s R x + t`
    /// (`FLAG_WORLD_MOVE`: the recorder re-expresses the session's earlier poses).
    fn world_move_pose(&self, t: &Tracked, m: &Sim3, now_ns: i64) -> TrackedPose {
        let mut meta = MsgMeta::new(self.cfg.client, t.vo_session, t.header.meta.seq, now_ns);
        meta.flags = FLAG_WORLD_MOVE;
        let iso = Isometry3::from_parts(nalgebra::Translation3::from(m.t), m.r);
        TrackedPose {
            meta,
            t_ns: t.header.t_mid_ns,
            pose: shoal_runtime::wire::wire_from_iso(&iso),
            world_scale: m.s,
            metric: 1,
            ..TrackedPose::default()
        }
    }

    /// The frame's wire pose: camera-to-world, or the orientation alone.
    fn wire_pose_of(t: &Tracked) -> Pose {
        match (t.t_cw, t.r_wc) {
            (Some(t_cw), _) => wire_pose(&t_cw),
            (None, Some(r_wc)) => {
                let iso = Isometry3::from_parts(nalgebra::Translation3::identity(), r_wc);
                shoal_runtime::wire::wire_from_iso(&iso)
            }
            (None, None) => Pose::IDENTITY,
        }
    }

    /// The frame's [`TrackedPose`].
    fn tracked_pose(&mut self, t: &Tracked, now_ns: i64) -> TrackedPose {
        let h = &t.header;
        let server_pose = t
            .t_cw
            .and_then(|t_cw| self.server.frame_pose(t.vo_session, &t_cw.inverse()));
        if server_pose.is_some() {
            self.counters.frames_server_pose += 1;
        }
        let mut stage_ms = t.stage_ms;
        stage_ms[stage::TOTAL] = (now_ns - t.recv_ns) as f32 * 1e-6;
        TrackedPose {
            meta: MsgMeta::new(self.cfg.client, t.vo_session, h.meta.seq, now_ns),
            t_ns: h.t_mid_ns,
            dataset_index: h.dataset_index,
            pose: Self::wire_pose_of(t),
            server_pose: server_pose.map_or(Pose::IDENTITY, |p| p.0),
            server_map_id: server_pose.map_or(0, |p| p.1.raw()),
            state: t.state as u32,
            has_server_pose: server_pose.is_some() as u32,
            tracked_points: t.tracked,
            is_keyframe: t.is_keyframe as u32,
            frame_publish_mono_ns: h.meta.publish_mono_ns,
            frame_receive_mono_ns: t.recv_ns,
            stage_ms,
            source: t.source as u32,
            metric: t.metric as u32,
            world_scale: 0.0,
        }
    }

    /// The per-frame counters and the VO's figures.
    fn count_frame(&mut self, t: &Tracked) {
        let c = &mut self.counters;
        c.frames_received += 1;
        c.frames_tracked += (t.state == TrackState::Tracking) as u64;
        c.poses_published += 1;
        match t.source {
            PoseSource::VisualInertial => c.frames_vio += 1,
            PoseSource::Inertial => c.frames_inertial += 1,
            PoseSource::OrientationOnly => c.frames_orientation_only += 1,
            _ => {}
        }
        self.resume.last_frame_seq = Some(t.header.meta.seq);
        if let Some(v) = self.client.as_ref().map(|c| c.vo()) {
            let s = &mut self.status;
            s.set_value("vo_relocalizations", v.relocalizations() as f64);
            s.set_value("keyframes_culled", v.keyframes_culled() as f64);
            c.local_mapping_sync_timeouts =
                self.vo_timeouts_base + v.local_mapping_sync_timeouts() as u64;
        }
    }

    /// The keyframes of the VO map newer than the last spooled one (of session `session`),
    /// as spool writes.
    fn spool_new_keyframes(&mut self, session: u32, out: &mut Vec<Out>) {
        let Some(v) = self.client.as_ref().map(|c| c.vo()) else {
            return;
        };
        let after = self.spooled.filter(|l| l.0 == session).map(|l| l.1);
        let client = self.cfg.client;
        let to_session = self.server.to_session(session);
        let new: Vec<_> = v.with_map(|m| {
            m.keyframes
                .range(after.map_or(0, |a| a + 1)..)
                .filter(|(id, _)| !slam_core::vo::is_prior_keyframe(**id))
                .map(|(id, kf)| (*id, spool_entry(m, client, kf, session, &to_session)))
                .collect()
        });
        for (id, entry) in new {
            out.push(Out::SpoolWrite(entry));
            self.spooled = Some((session, id));
            self.counters.keyframes_spooled += 1;
        }
    }
}

/// The spool entry of keyframe `kf` of `map` (VO session `session`): its message and the
/// positions of the map points it observes, in the session's own world (`to_session`).
fn spool_entry(
    map: &slam_core::vo::ClientMap,
    client: u32,
    kf: &slam_core::vo::Keyframe,
    session: u32,
    to_session: &Isometry3<f64>,
) -> crate::spool::SpoolEntry {
    let points = kf
        .points
        .iter()
        .flatten()
        .filter_map(|p| map.points.get(p))
        .map(|mp| shoal_runtime::journal::SpooledPoint {
            id: mp.id,
            p_w: (to_session * nalgebra::Point3::from(mp.p_w)).coords.into(),
        })
        .collect();
    crate::spool::SpoolEntry {
        msg: keyframe_message(client, kf, session, to_session),
        points,
    }
}
