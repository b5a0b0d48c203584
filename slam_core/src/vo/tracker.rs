//! The tracking state machine of the client VO (seed §3.3): two-view initialisation, tracking
//! with the constant-velocity motion model (fallback: the reference keyframe), local-map
//! tracking, keyframe decision and creation, the keyframe window and VO sessions.
//!
//! Rolling shutter: every observation carries its row's time offset from the mid-row time
//! (seed eq. 2.61-2.63) and the pose optimiser moves the camera along the motion model's
//! velocity over it; `VoParams::rolling_shutter = false` turns that off for comparison.
use std::sync::{Arc, Mutex};
use std::time::Instant;

use nalgebra::{Isometry3, Vector3};

use super::map::{ClientMap, Keyframe, KfId, PointId};
use super::search::LocalMapMatcher;
use super::{KeyframeRule, KeyframeRuleParams};
use crate::camera::PinholeRadtan;
use crate::features::{FeatureGrid, GrayImage, OrbExtractor, OrbFeatures, OrbParams};
use crate::lie::{se3_exp, se3_log, Sim3};
use crate::optim::{PoseObservation, PoseOptimizer, PosePrior, Velocity};
use crate::CoreError;

/// Parameters of the VO.
#[derive(Debug, Clone)]
pub struct VoParams {
    /// ORB extraction.
    pub orb: OrbParams,
    /// Keyframe rule.
    pub keyframe_rule: KeyframeRuleParams,
    /// Most keyframes kept in the client map; older ones are evicted (sent to the server).
    pub window: usize,
    /// Consecutive tracking failures that start a new session (seed: F = 10).
    pub max_failures: u32,
    /// Rolling-shutter compensation in pose optimisation.
    pub rolling_shutter: bool,
    /// Matches needed to try the two-view initialisation.
    pub init_min_matches: usize,
    /// Inliers needed to accept a tracked pose.
    pub min_inliers: usize,
    /// Keyframes of the local map (reference + best covisible).
    pub local_keyframes: usize,
    /// Local bundle adjustment at each new keyframe.
    pub local_ba: bool,
    /// The initialisation extracts this many times `orb.n_features` (ORB-SLAM: 2).
    pub init_feature_factor: usize,
    /// With a local-mapping thread ([`VoTracker::set_local_mapping`]; without one, local
    /// mapping runs inline at keyframe creation, deterministic): every frame waits, after
    /// its ORB extraction (which overlaps the mapping) and before it reads the map, until
    /// local mapping has finished every keyframe given to it (at most
    /// [`LOCAL_MAPPING_SYNC_TIMEOUT`]). Tracking and the keyframe decision then never
    /// depend on thread timing: a lock-step replay gives the same result on every run.
    /// `false`: free-running (real time).
    pub sync_local_mapping: bool,
    /// Neighbour keyframes of local mapping (triangulation and local BA).
    pub mapping_neighbours: usize,
    /// Keyframes tried per frame when relocalising.
    pub reloc_candidates: usize,
    /// The visual-inertial window of local mapping (it runs on keyframes with an inertial
    /// state and an IMU segment: a visual-inertial client's, once metric).
    pub vi_window: super::vi_window::ViMappingParams,
}

impl VoParams {
    fn local_mapping(&self) -> local_mapper::LocalMappingParams {
        local_mapper::LocalMappingParams {
            neighbours: self.mapping_neighbours,
            local_ba: self.local_ba,
            vi: self.vi_window,
        }
    }
}

impl Default for VoParams {
    fn default() -> Self {
        Self {
            orb: OrbParams::default(),
            keyframe_rule: KeyframeRuleParams::default(),
            window: 100,
            max_failures: 10,
            rolling_shutter: true,
            init_min_matches: 100,
            min_inliers: 15,
            local_keyframes: 15,
            local_ba: true,
            init_feature_factor: 2,
            sync_local_mapping: false,
            mapping_neighbours: 10,
            reloc_candidates: 8,
            vi_window: Default::default(),
        }
    }
}

/// Longest a frame waits for the local-mapping thread with
/// [`VoParams::sync_local_mapping`]; a longer wait is counted
/// ([`VoTracker::local_mapping_sync_timeouts`]) and the frame goes on (the run is then no
/// longer guaranteed to be reproducible).
pub const LOCAL_MAPPING_SYNC_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(30);

/// State of the tracker after a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VoState {
    /// Waiting for a first frame with enough features.
    NotInitialized,
    /// Have a reference frame, trying two-view initialisation.
    Initializing,
    /// Tracking.
    Tracking,
    /// Lost (counting failures until a new session).
    Lost,
}

