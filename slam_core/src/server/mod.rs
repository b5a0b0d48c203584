//! The server's keyframe handlers (seed §3.4.1), as pure functions and plain data: one
//! [`KeyframeHandler`] per client turns the keyframes its VO sends into a server map,
//! predicting each keyframe's server pose from the last one and the scale ratio
//! (eq. 3.1, 3.4), refining it against the local server map, tracking the scale ratio
//! (eq. 3.2-3.3), keeping only keyframes that add to the map, and, when idle, running local
//! BA and culling redundant keyframes, so that a revisited area reuses its keyframes.
//!
//! The server map reuses the VO's map structure ([`crate::vo::ClientMap`]) in the server
//! frame `s`; the BA, point creation and keyframe culling are the VO's own functions.
//!
//! Frames: a client keyframe pose is `T_ck` (camera → client map `c`), a server pose is
//! `T_sk` (camera → server map `s`); `λ` is server length over client length.

pub mod correction;
pub mod global_ba;
pub mod handler;
mod refine;
pub mod scale;
pub mod server_map;
#[cfg(any(test, feature = "testing"))]
pub mod test_scene;
pub mod types;

pub use correction::{
    apply_pose_corrections, merge_maps, relocalise_in_frozen, scale_ratio_after_loop,
    transform_map, transform_pose, CorrectionReport, MergeReport, Relocalisation,
};
pub use global_ba::{GlobalBa, GlobalBaApplied};
pub use handler::{
    names_loaded_points, HandlerParams, HandlerStats, IdleReport, KeyframeHandler, ServerMaps,
    MIN_JOIN_POINTS,
};
pub use scale::{measured_scale_ratio, predict_server_pose, smooth_scale_ratio};
pub use server_map::{Owner, ServerMap};
pub use types::{
    frame_pose_in_server_map, FeedbackPose, HandleReport, KeptKeyframe, KeptPoint, KeyframeStatus,
    MapFrame, MapId, ServerFeedback, ServerKeyframe,
};
