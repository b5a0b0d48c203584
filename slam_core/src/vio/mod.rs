//! The visual-inertial client core (issue 17; seed ch. 5; `VI_NOTES.md` §1, §2, §4): the
//! monocular VO ([`crate::vo::VoTracker`]), the inertial initialisation beside it
//! ([`crate::imu::coupler`]), a frame navigator ([`navigator`]) and the IMU samples
//! ([`imu_buffer`]), composed as plain data in, poses out: no threads, clocks or IO.
//!
//! **Clocks** (`VI_NOTES.md` §1). IMU samples are on the IMU clock. A frame's
//! [`VoFrame::t_ns`] is its **mid-row** time; its IMU-clock time is
//! `t_imu = t_ns + coupler.t_d_ns` ([`VioParams::coupler`]). The project's ingest applies
//! the calibrated `t_d` once to the frame stamps, so the tracker service passes
//! `t_d_ns = 0` (the residual offset); a caller with camera-clock stamps passes the
//! calibrated offset instead. Every time in this module's outputs is the IMU clock's.
//!
//! **Per frame** ([`VioTracker::process`]):
//! 1. Once initialised, the navigator predicts the frame's body state from the last one
//!    with the IMU (preintegration at the current biases, §4). The predicted camera pose
//!    replaces the motion model in the projection search, its camera twist (angular *and*
//!    linear) poses the rolling-shutter rows at their own time (§1, middle-row convention),
//!    and a pose prior (the gyro's rotation, the filter's position covariance) joins the
//!    pose optimisation ([`crate::optim::PosePrior`]; Table 5.1 "tracking = reprojections +
//!    IMU prior"). The optimisation itself starts from the VO's constant-velocity pose
//!    (see `VoTracker::optimisation_start` for why).
//! 2. The VO tracks the frame ([`VoTracker::process_with_hint`]); the navigator takes the
//!    visual pose: orientation from vision, position and velocity by a Kalman update whose
//!    measurement covariance is the pose optimisation's
//!    ([`crate::optim::PoseOptResult::information`]); with the prior in it, the optimised
//!    pose is already the posterior and the velocity follows by conditioning.
//! 3. **Keyframes.** A keyframe the VO makes from the frame carries, attached when it is made
//!    (before local mapping sees it, so inline and threaded mapping and lock-step runs stay
//!    deterministic), the IMU samples since the previous keyframe and the calibration
//!    ([`crate::vo::KeyframeImu`]; the VO is handed each IMU sample) and, once initialised,
//!    the IMU's prediction of its velocity and biases ([`crate::vo::Keyframe::inertial`]).
//!    The keyframe poses go to the coupler. When it initialises or refines, the VO's world
//!    and the navigator move by `x' = s R x` ([`VioOutput::world_move`]: the caller
//!    re-expresses the session's earlier poses the same way), and the navigator starts from
//!    the newest keyframe's state (the initialisation's velocity and biases).
//! 4. **Local mapping's visual-inertial window** (`crate::vo::vi_window`, on keyframes with
//!    an inertial state: never before the initialisation) refines the poses, velocities,
//!    biases and points of the last keyframes. The first frame after a keyframe's mapping
//!    ([`crate::vo::VoOutput::mapped`], the same frame inline or threaded) gives the
//!    navigator that keyframe's refined velocity and biases (the velocity carried to the
//!    frame with the IMU), so the biases are tracked at every keyframe. The first windows
//!    after the initialisation may also correct gravity and scale: that similarity moves the
//!    world like a refinement ([`crate::vo::VoOutput::world_correction`]).
//! 5. **Dropouts:** while vision fails and for at most [`VioParams::max_coast_s`] since the
//!    last tracked frame, the VO keeps its session and the frame gets the IMU-propagated
//!    pose ([`PoseSource::Inertial`]); when vision returns the local map is searched around
//!    the IMU prediction in a wide window ([`VioParams::rejoin_radius_px`]), relocalisation
//!    being the fallback. Beyond it the VO goes on as a monocular one (a new session after
//!    its failure count), and the initialisation starts over with the new session.
//! 6. **Before the initialisation** (or without a navigator) a frame the VO cannot pose
//!    gets an orientation only ([`PoseSource::OrientationOnly`]): the gyro propagates the
//!    last known orientation (the first frame's camera is the identity, the world a
//!    monocular map starts in when that frame is its reference). No scale is ever invented.
//! 6. **Resumed sessions** ([`VioTracker::resume`], `resume.rs`): a client can start on a
//!    VO holding a session rebuilt from stored keyframes (a killed tracker's spool) as
//!    initialised, from the newest keyframe's velocity and biases ([`VioStatus::Resumed`]).
use nalgebra::{Isometry3, Rotation3, UnitQuaternion, Vector3};