/// Per-stage times of one frame, ms.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTimes {
    /// ORB pyramid.
    pub pyramid: f32,
    /// FAST + distribution (+ orientation).
    pub detect: f32,
    /// Descriptors.
    pub describe: f32,
    /// Matching (motion model / reference keyframe / local map search).
    pub matching: f32,
    /// Pose optimisation.
    pub pose_opt: f32,
    /// Local map gathering.
    pub local_map: f32,
    /// Keyframe creation and local mapping.
    pub keyframe: f32,
    /// Whole step.
    pub total: f32,
}

/// What one frame produced.
#[derive(Debug, Clone)]
pub struct VoOutput {
    /// State after the frame.
    pub state: VoState,
    /// Camera pose (world → camera) when tracking.
    pub t_cw: Option<Isometry3<f64>>,
    /// Inlier map points of the frame.
    pub tracked: usize,
    /// Information of `t_cw` from its final pose optimisation (left increment `[ω; v]`,
    /// [`crate::optim::PoseOptResult::information`]; the hint's prior included).
    pub pose_information: Option<nalgebra::Matrix6<f64>>,
    /// The frame became this keyframe.
    pub keyframe: Option<KfId>,
    /// With [`VoOutput::keyframe`]: `(frame time, T_wc)` of every keyframe of the map when
    /// it was made, itself last, before local mapping adjusted them (the same whether local
    /// mapping runs inline or on its own thread).
    pub keyframe_poses: Vec<(i64, Isometry3<f64>)>,
    /// A new VO session started with this frame.
    pub new_session: bool,
    /// Keyframes evicted from the window (oldest first), to be sent to the server.
    pub evicted: Vec<Keyframe>,
    /// Poses `(frame time, T_cw)` of earlier frames found late: when the map was
    /// initialised with this frame, the reference frame and the frames between it and this
    /// one; once the map has a few keyframes, the frames before the reference, tracked
    /// backwards (newest first, `backward.rs`).
    pub backfill: Vec<(i64, Isometry3<f64>)>,
    /// Stage times.
    pub times: StageTimes,
    /// What the initialiser and the backward walk tried and why it failed (the caller
    /// prints them on request: the tracker service's `debug_init`).
    pub diagnostics: Vec<VoDiagnostic>,
    /// The newest keyframe whose local mapping had finished when this frame read the map
    /// (reported once, by the first frame after its mapping; never the keyframe this frame
    /// made), with its state then: e.g. the visual-inertial window's refined velocity and
    /// biases for the IMU navigator ([`crate::vio`]).
    pub mapped: Option<MappedKeyframe>,
    /// The map's pending gravity correction when this frame read it
    /// ([`ClientMap::world_correction`]; [`VoTracker::apply_world_correction`]).
    pub world_correction: Option<Sim3>,
}

/// A keyframe as local mapping left it ([`VoOutput::mapped`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MappedKeyframe {
    /// Its id.
    pub id: KfId,
    /// Frame time (mid-row), ns.
    pub t_ns: i64,
    /// World → camera pose.
    pub t_cw: Isometry3<f64>,
    /// Its inertial state, if any.
    pub inertial: Option<super::map::KeyframeInertial>,
}

/// A diagnostic of the VO's initialisation (issue 15: where and why frames stay unposed).
#[derive(Debug, Clone, PartialEq)]
pub enum VoDiagnostic {
    /// A two-view initialisation attempt failed: matches to the reference, frames matched
    /// since the reference, and why.
    InitFailed {
        /// Matches of the frame to the reference.
        matches: usize,
        /// Frames matched to the reference so far.
        frames: usize,
        /// Why the two-view geometry was rejected.
        reason: String,
    },
    /// The backward walk starts: frames kept before the oldest keyframe (at `t_ref_ns`).
    BackwardStart {
        /// Kept frames before the oldest keyframe.
        before: usize,
        /// Kept frames.
        kept: usize,
        /// Time of the oldest keyframe, ns.
        t_ref_ns: i64,
    },
    /// The backward walk stopped at a frame it could not track.
    BackwardStopped {
        /// Kept frames.
        kept: usize,
        /// The frame's time, ns.
        t_ns: i64,
        /// Its inliers.
        inliers: usize,
    },
}

