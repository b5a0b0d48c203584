//! Local mapping of the client VO (seed §3.3: "two threads, tracking and local mapping"), as
//! synchronous steps. The tracking thread inserts a keyframe (and triangulates with its
//! reference keyframe itself, seed change 3); local mapping then triangulates with the other
//! neighbours, culls recent points, runs the local bundle adjustment and culls redundant
//! keyframes (`vo::kf_culling`; culled keyframes are dropped, not sent to the server, as the
//! seed's trash list). A visual-inertial client's keyframes, once the world is metric (they
//! carry an inertial state and their IMU segment), get the visual-inertial window
//! (`vo::vi_window`, `VI_NOTES.md` §4 Fig. 5.5) instead of the visual local BA
//! ([`ViMappingMode`]; the visual BA when no window can be built or its solve fails, which
//! is counted, never a panic).
//!
//! Where it runs is not decided here (this crate starts no thread): inline at keyframe
//! creation ([`LocalMapper::step_inline`], the default of [`super::VoTracker`]), or behind
//! a [`LocalMappingRunner`] that [`super::VoTracker::set_local_mapping`] installs, e.g. the
//! tracker service's thread (`services/tracker/src/mapping_thread.rs`), which calls
//! [`LocalMapper::step`] for each keyframe it is given. The map is then shared as
//! [`SharedMap`]; each step holds the lock only for its own reads and writes and solves the
//! local BA (or the window) on a snapshot with the map unlocked. While newer keyframes
//! wait, a step skips the BA (ORB-SLAM aborts a running BA when a keyframe arrives, to the
//! same effect). Inline mapping is the same step on the map at hand, so both take the same
//! decisions.
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use crate::imu::window::{ViSolver, ViWindow};
use crate::optim::ba::{BaParams, BaProblem, BundleAdjuster};
use crate::vo::kf_culling::{cull_redundant_keyframes, KfCullingParams};
use crate::vo::local_mapping::{
    apply_local_ba, create_points_with_neighbours, cull_recent_points, prepare_local_ba, LocalBaJob,
};
use crate::vo::map::{ClientMap, KfId};
use crate::vo::vi_window::{
    apply_vi_window, prepare_vi_window, ViMappingMode, ViMappingParams, ViSkip, ViWindowJob,
};

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
    /// The visual-inertial window (a visual-inertial client's keyframes, once metric).
    pub vi: ViMappingParams,
}

/// What the visual-inertial window did for one keyframe.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub enum ViWindowRun {
    /// Not run: the keyframe has no inertial state (a monocular client, or before the
    /// inertial initialisation), the window is off, or newer keyframes were waiting.
    #[default]
    NotRun,
    /// No window could be built (see [`ViSkip`]).
    Skipped(ViSkip),
    /// Solved and written back.
    Solved {
        /// Keyframes of the window (the oldest fixed or gauged).
        keyframes: usize,
        /// Points.
        points: usize,
        /// Observations.
        observations: usize,
        /// Accepted Levenberg-Marquardt iterations.
        iterations: usize,
        /// Observations removed as outliers.
        outliers: usize,
        /// Time from building the window to writing it back, ms.
        ms: f32,
    },
    /// The solver failed (or gave a non-finite state): nothing written back.
    Failed,
}

/// What one local-mapping step did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LocalMappingStep {
    /// Keyframes culled as redundant.
    pub culled: usize,
    /// A local bundle adjustment was solved and applied.
    pub local_ba: bool,
    /// The visual-inertial window.
    pub vi_window: ViWindowRun,
}

