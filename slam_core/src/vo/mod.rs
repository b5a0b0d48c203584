//! Monocular visual odometry of a client (seed §3.3, "ORB-VO"): the client map and the
//! rules of the tracking and local-mapping threads, as pure functions on plain data. This
//! crate starts no thread and reads no environment: local mapping is a synchronous step
//! ([`LocalMapper::step`]) that the tracker service runs on its own thread
//! ([`VoTracker::set_local_mapping`]; inline by default), and what the initialiser tried
//! comes back with each frame ([`VoOutput::diagnostics`]).
//!
//! **Status:** the map structures and the keyframe rule are here; the tracking state machine
//! (initialisation, motion-model / reference-keyframe tracking, relocalisation, local-map
//! tracking) and local mapping come with the tracker issue, built on `features`,
//! `twoview`, `optim` and bundle adjustment.

pub mod keyframe_imu;
pub mod keyframe_rule;
pub mod kf_culling;
pub mod local_mapping;
pub mod map;
pub mod prior;
pub mod resume;
pub mod search;
pub mod tracker;
pub mod vi_window;

pub use keyframe_imu::{ImuCalibration, KeyframeImu};
pub use keyframe_rule::{KeyframeRule, KeyframeRuleParams};
pub use kf_culling::{cull_redundant_keyframes, KfCullingParams};
pub use map::{ClientMap, Keyframe, KeyframeInertial, KfId, MapPoint, PointId};
pub use prior::{is_prior_keyframe, prior_client_map};
pub use resume::{restore_map, RestoredMap, StoredPoint};
pub use tracker::{
    LocalMapper, LocalMappingRunner, LocalMappingStats, LocalMappingStep, MappedKeyframe, PoseHint,
    SharedMap, StageTimes, ViWindowRun, VoDiagnostic, VoFrame, VoOutput, VoParams, VoState,
    VoTracker, LOCAL_MAPPING_SYNC_TIMEOUT,
};
pub use vi_window::{ViMappingMode, ViMappingParams};