impl std::fmt::Display for VoDiagnostic {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            VoDiagnostic::InitFailed {
                matches,
                frames,
                reason,
            } => write!(f, "init: {matches} matches after {frames} frames: {reason}"),
            VoDiagnostic::BackwardStart {
                before,
                kept,
                t_ref_ns,
            } => write!(
                f,
                "backward: {before} of {kept} kept frames before the oldest keyframe (t {t_ref_ns} ns)"
            ),
            VoDiagnostic::BackwardStopped {
                kept,
                t_ns,
                inliers,
            } => write!(
                f,
                "backward: {kept} frames kept, stopped at t {t_ns} ns ({inliers} inliers)"
            ),
        }
    }
}

/// One frame given to the tracker.
#[derive(Debug, Clone, Copy)]
pub struct VoFrame<'a> {
    /// Gray image.
    pub image: GrayImage<'a>,
    /// Mid-row time, ns.
    pub t_ns: i64,
    /// Rolling-shutter readout time, ns.
    pub readout_ns: i64,
    /// Angular velocity of the camera in its own frame during the readout (rad/s), e.g. the
    /// bias-corrected gyro rotated into the camera. Without it the rolling-shutter
    /// compensation uses the motion model's angular velocity.
    pub angular_velocity: Option<Vector3<f64>>,
}

/// An outside prediction of a frame's pose for tracking, e.g. the IMU's ([`crate::vio`]):
/// it replaces the motion model's prediction in the projection search and in the
/// rolling-shutter model, and may add a prior to the pose optimisation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseHint {
    /// Predicted pose, world to camera at the frame's mid-row time.
    pub t_cw: Isometry3<f64>,
    /// Camera twist during the readout (camera frame, rad/s and m/s) for the rolling-shutter
    /// model of the pose optimiser; `None`: global-shutter model.
    pub velocity: Option<Velocity>,
    /// Prior on the pose in the pose optimisations of this frame's tracking (its `t_cw` is
    /// normally the prediction's).
    pub prior: Option<PosePrior>,
    /// The frame follows a visual dropout: the local map is first searched around the
    /// prediction in a window of this radius (pixels at octave 0), and a pose found so
    /// counts as a relocalisation (the motion model restarts).
    pub rejoin_radius: Option<f32>,
    /// A failed frame does not start a new session, however many failed before it (the
    /// caller coasts on the IMU meanwhile).
    pub hold_session: bool,
}

struct LastFrame {
    t_ns: i64,
    t_cw: Isometry3<f64>,
    features: OrbFeatures,
    points: Vec<Option<PointId>>,
}

/// The client VO.
pub struct VoTracker {
    params: VoParams,
    camera: PinholeRadtan,
    extractor: OrbExtractor,
    grid: FeatureGrid,
    optimizer: PoseOptimizer,
    rule: KeyframeRule,
    /// The client map of the current session while a frame is processed (swapped in from
    /// `shared`, whose lock is held meanwhile); an empty placeholder between frames.
    map: ClientMap,
    /// The client map, shared with the local-mapping thread.
    shared: SharedMap,
    /// Where local mapping runs off the tracking thread (`None`: inline at keyframe
    /// creation, with `inline_mapper`).
    mapping: Option<Box<dyn LocalMappingRunner>>,
    /// Inline local mapping (its buffers).
    inline_mapper: LocalMapper,
    /// Keyframes culled by inline local mapping.
    inline_stats: local_mapper::LocalMappingStats,
    /// Frames that waited for the local-mapping thread ([`VoParams::sync_local_mapping`]).
    sync_waits: usize,
    /// Of those, waits that ran into [`LOCAL_MAPPING_SYNC_TIMEOUT`].
    sync_timeouts: usize,
    /// The last frame became this keyframe and the local-mapping thread maps it: with
    /// [`VoParams::sync_local_mapping`] the next frame takes its new points as the last
    /// frame's (as inline mapping does at once).
    mapped_last_kf: Option<KfId>,
    /// Relocalisation: where the round over the map's keyframes continues.
    reloc_cursor: Option<usize>,
    /// Successful relocalisations.
    relocalized: usize,
    pnp: crate::pnp::PnpSolver,
    state: VoState,
    session_id: u32,
    next_kf_id: KfId,
    init: Option<init::InitState>,
    /// Frames seen while initialising, tracked backwards once the map exists.
    pre_init: backward::PreInitBuffer,
    /// Tracking backwards: the map's point statistics (`found`) are left alone, so the map
    /// evolves as without it.
    backward: bool,
    init_matches: Vec<crate::features::Match>,
    /// Extractor of the initialisation (more features, as ORB-SLAM's monocular initialiser).
    init_extractor: OrbExtractor,
    last: Option<LastFrame>,
    /// Motion model: `T_cw(k) * T_cw(k-1)^-1` per frame period and that period, s.
    velocity: Option<(Isometry3<f64>, f64)>,
    ref_kf: Option<KfId>,
    frames_since_kf: u32,
    failures: u32,
    /// The current frame's keypoints were rotated to its mid-row time.
    derotated: bool,
    /// The outside prediction of the frame being processed ([`VoTracker::process_with_hint`]).
    hint: Option<PoseHint>,
    /// The inertial state a keyframe made from the frame being processed starts with
    /// ([`VoTracker::process_inertial`]).
    kf_state: Option<super::map::KeyframeInertial>,
    /// The IMU samples cut into each keyframe's segment (a visual-inertial client's;
    /// [`VoTracker::enable_keyframe_imu`]).
    imu_source: Option<super::keyframe_imu::KeyframeImuSource>,
    /// The newest keyframe made whose mapping was not reported yet ([`VoOutput::mapped`]).
    unreported_kf: Option<KfId>,
    // Reusable buffers.
    feats: OrbFeatures,
    /// Matching by projection (last frame, local map).
    matcher: LocalMapMatcher,
    frame_points: Vec<Option<PointId>>,
    kf_counts: std::collections::HashMap<KfId, u32>,
    obs: Vec<PoseObservation>,
    obs_kp: Vec<usize>,
    inliers: Vec<bool>,
    /// Information of the last pose optimisation's result.
    last_information: nalgebra::Matrix6<f64>,
    /// In a prior map, no frame posed yet ([`VoTracker::start_in_prior_map`]).
    awaiting_prior: bool,
}

