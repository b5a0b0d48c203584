//! Loop detection and Sim(3) verification over server keyframes (seed §3.4.2).
//!
//! The pure-algorithm half of the loop closer: no threads, no IPC.
//!
//! * [`LoopDetector`] keeps every kept keyframe ([`KeptKeyframe`]) of every server map with
//!   its bag-of-words vector in a [`KeyframeDatabase`]. For each new keyframe it queries the
//!   database with the seed's threshold (the lowest score against the keyframe's covisible
//!   neighbours), drops the neighbours, and keeps a candidate only when it has been
//!   consistent (covisibility groups sharing a keyframe) over 3 consecutive keyframes of the
//!   querying map. Candidates from other maps are allowed: they are the map merges.
//! * [`compute_sim3`] verifies a candidate geometrically: descriptor matches between the
//!   points of the two keyframes, Sim(3) RANSAC with Umeyama on 3-point samples and a
//!   two-way reprojection inlier test (χ² 9.21 at the keypoint's octave, as ORB-SLAM),
//!   Levenberg-Marquardt refinement of the 7 parameters on the two-way reprojection
//!   errors, then guided matching of the matched keyframe's neighbourhood into the query.
//!
//! The caller (the loop-closer service) fuses the returned point pairs, and corrects the
//! map (pose graph) or merges the two maps with [`LoopMatch::s_qm`].

mod detect;
mod matching;
mod refine;
mod sim3_ransac;
#[cfg(test)]
mod tests;
#[cfg(test)]
mod tests_detect;

pub use detect::{LoopDetector, LoopDetectorParams, QueryDetail, QueryStats};
pub use matching::{match_kept_points, neighbourhood_points, NeighbourhoodPoint, PointMatch};
pub use refine::{refine_sim3, RefineParams, Sim3Correspondence};
pub use sim3_ransac::{compute_sim3, verify_sim3, Sim3Params, Sim3Reject, Sim3Result};

use crate::lie::Sim3;
use crate::server::MapId;
use crate::vo::{KfId, PointId};

#[cfg(doc)]
use crate::{place::KeyframeDatabase, server::KeptKeyframe};

/// A verified loop (or map merge when `query_map != matched_map`), seed §3.4.2.
#[derive(Debug, Clone, PartialEq)]
pub struct LoopMatch {
    /// The keyframe that closed the loop (the one given to [`LoopDetector::add`]).
    pub query: KfId,
    /// Its server map.
    pub query_map: MapId,
    /// The keyframe it was matched to.
    pub matched: KfId,
    /// Server map of the matched keyframe (another map = a merge).
    pub matched_map: MapId,
    /// Similarity taking points from the matched keyframe's camera frame into the query
    /// keyframe's camera frame: `p_q = s_qm.transform_point(p_m)` (the seed's `S~_cm`).
    pub s_qm: Sim3,
    /// Matched server point ids (query-side point, matched-side point), inliers only, used
    /// to fuse duplicates.
    pub point_pairs: Vec<(PointId, PointId)>,
    /// Guided matches of query keypoints that have no server point yet (keypoint index,
    /// matched-side point): new observations of existing points for the caller's fusion.
    pub extra_observations: Vec<(u32, PointId)>,
    /// Total matches supporting the loop: refined RANSAC inliers plus guided matches.
    pub inliers: usize,
    /// Consistent candidates that went through geometric verification for this query
    /// (the accepted one included).
    pub candidates_considered: usize,
    /// The matched keyframe and the covisible neighbours whose points were projected in
    /// guided matching (the matched keyframe first), for the caller's pose graph.
    pub matched_neighbourhood: Vec<KfId>,
}