use crate::imu::coupler::{CouplerEvent, CouplerParams, CouplerStatus, InertialCoupler};
use crate::imu::init::{InertialInit, InitError};
use crate::imu::static_init::{detect_static, StaticInit, StaticParams};
use crate::imu::{ImuBiases, ImuMeasurement, NavState, Preintegrated, PreintegrationParams};
use crate::lie::{so3_log, Sim3};
use crate::vo::{ImuCalibration, KeyframeInertial, PoseHint, VoFrame, VoOutput, VoTracker};
use crate::CoreError;

pub mod anchor;
pub mod imu_buffer;
pub mod navigator;
mod resume;

pub use imu_buffer::{ImuBuffer, ImuCheck, ImuSampleError};
pub use navigator::{NavParams, Navigator, Prediction};
pub use resume::Resumed;

/// Settings of [`VioTracker`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VioParams {
    /// The inertial initialisation (holds the residual time offset `t_d_ns`, module docs).
    pub coupler: CouplerParams,
    /// IMU noise and intrinsics of the preintegration.
    pub preint: PreintegrationParams,
    /// Camera pose in the body (IMU) frame, metric (EuRoC `T_BS`).
    pub t_bc: Isometry3<f64>,
    /// Longest visual dropout bridged with the IMU alone, s.
    pub max_coast_s: f64,
    /// Search radius around the IMU prediction when vision returns, pixels at octave 0.
    pub rejoin_radius_px: f32,
    /// Checks of the IMU samples.
    pub imu_check: ImuCheck,
    /// The navigator's filter and prior.
    pub nav: NavParams,
    /// The IMU's pose prior in the pose optimisation (`false`: prediction and rolling
    /// shutter only, for comparison).
    pub pose_prior: bool,
    /// Track every frame with the IMU's prediction and prior (module docs, step 1; on by
    /// default). `false`: the VO's motion model tracks and the IMU only initialises, coasts
    /// through dropouts and searches around its prediction when vision returns (for
    /// comparison).
    pub imu_tracking: bool,
    /// Run the inertial initialisation (`false`: the camera-IMU extrinsics are not known,
    /// `t_bc` is only a device-axis guess: the IMU gives the orientations of frames vision
    /// does not pose and the static gyro bias, never a scale, a velocity or the
    /// rolling-shutter rates of the VO).
    pub inertial_init: bool,
    /// The static initialisation before the visual-inertial one (gyro bias and gravity of a
    /// device at rest, [`crate::imu::static_init`]).
    pub static_init: StaticParams,
    /// The coupler's inertial-only refinements (at [`CouplerParams::refine_at_s`]) applied
    /// once local mapping's window tracks the keyframe states, counting those before: later
    /// ones are computed, counted ([`VioTracker::refinements_skipped`]) and dropped. The
    /// refinement holds the keyframe poses fixed; ten seconds into the window's tracking,
    /// the window (poses, points, velocities and biases together) knows the scale better.
    /// Measured in-process on `blackout` (24 s, seed 3): with both refinements 0.286 %
    /// (SE(3) ATE), scale +0.98 %; with the first only 0.105 %, −0.04 %; drone 0.053 % →
    /// 0.058 %, phone 0.081 % unchanged.
    pub refinements_with_window: usize,
    /// Times after the initialisation, s, at which local mapping is asked for a
    /// whole-session visual-inertial window (`crate::vo::vi_window`, "Session windows";
    /// ORB-SLAM3's visual-inertial BA at its refinements, ~5 s and ~15 s after the
    /// initialisation): scale, gravity, velocities, biases, poses and points of every
    /// keyframe of the session (the client map's), the correction it finds applied as a
    /// world move. An initialisation accepted several percent off in scale on a gentle
    /// motion (the coupler's keyframe poses are those of the monocular map, fixed) is then
    /// corrected with the visual structure. `f64::INFINITY`: never.
    pub session_windows_after_init_s: [f64; 2],
    /// Longest wait for the local-mapping runner before a world move
    /// ([`VoTracker::transform_world`]); a move that times out is retried at the next frame.
    pub world_move_timeout: std::time::Duration,
}

impl VioParams {
    /// Defaults around the calibration: 2 s of coasting, a 40 px rejoin window.
    pub fn new(preint: PreintegrationParams, t_bc: Isometry3<f64>) -> Self {
        Self {
            coupler: CouplerParams::default(),
            preint,
            t_bc,
            max_coast_s: 2.0,
            rejoin_radius_px: 40.0,
            imu_check: ImuCheck::default(),
            nav: NavParams::default(),
            pose_prior: true,
            imu_tracking: true,
            refinements_with_window: 1,
            session_windows_after_init_s: [5.0, 15.0],
            static_init: StaticParams::default(),
            inertial_init: true,
            world_move_timeout: std::time::Duration::from_secs(5),
        }
    }
}