impl VoTracker {
    /// A tracker for `camera` images, its local mapping inline (see
    /// [`VoTracker::set_local_mapping`] for a thread).
    pub fn new(params: VoParams, camera: PinholeRadtan) -> Result<Self, CoreError> {
        let (w, h) = (camera.width as usize, camera.height as usize);
        let shared = Arc::new(Mutex::new(ClientMap::new(1, 0)));
        Ok(Self {
            extractor: OrbExtractor::new(params.orb.clone(), w, h)?,
            grid: FeatureGrid::new(w, h, 16.0)?,
            optimizer: PoseOptimizer::with_capacity(2 * params.orb.n_features),
            rule: KeyframeRule {
                params: params.keyframe_rule,
            },
            map: ClientMap::new(1, 0),
            shared,
            mapping: None,
            inline_mapper: LocalMapper::new(params.local_mapping()),
            inline_stats: Default::default(),
            sync_waits: 0,
            sync_timeouts: 0,
            mapped_last_kf: None,
            reloc_cursor: None,
            relocalized: 0,
            pnp: crate::pnp::PnpSolver::new(),
            state: VoState::NotInitialized,
            session_id: 1,
            next_kf_id: 0,
            init: None,
            pre_init: backward::PreInitBuffer::default(),
            backward: false,
            init_matches: Vec::new(),
            init_extractor: OrbExtractor::new(
                OrbParams {
                    n_features: params.orb.n_features * params.init_feature_factor.max(1),
                    ..params.orb.clone()
                },
                w,
                h,
            )?,
            last: None,
            velocity: None,
            ref_kf: None,
            frames_since_kf: 0,
            failures: 0,
            derotated: false,
            hint: None,
            kf_state: None,
            imu_source: None,
            unreported_kf: None,
            feats: OrbFeatures::with_capacity(params.orb.n_features),
            matcher: LocalMapMatcher::new(),
            frame_points: Vec::new(),
            kf_counts: std::collections::HashMap::new(),
            obs: Vec::new(),
            obs_kp: Vec::new(),
            inliers: Vec::new(),
            last_information: nalgebra::Matrix6::zeros(),
            awaiting_prior: false,
            params,
            camera,
        })
    }

    /// The client map as shared with a local-mapping runner.
    pub fn shared_map(&self) -> SharedMap {
        Arc::clone(&self.shared)
    }

    /// The local-mapping steps with this VO's parameters, for a runner to own.
    pub fn local_mapper(&self) -> LocalMapper {
        LocalMapper::new(self.params.local_mapping())
    }

    /// Local mapping runs behind `runner` from now on (e.g. a thread calling
    /// [`LocalMapper::step`] on [`VoTracker::shared_map`]): each new keyframe is submitted to
    /// it instead of being mapped inline. To be called before the first frame.
    pub fn set_local_mapping(&mut self, runner: Box<dyn LocalMappingRunner>) {
        self.mapping = Some(runner);
    }

