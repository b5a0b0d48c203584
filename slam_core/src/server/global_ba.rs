//! The global BA of a server map after a loop correction, a merge or a revisit (seed §3.4.2;
//! §5.4, Fig. 5.6 "then VI global BA"), in three steps so that the solve can run on a
//! thread of its own while the handlers go on (the seed runs it on its own thread too):
//!
//! 1. [`GlobalBa::prepare`] copies the problem out of the map (cheap beside the solve): for
//!    a metric, gravity-aligned map the visual-inertial one ([`prepare_global_vi`]: every
//!    keyframe, one IMU chain per client), else, or when no IMU chain can be built, the
//!    visual one (every keyframe free but the oldest, every point).
//! 2. [`GlobalBa::solve`] needs nothing but the problem.
//! 3. [`GlobalBa::apply`] writes the solution back into the map as it is then, and carries
//!    the correction over to what entered the map meanwhile (as ORB-SLAM's loop closer does
//!    after its global BA, Mur-Artal & Tardós 2017): a keyframe inserted after step 1 moves
//!    with the newest problem keyframe of its client before it, `D = T_wc,after T_cw,before`
//!    (world before → world after; its velocity turns with `D`), a point created meanwhile
//!    with the keyframe of its first observation. Keyframes and points that left the map
//!    meanwhile are skipped.
//!
//! Whoever runs it must not apply a solution across a correction of the map (a merge or a
//! pose graph moved everything the problem holds): the caller drops such a stale solution
//! and prepares a new problem.
use std::collections::{BTreeMap, HashMap, HashSet};

use nalgebra::Isometry3;

use super::server_map::ServerMap;
use super::types::MapId;
use crate::ids::KeyframeId;
use crate::imu::window::{ViParams, ViSolver, ViWindow};
use crate::optim::ba::{BaParams, BaProblem, BundleAdjuster};
use crate::vo::local_mapping::{apply_local_ba, prepare_global_ba, LocalBaJob};
use crate::vo::vi_window::{
    apply_global_vi, prepare_global_vi, ViMappingMode, ViMappingParams, ViWindowJob,
};
use crate::vo::{KfId, PointId};

/// The problem of a global BA (module docs, step 1).
#[derive(Debug)]
enum Problem {
    /// Reprojections only (a visual map, or no IMU chain).
    Visual {
        problem: BaProblem,
        job: LocalBaJob,
        inliers: Vec<bool>,
    },
    /// Reprojections and IMU factors (a metric, gravity-aligned map).
    Inertial { w: Box<ViWindow>, job: ViWindowJob },
}

/// A global BA of one server map, prepared, solved and applied in turn (module docs).
#[derive(Debug)]
pub struct GlobalBa {
    /// The map it is for.
    pub map: MapId,
    problem: Problem,
    /// Every problem keyframe's `T_cw` when the problem was built.
    before: BTreeMap<KfId, Isometry3<f64>>,
    solved: bool,
}

/// What [`GlobalBa::apply`] did.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct GlobalBaApplied {
    /// Problem keyframes written back.
    pub keyframes: usize,
    /// Keyframes that entered the map after the problem was built, moved with it.
    pub keyframes_propagated: usize,
    /// Points created after the problem was built, moved with it.
    pub points_propagated: usize,
    /// Observations removed as outliers.
    pub observations_removed: usize,
    /// Per client with keyframes in the map, the correction `D` of its newest keyframe
    /// (world before → world after; a handler's pending pose follows it).
    pub client_deltas: BTreeMap<u32, Isometry3<f64>>,
}

impl GlobalBa {
    /// The problem of map `map` (module docs, step 1): visual-inertial when the map is
    /// metric and gravity-aligned and `vi` allows it. `None` when there is too little to
    /// adjust.
    pub fn prepare(map: &ServerMap, vi: &ViMappingParams) -> Option<Self> {
        let mut problem = None;
        if map.frame.is_inertial() && vi.mode != ViMappingMode::Off {
            let (mut w, mut job) = (Box::new(ViWindow::empty()), ViWindowJob::default());
            if prepare_global_vi(&map.map, &mut w, &mut job).is_ok() {
                problem = Some(Problem::Inertial { w, job });
            }
        }
        let problem = match problem {
            Some(p) => p,
            None => {
                let mut problem = BaProblem::new();
                let job = prepare_global_ba(&map.map, &mut problem)?;
                Problem::Visual {
                    problem,
                    job,
                    inliers: Vec::new(),
                }
            }
        };
        let before = map
            .map
            .keyframes
            .iter()
            .map(|(k, kf)| (*k, kf.t_cw))
            .collect();
        Some(Self {
            map: map.id,
            problem,
            before,
            solved: false,
        })
    }

