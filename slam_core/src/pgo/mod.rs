//! Pose graph optimisation (seed §3.4.3, eq. 3.9-3.13): SE(3) graphs as GTSAM optimises
//! them, and Sim(3) graphs of monocular keyframes with scale drift, directly or stepwise.
//!
//! **Poses.** Vertices hold `T_wk` / `S_wk` with `x_w = s R x_k + t` ([`Sim3`]). An edge
//! measures `Z_ij ≈ X_i⁻¹ X_j`; its residual is `r = Log(Z_ij⁻¹ X_i⁻¹ X_j)` (the constraint
//! of eq. 3.9 written for world-from-keyframe poses) and the cost is
//! `E = ½ Σ rᵀ Ω r` — exactly GTSAM's `graph.error()`: for SE(3), `r` is ordered
//! `(rotation, translation)` with the translation part `V(θ)⁻¹ t` and `Ω` is the file's
//! information with its `(t, R)` blocks permuted; for Sim(3), `r = [ω, ρ, σ]` and `Ω` is
//! the file's 7x7 information (stored `[ρ, ω, σ]`) with its first two blocks permuted.
//! Tangent orders, `Log`, `Exp`, adjoints and Jacobians are those of [`crate::lie`].
//!
//! **Gauge.** `FIX` vertices are held constant. An SE(3) graph without `FIX` gets GTSAM's
//! prior on its smallest-id vertex (at the vertex's input value, information
//! `diag(1e6, 1e6, 1e6, 1e4, 1e4, 1e4)`), included in the reported `E` (it is ~0 at the
//! optimum); a Sim(3) graph without `FIX` holds its smallest-id vertex fixed.
//!
//! **Methods** ([`PgoMethod`], Sim(3) graphs):
//! - `Direct`: Levenberg-Marquardt on all 7 degrees of freedom per vertex from the input.
//! - `Stepwise` (eq. 3.10-3.12): step 1 solves all scales by linear least squares
//!   `s̃_ij s_i - s_j = n₁` (sparse QR, [`solve_scales`]); step 2 optimises translations and
//!   scales with rotations fixed — we minimise the same Sim(3) cost `E` restricted to the
//!   `[ρ, σ]` coordinates instead of the seed's eq. 3.12 residual form.
//! - `StepwiseDirect`: `Stepwise`, then `Direct` from its result (the seed's advice).
//!
//! SE(3) graphs are optimised by LM on SE(3) ([`optimize_se3`]), optionally after a
//! chordal initialisation ([`PgoInit::Chordal`]). All normal equations are solved by faer's
//! sparse Cholesky, symbolic analysis once per problem, numeric factorisation per step.
//!
//! After optimisation, map points follow the keyframe that first observed them
//! ([`correct_point`], eq. 3.13).
//!
//! ```
//! use nalgebra::{Isometry3, Matrix6, Translation3, UnitQuaternion};
//! use slam_core::pgo::{optimize_se3, Edge, PgoParams, Se3Graph, Vertex};
//!
//! let mut g = Se3Graph::default();
//! for k in 0..3u64 {
//!     let t = Translation3::new(k as f64 * 1.1, 0.0, 0.0); // odometry says 1.0 per step
//!     g.vertices.push(Vertex { id: k, pose: Isometry3::from_parts(t, UnitQuaternion::identity()) });
//! }
//! let z = Isometry3::translation(1.0, 0.0, 0.0);
//! for (i, j) in [(0, 1), (1, 2)] {
//!     g.edges.push(Edge { i, j, measurement: z, info: Matrix6::identity() });
//! }
//! let report = optimize_se3(&mut g, &PgoParams::default()).unwrap();
//! assert!(report.final_cost < 1e-12);
//! assert!((g.vertices[2].pose.translation.x - 2.0).abs() < 1e-6);
//! ```

mod chordal;
mod four_dof;
mod g2o;
mod graph;
mod information;
mod lm;
mod loop_graph;
mod stepwise;

use std::time::Instant;