/// Where the pose of a frame came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PoseSource {
    /// Vision alone (before the inertial initialisation, or the IMU did not cover the
    /// frame): the monocular map's world, up to scale before the initialisation.
    Visual,
    /// Vision with the IMU's prediction and prior, metric and gravity-aligned.
    VisualInertial,
    /// The IMU alone, coasting through a visual dropout (metric).
    Inertial,
    /// Only an orientation, propagated with the gyro ([`VioOutput::r_wc`]).
    OrientationOnly,
    /// Nothing (no orientation known yet and no IMU to propagate).
    None,
}

/// A similarity applied to the VO's world with a frame: `x' = s R x + t` for positions,
/// `R_wc' = R R_wc` for orientations (an initialisation or refinement about the origin,
/// `t = 0`; a window's correction about its gauged keyframe).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WorldMove {
    /// The similarity (old world to new).
    pub world: Sim3,
    /// The initialisation (`false`: a refinement, close to identity).
    pub initialisation: bool,
}

impl WorldMove {
    /// The move `earlier` (if any) followed by `later`: `x'' = M_l (M_e x)`.
    pub fn then(earlier: Option<WorldMove>, later: WorldMove) -> WorldMove {
        let Some(e) = earlier else {
            return later;
        };
        WorldMove {
            world: later.world.compose(&e.world),
            initialisation: e.initialisation || later.initialisation,
        }
    }
}

/// Where the client stands.
#[derive(Debug, Clone, PartialEq)]
pub enum VioStatus {
    /// Not enough keyframes for an attempt yet (or a new VO session started over).
    Collecting,
    /// The last attempt was refused, and why (e.g. too little acceleration).
    Refused(InitError),
    /// Metric and gravity-aligned.
    Initialised {
        /// IMU time of the initialisation, ns.
        t_ns: i64,
        /// Scale of the monocular map at the initialisation (refinements included).
        scale: f64,
        /// 1σ of `log scale` of the latest estimate.
        scale_sigma: f64,
        /// Refinements done (0-2).
        refinements: usize,
        /// Coasting on the IMU through a visual dropout now.
        coasting: bool,
    },
    /// Metric and gravity-aligned: a session initialised by a predecessor and resumed from
    /// its stored keyframes ([`VioTracker::resume`]); no initialisation runs.
    Resumed {
        /// Where it started.
        from: Resumed,
        /// Coasting on the IMU (from the stored keyframe, or through a dropout) now.
        coasting: bool,
    },
}

impl VioStatus {
    /// The client's poses are metric and gravity-aligned.
    pub fn is_metric(&self) -> bool {
        matches!(self, Self::Initialised { .. } | Self::Resumed { .. })
    }
}

/// What one frame produced.
#[derive(Debug, Clone)]
pub struct VioOutput {
    /// The VO's output (keyframes evicted, backfill, times, ...; its `t_cw` is vision's).
    pub vo: VoOutput,
    /// The world moved with this frame (module docs, step 3).
    pub world_move: Option<WorldMove>,
    /// The world was anchored to the server map before this frame ([`anchor`]; the frame's
    /// outputs are in the anchored world, earlier ones are not re-expressed here).
    pub anchor: Option<Isometry3<f64>>,
    /// The frame's pose, world to camera: visual(-inertial), or the IMU's while coasting.
    pub t_cw: Option<Isometry3<f64>>,
    /// Where `t_cw` (or `r_wc`) came from.
    pub source: PoseSource,
    /// Camera orientation `R_wc` when only that is known ([`PoseSource::OrientationOnly`]).
    pub r_wc: Option<UnitQuaternion<f64>>,
    /// Metric body state at the frame once initialised.
    pub nav: Option<NavState>,
    /// The navigator's prediction of this frame (before vision), when it had one.
    pub prediction: Option<Prediction>,
}

/// Longest start of the IMU stream after an orientation over which the orientation is held
/// (no rotation assumed), ns.
pub const ORIENTATION_HOLD_NS: i64 = 100_000_000;

/// The VO failed its last frame (the next one may start a dropout).
fn out_of_vision(vo: &VoTracker) -> bool {
    vo.frames_failed() > 0
}

/// Summary of the accepted initialisation.
#[derive(Debug, Clone, Copy, PartialEq)]
struct InitSummary {
    t_ns: i64,
    scale: f64,
    scale_sigma: f64,
    refinements: usize,
}

