//! The tracker's core: everything the service decides, with typed inputs and outputs and no
//! IPC, file or clock access of its own (times come in as arguments), so that it is tested
//! in-process by feeding it recorded frames, IMU samples and feedback (`tests.rs`).
//!
//! Inputs: [`TrackerCore::on_imu`], [`TrackerCore::on_feedback`], [`TrackerCore::on_tick`],
//! the frame in two steps ([`TrackerCore::track`], then, after a lock-step wait for the
//! server, [`TrackerCore::publish_frame`]), the end of stream ([`TrackerCore::take_window`],
//! [`TrackerCore::end_of_stream`]) and the spool's recovered keyframes
//! ([`TrackerCore::recover_spool`]: sent, or held to resume a visual-inertial session,
//! `resume.rs`). Outputs: [`Out`] messages, in the order the ports
//! must carry them out. Counters and errors go to the core's [`Status`].
use shm_schema::{
    Feedback, FrameAck, FrameHeader, ImuMsg, MsgMeta, TrackedPose, FLAG_END_OF_STREAM,
};
use shoal_runtime::Status;
use slam_core::ids::{ClientKeyframeId, SessionId};
use slam_core::vo::{VoDiagnostic, VoParams, VoTracker};

pub use calib::{
    CalibClient, CalibReport, CalibValues, Estimate, InitReport, IMPLAUSIBLE_PRIOR_SIGMAS,
    LOG_NAMES,
};
pub use client::{Client, ClientOutput};

use crate::imu::ImuInput;
use crate::mapping_thread::LocalMappingThread;
use crate::outbox::{keyframe_message, KeyframeMsg, Outbox};

mod calib;
mod client;
mod counters;
mod frame;
mod prior;
mod resume;
mod server;
#[cfg(test)]
mod tests;

pub use counters::{
    AnchorReport, StaticReport, TrackerCounters, TrackerResume, VioReport, RESUME_VERSION,
};
pub use frame::{FrameIn, FrameStep, Tracked};
pub use server::{KeyframeCounts, KeyframeKey, ServerRef, ServerState};

/// The ids one start (life) of the tracker process gives out (the packing is
/// [`slam_core::ids`]'s): its sessions are new ones ([`SessionId`]: the start count and the
/// VO's own session counter), its keyframe ids start at
/// [`ClientKeyframeId::first_of_start`] (unique per client across restarts: the server names
/// keyframes by them). A start that resumes its predecessor's session (`resume.rs`) gives
/// the VO's first session that session's id.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StartIds {
    start: u32,
    /// The wire session id the VO's first session continues, when resumed.
    resumed: Option<u32>,
}

impl StartIds {
    /// The ids of start number `start` (1 for the first).
    pub fn new(start: u64) -> Self {
        Self {
            start: start as u32,
            resumed: None,
        }
    }

    /// The start number.
    pub fn start(self) -> u32 {
        self.start
    }

    /// The VO's first session continues wire session `session` (a predecessor's).
    pub fn resume_session(&mut self, session: u32) {
        self.resumed = Some(session);
    }

    /// The wire session id of the VO's session `vo_session` in this start.
    pub fn session(self, vo_session: u32) -> u32 {
        match self.resumed {
            Some(s) if vo_session == 1 => s,
            _ => SessionId::new(self.start, vo_session).raw(),
        }
    }

    /// The first keyframe id of this start.
    pub fn first_keyframe_id(self) -> u64 {
        ClientKeyframeId::first_of_start(self.start).raw()
    }
}

/// IMU samples kept from before the first frame for the visual-inertial client, ns.
const PENDING_IMU_NS: i64 = 2_000_000_000;

/// IMU samples kept from before the first frame for the calibration mode, ns (its default
/// start window, [`slam_core::calib::online::OnlineParams::start_window_ns`], and a margin;
/// a longer `tracker.calib.start_seconds` keeps that plus 1 s).
const PENDING_IMU_CALIB_NS: i64 = 3_000_000_000;