    /// Whether local mapping runs behind a runner (not inline).
    pub fn local_mapping_runner(&self) -> bool {
        self.mapping.is_some()
    }

    /// Current VO session id.
    pub fn session_id(&self) -> u32 {
        self.session_id
    }

    /// The last tracked frame's time and its keypoints matched to map points, `(point, x,
    /// y)` in level-0 pixels as the VO used them (under a rolling shutter, rotated to the
    /// middle row's time; a keyframe's include the points it made): what a viewer draws on
    /// the image.
    pub fn last_matches(&self) -> Option<(i64, impl Iterator<Item = (PointId, f32, f32)> + '_)> {
        let last = self.last.as_ref()?;
        let kps = last.features.keypoints.iter();
        let matched = (kps.zip(&last.points)).filter_map(|(k, p)| p.map(|p| (p, k.x, k.y)));
        Some((last.t_ns, matched))
    }

    /// Current state.
    pub fn state(&self) -> VoState {
        self.state
    }

    /// Processes one frame.
    pub fn process(&mut self, frame: &VoFrame<'_>) -> Result<VoOutput, CoreError> {
        self.process_with_hint(frame, None)
    }

    /// Processes one frame with an outside prediction of its pose ([`PoseHint`]; used
    /// once the map is initialised, ignored before). `None` is [`VoTracker::process`].
    pub fn process_with_hint(
        &mut self,
        frame: &VoFrame<'_>,
        hint: Option<&PoseHint>,
    ) -> Result<VoOutput, CoreError> {
        self.process_inertial(frame, hint, None)
    }

    /// [`VoTracker::process_with_hint`] for a visual-inertial client: a keyframe made from
    /// this frame starts with the inertial state `kf_state` (e.g. the IMU's prediction of
    /// the frame, once the world is metric) and, with [`VoTracker::enable_keyframe_imu`],
    /// carries the IMU samples since the previous keyframe. Both are attached when the
    /// keyframe is made, before local mapping sees it.
    pub fn process_inertial(
        &mut self,
        frame: &VoFrame<'_>,
        hint: Option<&PoseHint>,
        kf_state: Option<super::map::KeyframeInertial>,
    ) -> Result<VoOutput, CoreError> {
        self.hint = hint.copied();
        self.kf_state = kf_state;
        let res = self.process_frame(frame);
        self.hint = None;
        self.kf_state = None;
        res
    }

    /// Consecutive frames that failed to track (0 while tracking).
    pub fn frames_failed(&self) -> u32 {
        self.failures
    }

    fn process_frame(&mut self, frame: &VoFrame<'_>) -> Result<VoOutput, CoreError> {
        let start = Instant::now();
        let mut times = StageTimes::default();
        let mut timings = crate::features::OrbTimings::default();
        let mut feats = std::mem::take(&mut self.feats);
        let initializing = matches!(self.state, VoState::NotInitialized | VoState::Initializing);
        let extractor = if initializing {
            &mut self.init_extractor
        } else {
            &mut self.extractor
        };
        extractor.extract_timed(&frame.image, &mut feats, &mut timings)?;
        // Rolling shutter: every bearing rotated to the mid-row time before anything uses it.
        self.derotated = false;
        if self.params.rolling_shutter && frame.readout_ns != 0 {
            let omega = frame.angular_velocity.or_else(|| {
                (!initializing)
                    .then(|| self.predict(frame.t_ns))
                    .flatten()
                    .and_then(|(_, v)| v)
                    .map(|v| v.angular)
            });
            if let Some(w) = omega {
                crate::rolling_shutter::derotate_keypoints(
                    &self.camera,
                    frame.readout_ns,
                    &w,
                    &mut feats.keypoints,
                );
                self.derotated = true;
            }
        }
        times.pyramid = timings.pyramid.as_secs_f32() * 1e3;
        times.detect = (timings.detect + timings.orient).as_secs_f32() * 1e3;
        times.describe = timings.describe.as_secs_f32() * 1e3;
        self.grid.build(&feats.keypoints);
        let mut out = VoOutput {
            state: self.state,
            t_cw: None,
            tracked: 0,
            pose_information: None,
            keyframe: None,
            keyframe_poses: Vec::new(),
            new_session: false,
            evicted: Vec::new(),
            backfill: Vec::new(),
            times,
            diagnostics: Vec::new(),
            mapped: None,
            world_correction: None,
        };
        // Lock-step: local mapping of earlier keyframes has finished before the map is used.
        self.sync_with_local_mapping(LOCAL_MAPPING_SYNC_TIMEOUT);
        // The map is locked (and swapped into `self.map`) for the rest of the frame; the
        // local-mapping thread works between frames.
        let shared = Arc::clone(&self.shared);
        let mut guard = lock(&shared);
        std::mem::swap(&mut self.map, &mut *guard);
        self.adopt_mapped_points();
        out.mapped = self.report_mapped_keyframe();
        out.world_correction = self.map.world_correction;
        let res = match self.state {
            VoState::NotInitialized | VoState::Initializing => {
                self.try_initialize(frame, &feats, &mut out);
                match out.backfill.first() {
                    // Initialised: the reference and the frames after it are posed.
                    Some(&(t_ref, _)) => self.pre_init.keep_before(t_ref),
                    None => self.pre_init.push(frame.t_ns, frame.readout_ns, &feats),
                }
                Ok(())
            }
            VoState::Tracking | VoState::Lost => self.track(frame, &feats, &mut out),
        };
        if self.state == VoState::Tracking {
            self.maybe_track_backwards(&mut out);
        }
        std::mem::swap(&mut self.map, &mut *guard);
        drop(guard);
        res?;
        self.feats = feats;
        out.state = self.state;
        out.times.total = start.elapsed().as_secs_f32() * 1e3;
        Ok(out)
    }