/// The visual-inertial client (module docs).
pub struct VioTracker {
    vo: VoTracker,
    params: VioParams,
    coupler: InertialCoupler,
    imu: ImuBuffer,
    nav: Option<Navigator>,
    init: Option<InitSummary>,
    /// IMU time of the last frame vision posed, ns.
    last_visual_ns: Option<i64>,
    /// A world move that timed out, retried at the next frame.
    pending: Option<(InertialInit, bool)>,
    /// Last known body orientation `R_wb` and its IMU time (for orientation-only frames).
    orientation: Option<(i64, Rotation3<f64>)>,
    /// Best known biases (the initialisation's, then local mapping's window's; before
    /// them, the static gyro bias or zero).
    biases: ImuBiases,
    coasting: bool,
    /// The device was found at rest before the initialisation, and "up" then in the world
    /// of the orientations (when the frame had one).
    static_init: Option<(StaticInit, Option<Vector3<f64>>)>,
    /// The session was resumed from stored keyframes ([`VioTracker::resume`]).
    resumed: Option<Resumed>,
    /// The last keyframe made and its IMU time, until local mapping's result for it (or a
    /// later one) is taken ([`VioTracker::adopt_window_state`]).
    last_kf: Option<(crate::vo::KfId, i64)>,
    /// Local mapping's window has refined a keyframe of this session (it tracks the
    /// velocities and biases).
    window_tracks: bool,
    /// Refinements not applied ([`VioParams::refinements_with_window`]), all sessions.
    refinements_skipped: usize,
    /// Session windows asked of local mapping in this session
    /// ([`VioParams::session_windows_after_init_s`]).
    session_windows: usize,
    /// An anchor asked for and not applied yet: (VO session, rigid move of the world).
    anchor: Option<(u32, Isometry3<f64>)>,
    /// Anchors dropped, all sessions ([`VioTracker::anchors_dropped`]).
    anchors_dropped: usize,
}

impl VioTracker {
    /// A client around `vo` (a fresh VO: its world becomes metric once initialised).
    pub fn new(mut vo: VoTracker, params: VioParams) -> Self {
        vo.enable_keyframe_imu(ImuCalibration {
            preint: params.preint,
            t_bc: params.t_bc,
            t_d_ns: params.coupler.t_d_ns,
        });
        Self {
            vo,
            coupler: InertialCoupler::new(params.coupler, params.preint, params.t_bc),
            imu: ImuBuffer::new(params.imu_check),
            nav: None,
            init: None,
            last_visual_ns: None,
            pending: None,
            orientation: None,
            biases: ImuBiases::default(),
            coasting: false,
            last_kf: None,
            window_tracks: false,
            refinements_skipped: 0,
            anchor: None,
            anchors_dropped: 0,
            session_windows: 0,
            static_init: None,
            resumed: None,
            params,
        }
    }

    /// The VO.
    pub fn vo(&self) -> &VoTracker {
        &self.vo
    }

    /// The VO (e.g. to attach a local-mapping thread).
    pub fn vo_mut(&mut self) -> &mut VoTracker {
        &mut self.vo
    }

    /// The settings.
    pub fn params(&self) -> &VioParams {
        &self.params
    }

    /// The coupler's refinements computed but not applied because local mapping's window
    /// tracked the states ([`VioParams::refinements_with_window`]), all sessions.
    pub fn refinements_skipped(&self) -> usize {
        self.refinements_skipped
    }

    /// The static initialisation, if the device rested before the visual-inertial one, and
    /// the "up" direction in the world of the orientations then.
    pub fn static_init(&self) -> Option<&(StaticInit, Option<Vector3<f64>>)> {
        self.static_init.as_ref()
    }

    /// Anchors asked for and dropped ([`VioTracker::request_anchor`]), all sessions: the
    /// session changed, another world move came first, the client was not metric, or local
    /// mapping did not become idle in time (the next feedback asks again).
    pub fn anchors_dropped(&self) -> usize {
        self.anchors_dropped
    }

    /// Moves VO session `session`'s world by the rigid `delta` (`x' = R x + t`) before the
    /// next frame: the anchor to the server map ([`anchor`]). The VO map and tracking state,
    /// the coupler, the orientation and the navigator move together, so the local window
    /// keeps its relative poses, biases and (turned) velocities: nothing of it jumps.
    /// Replaces a request not applied yet (`None` withdraws it).
    pub fn request_anchor(&mut self, session: u32, delta: Option<Isometry3<f64>>) {
        self.anchor = delta.map(|d| (session, d));
    }

    /// Applies the anchor asked for, if it still applies (same session, metric, no other
    /// world move with this frame) and local mapping becomes idle in time.
    fn apply_anchor(&mut self, moved: bool) -> Option<Isometry3<f64>> {
        let (session, delta) = self.anchor.take()?;
        let m = Sim3::from_isometry(&delta, 1.0);
        let ok = session == self.vo.session_id()
            && !moved
            && self.pending.is_none()
            && self.status().is_metric()
            && self.vo.transform_world(&m, self.params.world_move_timeout);
        if !ok {
            self.anchors_dropped += 1;
            return None;
        }
        self.move_beside_vo(&m);
        Some(delta)
    }

