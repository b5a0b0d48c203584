//! The tracking state machine of the client VO (seed §3.3): two-view initialisation, tracking
//! with the constant-velocity motion model (fallback: the reference keyframe), local-map
//! tracking, keyframe decision and creation, the keyframe window and VO sessions.
//!
//! Rolling shutter: every observation carries its row's time offset from the mid-row time
//! (seed eq. 2.61-2.63) and the pose optimiser moves the camera along the motion model's
//! velocity over it; `VoParams::rolling_shutter = false` turns that off for comparison.
use std::time::Instant;

use nalgebra::{Isometry3, Vector2, Vector3};

use super::map::{ClientMap, Keyframe, KfId, PointId};
use super::search::ProjCandidate;
use super::{KeyframeRule, KeyframeRuleParams};
use crate::camera::PinholeRadtan;
use crate::features::{
    match_two_frames_windowed, FeatureGrid, GrayImage, OrbExtractor, OrbFeatures, OrbParams,
    WindowMatchParams,
};
use crate::optim::{PoseObservation, PoseOptimizer, Velocity};
use crate::twoview::{initialize, normalize_pixels, TwoViewParams};
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
        }
    }
}

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
    /// The frame became this keyframe.
    pub keyframe: Option<KfId>,
    /// A new VO session started with this frame.
    pub new_session: bool,
    /// Keyframes evicted from the window (oldest first), to be sent to the server.
    pub evicted: Vec<Keyframe>,
    /// Stage times.
    pub times: StageTimes,
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
    /// The client map of the current session.
    pub map: ClientMap,
    state: VoState,
    session_id: u32,
    next_kf_id: KfId,
    init_ref: Option<LastFrame>,
    last: Option<LastFrame>,
    /// Motion model: `T_cw(k) * T_cw(k-1)^-1` per frame period and that period, s.
    velocity: Option<(Isometry3<f64>, f64)>,
    ref_kf: Option<KfId>,
    frames_since_kf: u32,
    failures: u32,
    // Reusable buffers.
    feats: OrbFeatures,
    cands: Vec<ProjCandidate>,
    found: Vec<Option<(usize, u32)>>,
    taken: Vec<bool>,
    frame_points: Vec<Option<PointId>>,
    obs: Vec<PoseObservation>,
    obs_kp: Vec<usize>,
    inliers: Vec<bool>,
    ba: crate::optim::ba::BundleAdjuster,
    ba_problem: crate::optim::ba::BaProblem,
}

impl VoTracker {
    /// A tracker for `camera` images.
    pub fn new(params: VoParams, camera: PinholeRadtan) -> Result<Self, CoreError> {
        let (w, h) = (camera.width as usize, camera.height as usize);
        Ok(Self {
            extractor: OrbExtractor::new(params.orb.clone(), w, h)?,
            grid: FeatureGrid::new(w, h, 16.0)?,
            optimizer: PoseOptimizer::with_capacity(2 * params.orb.n_features),
            rule: KeyframeRule {
                params: params.keyframe_rule,
            },
            map: ClientMap::new(1, 0),
            state: VoState::NotInitialized,
            session_id: 1,
            next_kf_id: 0,
            init_ref: None,
            last: None,
            velocity: None,
            ref_kf: None,
            frames_since_kf: 0,
            failures: 0,
            feats: OrbFeatures::with_capacity(params.orb.n_features),
            cands: Vec::new(),
            found: Vec::new(),
            taken: Vec::new(),
            frame_points: Vec::new(),
            obs: Vec::new(),
            obs_kp: Vec::new(),
            inliers: Vec::new(),
            ba: crate::optim::ba::BundleAdjuster::new(),
            ba_problem: crate::optim::ba::BaProblem::new(),
            params,
            camera,
        })
    }

    /// Current VO session id.
    pub fn session_id(&self) -> u32 {
        self.session_id
    }

    /// Current state.
    pub fn state(&self) -> VoState {
        self.state
    }