/// Why a visual-inertial client without camera-IMU extrinsics does not initialise, and what
/// it does instead.
pub const NO_EXTRINSICS: &str = "no camera-IMU extrinsics (T_BS) given: no inertial \
     initialisation (no metric scale); the VO tracks monocular, frames it cannot pose get a \
     gyro orientation through the dataset's assumed camera-IMU rotation (its device-axis \
     convention, identity when it has none), and a device at rest its gyro bias";

/// A keyframe unacknowledged for this long is sent again (e.g. to a restarted mapper), ns.
pub const RESEND_AFTER_NS: i64 = 2_000_000_000;

/// What the ports must do, in order.
#[derive(Debug, Clone)]
pub enum Out {
    /// Publish a frame acknowledgement (lock-step pacing of the ingests).
    Ack(FrameAck),
    /// Publish a tracked pose (a frame's, a backfilled one, or the end of stream).
    Pose(TrackedPose),
    /// Publish a keyframe message to the mapper (first send or re-send).
    Keyframe(KeyframeMsg),
    /// Publish a frame's tracked features (`publish_features`).
    Features(
        shm_schema::TrackedFeaturesHeader,
        Vec<shm_schema::TrackedFeature>,
    ),
    /// Append a line to the calibration log (`tracker.calib.log`; the first is its header).
    CalibLog(String),
    /// Write a keyframe of the VO map and its points' positions to the spool (it survives
    /// a SIGKILL there).
    SpoolWrite(crate::spool::SpoolEntry),
    /// A keyframe left the VO map and was sent: drop it from the spool.
    SpoolSent(KeyframeKey),
}

/// The tracker's settings that the core uses (from the service's configuration).
#[derive(Debug, Clone)]
pub struct CoreConfig {
    /// Client index.
    pub client: u32,
    /// Run no VO (transport only).
    pub no_vo: bool,
    /// Rolling-shutter compensation off.
    pub no_rs: bool,
    /// Most keyframes in the client map.
    pub window: usize,
    /// ORB features per frame.
    pub features: usize,
    /// Local mapping inline in the tracking thread.
    pub inline_mapping: bool,
    /// Lock-step synchronisation with local mapping and the server.
    pub lockstep_sync: bool,
    /// A keyframe spool is kept (the core asks for spool writes).
    pub spool: bool,
    /// Each tracked frame's matched keypoints are published.
    pub publish_features: bool,
    /// What the client runs (`Auto` runs `Mono`: the launcher decides per client).
    pub mode: crate::ClientMode,
    /// The IMU calibration of the visual-inertial mode.
    pub imu: crate::ImuCalibConfig,
    /// The calibration mode's priors.
    pub calib: crate::CalibModeConfig,
    /// The calibration mode writes a log (the ports have one open).
    pub calib_log: bool,
    /// The camera's rolling-shutter line order.
    pub readout: slam_core::rolling_shutter::ReadoutDirection,
    /// Anchoring a visual-inertial client to its server map.
    pub anchor: slam_core::vio::anchor::AnchorParams,
}

impl CoreConfig {
    /// The core's settings from the service's command line and configuration.
    pub fn new(p: &crate::Params, cfg: &crate::TrackerConfig) -> Self {
        Self {
            client: p.client,
            no_vo: !cfg.vo,
            no_rs: !cfg.rolling_shutter,
            window: cfg.window,
            features: cfg.features,
            inline_mapping: cfg.local_mapping == crate::LocalMapping::Inline,
            lockstep_sync: p.lockstep_sync(cfg),
            spool: p.spool.is_some(),
            publish_features: cfg.publish_features,
            mode: cfg.mode,
            imu: cfg.imu.clone(),
            calib: cfg.calib.clone(),
            calib_log: cfg.calib.log.is_some(),
            readout: cfg.readout_direction,
            anchor: cfg.anchor.params(),
        }
    }
}