    /// The coupler (attempts, span).
    pub fn coupler(&self) -> &InertialCoupler {
        &self.coupler
    }

    /// One IMU sample (body frame, IMU clock). Refused (named, never a panic) when not
    /// after the last one, not finite or saturated; a gap is reported but the sample kept
    /// ([`ImuSampleError::refused`]); the caller counts them.
    pub fn on_imu(&mut self, m: ImuMeasurement) -> Result<(), ImuSampleError> {
        let res = self.imu.push(m);
        if res.is_ok() || res.is_err_and(|e| !e.refused()) {
            self.coupler.on_imu(m);
            self.vo.push_imu(m);
        }
        res
    }

    /// Where the client stands.
    pub fn status(&self) -> VioStatus {
        if let Some(r) = self.resumed_status() {
            return r;
        }
        if let Some(i) = self.init {
            return VioStatus::Initialised {
                t_ns: i.t_ns,
                scale: i.scale,
                scale_sigma: i.scale_sigma,
                refinements: i.refinements,
                coasting: self.coasting,
            };
        }
        match self.coupler.status() {
            CouplerStatus::Refused(e) => VioStatus::Refused(e.clone()),
            _ => VioStatus::Collecting,
        }
    }

    /// The frame's IMU-clock time (module docs).
    fn t_imu(&self, frame: &VoFrame<'_>) -> i64 {
        frame.t_ns + self.params.coupler.t_d_ns
    }

    /// One frame (module docs).
    pub fn process(&mut self, frame: &VoFrame<'_>) -> Result<VioOutput, CoreError> {
        let t_ns = self.t_imu(frame);
        let retried = self.apply_pending();
        let anchored = self.apply_anchor(retried.is_some());
        let rate_b = self.mean_rate_b(t_ns, frame.readout_ns);
        let frame = VoFrame {
            angular_velocity: frame.angular_velocity.or_else(|| {
                (frame.readout_ns > 0 && self.params.inertial_init)
                    .then_some(rate_b)
                    .flatten()
                    .map(|w| self.params.t_bc.rotation.inverse() * w)
            }),
            ..*frame
        };
        let pred = self.predict(t_ns, &rate_b.unwrap_or_default());
        let coast_ok = self
            .last_visual_ns
            .is_some_and(|t| (t_ns - t) as f64 * 1e-9 <= self.params.max_coast_s);
        let use_imu = self.params.imu_tracking || self.coasting || out_of_vision(&self.vo);
        let hint = pred.as_ref().filter(|_| use_imu).map(|p| PoseHint {
            t_cw: p.t_cw,
            velocity: Some(p.velocity),
            prior: self.params.pose_prior.then_some(p.prior),
            rejoin_radius: self.coasting.then_some(self.params.rejoin_radius_px),
            hold_session: coast_ok,
        });
        let kf_state = pred
            .map(|p| p.nav)
            .or_else(|| self.nav.as_ref().map(|n| *n.state()));
        let kf_state = kf_state.map(|n| KeyframeInertial {
            v_wb: n.v,
            biases: n.biases,
            refined: 0,
        });
        let vo = self.vo.process_inertial(&frame, hint.as_ref(), kf_state)?;
        let mut out = VioOutput {
            world_move: retried,
            anchor: anchored,
            t_cw: None,
            source: PoseSource::None,
            r_wc: None,
            nav: None,
            prediction: pred,
            vo,
        };
        if out.vo.new_session {
            self.start_over();
        }
        let with_prior = hint.is_some_and(|h| h.prior.is_some());
        self.update_pose(t_ns, pred.as_ref(), coast_ok, with_prior, &mut out);
        self.adopt_window_state(&mut out);
        self.apply_world_correction(&mut out);
        self.keyframe(t_ns, &mut out);
        self.ask_session_window(t_ns);
        self.detect_rest(t_ns);
        self.imu
            .keep_from(self.oldest_needed_ns(t_ns) - frame.readout_ns / 2 - 10_000_000);
        Ok(out)
    }

    /// The bias-corrected mean body rate over the frame's readout (±5 ms for a global
    /// shutter), from the preintegrated rotation.
    fn mean_rate_b(&self, t_ns: i64, readout_ns: i64) -> Option<Vector3<f64>> {
        let half = (readout_ns / 2).max(5_000_000);
        let (t0, t1) = (t_ns - half, t_ns + half);
        if !self.imu.covers(t0, t1) {
            return None;
        }
        let pre = Preintegrated::from_window(
            self.imu.samples(),
            t0,
            t1,
            self.biases,
            self.params.preint,
        )?;
        Some(so3_log(&pre.delta_r()) / pre.delta_t())
    }