use nalgebra::{Isometry3, Matrix6, Vector3, Vector6};

pub use chordal::{chordal_init, project_to_so3};
pub use four_dof::{optimize_four_dof, yaw, FourDofEdge};
pub use g2o::{parse_g2o, swap_rt_blocks, write_g2o_se3, write_g2o_sim3};
pub use graph::{AnyGraph, Edge, GraphPose, PoseGraph, Se3Graph, Sim3Graph, Vertex};
pub use information::gtsam_effective_information;
pub use lm::{graph_cost, LiePose, LmParams, LmSummary, Prior};
pub use loop_graph::{
    correct_loop, correct_loop_four_dof, GraphKeyframe, LoopConstraint, LoopCorrection,
    LoopGraphParams,
};
pub use stepwise::{solve_scales, STEP2_ACTIVE};

use lm::{levenberg_marquardt, BetweenProblem};

use crate::lie::Sim3;
use crate::optim::block_sparse::BlockSparseSystem;
use crate::CoreError;

/// How a Sim(3) graph is optimised.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PgoMethod {
    /// Scales by linear least squares, then scales + translations (seed eq. 3.10-3.12).
    Stepwise,
    /// Levenberg-Marquardt on all Sim(3) parameters.
    Direct,
    /// `Stepwise`, then `Direct` from its result.
    StepwiseDirect,
}

impl std::str::FromStr for PgoMethod {
    type Err = String;

    /// `stepwise`, `direct` or `stepwise+direct` (the names of `shoal pgo --method`).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "stepwise" => Ok(PgoMethod::Stepwise),
            "direct" => Ok(PgoMethod::Direct),
            "stepwise+direct" => Ok(PgoMethod::StepwiseDirect),
            _ => Err(format!(
                "unknown method {s:?}: stepwise, direct or stepwise+direct"
            )),
        }
    }
}

/// Starting point of an SE(3) optimisation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PgoInit {
    /// The input vertex values (usually chained odometry).
    #[default]
    Odometry,
    /// Chordal relaxation of the rotations, then linear translations ([`chordal_init`]).
    Chordal,
}

/// Parameters of [`optimize_se3`] / [`optimize_sim3`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PgoParams {
    /// Levenberg-Marquardt settings (GTSAM defaults), used by every LM stage.
    pub lm: LmParams,
    /// Initialisation of SE(3) graphs (ignored for Sim(3)).
    pub init: PgoInit,
}

/// One stage of an optimisation (chordal init, scales, LM, ...).
#[derive(Debug, Clone, PartialEq)]
pub struct StageReport {
    /// Stage name: `chordal`, `scales`, `lm_se3`, `lm_sim3_scale_translation`, `lm_sim3`.
    pub name: &'static str,
    /// LM linearisations (0 for linear stages).
    pub iterations: usize,
    /// Cost before the stage.
    pub initial_cost: f64,
    /// Cost after the stage.
    pub final_cost: f64,
    /// Wall time of the stage, s.
    pub time_s: f64,
    /// Whether an LM stage met a tolerance (linear stages: `true`).
    pub converged: bool,
}

/// Result of [`optimize_se3`] / [`optimize_sim3`].
#[derive(Debug, Clone, PartialEq)]
pub struct PgoReport {
    /// LM linearisations over all stages.
    pub iterations: usize,
    /// Cost `E` of the input poses.
    pub initial_cost: f64,
    /// Cost `E` at the end.
    pub final_cost: f64,
    /// Wall time of all stages (initialisation included, parsing excluded), s.
    pub solve_time_s: f64,
    /// Per-stage details.
    pub stages: Vec<StageReport>,
    /// Edges whose information was not positive definite and was replaced by GTSAM's
    /// effective `RᵀR` ([`gtsam_effective_information`]) for the optimisation.
    pub repaired_information: usize,
}