/// The tracker of one client, without its ports.
pub struct TrackerCore {
    cfg: CoreConfig,
    /// Errors and gauges (the counters are put in when it is asked for).
    status: Status,
    counters: TrackerCounters,
    /// The crash-recovery state as of now.
    resume: TrackerResume,
    /// The ids this start gives out.
    ids: StartIds,
    client: Option<Client>,
    /// The calibration mode's client (created with the first frame).
    calib: Option<Box<CalibClient>>,
    /// The calibration mode cannot run, and why.
    calib_disabled: Option<String>,
    /// The visual-inertial mode cannot run, and why (no extrinsics, bad calibration).
    vio_disabled: Option<String>,
    /// IMU time of the first frame tracked (the report's time to initialise).
    first_frame_ns: Option<i64>,
    /// Biases of the last frame's metric state.
    last_biases: Option<slam_core::imu::ImuBiases>,
    /// Anchor moves applied ([`AnchorReport`]; the dropped ones are the client's count).
    anchors: AnchorReport,
    /// IMU samples taken before the client exists (its first frame): the last
    /// [`PENDING_IMU_NS`] of them are given to it then (and all those from
    /// `pending_imu_from_ns` on, the replay a resumed session asked for).
    pending_imu: std::collections::VecDeque<slam_core::imu::ImuMeasurement>,
    /// Samples from this IMU time on are kept until the client exists, ns.
    pending_imu_from_ns: Option<i64>,
    outbox: Outbox,
    kf_counts: KeyframeCounts,
    server: ServerState,
    imu: ImuInput,
    /// Lock-step: a frame waited in vain for the IMU stream's first sample.
    imu_never_came: bool,
    /// The next frame is the first after a restart (its gap is counted apart).
    first_after_restart: bool,
    /// The next frame is the first after a restart: in lock-step it does not wait for IMU
    /// samples ([`TrackerCore::imu_missing`]), unless it asked for them again to resume a
    /// visual-inertial session (`resume.rs`).
    imu_wait_waived: bool,
    ack_seq: u64,
    ended: bool,
    /// Newest keyframe written to the spool: (VO session, id).
    spooled: Option<KeyframeKey>,
    /// Local-mapping waits that timed out before this start.
    vo_timeouts_base: u64,
    /// The VO's diagnostics of the last frame tracked.
    diagnostics: Vec<VoDiagnostic>,
    /// Resuming a killed predecessor's visual-inertial session (`resume.rs`).
    spool_resume: resume::SpoolResume,
    /// The predecessor's visual-inertial report (its initialisation, for a resumed one).
    predecessor_vio: Option<VioReport>,
    /// A saved map to localise in before the VO initialises (`prior.rs`).
    prior: Option<prior::Prior>,
}

impl TrackerCore {
    /// A core resuming `status` (that of a killed predecessor, or a fresh one).
    pub fn new(cfg: CoreConfig, mut status: Status) -> Self {
        let mut counters: TrackerCounters = status.counters_as();
        let resume: TrackerResume = status.take_resume(RESUME_VERSION).unwrap_or_default();
        let restarted = status.starts > 1;
        let kf_counts = KeyframeCounts::resume(&mut counters, &resume, restarted);
        counters.lockstep_sync = cfg.lockstep_sync as u64;
        let predecessor_vio = status.details_as::<VioReport>().filter(|_| restarted);
        Self {
            ids: StartIds::new(status.starts),
            client: None,
            calib: None,
            calib_disabled: None,
            vio_disabled: None,
            first_frame_ns: None,
            last_biases: None,
            anchors: AnchorReport::default(),
            pending_imu: Default::default(),
            pending_imu_from_ns: None,
            outbox: Outbox::new(cfg.client),
            kf_counts,
            server: ServerState::new(cfg.client, cfg.lockstep_sync, cfg.anchor),
            imu: ImuInput::default(),
            imu_never_came: false,
            // After a restart `last_frame_seq` is the dead process's last status write: the
            // first frame's jump past it also covers frames that process handled after it.
            first_after_restart: restarted,
            imu_wait_waived: restarted,
            ack_seq: 0,
            ended: false,
            spooled: None,
            vo_timeouts_base: counters.local_mapping_sync_timeouts,
            diagnostics: Vec::new(),
            spool_resume: Default::default(),
            predecessor_vio,
            prior: None,
            cfg,
            status,
            counters,
            resume,
        }
    }