    /// Removes every keyframe from the client map (oldest first), e.g. to send them all to
    /// the server at the end of the stream.
    /// Waits (up to 10 s) for the local-mapping thread to finish its keyframes first.
    pub fn drain_keyframes(&mut self) -> Vec<Keyframe> {
        if let Some(m) = &self.mapping {
            m.wait_idle(std::time::Duration::from_secs(10));
        }
        let mut map = lock(&self.shared);
        let ids: Vec<KfId> = map.keyframes.keys().copied().collect();
        ids.into_iter()
            .filter_map(|k| map.remove_keyframe(k, 0))
            .collect()
    }

    /// Keyframes culled as redundant by local mapping so far.
    pub fn keyframes_culled(&self) -> usize {
        self.local_mapping_stats().culled
    }

    /// Totals of local mapping so far (inline and behind a runner).
    pub fn local_mapping_stats(&self) -> LocalMappingStats {
        let runner = self.mapping.as_ref().map(|m| m.stats()).unwrap_or_default();
        self.inline_stats.merged(&runner)
    }

    /// Frames that waited for the local-mapping thread to be idle
    /// ([`VoParams::sync_local_mapping`]; 0 without the thread).
    pub fn local_mapping_sync_waits(&self) -> usize {
        self.sync_waits
    }

    /// Waits for the local-mapping thread that timed out (the frame went on while local
    /// mapping was still busy: that run's decisions may depend on timing).
    pub fn local_mapping_sync_timeouts(&self) -> usize {
        self.sync_timeouts
    }

    /// With [`VoParams::sync_local_mapping`] and the local-mapping thread: waits (at most
    /// `timeout`) until it has mapped every keyframe given to it, counting the wait and
    /// whether it timed out.
    fn sync_with_local_mapping(&mut self, timeout: std::time::Duration) {
        let Some(m) = self
            .mapping
            .as_ref()
            .filter(|_| self.params.sync_local_mapping)
        else {
            return;
        };
        if m.idle() {
            return;
        }
        self.sync_waits += 1;
        if !m.wait_idle(timeout) {
            self.sync_timeouts += 1;
        }
    }

    /// With [`VoParams::sync_local_mapping`]: the last frame became a keyframe that local
    /// mapping (now finished) gave new points and culled points of: the last frame sees
    /// the same points as its keyframe, as after inline mapping, so the thread and inline
    /// mapping take the same decisions.
    fn adopt_mapped_points(&mut self) {
        let Some(k) = self.mapped_last_kf.take() else {
            return;
        };
        let (Some(last), Some(kf)) = (self.last.as_mut(), self.map.keyframes.get(&k)) else {
            return;
        };
        if kf.t_ns != last.t_ns || kf.points.len() != last.points.len() {
            return;
        }
        for (p, q) in last.points.iter_mut().zip(&kf.points) {
            if p.is_none() {
                *p = *q;
            }
            if p.is_some_and(|id| !self.map.points.contains_key(&id)) {
                *p = None;
            }
        }
    }

    /// Successful relocalisations so far.
    pub fn relocalizations(&self) -> usize {
        self.relocalized
    }

