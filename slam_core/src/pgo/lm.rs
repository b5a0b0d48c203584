//! Levenberg-Marquardt on a pose graph with relative-pose ("between") factors, generic over
//! the pose group (SE(3) with 6 or Sim(3) with 7 degrees of freedom), following GTSAM's
//! `LevenbergMarquardtOptimizer` defaults: damping `H + λI`, `λ₀ = 1e-5`, `λ ×10` after a
//! rejected step and `/10` after an accepted one, give up when `λ > 1e5`; stop after an
//! accepted step whose relative decrease is `≤ relTol` or absolute decrease `≤ absTol`, or
//! after `maxIter` linearisations.
//!
//! Cost (seed eq. 3.9 with the information of each constraint):
//! `E = ½ Σ_k r_kᵀ Ω_k r_k`, `r_k = Log(Z_ij⁻¹ X_i⁻¹ X_j)`; optionally a prior
//! `½ Log(P⁻¹ X_p)ᵀ Ω_p Log(P⁻¹ X_p)` (GTSAM's `PriorFactor`). Vertices are perturbed on
//! the right, `X ← X Exp(δ)`; Jacobians `∂r/∂δ_j = Jr(r)⁻¹`,
//! `∂r/∂δ_i = -Jr(r)⁻¹ Ad(X_j⁻¹ X_i)`. A subset of the tangent coordinates can be optimised
//! while the others stay fixed (stepwise Sim(3) step 2: translation and scale only).
//! Tangent orders and Jacobians are those of [`crate::lie`] (rotation first).

use nalgebra::{Isometry3, SMatrix, SVector};

use super::graph::{Edge, GraphPose};
use crate::lie::{se3_adjoint, se3_exp, se3_jr_inv, se3_log, sim3_jr_inv, Sim3};
use crate::optim::block_sparse::{BlockSparseSystem, Factorization};
use crate::CoreError;

/// Stopping and damping parameters (defaults = GTSAM's `LevenbergMarquardtParams()`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LmParams {
    /// Largest number of linearisations (outer iterations).
    pub max_iterations: usize,
    /// Stop when `(E_old - E_new) / E_old <= rel_tol`.
    pub rel_tol: f64,
    /// Stop when `E_old - E_new <= abs_tol`.
    pub abs_tol: f64,
    /// Initial damping `λ₀`.
    pub lambda_initial: f64,
    /// Factor by which `λ` grows after a rejected step and shrinks after an accepted one.
    pub lambda_factor: f64,
    /// Give up when `λ` exceeds this.
    pub lambda_upper: f64,
    /// A step is accepted when `actual / predicted` decrease exceeds this.
    pub min_model_fidelity: f64,
}

impl Default for LmParams {
    fn default() -> Self {
        Self {
            max_iterations: 100,
            rel_tol: 1e-5,
            abs_tol: 1e-5,
            lambda_initial: 1e-5,
            lambda_factor: 10.0,
            lambda_upper: 1e5,
            min_model_fidelity: 1e-3,
        }
    }
}

/// What one LM run did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LmSummary {
    /// Linearisations (GTSAM's `iterations()`).
    pub iterations: usize,
    /// Cost at the start.
    pub initial_cost: f64,
    /// Cost at the end.
    pub final_cost: f64,
    /// `true` when a tolerance was met (not stopped by `max_iterations` or `λ`).
    pub converged: bool,
}

/// A group element usable as a graph vertex by the LM, with tangent dimension `D`.
pub trait LiePose<const D: usize>: GraphPose<Info = SMatrix<f64, D, D>> {
    /// Group composition `self ∘ other`.
    fn compose(&self, other: &Self) -> Self;
    /// Group inverse.
    fn inv(&self) -> Self;
    /// Logarithm.
    fn log(&self) -> SVector<f64, D>;
    /// `self ∘ Exp(d)`.
    fn retract(&self, d: &SVector<f64, D>) -> Self;
    /// Inverse right Jacobian at tangent `r`.
    fn jr_inv(r: &SVector<f64, D>) -> SMatrix<f64, D, D>;
    /// Adjoint matrix.
    fn adjoint(&self) -> SMatrix<f64, D, D>;
}