    /// The status as of now (counters and crash-recovery state put in), to write.
    pub fn status(&mut self) -> &Status {
        self.status.put_counters(&self.counters);
        self.status.set_resume(RESUME_VERSION, &self.resume);
        if let Some(r) = self.vio_report() {
            self.status.set_details(&r);
        }
        if let Some(r) = self.calib_report() {
            self.status.set_details(&r);
        }
        &self.status
    }

    /// The visual-inertial client's report (`None` in the monocular mode).
    pub fn vio_report(&self) -> Option<VioReport> {
        if self.cfg.mode != crate::ClientMode::Vio {
            return None;
        }
        let vio = self.client.as_ref().and_then(|c| c.vio());
        if let Some(why) = &self.vio_disabled {
            // Orientation-only (no extrinsics): the static initialisation still reports.
            let static_init = vio.and_then(|v| client::vio_report(v, None).static_init);
            return Some(VioReport {
                static_init,
                ..client::vio_disabled(why)
            });
        }
        let Some(v) = vio else {
            return Some(client::vio_disabled("no frame tracked yet"));
        };
        let mut r = client::vio_report(v, self.first_frame_ns);
        if let Some(b) = self.last_biases {
            r.gyro_bias = Some(b.gyro.into());
            r.accel_bias = Some(b.accel.into());
        }
        self.put_resume_report(v, &mut r);
        if self.cfg.anchor.enabled {
            r.anchor = Some(AnchorReport {
                dropped: v.anchors_dropped() as u64,
                ..self.anchors.clone()
            });
        }
        Some(r)
    }

    /// For the ports' own errors (spool, publish).
    pub fn status_mut(&mut self) -> &mut Status {
        &mut self.status
    }

    /// The counters so far.
    pub fn counters(&self) -> &TrackerCounters {
        &self.counters
    }

    /// Lock-step: a wait for the server that timed out.
    pub fn count_server_timeout(&mut self) {
        self.counters.lockstep_server_timeouts += 1;
    }

    /// The settings.
    pub fn config(&self) -> &CoreConfig {
        &self.cfg
    }

    /// What the VO's initialiser and backward walk tried on the last frame given to
    /// [`TrackerCore::track`] (the ports print them with `debug_init`).
    pub fn diagnostics(&self) -> &[VoDiagnostic] {
        &self.diagnostics
    }

    /// The session id of this start's non-VO messages (acks, end of stream).
    fn session_id(&self) -> u32 {
        self.ids.session(1)
    }

    /// The frames' end of stream was taken.
    pub fn ended(&self) -> bool {
        self.ended
    }

    /// The IMU stream ended and every keyframe was acknowledged: nothing more to wait for.
    pub fn drained(&self) -> bool {
        self.imu.ended && self.outbox.pending() == 0
    }

    /// Keyframe traffic so far (sent, re-sent, acknowledged): the status is to be written
    /// when it changes.
    pub fn keyframe_progress(&self) -> (u64, u64, u64) {
        (self.outbox.sent, self.outbox.resent, self.outbox.acked)
    }

    /// Puts the current keyframe counts into the status.
    pub fn put_keyframe_counts(&mut self) {
        let (c, r) = (&mut self.counters, &mut self.resume);
        self.kf_counts.set(&self.outbox, c, r);
    }

    /// Takes one IMU message; returns whether it was accepted (for the frame log).
    pub fn on_imu(&mut self, m: &ImuMsg) -> bool {
        let (s, c) = (&mut self.status, &mut self.counters);
        let taken = self.imu.on_sample(m, s, c, self.cfg.client);
        if taken {
            self.imu_to_client(m);
        }
        taken
    }