    /// Processes one frame.
    pub fn process(&mut self, frame: &VoFrame<'_>) -> Result<VoOutput, CoreError> {
        let start = Instant::now();
        let mut times = StageTimes::default();
        let mut timings = crate::features::OrbTimings::default();
        let mut feats = std::mem::take(&mut self.feats);
        self.extractor
            .extract_timed(&frame.image, &mut feats, &mut timings)?;
        times.pyramid = timings.pyramid.as_secs_f32() * 1e3;
        times.detect = (timings.detect + timings.orient).as_secs_f32() * 1e3;
        times.describe = timings.describe.as_secs_f32() * 1e3;
        self.grid.build(&feats.keypoints);
        let mut out = VoOutput {
            state: self.state,
            t_cw: None,
            tracked: 0,
            keyframe: None,
            new_session: false,
            evicted: Vec::new(),
            times,
        };
        match self.state {
            VoState::NotInitialized | VoState::Initializing => {
                self.try_initialize(frame, &feats, &mut out);
            }
            VoState::Tracking | VoState::Lost => self.track(frame, &feats, &mut out)?,
        }
        self.feats = feats;
        out.state = self.state;
        out.times.total = start.elapsed().as_secs_f32() * 1e3;
        Ok(out)
    }

    /// Removes every keyframe from the client map (oldest first), e.g. to send them all to
    /// the server at the end of the stream.
    pub fn drain_keyframes(&mut self) -> Vec<Keyframe> {
        let ids: Vec<KfId> = self.map.keyframes.keys().copied().collect();
        ids.into_iter()
            .filter_map(|k| self.map.remove_keyframe(k, 0))
            .collect()
    }

    fn start_new_session(&mut self, out: &mut VoOutput) {
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
        self.init_ref = None;
        self.last = None;
        self.velocity = None;
        self.ref_kf = None;
        self.failures = 0;
        out.new_session = true;
    }

    fn try_initialize(&mut self, frame: &VoFrame<'_>, feats: &OrbFeatures, out: &mut VoOutput) {
        let enough = feats.len() >= self.params.init_min_matches;
        let Some(reference) = self.init_ref.as_ref() else {
            if enough {
                self.set_init_ref(frame, feats);
            }
            return;
        };
        let m0 = Instant::now();
        let mut matches = Vec::new();
        let wp = WindowMatchParams {
            radius: 100.0,
            ..WindowMatchParams::default()
        };
        if match_two_frames_windowed(
            &reference.features,
            feats,
            &self.grid,
            None,
            &wp,
            &mut matches,
        )
        .is_err()
            || matches.len() < self.params.init_min_matches
        {
            out.times.matching = m0.elapsed().as_secs_f32() * 1e3;
            // Too far from the reference: start again from this frame.
            if enough {
                self.set_init_ref(frame, feats);
            }
            return;
        }
        let px = |f: &OrbFeatures, i: usize| {
            let k = f.keypoints[i];
            Vector2::new(k.x as f64, k.y as f64)
        };
        let p1: Vec<Vector2<f64>> = matches
            .iter()
            .map(|m| px(&reference.features, m.query as usize))
            .collect();
        let p2: Vec<Vector2<f64>> = matches
            .iter()
            .map(|m| px(feats, m.train as usize))
            .collect();
        let (mut x1, mut x2) = (Vec::new(), Vec::new());
        normalize_pixels(&self.camera, &p1, &mut x1);
        normalize_pixels(&self.camera, &p2, &mut x2);
        out.times.matching = m0.elapsed().as_secs_f32() * 1e3;
        let tv = TwoViewParams::for_camera(&self.camera);
        let Ok(res) = initialize(&x1, &x2, &tv) else {
            return;
        };
        // Scale: median depth of the initial points = 1 (the map's unit).
        let mut depths: Vec<f64> = res
            .points
            .iter()
            .zip(&res.triangulated)
            .filter(|(_, t)| **t)
            .map(|(p, _)| p.z)
            .collect();
        if depths.len() < 50 {
            return;
        }
        depths.sort_by(f64::total_cmp);
        let s = 1.0 / depths[depths.len() / 2].max(1e-9);
        let t_21 = res.pose_21();
        let t_cw2 = Isometry3::from_parts((t_21.translation.vector * s).into(), t_21.rotation);
        let Some(reference) = self.init_ref.take() else {
            return;
        };
        let id1 = self.next_kf_id;
        let id2 = id1 + 1;
        self.next_kf_id += 2;
        let n1 = reference.features.len();
        let kf1 = Keyframe {
            id: id1,
            t_ns: reference.t_ns,
            t_cw: Isometry3::identity(),
            camera: self.camera,
            readout_ns: 0,
            features: reference.features,
            points: vec![None; n1],
        };
        let kf2 = Keyframe {
            id: id2,
            t_ns: frame.t_ns,
            t_cw: t_cw2,
            camera: self.camera,
            readout_ns: frame.readout_ns,
            features: feats.clone(),
            points: vec![None; feats.len()],
        };
        self.map.insert_keyframe(kf1);
        self.map.insert_keyframe(kf2);
        for (k, m) in matches.iter().enumerate() {
            if res.triangulated[k] {
                self.map
                    .add_point(res.points[k] * s, id1, &[(id1, m.query), (id2, m.train)]);
            }
        }
        self.map.update_covisibility(id1);
        self.map.update_covisibility(id2);
        let dt = (frame.t_ns - reference.t_ns) as f64 * 1e-9;
        self.velocity = Some((t_cw2, dt.max(1e-6)));
        self.ref_kf = Some(id2);
        self.last = Some(self.last_from_kf(id2));
        self.state = VoState::Tracking;
        self.frames_since_kf = 0;
        out.t_cw = Some(t_cw2);
        out.keyframe = Some(id2);
        out.tracked = self.map.keyframes.get(&id2).map_or(0, |k| k.n_points());
    }