    /// The navigator's prediction at `t_ns`, when initialised and the IMU covers it.
    fn predict(&self, t_ns: i64, rate_b: &Vector3<f64>) -> Option<Prediction> {
        let nav = self.nav.as_ref()?;
        if !self.imu.covers(nav.t_ns(), t_ns) {
            return None;
        }
        nav.predict(self.imu.samples(), t_ns, rate_b)
    }

    /// A new VO session: a new world, the initialisation starts over.
    fn start_over(&mut self) {
        self.coupler.reset();
        // The samples already received (up to ahead of this frame) serve the new session.
        for m in self.imu.samples() {
            self.coupler.on_imu(*m);
        }
        self.nav = None;
        self.init = None;
        self.resumed = None;
        self.pending = None;
        self.last_visual_ns = None;
        self.coasting = false;
        self.last_kf = None;
        self.window_tracks = false;
        self.anchor = None;
        self.session_windows = 0;
    }

    /// Asks local mapping for a whole-session window when the next time after the
    /// initialisation is reached ([`VioParams::session_windows_after_init_s`]; not in a
    /// resumed session, whose predecessor corrected its scale): for the keyframes after
    /// this frame (the camera time after `t_ns`'s), so that no keyframe already queued to
    /// a local-mapping thread takes it.
    fn ask_session_window(&mut self, t_ns: i64) {
        let Some(init) = self.init.filter(|_| self.resumed.is_none()) else {
            return;
        };
        let Some(&at_s) = self
            .params
            .session_windows_after_init_s
            .get(self.session_windows)
        else {
            return;
        };
        if (t_ns - init.t_ns) as f64 * 1e-9 >= at_s {
            let t_cam = t_ns - self.params.coupler.t_d_ns;
            self.vo.request_session_window(t_cam + 1);
            self.session_windows += 1;
        }
    }

    /// The frame's pose: vision's (the navigator corrected), the IMU's while coasting,
    /// else an orientation from the gyro.
    fn update_pose(
        &mut self,
        t_ns: i64,
        pred: Option<&Prediction>,
        coast_ok: bool,
        with_prior: bool,
        out: &mut VioOutput,
    ) {
        let r_cb = self.params.t_bc.rotation.inverse();
        if let Some(t_cw) = out.vo.t_cw {
            out.t_cw = Some(t_cw);
            out.source = PoseSource::Visual;
            if let Some(nav) = self.nav.as_mut() {
                match pred {
                    Some(p) => {
                        nav.correct(p, &t_cw, out.vo.pose_information.as_ref(), with_prior);
                        if self.params.imu_tracking {
                            out.source = PoseSource::VisualInertial;
                        }
                    }
                    None => nav.reset_to(&t_cw, t_ns),
                }
                out.nav = Some(*nav.state());
            }
            let r_wb = t_cw.rotation.inverse() * r_cb;
            self.orientation = Some((t_ns, r_wb.to_rotation_matrix()));
            self.last_visual_ns = Some(t_ns);
            self.coasting = false;
            self.note_visual_pose(t_ns);
            return;
        }
        if let (Some(nav), Some(p), true) = (self.nav.as_mut(), pred, coast_ok) {
            nav.coast(p);
            out.t_cw = Some(p.t_cw);
            out.nav = Some(p.nav);
            out.source = PoseSource::Inertial;
            self.orientation = Some((t_ns, p.nav.r));
            self.coasting = true;
            return;
        }
        self.coasting = false;
        if let Some(r_wb) = self.propagate_orientation(t_ns) {
            self.orientation = Some((t_ns, r_wb));
            let r_wc = UnitQuaternion::from_rotation_matrix(&r_wb) * self.params.t_bc.rotation;
            out.r_wc = Some(r_wc);
            out.source = PoseSource::OrientationOnly;
        }
    }

    /// The last orientation propagated to `t_ns` with the gyro (identity camera
    /// orientation at the first frame); `None` without IMU over the interval. When the IMU
    /// stream starts up to [`ORIENTATION_HOLD_NS`] after the last orientation (a camera
    /// that starts first, as on the phone clip), the orientation is held until its first
    /// sample.
    fn propagate_orientation(&self, t_ns: i64) -> Option<Rotation3<f64>> {
        let Some((t_last, r_wb)) = self.orientation else {
            return Some(self.params.t_bc.rotation.inverse().to_rotation_matrix());
        };
        let first = self.imu.samples().first().map_or(t_last, |m| m.t_ns);
        let t0 = if first > t_last && first - t_last <= ORIENTATION_HOLD_NS {
            first
        } else {
            t_last
        };
        if !self.imu.covers(t0, t_ns) {
            return None;
        }
        let pre = Preintegrated::from_window(
            self.imu.samples(),
            t0,
            t_ns,
            self.biases,
            self.params.preint,
        )?;
        Some(r_wb * pre.delta_r())
    }