/// GTSAM's prior of `gtsam_baseline.py` on the smallest-id vertex at its current value:
/// information `diag(1e6, 1e6, 1e6, 1e4, 1e4, 1e4)` in `(R, t)` order.
pub fn gtsam_prior(graph: &Se3Graph) -> Option<Prior<Isometry3<f64>>> {
    let v = graph.first_vertex()?;
    Some(Prior {
        vertex: v,
        mean: graph.vertices[v].pose,
        info: Matrix6::from_diagonal(&Vector6::new(1e6, 1e6, 1e6, 1e4, 1e4, 1e4)),
    })
}

/// `E` of an SE(3) graph (with `prior` if given).
pub fn se3_cost(graph: &Se3Graph, prior: Option<&Prior<Isometry3<f64>>>) -> f64 {
    graph_cost(&graph.poses(), &graph.edges, prior)
}

/// `E` of a Sim(3) graph.
pub fn sim3_cost(graph: &Sim3Graph) -> f64 {
    graph_cost::<Sim3, 7>(&graph.poses(), &graph.edges, None)
}

fn fixed_mask<P: GraphPose>(graph: &PoseGraph<P>) -> Vec<bool> {
    let mut m = vec![false; graph.vertices.len()];
    for &f in &graph.fixed {
        if let Some(x) = m.get_mut(f) {
            *x = true;
        }
    }
    m
}

/// Runs one LM stage over the active coordinates and writes the poses back.
fn lm_stage<P: LiePose<D>, const D: usize>(
    graph: &mut PoseGraph<P>,
    fixed: &[bool],
    prior: Option<Prior<P>>,
    active: &[usize],
    params: &LmParams,
    name: &'static str,
) -> Result<StageReport, CoreError> {
    let t0 = Instant::now();
    let mut sys = BlockSparseSystem::new("pgo");
    let poses = graph.poses();
    let (summary, poses) = {
        let mut problem = BetweenProblem::new(poses, &graph.edges, fixed, prior, active, &mut sys)?;
        let s = levenberg_marquardt(&mut problem, &mut sys, params)?;
        (s, problem.poses)
    };
    for (v, p) in graph.vertices.iter_mut().zip(poses) {
        v.pose = p;
    }
    Ok(StageReport {
        name,
        iterations: summary.iterations,
        initial_cost: summary.initial_cost,
        final_cost: summary.final_cost,
        time_s: t0.elapsed().as_secs_f64(),
        converged: summary.converged,
    })
}

fn finish(initial_cost: f64, stages: Vec<StageReport>, t0: Instant) -> PgoReport {
    PgoReport {
        repaired_information: 0,
        iterations: stages.iter().map(|s| s.iterations).sum(),
        initial_cost,
        final_cost: stages.last().map_or(initial_cost, |s| s.final_cost),
        solve_time_s: t0.elapsed().as_secs_f64(),
        stages,
    }
}

/// Optimises an SE(3) graph in place: optional chordal initialisation, then LM minimising
/// GTSAM's `E` (with GTSAM's prior when the graph has no `FIX`, see the module docs).
/// Edges with an information matrix that is not positive definite use GTSAM's effective
/// information instead ([`gtsam_effective_information`], counted in the report); the
/// caller's graph keeps its edges, only the poses change.
pub fn optimize_se3(graph: &mut Se3Graph, params: &PgoParams) -> Result<PgoReport, CoreError> {
    graph.validate()?;
    let (repaired, mut work) = repaired_copy(graph);
    let mut report = match work.as_mut() {
        Some(w) => optimize_se3_inner(w, params)?,
        None => optimize_se3_inner(graph, params)?,
    };
    if let Some(w) = work {
        for (v, p) in graph.vertices.iter_mut().zip(&w.vertices) {
            v.pose = p.pose;
        }
    }
    report.repaired_information = repaired;
    Ok(report)
}

/// A copy of `graph` with GTSAM's effective information on the edges whose information is
/// not positive definite (`None` when there are none), and their count.
fn repaired_copy<P: LiePose<D>, const D: usize>(
    graph: &PoseGraph<P>,
) -> (usize, Option<PoseGraph<P>>) {
    let mut work: Option<PoseGraph<P>> = None;
    let mut count = 0;
    for (k, e) in graph.edges.iter().enumerate() {
        if let Some(info) = gtsam_effective_information(&e.info) {
            count += 1;
            work.get_or_insert_with(|| graph.clone()).edges[k].info = info;
        }
    }
    (count, work)
}