    /// An IMU sample the stream checks let through, to the visual-inertial client: a
    /// saturated or non-finite one is refused there, a gap reported (both counted).
    fn imu_to_client(&mut self, m: &ImuMsg) {
        let sample = slam_core::imu::ImuMeasurement {
            t_ns: m.t_ns,
            gyro: m.gyro.into(),
            accel: m.accel.into(),
        };
        if let Some(c) = self.calib.as_deref_mut() {
            c.push_imu(sample);
            return;
        }
        if self.client.is_none() {
            let keep_ns = match self.cfg.mode {
                crate::ClientMode::Vio => PENDING_IMU_NS,
                crate::ClientMode::Calib => PENDING_IMU_CALIB_NS
                    .max((self.cfg.calib.start_seconds * 1e9) as i64 + 1_000_000_000),
                _ => return,
            };
            self.pending_imu.push_back(sample);
            let keep_from = self.pending_imu_from_ns.unwrap_or(i64::MAX);
            while self
                .pending_imu
                .front()
                .is_some_and(|f| f.t_ns < m.t_ns - keep_ns && f.t_ns < keep_from)
            {
                self.pending_imu.pop_front();
            }
            return;
        }
        self.sample_to_client(sample);
    }

    /// Gives `sample` to the client, counting its complaint.
    fn sample_to_client(&mut self, sample: slam_core::imu::ImuMeasurement) {
        let Some(client) = self.client.as_mut() else {
            return;
        };
        let Err(e) = client.on_imu(sample) else {
            return;
        };
        let kind = match e {
            slam_core::vio::ImuSampleError::Gap { .. } => {
                self.counters.imu_gaps += 1;
                shoal_runtime::ErrorKind::ImuGap
            }
            slam_core::vio::ImuSampleError::NotAfterLast { .. } => {
                shoal_runtime::ErrorKind::NonMonotonic
            }
            _ => {
                self.counters.imu_samples_refused += 1;
                shoal_runtime::ErrorKind::ImuSaturated
            }
        };
        let c = self.cfg.client;
        self.status.error(kind, format!("imu of client {c}: {e}"));
    }

    /// Takes one feedback message of the mapper.
    pub fn on_feedback(&mut self, f: &Feedback) {
        let (s, c) = (&mut self.status, &mut self.counters);
        self.server.on_feedback(f, &mut self.outbox, s, c);
        self.forward_anchor();
    }

    /// A metric client asked to anchor its world to the server map the last feedback was
    /// in, when that changed enough (`slam_core::vio::anchor`); applied before its next
    /// frame. A feedback that asks for nothing withdraws an earlier request.
    fn forward_anchor(&mut self) {
        let Some(Client::Vio(v)) = self.client.as_mut() else {
            return;
        };
        let vo_session = v.vo().session_id();
        // The client's pending move is always the tracker's request (or none), so what it
        // applies is what the tracker accounts for.
        let r = self
            .server
            .anchor_request()
            .filter(|r| v.status().is_metric() && r.session == self.ids.session(vo_session));
        v.request_anchor(vo_session, r.map(|r| r.delta));
    }

    /// Lock-step: whether the server has finished keyframe `key` (see
    /// [`ServerState::take_handled`]).
    pub fn take_handled(&mut self, key: KeyframeKey) -> bool {
        self.server.take_handled(key)
    }

    /// Periodic work at `now_ns`: keyframes unacknowledged for [`RESEND_AFTER_NS`] are sent
    /// again, queued ones sent when the in-flight limit allows.
    pub fn on_tick(&mut self, now_ns: i64) -> Vec<Out> {
        let mut msgs = vec![];
        self.outbox.resend_stale(now_ns, RESEND_AFTER_NS, &mut msgs);
        msgs.into_iter().map(Out::Keyframe).collect()
    }