    /// A new keyframe: its inertial state, then the coupler (and the world move it asks).
    fn keyframe(&mut self, t_ns: i64, out: &mut VioOutput) {
        let Some(id) = out.vo.keyframe else {
            return;
        };
        self.last_kf = Some((id, t_ns));
        // The poses before local mapping adjusted them, inline or threaded alike.
        let window = &out.vo.keyframe_poses;
        if !self.params.inertial_init {
            return;
        }
        for (t, t_wc) in window {
            self.coupler.set_keyframe(*t, *t_wc);
        }
        let (init, first) = match self.coupler.step() {
            Some(CouplerEvent::Initialised(i)) => (i, true),
            Some(CouplerEvent::Refined(i)) => (i, false),
            None => return,
        };
        let newest = window.last().map(|&(t, t_wc)| (t, t_wc.inverse(), id));
        if let Some(m) = self.move_world(&init, first, t_ns, newest) {
            self.moved_output(&m, out);
            out.world_move = Some(WorldMove::then(out.world_move, m));
        }
    }

    /// After a world move with this frame: its outputs in the new world (the VO's
    /// backfilled poses too: every pose of a [`VioOutput`] is in the world after its move).
    fn moved_output(&self, m: &WorldMove, out: &mut VioOutput) {
        for (_, t_cw) in out.vo.backfill.iter_mut() {
            *t_cw = crate::vo::map::transform_pose_cw(t_cw, &m.world);
        }
        if let Some(nav) = &self.nav {
            out.nav = Some(*nav.state());
            out.t_cw = Some(nav.camera_pose(nav.state()));
            if out.source == PoseSource::Visual {
                out.source = PoseSource::VisualInertial;
            }
        }
    }

    /// What moves with the VO's world besides it (the VO moved already): the coupler's
    /// poses, the orientation, the navigator.
    fn move_beside_vo(&mut self, m: &Sim3) {
        self.coupler.transform_world(m);
        if let Some((t, r_wb)) = self.orientation {
            self.orientation = Some((t, m.r.to_rotation_matrix() * r_wb));
        }
        if let Some(nav) = self.nav.as_mut() {
            nav.transform_world(m);
        }
    }

    /// Local mapping's window left a gravity correction (a rotation `R` of the world,
    /// `crate::vo::vi_window`): the session's world moves by `x' = R x` like at a
    /// refinement (the VO, the coupler, the navigator, and the caller's earlier poses
    /// through [`VioOutput::world_move`]). Retried at the next frame when local mapping
    /// does not become idle in time.
    fn apply_world_correction(&mut self, out: &mut VioOutput) {
        if out.vo.world_correction.is_none() {
            return;
        }
        let Some(c) = self
            .vo
            .apply_world_correction(self.params.world_move_timeout)
        else {
            return;
        };
        self.move_beside_vo(&c);
        let m = WorldMove {
            world: c,
            initialisation: false,
        };
        for (_, t_cw) in out.vo.backfill.iter_mut() {
            *t_cw = crate::vo::map::transform_pose_cw(t_cw, &c);
        }
        out.t_cw = out.t_cw.map(|t| crate::vo::map::transform_pose_cw(&t, &c));
        out.r_wc = out.r_wc.map(|q| c.r * q);
        if let Some(nav) = &self.nav {
            out.nav = out.nav.map(|_| *nav.state());
        }
        out.world_move = Some(WorldMove::then(out.world_move, m));
    }

    /// Applies an initialisation or refinement (module docs, step 3); `None` when the VO's
    /// local mapping did not become idle in time (retried at the next frame).
    fn move_world(
        &mut self,
        init: &InertialInit,
        first: bool,
        t_ns: i64,
        newest: Option<(i64, Isometry3<f64>, crate::vo::KfId)>,
    ) -> Option<WorldMove> {
        let r = UnitQuaternion::from_rotation_matrix(&init.r_gw);
        let world = Sim3::new(r, Vector3::zeros(), init.scale);
        let done = self.init.map_or(0, |i| i.refinements);
        if !first && self.window_tracks && done >= self.params.refinements_with_window {
            self.refinements_skipped += 1;
            return None;
        }
        if !self
            .vo
            .transform_world(&world, self.params.world_move_timeout)
        {
            self.pending = Some((init.clone(), first));
            return None;
        }
        self.move_beside_vo(&world);
        // Once local mapping's window tracks them, a refinement moves the world but leaves
        // the velocities and biases to the window.
        let keep = !first && self.window_tracks;
        if !keep {
            self.biases = init.biases;
        }
        let v_wb = init
            .velocities_w
            .last()
            .map(|v| init.r_gw * v)
            .unwrap_or_default();
        match (self.nav.as_mut(), newest) {
            (Some(nav), _) if !keep => nav.set_velocity_biases(v_wb, init.biases),
            (Some(_), _) => {}
            (None, Some((t_kf, t_cw_old, _))) => {
                let t_cw = crate::vo::map::transform_pose_cw(&t_cw_old, &world);
                let state = navigator::nav_from_camera(&t_cw, &self.params.t_bc, v_wb, init.biases);
                let t_kf_imu = t_kf + self.params.coupler.t_d_ns;
                self.nav = Some(Navigator::new(
                    state,
                    t_kf_imu,
                    self.params.t_bc,
                    self.params.preint,
                    self.params.nav,
                ));
            }
            (None, None) => {}
        }
        if let (Some(nav), Some((_, _, id)), false) = (&self.nav, newest, keep) {
            self.vo.set_keyframe_inertial(
                id,
                KeyframeInertial {
                    v_wb: nav.state().v,
                    biases: init.biases,
                    refined: 0,
                },
            );
        }
        self.record_init(init, first, t_ns);
        Some(WorldMove {
            world,
            initialisation: first,
        })
    }