fn optimize_se3_inner(graph: &mut Se3Graph, params: &PgoParams) -> Result<PgoReport, CoreError> {
    let t0 = Instant::now();
    let fixed = fixed_mask(graph);
    let prior = if graph.fixed.is_empty() {
        gtsam_prior(graph)
    } else {
        None
    };
    let initial_cost = se3_cost(graph, prior.as_ref());
    let mut stages = Vec::new();
    if params.init == PgoInit::Chordal {
        let t1 = Instant::now();
        let mut anchored = fixed.clone();
        if let Some(p) = &prior {
            anchored[p.vertex] = true;
        }
        chordal_init(graph, &anchored)?;
        stages.push(StageReport {
            name: "chordal",
            iterations: 0,
            initial_cost,
            final_cost: se3_cost(graph, prior.as_ref()),
            time_s: t1.elapsed().as_secs_f64(),
            converged: true,
        });
    }
    stages.push(lm_stage(
        graph,
        &fixed,
        prior,
        &[0, 1, 2, 3, 4, 5],
        &params.lm,
        "lm_se3",
    )?);
    Ok(finish(initial_cost, stages, t0))
}

/// Optimises a Sim(3) graph in place with `method` (see the module docs).
pub fn optimize_sim3(
    graph: &mut Sim3Graph,
    method: PgoMethod,
    params: &PgoParams,
) -> Result<PgoReport, CoreError> {
    graph.validate()?;
    let t0 = Instant::now();
    let mut fixed = fixed_mask(graph);
    if graph.fixed.is_empty() {
        if let Some(v) = graph.first_vertex() {
            fixed[v] = true;
        }
    }
    let initial_cost = sim3_cost(graph);
    let mut stages = Vec::new();
    if matches!(method, PgoMethod::Stepwise | PgoMethod::StepwiseDirect) {
        let t1 = Instant::now();
        solve_scales(graph, &fixed)?;
        stages.push(StageReport {
            name: "scales",
            iterations: 0,
            initial_cost,
            final_cost: sim3_cost(graph),
            time_s: t1.elapsed().as_secs_f64(),
            converged: true,
        });
        stages.push(lm_stage(
            graph,
            &fixed,
            None,
            &STEP2_ACTIVE,
            &params.lm,
            "lm_sim3_scale_translation",
        )?);
    }
    if matches!(method, PgoMethod::Direct | PgoMethod::StepwiseDirect) {
        stages.push(lm_stage(
            graph,
            &fixed,
            None,
            &[0, 1, 2, 3, 4, 5, 6],
            &params.lm,
            "lm_sim3",
        )?);
    }
    Ok(finish(initial_cost, stages, t0))
}

/// Eq. 3.13: moves a map point `p_w` with the correction of its reference keyframe (the one
/// that first observed it), from the keyframe's pose `old` before optimisation to `new`
/// after: `p_w ← S_new S_old⁻¹ p_w` (the point keeps its coordinates in the keyframe frame,
/// whose unit is rescaled by `s_new / s_old`). With `old` rigid and the seed's
/// world-to-camera notation this is `p ← [p + R_rgᵀ(t_r_old - t_r_new)] / s_r`.
pub fn correct_point(p_w: &Vector3<f64>, old: &Sim3, new: &Sim3) -> Vector3<f64> {
    new.transform_point(&old.inverse().transform_point(p_w))
}

/// [`correct_point`] for a rigid keyframe pose before optimisation.
pub fn correct_point_se3(p_w: &Vector3<f64>, old: &Isometry3<f64>, new: &Sim3) -> Vector3<f64> {
    correct_point(p_w, &Sim3::from_isometry(old, 1.0), new)
}

#[cfg(test)]
mod tests;
