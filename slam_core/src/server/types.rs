//! Plain data of the server keyframe handler (seed §3.4.1): the keyframe as the server
//! receives it, what a handled keyframe produced, the summary handed to loop closing and the
//! pose feedback to the client.
use nalgebra::{Isometry3, Vector3};

use crate::camera::PinholeRadtan;
use crate::features::OrbFeatures;
use crate::ids::ClientKeyframeId;
use crate::vo::keyframe_imu::KeyframeImu;
use crate::vo::{Keyframe, KeyframeInertial, KfId, PointId};
use crate::CoreError;

pub use crate::ids::MapId;

/// A keyframe as the client sends it (seed §3.3, keyframe message).
#[derive(Debug, Clone)]
pub struct ServerKeyframe {
    /// Client (agent) id.
    pub client_id: u32,
    /// VO session of the client that made the keyframe.
    pub session_id: u32,
    /// Keyframe id, unique per client across sessions (≤ [`ClientKeyframeId::MAX`]: the
    /// server's [`crate::ids::KeyframeId`] puts the client in the bits above).
    pub id: KfId,
    /// Frame time (mid-row), ns.
    pub t_ns: i64,
    /// Pose in the client map, `T_ck` (`p_c = R_ck p_k + t_ck`): the inverse of the VO's
    /// [`Keyframe::t_cw`]. Absolute, so a lost message does not corrupt later ones.
    pub t_ck: Isometry3<f64>,
    /// Camera model.
    pub camera: PinholeRadtan,
    /// Rolling-shutter readout time, ns (0 = global shutter).
    pub readout_ns: i64,
    /// Keypoints and 32-byte descriptors.
    pub features: OrbFeatures,
    /// Client map-point id seen by each keypoint, if any.
    pub client_points: Vec<Option<PointId>>,
    /// Velocity and biases of a visual-inertial client's keyframe once its world is metric
    /// and gravity-aligned (`VI_NOTES.md` §4 "Server"); `None` for a monocular client, or
    /// before the client's inertial initialisation.
    pub inertial: Option<KeyframeInertial>,
    /// The IMU samples since the client's previous keyframe and the calibration to
    /// preintegrate them (`VI_NOTES.md` §4, Fig. 5.4); `None` for a monocular client.
    pub imu: Option<KeyframeImu>,
}

impl ServerKeyframe {
    /// The message the client sends for its VO keyframe `kf` of session `session_id`.
    pub fn from_vo(client_id: u32, session_id: u32, kf: &Keyframe) -> Self {
        Self {
            client_id,
            session_id,
            id: kf.id,
            t_ns: kf.t_ns,
            t_ck: kf.t_cw.inverse(),
            camera: kf.camera,
            readout_ns: kf.readout_ns,
            features: kf.features.clone(),
            client_points: kf.points.clone(),
            inertial: kf.inertial,
            imu: kf.imu.clone(),
        }
    }

    /// Whether the client says this keyframe's pose is metric and gravity-aligned (a
    /// visual-inertial client after its inertial initialisation) and it carries the IMU
    /// since its previous keyframe.
    pub fn is_inertial(&self) -> bool {
        self.inertial.is_some() && self.imu.is_some()
    }

    /// Checks what the handler relies on: one descriptor and one client point slot per
    /// keypoint, a finite pose, an id in range, finite keypoints.
    pub fn validate(&self) -> Result<(), CoreError> {
        let n = self.features.keypoints.len();
        if self.features.descriptors.len() != n || self.client_points.len() != n {
            return Err(CoreError::InvalidArgument(format!(
                "keyframe {}: {} keypoints, {} descriptors, {} point slots",
                self.id,
                n,
                self.features.descriptors.len(),
                self.client_points.len()
            )));
        }
        if self.id > ClientKeyframeId::MAX {
            return Err(CoreError::InvalidArgument(format!(
                "keyframe id {} above {}",
                self.id,
                ClientKeyframeId::MAX
            )));
        }
        let t = self.t_ck.translation.vector;
        let q = self.t_ck.rotation.coords;
        if !t.iter().chain(q.iter()).all(|v| v.is_finite()) {
            return Err(CoreError::InvalidArgument(format!(
                "keyframe {}: non-finite pose",
                self.id
            )));
        }
        if !self
            .features
            .keypoints
            .iter()
            .all(|k| k.x.is_finite() && k.y.is_finite())
        {
            return Err(CoreError::InvalidArgument(format!(
                "keyframe {}: non-finite keypoint",
                self.id
            )));
        }
        Ok(())
    }
}

/// What a server map's frame is (`VI_NOTES.md` §4 "Server"): the map of a visual-inertial
/// client is metric and gravity-aligned (its server frame is the client's world after the
/// inertial initialisation), a monocular client's map is neither (arbitrary unit and
/// orientation, seed ch. 3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct MapFrame {
    /// Lengths are metres.
    pub metric: bool,
    /// The z axis is up (gravity is `(0, 0, -g)`).
    pub gravity_aligned: bool,
}