    /// Numbers this tracker's keyframes from `first` on (a restarted tracker process keeps
    /// keyframe ids unique per client across its lives: the server names keyframes by them).
    /// Only raises the counter.
    pub fn start_keyframe_ids_at(&mut self, first: KfId) {
        self.next_kf_id = self.next_kf_id.max(first);
    }

    /// Sets the inertial state of keyframe `id` (visual-inertial client, [`crate::vio`]);
    /// `false` when the map has no such keyframe. Locks the map.
    pub fn set_keyframe_inertial(&self, id: KfId, inertial: super::map::KeyframeInertial) -> bool {
        lock(&self.shared)
            .keyframes
            .get_mut(&id)
            .map(|kf| kf.inertial = Some(inertial))
            .is_some()
    }

    /// Asks local mapping for a whole-session visual-inertial window at the first keyframe
    /// at or after camera time `from_ns` ([`ClientMap::session_window_from_ns`]; a time
    /// after the last frame's keeps inline and threaded mapping deterministic: no keyframe
    /// already queued takes it). Locks the map.
    pub fn request_session_window(&self, from_ns: i64) {
        lock(&self.shared).session_window_from_ns = Some(from_ns);
    }

    /// Reads the client map (locks it; the local-mapping thread waits meanwhile).
    pub fn with_map<R>(&self, f: impl FnOnce(&ClientMap) -> R) -> R {
        f(&lock(&self.shared))
    }

    /// Moves the session's map and the tracking state into another world frame by the
    /// similarity `x' = s R x + t` (the metric, gravity-aligned world an inertial
    /// initialisation found, `imu::coupler`, or the server map's frame, `vio::anchor`): map
    /// ([`ClientMap::transform_world`]), the last frame's pose, the motion model's
    /// translation (scaled by `s`). Waits for the local-mapping runner to be idle first (a
    /// BA solved on a snapshot of the old frame must not land afterwards); `false`, and
    /// nothing moved, when it does not become idle within `timeout`. Keyframes already
    /// evicted (sent) are not this map's any more.
    pub fn transform_world(&mut self, m: &Sim3, timeout: std::time::Duration) -> bool {
        if !self.wait_local_mapping(timeout) {
            return false;
        }
        lock(&self.shared).transform_world(m);
        self.move_tracking_state(m);
        true
    }

    /// Applies the map's pending world correction ([`ClientMap::world_correction`], a
    /// similarity found by local mapping's visual-inertial window): the map and the
    /// tracking state move as with [`VoTracker::transform_world`]. Returns it; `None`
    /// (nothing moved) when none is pending or local mapping does not become idle within
    /// `timeout`.
    pub fn apply_world_correction(&mut self, timeout: std::time::Duration) -> Option<Sim3> {
        if !self.wait_local_mapping(timeout) {
            return None;
        }
        let c = {
            let mut m = lock(&self.shared);
            let c = m.world_correction.take()?;
            m.transform_world(&c);
            c
        };
        self.move_tracking_state(&c);
        Some(c)
    }

    /// The last frame's pose and the motion model after a world move `x' = s R x + t` (the
    /// motion model is a camera-to-camera motion: its translation scales by `s`).
    fn move_tracking_state(&mut self, m: &Sim3) {
        if let Some(last) = self.last.as_mut() {
            last.t_cw = super::map::transform_pose_cw(&last.t_cw, m);
        }
        if let Some((v, _)) = self.velocity.as_mut() {
            v.translation.vector *= m.s;
        }
    }

    /// Waits until the local-mapping thread has mapped every keyframe (at most `timeout`).
    pub fn wait_local_mapping(&self, timeout: std::time::Duration) -> bool {
        self.mapping.as_ref().is_none_or(|m| m.wait_idle(timeout))
    }

    fn start_new_session(&mut self, out: &mut VoOutput) {
        self.reloc_cursor = None;
        // The old map's keyframes go to the server before it is dropped.
        let ids: Vec<KfId> = self.map.keyframes.keys().copied().collect();
        for k in ids {
            if let Some(kf) = self.map.remove_keyframe(k, 0) {
                out.evicted.push(kf);
            }
        }
        self.session_id += 1;
        let next_point = self.map.next_point_id();
        self.map = ClientMap::new(self.session_id, next_point);
        self.state = VoState::NotInitialized;
        self.init = None;
        self.pre_init.clear();
        self.last = None;
        self.velocity = None;
        self.ref_kf = None;
        self.failures = 0;
        self.unreported_kf = None;
        if let Some(s) = self.imu_source.as_mut() {
            s.new_session();
        }
        out.new_session = true;
    }