/// Totals of local-mapping steps (a runner's, or the inline mapping's).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LocalMappingStats {
    /// Keyframes mapped.
    pub steps: usize,
    /// Keyframes culled as redundant.
    pub culled: usize,
    /// Visual local BAs applied.
    pub local_ba: usize,
    /// Visual-inertial windows solved and applied.
    pub vi_windows: usize,
    /// Keyframes with an inertial state for which no window could be built.
    pub vi_skipped: usize,
    /// Windows whose solve failed (skipped, nothing written).
    pub vi_failed: usize,
    /// Total time of the solved windows, ms.
    pub vi_ms_total: f64,
    /// Longest solved window, ms.
    pub vi_ms_max: f64,
}

impl LocalMappingStats {
    /// Counts one step.
    pub fn add(&mut self, s: &LocalMappingStep) {
        self.steps += 1;
        self.culled += s.culled;
        self.local_ba += usize::from(s.local_ba);
        match s.vi_window {
            ViWindowRun::NotRun => {}
            ViWindowRun::Skipped(_) => self.vi_skipped += 1,
            ViWindowRun::Failed => self.vi_failed += 1,
            ViWindowRun::Solved { ms, .. } => {
                self.vi_windows += 1;
                self.vi_ms_total += f64::from(ms);
                self.vi_ms_max = self.vi_ms_max.max(f64::from(ms));
            }
        }
    }

    /// The totals of two sets of steps.
    pub fn merged(&self, o: &LocalMappingStats) -> LocalMappingStats {
        LocalMappingStats {
            steps: self.steps + o.steps,
            culled: self.culled + o.culled,
            local_ba: self.local_ba + o.local_ba,
            vi_windows: self.vi_windows + o.vi_windows,
            vi_skipped: self.vi_skipped + o.vi_skipped,
            vi_failed: self.vi_failed + o.vi_failed,
            vi_ms_total: self.vi_ms_total + o.vi_ms_total,
            vi_ms_max: self.vi_ms_max.max(o.vi_ms_max),
        }
    }
}

/// The local-mapping steps of one VO with their reusable buffers (bundle adjuster and
/// problem, visual-inertial solver and window). Synchronous: whoever owns it decides on
/// which thread a step runs.
pub struct LocalMapper {
    params: LocalMappingParams,
    ba: BundleAdjuster,
    problem: BaProblem,
    vi: ViSolver,
    vi_window: ViWindow,
    vi_job: ViWindowJob,
}

impl LocalMapper {
    pub(crate) fn new(params: LocalMappingParams) -> Self {
        Self {
            params,
            ba: BundleAdjuster::new(),
            problem: BaProblem::new(),
            vi: ViSolver::new(),
            vi_window: ViWindow::empty(),
            vi_job: ViWindowJob::default(),
        }
    }

    /// Local mapping of keyframe `k` on the shared `map` (the body of a local-mapping
    /// thread): triangulation with neighbours and culling of recent points under the lock;
    /// the adjustment (skipped when `newer_waiting()` says another keyframe is queued)
    /// solved with the map unlocked: the visual local BA, and once the keyframe has an
    /// inertial state the visual-inertial window after it or instead of it
    /// ([`ViMappingMode`]); each result applied and redundant keyframes culled under the
    /// lock. A keyframe no longer in the map (evicted meanwhile) is skipped.
    pub fn step(
        &mut self,
        map: &Mutex<ClientMap>,
        k: KfId,
        newer_waiting: impl Fn() -> bool,
    ) -> LocalMappingStep {
        let p = self.params;
        let mut step = LocalMappingStep::default();
        let (ba_job, vi_first) = {
            let mut m = lock(map);
            if !m.keyframes.contains_key(&k) {
                return step;
            }
            create_points_with_neighbours(&mut m, k, p.neighbours);
            cull_recent_points(&mut m, k);
            let busy = newer_waiting();
            let vi_first = (!busy && p.vi.mode == ViMappingMode::InsteadOfVisualBa)
                .then(|| self.prepare_vi(&m, k, &mut step))
                .flatten();
            let ba = (!busy && p.local_ba && vi_first.is_none())
                .then(|| prepare_local_ba(&m, k, &mut self.problem, p.neighbours))
                .flatten();
            (ba, vi_first)
        };
        if let Some(t0) = vi_first {
            self.solve_vi(map, t0, &mut step);
            if step.vi_window == ViWindowRun::Failed && p.local_ba {
                let job = prepare_local_ba(&lock(map), k, &mut self.problem, p.neighbours);
                self.solve_visual(map, job, &mut step);
            }
        }
        self.solve_visual(map, ba_job, &mut step);
        if p.vi.mode == ViMappingMode::AfterVisualBa && !newer_waiting() {
            let t0 = self.prepare_vi(&lock(map), k, &mut step);
            if let Some(t0) = t0 {
                self.solve_vi(map, t0, &mut step);
            }
        }
        let mut m = lock(map);
        if m.keyframes.contains_key(&k) {
            let n = cull_redundant_keyframes(&mut m, k, &[], &KfCullingParams::default());
            step.culled = n.len();
        }
        step
    }