impl LiePose<6> for Isometry3<f64> {
    fn compose(&self, other: &Self) -> Self {
        self * other
    }
    fn inv(&self) -> Self {
        self.inverse()
    }
    fn log(&self) -> SVector<f64, 6> {
        se3_log(self)
    }
    fn retract(&self, d: &SVector<f64, 6>) -> Self {
        self * se3_exp(d)
    }
    fn jr_inv(r: &SVector<f64, 6>) -> SMatrix<f64, 6, 6> {
        se3_jr_inv(r)
    }
    fn adjoint(&self) -> SMatrix<f64, 6, 6> {
        se3_adjoint(self)
    }
}

impl LiePose<7> for Sim3 {
    fn compose(&self, other: &Self) -> Self {
        Sim3::compose(self, other)
    }
    fn inv(&self) -> Self {
        self.inverse()
    }
    fn log(&self) -> SVector<f64, 7> {
        Sim3::log(self)
    }
    fn retract(&self, d: &SVector<f64, 7>) -> Self {
        Sim3::compose(self, &Sim3::exp(d))
    }
    fn jr_inv(r: &SVector<f64, 7>) -> SMatrix<f64, 7, 7> {
        sim3_jr_inv(r)
    }
    fn adjoint(&self) -> SMatrix<f64, 7, 7> {
        Sim3::adjoint(self)
    }
}

/// A unary factor `½ Log(P⁻¹ X_v)ᵀ Ω Log(P⁻¹ X_v)` on vertex `vertex`.
#[derive(Debug, Clone, Copy)]
pub struct Prior<P: GraphPose> {
    /// Vertex index.
    pub vertex: usize,
    /// Prior mean `P`.
    pub mean: P,
    /// Information `Ω`.
    pub info: P::Info,
}

/// `E = ½ Σ rᵀΩr` of the edges (+ the prior) at `poses`.
pub fn graph_cost<P: LiePose<D>, const D: usize>(
    poses: &[P],
    edges: &[Edge<P>],
    prior: Option<&Prior<P>>,
) -> f64 {
    let mut e = 0.0;
    for ed in edges {
        let d = ed
            .measurement
            .inv()
            .compose(&poses[ed.i].inv().compose(&poses[ed.j]));
        let r = d.log();
        e += 0.5 * r.dot(&(ed.info * r));
    }
    if let Some(p) = prior {
        let r = p.mean.inv().compose(&poses[p.vertex]).log();
        e += 0.5 * r.dot(&(p.info * r));
    }
    e
}

/// The variable index of each vertex (`None` for a vertex held by `fixed`) and the number
/// of variables; errors (named `what`) when every vertex is fixed.
pub(crate) fn free_vertices(
    fixed: &[bool],
    what: &str,
) -> Result<(Vec<Option<usize>>, usize), CoreError> {
    let mut var = vec![None; fixed.len()];
    let mut nv = 0;
    for (slot, f) in var.iter_mut().zip(fixed) {
        if !f {
            *slot = Some(nv);
            nv += 1;
        }
    }
    if nv == 0 {
        return Err(CoreError::NotEnoughData(format!(
            "{what}: every vertex is fixed"
        )));
    }
    Ok((var, nv))
}

/// Per-edge precomputation: `Z⁻¹`, variable indices and block positions.
#[derive(Debug, Clone, Copy)]
struct EdgeSlot<P> {
    z_inv: P,
    vi: Option<usize>,
    vj: Option<usize>,
    kii: usize,
    kjj: usize,
    /// Block `(min(vi,vj), max(vi,vj))` and whether it stores `H_ijᵀ` (`vi > vj`).
    kij: usize,
    ij_transposed: bool,
}

/// A pose-graph least-squares problem ready for [`levenberg_marquardt`].
pub struct BetweenProblem<'a, P: LiePose<D>, const D: usize> {
    edges: &'a [Edge<P>],
    slots: Vec<EdgeSlot<P>>,
    prior: Option<Prior<P>>,
    /// Vertex index → variable index (`None` = fixed).
    var: Vec<Option<usize>>,
    /// Optimised tangent coordinates (all `D`, or a subset).
    active: Vec<usize>,
    /// Current poses (all vertices).
    pub poses: Vec<P>,
    backup: Vec<P>,
    /// Scratch for one block (`m*m`) and one rhs segment.
    buf: Vec<f64>,
    vbuf: Vec<f64>,
}

