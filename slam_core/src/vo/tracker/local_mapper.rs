//! Local mapping of the client VO (seed §3.3: "two threads, tracking and local mapping"), as
//! synchronous steps. The tracking thread inserts a keyframe (and triangulates with its
//! reference keyframe itself, seed change 3); local mapping then triangulates with the other
//! neighbours, culls recent points, runs the local bundle adjustment and culls redundant
//! keyframes (`vo::kf_culling`; culled keyframes are dropped, not sent to the server, as the
//! seed's trash list).
//!
//! Where it runs is not decided here (this crate starts no thread): inline at keyframe
//! creation ([`LocalMapper::step_inline`], the default of [`super::VoTracker`]), or behind
//! a [`LocalMappingRunner`] that [`super::VoTracker::set_local_mapping`] installs, e.g. the
//! tracker service's thread (`services/tracker/src/mapping_thread.rs`), which calls
//! [`LocalMapper::step`] for each keyframe it is given. The map is then shared as
//! [`SharedMap`]; each step holds the lock only for its own reads and writes and solves the
//! local BA on a snapshot with the map unlocked. While newer keyframes wait, a step skips
//! the BA (ORB-SLAM aborts a running BA when a keyframe arrives, to the same effect).
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use crate::optim::ba::{BaParams, BaProblem, BundleAdjuster};
use crate::vo::kf_culling::{cull_redundant_keyframes, KfCullingParams};
use crate::vo::local_mapping::{
    apply_local_ba, create_points_with_neighbours, cull_recent_points, prepare_local_ba,
};
use crate::vo::map::{ClientMap, KfId};

/// The client map shared between the tracking and the local-mapping thread.
pub type SharedMap = Arc<Mutex<ClientMap>>;

/// Locks the shared map; a panic elsewhere while holding it does not make the map unusable
/// (its invariants are restored by every step before it unlocks).
pub fn lock(map: &Mutex<ClientMap>) -> MutexGuard<'_, ClientMap> {
    map.lock().unwrap_or_else(|e| e.into_inner())
}

/// What the local-mapping steps do for one keyframe.
#[derive(Debug, Clone, Copy)]
pub(crate) struct LocalMappingParams {
    /// Neighbour keyframes to triangulate with and to adjust.
    pub neighbours: usize,
    /// Run the local bundle adjustment.
    pub local_ba: bool,
}

/// What one local-mapping step did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LocalMappingStep {
    /// Keyframes culled as redundant.
    pub culled: usize,
    /// A local bundle adjustment was solved and applied.
    pub local_ba: bool,
}

/// The local-mapping steps of one VO with their reusable buffers (bundle adjuster and
/// problem). Synchronous: whoever owns it decides on which thread a step runs.
pub struct LocalMapper {
    params: LocalMappingParams,
    ba: BundleAdjuster,
    problem: BaProblem,
}

impl LocalMapper {
    pub(crate) fn new(params: LocalMappingParams) -> Self {
        Self {
            params,
            ba: BundleAdjuster::new(),
            problem: BaProblem::new(),
        }
    }

    /// Local mapping of keyframe `k` on the shared `map` (the body of a local-mapping
    /// thread): triangulation with neighbours and culling of recent points under the lock;
    /// the local BA (skipped when `newer_waiting()` says another keyframe is queued) solved
    /// with the map unlocked; its result applied and redundant keyframes culled under the
    /// lock. A keyframe no longer in the map (evicted meanwhile) is skipped.
    pub fn step(
        &mut self,
        map: &Mutex<ClientMap>,
        k: KfId,
        newer_waiting: impl Fn() -> bool,
    ) -> LocalMappingStep {
        let p = self.params;
        let job = {
            let mut m = lock(map);
            if m.keyframes.contains_key(&k) {
                create_points_with_neighbours(&mut m, k, p.neighbours);
                cull_recent_points(&mut m, k);
                if p.local_ba && !newer_waiting() {
                    prepare_local_ba(&m, k, &mut self.problem, p.neighbours)
                } else {
                    None
                }
            } else {
                None
            }
        };
        let (ba, problem) = (&mut self.ba, &mut self.problem);
        let solved = job.filter(|_| ba.optimize(problem, &BaParams::local()).is_ok());
        let mut step = LocalMappingStep::default();
        let mut m = lock(map);
        if let Some(job) = solved {
            apply_local_ba(&mut m, &job, &self.problem, self.ba.inliers());
            step.local_ba = true;
        }
        if m.keyframes.contains_key(&k) {
            let n = cull_redundant_keyframes(&mut m, k, &[], &KfCullingParams::default());
            step.culled = n.len();
        }
        step
    }

    /// Local mapping of keyframe `k` inline, in the tracking thread at keyframe creation
    /// (the same steps, the map already at hand).
    pub(crate) fn step_inline(&mut self, map: &mut ClientMap, k: KfId) -> LocalMappingStep {
        let p = self.params;
        let mut step = LocalMappingStep::default();
        create_points_with_neighbours(map, k, p.neighbours);
        cull_recent_points(map, k);
        if p.local_ba {
            if let Some(job) = prepare_local_ba(map, k, &mut self.problem, p.neighbours) {
                if self
                    .ba
                    .optimize(&mut self.problem, &BaParams::local())
                    .is_ok()
                {
                    apply_local_ba(map, &job, &self.problem, self.ba.inliers());
                    step.local_ba = true;
                }
            }
        }
        step.culled = cull_redundant_keyframes(map, k, &[], &KfCullingParams::default()).len();
        step
    }
}

/// Local mapping off the tracking thread, as the VO sees it
/// ([`super::VoTracker::set_local_mapping`]): keyframes are queued to it and mapped with
/// [`LocalMapper::step`] on the [`SharedMap`], in the order given.
pub trait LocalMappingRunner: Send {
    /// Queues keyframe `k` (already in the shared map).
    fn submit(&self, k: KfId);
    /// No keyframe waiting or being mapped.
    fn idle(&self) -> bool;
    /// Waits until idle (at most `timeout`); returns whether it is.
    fn wait_idle(&self, timeout: Duration) -> bool;
    /// Keyframes culled as redundant so far.
    fn culled(&self) -> usize;
}