    /// Whether the problem is the visual-inertial one.
    pub fn is_inertial(&self) -> bool {
        matches!(self.problem, Problem::Inertial { .. })
    }

    /// Keyframes in the problem.
    pub fn keyframes(&self) -> usize {
        self.before.len()
    }

    /// Solves the problem (module docs, step 2; `params` for the visual-inertial one, the
    /// visual one takes the local BA's settings). Returns whether it was solved with a
    /// finite solution.
    pub fn solve(&mut self, params: &ViParams) -> bool {
        self.solved = match &mut self.problem {
            Problem::Visual {
                problem, inliers, ..
            } => {
                let mut ba = BundleAdjuster::new();
                let ok = ba.optimize(problem, &BaParams::local()).is_ok();
                inliers.clear();
                inliers.extend_from_slice(ba.inliers());
                ok
            }
            Problem::Inertial { w, .. } => {
                ViSolver::new().optimize(w, params).is_ok() && w.is_finite()
            }
        };
        self.solved
    }

    /// Writes a solved problem back into `map` and carries the correction over to what
    /// entered it meanwhile (module docs, step 3). `None` when it was not solved or `map`
    /// is another map.
    pub fn apply(mut self, map: &mut ServerMap) -> Option<GlobalBaApplied> {
        if !self.solved || map.id != self.map {
            return None;
        }
        let mut out = GlobalBaApplied::default();
        let in_problem: HashSet<PointId> = match &mut self.problem {
            Problem::Visual {
                problem,
                job,
                inliers,
            } => {
                apply_local_ba(&mut map.map, job, problem, inliers);
                out.observations_removed = inliers.iter().filter(|i| !**i).count();
                job.pt_ids.iter().copied().collect()
            }
            Problem::Inertial { w, job } => {
                out.observations_removed = apply_global_vi(&mut map.map, job, w);
                job.pt_ids.iter().copied().collect()
            }
        };
        let deltas = self.propagate(map, &in_problem, &mut out);
        for (id, d) in deltas.iter().rev() {
            let c = KeyframeId::from_raw(*id).client().raw();
            out.client_deltas.entry(c).or_insert(*d);
        }
        out.keyframes = self.before.len();
        Some(out)
    }

    /// The correction `D` of every keyframe of the map: the problem keyframes' own, and for
    /// those that entered meanwhile their client's newest problem keyframe before them (they
    /// are moved by it); points created meanwhile move with their first observation's
    /// keyframe.
    fn propagate(
        &self,
        map: &mut ServerMap,
        in_problem: &HashSet<PointId>,
        out: &mut GlobalBaApplied,
    ) -> BTreeMap<KfId, Isometry3<f64>> {
        let mut deltas = BTreeMap::new();
        for (id, kf) in map.map.keyframes.iter_mut() {
            if let Some(t_cw_before) = self.before.get(id) {
                deltas.insert(*id, kf.t_cw.inverse() * t_cw_before);
                continue;
            }
            let client = KeyframeId::from_raw(*id).client();
            // The nearest keyframe before it still in the map (a problem keyframe, or one
            // that entered meanwhile and already carries its predecessor's correction).
            let reference = deltas
                .range(..*id)
                .next_back()
                .filter(|(r, _)| KeyframeId::from_raw(**r).client() == client)
                .map(|(_, d)| *d);
            let Some(d) = reference else {
                continue;
            };
            kf.t_cw *= d.inverse();
            if let Some(i) = kf.inertial.as_mut() {
                i.v_wb = d.rotation * i.v_wb;
            }
            deltas.insert(*id, d);
            out.keyframes_propagated += 1;
        }
        let moved: HashMap<PointId, Isometry3<f64>> = map
            .map
            .points
            .iter()
            .filter(|(p, _)| !in_problem.contains(p))
            .filter_map(|(p, mp)| {
                let (k, _) = mp.observations.first()?;
                deltas.get(k).map(|d| (*p, *d))
            })
            .collect();
        for (p, d) in &moved {
            if let Some(mp) = map.map.points.get_mut(p) {
                mp.p_w = d.transform_point(&mp.p_w.into()).coords;
            }
        }
        out.points_propagated = moved.len();
        deltas
    }
}