    /// `(frame time, T_wc)` of every keyframe of the map into `out` (oldest first).
    fn keyframe_poses(&self, out: &mut Vec<(i64, Isometry3<f64>)>) {
        out.clear();
        out.extend(
            self.map
                .keyframes
                .values()
                .map(|kf| (kf.t_ns, kf.t_cw.inverse())),
        );
    }

    fn last_from_kf(&self, k: KfId) -> LastFrame {
        let kf = &self.map.keyframes[&k];
        LastFrame {
            t_ns: kf.t_ns,
            t_cw: kf.t_cw,
            features: kf.features.clone(),
            points: kf.points.clone(),
        }
    }

    /// Predicted pose and velocity (per second) for time `t_ns`.
    fn predict(&self, t_ns: i64) -> Option<(Isometry3<f64>, Option<Velocity>)> {
        let last = self.last.as_ref()?;
        let Some((v, period)) = self.velocity else {
            return Some((last.t_cw, None));
        };
        let dt = (t_ns - last.t_ns) as f64 * 1e-9;
        let a = dt / period;
        let log = se3_log(&v);
        let pred = se3_exp(&(log * a)) * last.t_cw;
        // Body twist per second, camera frame: T_cw(t + dt) = Exp(-dt ξ) T_cw(t)
        // (the pose optimiser's rolling-shutter convention).
        let vel = Velocity::from_twist(&(-log / period));
        Some((pred, Some(vel)))
    }
}

#[cfg(test)]
mod tests {
    use super::VoDiagnostic;
    use crate::lie::Sim3;

    /// After a world move the motion model predicts the moved pose of what it predicted
    /// before: `V' T'_last = move(V T_last)` (velocity translation scaled, last pose moved).
    #[test]
    fn a_world_move_moves_the_motion_model_prediction() {
        use nalgebra::{Isometry3, UnitQuaternion, Vector3};
        let cam = crate::camera::PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0);
        let mut vo = super::VoTracker::new(super::VoParams::default(), cam).expect("vo");
        let t_last = Isometry3::new(Vector3::new(0.5, -0.2, 1.0), Vector3::new(0.2, 0.1, -0.3));
        let v = Isometry3::new(
            Vector3::new(0.05, 0.01, -0.02),
            Vector3::new(0.01, 0.02, 0.0),
        );
        vo.last = Some(super::LastFrame {
            t_ns: 0,
            t_cw: t_last,
            features: Default::default(),
            points: vec![],
        });
        vo.velocity = Some((v, 0.05));
        let m = Sim3::new(
            UnitQuaternion::from_scaled_axis(Vector3::new(-0.3, 0.8, 0.2)),
            Vector3::new(2.0, -1.0, 0.5),
            0.4,
        );
        let expected = crate::vo::map::transform_pose_cw(&(v * t_last), &m);
        assert!(vo.transform_world(&m, std::time::Duration::from_secs(1)));
        let (v2, _) = vo.velocity.expect("velocity");
        let got = v2 * vo.last.as_ref().expect("last").t_cw;
        assert!((got.translation.vector - expected.translation.vector).norm() < 1e-12);
        assert!(got.rotation.angle_to(&expected.rotation) < 1e-12);
    }

    /// The diagnostics print as `SHOAL_DEBUG_INIT` printed them before they were returned.
    #[test]
    fn diagnostics_print_as_before() {
        let d = VoDiagnostic::InitFailed {
            matches: 120,
            frames: 3,
            reason: "ambiguous".into(),
        };
        assert_eq!(d.to_string(), "init: 120 matches after 3 frames: ambiguous");
        let d = VoDiagnostic::BackwardStart {
            before: 12,
            kept: 14,
            t_ref_ns: 5,
        };
        assert_eq!(
            d.to_string(),
            "backward: 12 of 14 kept frames before the oldest keyframe (t 5 ns)"
        );
        let d = VoDiagnostic::BackwardStopped {
            kept: 14,
            t_ns: 3,
            inliers: 9,
        };
        assert_eq!(
            d.to_string(),
            "backward: 14 frames kept, stopped at t 3 ns (9 inliers)"
        );
    }
}

mod backward;
mod inertial;
mod init;
mod local_mapper;
mod reloc;
mod resume;
mod track;

use local_mapper::lock;
pub use local_mapper::{
    LocalMapper, LocalMappingRunner, LocalMappingStats, LocalMappingStep, SharedMap, ViWindowRun,
};