    /// A keyframe that a killed predecessor left in the spool: sent before this start's
    /// own keyframes.
    pub fn recover_keyframe(&mut self, msg: KeyframeMsg, now_ns: i64) -> Vec<Out> {
        self.counters.keyframes_recovered += 1;
        self.send_keyframe(msg, now_ns)
    }

    /// Sends a keyframe message (kept until acknowledged) and drops it from the spool.
    pub fn send_keyframe(&mut self, msg: KeyframeMsg, now_ns: i64) -> Vec<Out> {
        self.count_imu_segment(&msg);
        let key = msg.key();
        let mut msgs = vec![];
        self.outbox.send(msg, now_ns, &mut msgs);
        let mut out: Vec<Out> = msgs.into_iter().map(Out::Keyframe).collect();
        if self.cfg.spool {
            out.push(Out::SpoolSent(key));
        }
        out
    }

    /// Counts a keyframe message's IMU segment; one cut to `MAX_IMU_RECORDS` is an error
    /// in the status (`shm_schema::topics::MAX_IMU_RECORDS`).
    fn count_imu_segment(&mut self, msg: &KeyframeMsg) {
        if !msg.imu.is_empty() {
            self.counters.keyframes_with_imu += 1;
            self.counters.keyframe_imu_samples += msg.imu.len() as u64;
        }
        if msg.imu_cut > 0 {
            self.counters.keyframe_imu_cut += 1;
            let detail = format!(
                "keyframe {}: IMU segment of {} samples cut to {} (the server sees no link)",
                msg.header.keyframe_id,
                msg.imu.len() + msg.imu_cut,
                msg.imu.len()
            );
            self.status
                .error(shoal_runtime::ErrorKind::ImuSegmentCut, detail);
        }
    }

    /// At the end of stream: the keyframes still in the VO map, oldest first, to send one
    /// by one with [`TrackerCore::send_window_keyframe`] (in lock-step waiting for the
    /// server to finish each, so it handles them on the same schedule on every run).
    pub fn take_window(&mut self) -> Vec<slam_core::vo::Keyframe> {
        let mut kfs = self
            .client
            .as_mut()
            .map_or_else(Vec::new, |v| v.vo_mut().drain_keyframes());
        self.counters.prior_keyframes_dropped += prior::drop_prior_keyframes(&mut kfs);
        kfs
    }

    /// Sends keyframe `kf` of the VO window (of the VO's current session); returns its key
    /// and the outputs.
    pub fn send_window_keyframe(
        &mut self,
        kf: &slam_core::vo::Keyframe,
        now_ns: i64,
    ) -> (KeyframeKey, Vec<Out>) {
        let vo_session = self.client.as_ref().map_or(1, |v| v.vo().session_id());
        let session = self.ids.session(vo_session);
        let to_session = self.server.to_session(session);
        let msg = keyframe_message(self.cfg.client, kf, session, &to_session);
        let key = msg.key();
        (key, self.send_keyframe(msg, now_ns))
    }

    /// The frames' end of stream `h` (after [`TrackerCore::take_window`]): acknowledged, and
    /// passed on to the recorder as an end-of-stream pose.
    pub fn end_of_stream(&mut self, h: &FrameHeader, now_ns: i64) -> Vec<Out> {
        let mut out = self.flush_calib(h, now_ns);
        self.ended = true;
        let c = self.cfg.client;
        let ack = FrameAck {
            meta: MsgMeta::new(c, self.session_id(), self.ack_seq, now_ns),
            frame_seq: h.meta.seq,
            frame_t_ns: i64::MAX,
        };
        self.status
            .set_value("end_of_stream_seq", h.meta.seq as f64);
        let mut meta = MsgMeta::new(c, self.session_id(), h.meta.seq, now_ns);
        meta.flags = FLAG_END_OF_STREAM;
        let eos = TrackedPose {
            meta,
            ..TrackedPose::default()
        };
        out.extend([Out::Ack(ack), Out::Pose(eos)]);
        out
    }