impl<'a, P: LiePose<D>, const D: usize> BetweenProblem<'a, P, D> {
    /// Builds the problem and sets up `sys` (pattern, symbolic factorisation).
    /// `fixed[v]` marks vertices held constant; `active` lists optimised tangent indices.
    pub(crate) fn new(
        poses: Vec<P>,
        edges: &'a [Edge<P>],
        fixed: &[bool],
        prior: Option<Prior<P>>,
        active: &[usize],
        sys: &mut BlockSparseSystem,
    ) -> Result<Self, CoreError> {
        let n = poses.len();
        if fixed.len() != n || active.is_empty() || active.iter().any(|&a| a >= D) {
            return Err(CoreError::InvalidArgument(
                "pgo: bad fixed mask or active coordinates".into(),
            ));
        }
        let (var, nv) = free_vertices(fixed, "pgo")?;
        let mut pairs: Vec<(u32, u32)> = Vec::with_capacity(edges.len() + nv);
        for e in edges {
            if e.i >= n || e.j >= n {
                return Err(CoreError::InvalidArgument(
                    "pgo: edge vertex out of range".into(),
                ));
            }
            if let (Some(a), Some(b)) = (var[e.i], var[e.j]) {
                if a != b {
                    pairs.push((a as u32, b as u32));
                }
            }
        }
        let m = active.len();
        sys.setup_uniform(nv, m, 1, &mut pairs, Factorization::SparseBlockAmd)?;
        let mut slots = Vec::with_capacity(edges.len());
        for e in edges {
            let (vi, vj) = (var[e.i], var[e.j]);
            let kii = vi.and_then(|a| sys.block_index(a, a)).unwrap_or(0);
            let kjj = vj.and_then(|b| sys.block_index(b, b)).unwrap_or(0);
            let (kij, ij_transposed) = match (vi, vj) {
                (Some(a), Some(b)) => (sys.block_index(a, b).unwrap_or(0), a > b),
                _ => (0, false),
            };
            slots.push(EdgeSlot {
                z_inv: e.measurement.inv(),
                vi,
                vj,
                kii,
                kjj,
                kij,
                ij_transposed,
            });
        }
        if let Some(p) = &prior {
            if p.vertex >= n {
                return Err(CoreError::InvalidArgument(
                    "pgo: prior vertex out of range".into(),
                ));
            }
        }
        Ok(Self {
            edges,
            slots,
            prior,
            var,
            active: active.to_vec(),
            backup: poses.clone(),
            poses,
            buf: vec![0.0; m * m],
            vbuf: vec![0.0; m],
        })
    }

    fn add_h(
        &mut self,
        sys: &mut BlockSparseSystem,
        k: usize,
        h: &SMatrix<f64, D, D>,
        transpose: bool,
    ) {
        let m = self.active.len();
        for (b, &cb) in self.active.iter().enumerate() {
            for (a, &ca) in self.active.iter().enumerate() {
                self.buf[a + m * b] = h[(ca, cb)];
            }
        }
        sys.add_block(k, &self.buf, transpose);
    }

    fn add_g(&mut self, sys: &mut BlockSparseSystem, v: usize, g: &SVector<f64, D>) {
        for (a, &ca) in self.active.iter().enumerate() {
            self.vbuf[a] = -g[ca];
        }
        sys.add_rhs(v, 0, &self.vbuf);
    }
}

/// What [`levenberg_marquardt`] needs from a problem.
pub(crate) trait LmProblem {
    /// Cost at the current state.
    fn cost(&self) -> f64;
    /// Fills `sys` (already cleared) with `H = JᵀΩJ` and `rhs = -JᵀΩr` at the current state.
    fn linearize(&mut self, sys: &mut BlockSparseSystem);
    /// Current state ← last committed state ⊕ `delta`.
    fn retract(&mut self, delta: &[f64]);
    /// Keeps the current state.
    fn commit(&mut self);
    /// Returns to the last committed state.
    fn rollback(&mut self);
}