    /// Local mapping of keyframe `k` inline, in the tracking thread at keyframe creation:
    /// the same steps ([`LocalMapper::step`], nothing waiting), the map already at hand.
    pub(crate) fn step_inline(&mut self, map: &mut ClientMap, k: KfId) -> LocalMappingStep {
        let shared = Mutex::new(std::mem::take(map));
        let step = self.step(&shared, k, || false);
        *map = shared.into_inner().unwrap_or_else(|e| e.into_inner());
        step
    }

    /// Solves a visual local BA job (map unlocked) and applies it (locked).
    fn solve_visual(
        &mut self,
        map: &Mutex<ClientMap>,
        job: Option<LocalBaJob>,
        step: &mut LocalMappingStep,
    ) {
        let Some(job) = job else {
            return;
        };
        if self
            .ba
            .optimize(&mut self.problem, &BaParams::local())
            .is_ok()
        {
            apply_local_ba(&mut lock(map), &job, &self.problem, self.ba.inliers());
            step.local_ba = true;
        }
    }

    /// Builds the visual-inertial window of `k` (map locked); its start time when built,
    /// else why not in `step`.
    fn prepare_vi(
        &mut self,
        m: &ClientMap,
        k: KfId,
        step: &mut LocalMappingStep,
    ) -> Option<Instant> {
        let t0 = Instant::now();
        match prepare_vi_window(m, k, &self.params.vi, &mut self.vi_window, &mut self.vi_job) {
            Ok(()) => Some(t0),
            Err(ViSkip::NotInertial) => None,
            Err(why) => {
                step.vi_window = ViWindowRun::Skipped(why);
                None
            }
        }
    }

    /// Solves the prepared window (map unlocked) and writes it back (locked); a failure
    /// (or a non-finite state) writes nothing.
    fn solve_vi(&mut self, map: &Mutex<ClientMap>, t0: Instant, step: &mut LocalMappingStep) {
        let w = &mut self.vi_window;
        let report = self.vi.optimize(w, &self.params.vi.solver);
        let finite = w.keyframes.iter().all(|k| {
            let s = &k.state;
            s.p.iter()
                .chain(s.v.iter())
                .chain(s.biases.gyro.iter())
                .chain(s.biases.accel.iter())
                .all(|x| x.is_finite())
        }) && w.points_w.iter().all(|p| p.iter().all(|x| x.is_finite()));
        let Some(report) = report.ok().filter(|_| finite) else {
            step.vi_window = ViWindowRun::Failed;
            return;
        };
        let outliers = apply_vi_window(&mut lock(map), &mut self.vi_job, w);
        step.vi_window = ViWindowRun::Solved {
            keyframes: w.keyframes.len(),
            points: w.points_w.len(),
            observations: w.observations.len(),
            iterations: report.iterations,
            outliers,
            ms: t0.elapsed().as_secs_f32() * 1e3,
        };
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
    /// Totals of the steps run so far.
    fn stats(&self) -> LocalMappingStats;
}