    fn record_init(&mut self, init: &InertialInit, first: bool, t_ns: i64) {
        if self.note_resumed_refinement() {
            return;
        }
        self.init = Some(match (self.init, first) {
            (Some(i), false) => InitSummary {
                scale: i.scale * init.scale,
                scale_sigma: init.scale_sigma,
                refinements: i.refinements + 1,
                ..i
            },
            _ => InitSummary {
                t_ns,
                scale: init.scale,
                scale_sigma: init.scale_sigma,
                refinements: 0,
            },
        });
    }

    /// Retries a world move that timed out (the newest keyframe is not known here: the
    /// navigator starts at the next keyframe's refinement, or from the map's newest).
    fn apply_pending(&mut self) -> Option<WorldMove> {
        let (init, first) = self.pending.take()?;
        let newest = self.vo.with_map(|m| {
            m.keyframes
                .values()
                .next_back()
                .map(|kf| (kf.t_ns, kf.t_cw, kf.id))
        });
        let t_ns = newest.map_or(0, |n| n.0);
        self.move_world(&init, first, t_ns, newest)
    }

    /// The static initialisation (module docs of [`crate::imu::static_init`]) while neither
    /// it nor the visual-inertial one happened: the window ending at this frame; its gyro
    /// bias then propagates the orientations.
    fn detect_rest(&mut self, t_ns: i64) {
        if self.init.is_some() || self.static_init.is_some() {
            return;
        }
        let c = &self.params.preint.correction;
        let Some(s) = detect_static(self.imu.samples(), t_ns, c, &self.params.static_init) else {
            return;
        };
        self.biases.gyro = s.gyro_bias;
        let up_w = self
            .orientation
            .filter(|o| o.0 == t_ns)
            .map(|(_, r_wb)| r_wb * s.up_b);
        self.static_init = Some((s, up_w));
    }

    /// The oldest IMU time still needed (the navigator's, the orientation's, the last
    /// keyframe's until its window's result is taken, and the static window while it may
    /// still be found).
    fn oldest_needed_ns(&self, t_ns: i64) -> i64 {
        let nav = self.nav.as_ref().map_or(t_ns, |n| n.t_ns());
        let ori = self.orientation.map_or(t_ns, |o| o.0);
        let kf = self.last_kf.map_or(t_ns, |k| k.1);
        let rest = match (self.init, self.static_init) {
            (None, None) => t_ns - (self.params.static_init.window_s * 1e9) as i64,
            _ => t_ns,
        };
        nav.min(ori).min(kf).min(t_ns).min(rest)
    }

    /// Local mapping's visual-inertial window refined the newest keyframe it finished
    /// ([`crate::vo::VoOutput::mapped`], reported by the first frame after its mapping,
    /// inline or threaded alike): the navigator takes its biases and its velocity carried
    /// to this frame, so the biases are tracked at every keyframe, not only at the
    /// initialisation's refinements.
    fn adopt_window_state(&mut self, out: &mut VioOutput) {
        let Some(m) = out.vo.mapped else {
            return;
        };
        if self.last_kf.is_some_and(|(id, _)| id <= m.id) {
            self.last_kf = None;
        }
        let (Some(i), Some(nav)) = (m.inertial.filter(|i| i.refined > 0), self.nav.as_mut()) else {
            return;
        };
        let t_kf = m.t_ns + self.params.coupler.t_d_ns;
        let kf = NavState::from_camera(&m.t_cw, &self.params.t_bc, i.v_wb, i.biases);
        nav.adopt_keyframe(self.imu.samples(), &kf, t_kf);
        out.nav = Some(*nav.state());
        self.biases = i.biases;
        self.window_tracks = true;
    }
}