    /// The final status (counters put in, `finished` when the stream ended).
    pub fn finish(mut self) -> Status {
        self.put_keyframe_counts();
        let kept = self.outbox.sent_poses_kept() as f64;
        self.status.set_value("sent_poses_kept", kept);
        self.status.finished = self.ended;
        self.status();
        self.status
    }

    /// The client for frames like `h` (at host time `now_ns`): the visual-inertial one
    /// continuing a held session (`resume.rs`), or a new one on a new VO; with the outputs
    /// of held keyframes not resumed (sent now, before the frame's own keyframes).
    fn new_client(&mut self, h: &FrameHeader, now_ns: i64) -> anyhow::Result<(Client, Vec<Out>)> {
        let params = match self.cfg.mode {
            crate::ClientMode::Vio => self.vio_params(h).map_err(|why| {
                self.vio_disabled = Some(why);
            }),
            _ => Err(()),
        };
        if let (Ok(p), true) = (params, self.holds_session()) {
            match self.resume_client(h, p) {
                Ok(v) => return Ok((Client::Vio(Box::new(v)), vec![])),
                Err(why) => {
                    let detail = format!("client {}: not resumed: {why}", self.cfg.client);
                    self.status
                        .error(shoal_runtime::ErrorKind::VioResume, detail);
                    self.spool_resume.refused = Some(why);
                }
            }
        }
        let out = self.release_held(now_ns);
        if params.is_err() {
            self.start_prior(h);
        }
        let vo = self.new_vo(h)?;
        let client = match params {
            Ok(p) => Client::Vio(Box::new(slam_core::vio::VioTracker::new(vo, p))),
            Err(()) => Client::Mono(Box::new(vo)),
        };
        Ok((client, out))
    }

    /// The visual-inertial client's settings for frames like `h` (without given extrinsics:
    /// orientation-only, [`NO_EXTRINSICS`]) (its `T_BS` is the
    /// camera-IMU extrinsic); why it cannot run otherwise.
    fn vio_params(&mut self, h: &FrameHeader) -> Result<slam_core::vio::VioParams, String> {
        let preint = self.cfg.imu.preintegration().map_err(|e| {
            self.status
                .error(shoal_runtime::ErrorKind::ImuCalibration, e.clone());
            format!("{e}: running monocular")
        })?;
        let t_bc = shoal_runtime::wire::iso_from_wire(&h.t_bs)
            .ok_or("the frames' T_BS is not a rigid transform: running monocular")?;
        // The ingest applied t_d to the frame stamps: they are on the IMU clock already.
        let given = self.cfg.imu.extrinsics_given;
        if !given {
            self.vio_disabled = Some(NO_EXTRINSICS.into());
        }
        Ok(slam_core::vio::VioParams {
            inertial_init: given,
            ..slam_core::vio::VioParams::new(preint, t_bc)
        })
    }

    /// A new VO for frames like `h`, its keyframe ids in this start's own range (the server
    /// names keyframes by them, so they stay unique per client across restarts), its local
    /// mapping on this service's thread ([`crate::mapping_thread`]) unless inline.
    fn new_vo(&mut self, h: &FrameHeader) -> anyhow::Result<VoTracker> {
        let mut camera =
            shoal_runtime::wire::camera_from_intrinsics(&h.intrinsics, h.width, h.height);
        camera.readout = self.cfg.readout;
        let mut vp = VoParams {
            rolling_shutter: !self.cfg.no_rs,
            window: self.cfg.window.max(2),
            sync_local_mapping: self.cfg.lockstep_sync,
            ..VoParams::default()
        };
        vp.orb.n_features = self.cfg.features;
        let mut v = VoTracker::new(vp, camera)?;
        if !self.cfg.inline_mapping {
            LocalMappingThread::attach(&mut v)
                .map_err(|e| anyhow::anyhow!("local-mapping thread: {e}"))?;
        }
        v.start_keyframe_ids_at(self.ids.first_keyframe_id());
        self.counters.local_mapping_thread = Some(!self.cfg.inline_mapping as u64);
        Ok(v)
    }
}