impl MapFrame {
    /// The frame of a map built from visual-inertial keyframes.
    pub const INERTIAL: Self = Self {
        metric: true,
        gravity_aligned: true,
    };
    /// The frame of a monocular map.
    pub const VISUAL: Self = Self {
        metric: false,
        gravity_aligned: false,
    };

    /// Metric and gravity-aligned: loops and merges with another such map have 4 degrees
    /// of freedom (x, y, z, yaw), not 7.
    pub fn is_inertial(&self) -> bool {
        self.metric && self.gravity_aligned
    }
}

/// What happened to a keyframe given to [`super::KeyframeHandler::handle`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KeyframeStatus {
    /// First keyframe of a (new) session: remembered, no map yet.
    First,
    /// Second keyframe of a session: the session's server map was built from the two.
    MapCreated,
    /// Refined and kept in the server map.
    Kept,
    /// Refined but redundant: its pose and the scale ratio were updated, the map not.
    Discarded,
    /// Already handled (id not above the last one of its session): ignored.
    Duplicate,
}

/// A point of a kept keyframe, for place recognition and loop closing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeptPoint {
    /// Keypoint index.
    pub keypoint: u32,
    /// Server map point id.
    pub point: PointId,
    /// Point in the keyframe's camera frame.
    pub p_k: Vector3<f64>,
}

/// What loop closing needs of a kept keyframe (seed §3.4.2): its descriptors, its points in
/// its own frame and its covisible neighbours.
#[derive(Debug, Clone)]
pub struct KeptKeyframe {
    /// Server map it belongs to.
    pub map_id: MapId,
    /// Server keyframe id ([`crate::ids::KeyframeId`]).
    pub kf_id: KfId,
    /// Client keyframe id.
    pub client_kf_id: KfId,
    /// Frame time, ns.
    pub t_ns: i64,
    /// Server pose `T_sk` (camera → server map).
    pub t_sk: Isometry3<f64>,
    /// Camera model.
    pub camera: PinholeRadtan,
    /// Keypoints and descriptors.
    pub features: OrbFeatures,
    /// Its map points, in its frame.
    pub points: Vec<KeptPoint>,
    /// Covisible keyframes with their weights (shared points), best first.
    pub covisible: Vec<(KfId, u32)>,
    /// The frame of its map (metric and gravity-aligned or not) when it was summarised:
    /// loops and merges between metric, gravity-aligned maps have 4 degrees of freedom.
    pub frame: MapFrame,
}

/// Result of handling one keyframe.
#[derive(Debug, Clone)]
pub struct HandleReport {
    /// Client keyframe id.
    pub client_kf_id: KfId,
    /// What happened.
    pub status: KeyframeStatus,
    /// Server map of the keyframe (`None` before a map exists).
    pub map_id: Option<MapId>,
    /// Server pose `T_sk` (camera → server map), when there is a map.
    pub t_sk: Option<Isometry3<f64>>,
    /// Prediction of eq. 3.4 before refinement.
    pub t_sk_predicted: Option<Isometry3<f64>>,
    /// Measured scale ratio (eq. 3.2), when measurable.
    pub lambda_measured: Option<f64>,
    /// Smoothed scale ratio after this keyframe (eq. 3.3).
    pub lambda: f64,
    /// Server points matched and kept as inliers by the refinement.
    pub inliers: usize,
    /// Points created with this keyframe (kept keyframes and map creation).
    pub new_points: usize,
    /// Summaries for loop closing of the keyframes inserted (one when kept, two when the
    /// map was created, none otherwise).
    pub kept: Vec<KeptKeyframe>,
}

/// Pose feedback to the client (seed §3.4.1): the server pose of its last keyframe and the
/// scale ratio, plus the acknowledgement of the last keyframe applied.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ServerFeedback {
    /// Client the feedback is for.
    pub client_id: u32,
    /// Last keyframe applied (client id).
    pub acked_keyframe_id: KfId,
    /// Its session.
    pub acked_session_id: u32,
    /// The server pose of the client's last keyframe; `None` while the session has only
    /// one keyframe.
    pub pose: Option<FeedbackPose>,
}

/// The pose part of a [`ServerFeedback`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FeedbackPose {
    /// Server map of the client's keyframes.
    pub map_id: MapId,
    /// Server pose of the client's last keyframe, `T_sk` (camera → server map).
    pub t_sk: Isometry3<f64>,
    /// Scale ratio `λ` (eq. 3.2-3.3; 1 when `metric`).
    pub lambda: f64,
    /// A metric keyframe in a metric, gravity-aligned map: the client may anchor its world
    /// to the map (`vio::anchor`).
    pub metric: bool,
}

/// Client side of the feedback (eq. 3.1, 3.4): the server-map pose of a frame with client
/// pose `t_cf`, given the client pose `t_cj` of the fed-back keyframe `j` (the client
/// remembers the poses it sent), its server pose `t_sj` and `λ`. The client map is not
/// transformed.
pub fn frame_pose_in_server_map(
    t_cj: &Isometry3<f64>,
    t_sj: &Isometry3<f64>,
    lambda: f64,
    t_cf: &Isometry3<f64>,
) -> Isometry3<f64> {
    super::scale::predict_server_pose(t_cj, t_sj, lambda, t_cf)
}