    fn set_init_ref(&mut self, frame: &VoFrame<'_>, feats: &OrbFeatures) {
        self.init_ref = Some(LastFrame {
            t_ns: frame.t_ns,
            t_cw: Isometry3::identity(),
            features: feats.clone(),
            points: Vec::new(),
        });
        self.state = VoState::Initializing;
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
        let pred = crate::optim::se3::se3_exp(&(log * a)) * last.t_cw;
        // Body twist per second, camera frame: T_cw(t + dt) = Exp(-dt ξ) T_cw(t)
        // (the pose optimiser's rolling-shutter convention).
        let xi = -log / period;
        let vel = Velocity {
            linear: Vector3::new(xi[0], xi[1], xi[2]),
            angular: Vector3::new(xi[3], xi[4], xi[5]),
        };
        Some((pred, Some(vel)))
    }
}

/// Logarithm of an SE(3) pose as `[ρ; φ]` (translation first), the inverse of
/// [`crate::optim::se3::se3_exp`]: `φ = Log(R)`, `ρ = J(φ)⁻¹ t`.
pub fn se3_log(t: &Isometry3<f64>) -> nalgebra::Vector6<f64> {
    let phi = crate::geometry::so3_log(&t.rotation.to_rotation_matrix());
    let theta = phi.norm();
    let w = crate::geometry::skew(&phi);
    let j_inv = if theta < 1e-6 {
        nalgebra::Matrix3::identity() - 0.5 * w + w * w / 12.0
    } else {
        let half = 0.5 * theta;
        let c = (1.0 - half * half.cos() / half.sin()) / (theta * theta);
        nalgebra::Matrix3::identity() - 0.5 * w + c * w * w
    };
    let rho = j_inv * t.translation.vector;
    nalgebra::Vector6::new(rho.x, rho.y, rho.z, phi.x, phi.y, phi.z)
}

mod track;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn se3_log_inverts_exp() {
        let xi = nalgebra::Vector6::new(0.3, -0.2, 0.5, 0.4, -0.1, 0.25);
        let t = crate::optim::se3::se3_exp(&xi);
        assert!((se3_log(&t) - xi).norm() < 1e-9);
        let small = nalgebra::Vector6::new(1e-3, 0.0, 2e-3, 1e-8, 0.0, 0.0);
        assert!((se3_log(&crate::optim::se3::se3_exp(&small)) - small).norm() < 1e-12);
    }
}