impl<P: LiePose<D>, const D: usize> LmProblem for BetweenProblem<'_, P, D> {
    fn cost(&self) -> f64 {
        graph_cost(&self.poses, self.edges, self.prior.as_ref())
    }

    fn linearize(&mut self, sys: &mut BlockSparseSystem) {
        for k in 0..self.slots.len() {
            let s = self.slots[k];
            let e = &self.edges[k];
            let (xi, xj) = (self.poses[e.i], self.poses[e.j]);
            let r = s.z_inv.compose(&xi.inv().compose(&xj)).log();
            let jinv = P::jr_inv(&r);
            let jj = jinv;
            let ji = -(jinv * xj.inv().compose(&xi).adjoint());
            let omega = e.info;
            let wr = omega * r;
            if let Some(a) = s.vi {
                let ji_t_omega = ji.transpose() * omega;
                self.add_h(sys, s.kii, &(ji_t_omega * ji), false);
                self.add_g(sys, a, &(ji.transpose() * wr));
                if s.vj.is_some() {
                    self.add_h(sys, s.kij, &(ji_t_omega * jj), s.ij_transposed);
                }
            }
            if let Some(b) = s.vj {
                self.add_h(sys, s.kjj, &(jj.transpose() * omega * jj), false);
                self.add_g(sys, b, &(jj.transpose() * wr));
            }
        }
        if let Some(p) = self.prior {
            if let Some(v) = self.var[p.vertex] {
                let r = p.mean.inv().compose(&self.poses[p.vertex]).log();
                let j = P::jr_inv(&r);
                let jt_omega = j.transpose() * p.info;
                let k = sys.block_index(v, v).unwrap_or(0);
                self.add_h(sys, k, &(jt_omega * j), false);
                self.add_g(sys, v, &(jt_omega * r));
            }
        }
    }

    fn retract(&mut self, delta: &[f64]) {
        let m = self.active.len();
        for (v, var) in self.var.iter().enumerate() {
            if let Some(x) = var {
                let mut d = SVector::<f64, D>::zeros();
                for (a, &ca) in self.active.iter().enumerate() {
                    d[ca] = delta[x * m + a];
                }
                self.poses[v] = self.backup[v].retract(&d);
            }
        }
    }

    fn commit(&mut self) {
        self.backup.copy_from_slice(&self.poses);
    }

    fn rollback(&mut self) {
        self.poses.copy_from_slice(&self.backup);
    }
}

/// GTSAM-style Levenberg-Marquardt (see the module docs). `sys` must have been set up for
/// `problem`. Allocates nothing per iteration beyond what `problem` does.
pub(crate) fn levenberg_marquardt(
    problem: &mut impl LmProblem,
    sys: &mut BlockSparseSystem,
    params: &LmParams,
) -> Result<LmSummary, CoreError> {
    let initial_cost = problem.cost();
    if !initial_cost.is_finite() {
        return Err(CoreError::Degenerate(
            "pgo: initial cost is not finite".into(),
        ));
    }
    let mut cost = initial_cost;
    let mut lambda = params.lambda_initial;
    let mut iterations = 0;
    let mut converged = cost <= 0.0;
    while !converged && iterations < params.max_iterations {
        sys.clear();
        problem.linearize(sys);
        iterations += 1;
        let mut accepted = None;
        loop {
            if lambda > params.lambda_upper {
                break;
            }
            if sys.solve_shifted(Some(lambda)).is_err() {
                lambda *= params.lambda_factor;
                continue;
            }
            // Predicted decrease of the undamped model: ½(δᵀb + λ|δ|²) with (H+λI)δ = b.
            let (mut db, mut dd) = (0.0, 0.0);
            for (x, b) in sys.x().iter().zip(sys.rhs()) {
                db += x * b;
                dd += x * x;
            }
            let predicted = 0.5 * (db + lambda * dd);
            problem.retract(sys.x());
            let new_cost = problem.cost();
            let actual = cost - new_cost;
            if new_cost.is_finite()
                && actual >= 0.0
                && (predicted <= 0.0 || actual / predicted > params.min_model_fidelity)
            {
                problem.commit();
                lambda = (lambda / params.lambda_factor).max(0.0);
                accepted = Some(new_cost);
                break;
            }
            problem.rollback();
            lambda *= params.lambda_factor;
        }
        let Some(new_cost) = accepted else {
            break;
        };
        let dec = cost - new_cost;
        cost = new_cost;
        if dec <= params.abs_tol || dec <= params.rel_tol * (cost + dec) || cost <= 0.0 {
            converged = true;
        }
    }
    Ok(LmSummary {
        iterations,
        initial_cost,
        final_cost: cost,
        converged,
    })
}
