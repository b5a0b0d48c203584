//! Normal equations of the bundle adjustment and their Schur complement on the points.
//!
//! With camera blocks `U_c = Σ w J_cᵀ J_c`, point blocks `V_p = Σ w J_pᵀ J_p`, coupling
//! blocks `W_i = w J_cᵀ J_p` (one per observation of a free point by a free keyframe) and
//! gradients `b = Σ w Jᵀ r`, one LM step solves
//! `[U* W; Wᵀ V*] [δc; δp] = -[b_c; b_p]` (`*`: damped diagonal). Eliminating the points:
//! `S δc = -b_c + Σ W V*⁻¹ b_p` with `S = U* - Σ_p W_p V*_p⁻¹ W_pᵀ` (the reduced camera
//! system, a [`BlockSparseSystem`] of 6x6 blocks); then `δp = V*⁻¹ (-b_p - Wᵀ δc)` per point.
//! `w = Ω ρ'(χ²)` is the IRLS weight of the robust kernel.

use nalgebra::{Isometry3, Matrix3, Matrix6, Matrix6x3, Vector3, Vector6};

use super::problem::{linearize_reprojection, BaProblem};
use crate::optim::block_sparse::{BlockSparseSystem, Factorization};
use crate::optim::robust::RobustKernel;
use crate::CoreError;

/// Marks a fixed keyframe or a fixed / unobserved point in the index maps.
pub(super) const NONE: u32 = u32::MAX;

/// Bounds of the LM damping diagonal (Ceres' defaults): `D_kk = clamp(H_kk)`.
const MIN_DIAG: f64 = 1e-6;
const MAX_DIAG: f64 = 1e32;

/// Preallocated normal equations (sizes fixed by [`NormalEquations::setup`]).
#[derive(Debug)]
pub(super) struct NormalEquations {
    /// Free-keyframe index of each keyframe ([`NONE`] when fixed).
    pub cam_of_kf: Vec<u32>,
    /// Free-point index of each point ([`NONE`] when fixed or unobserved).
    pub pt_of_point: Vec<u32>,
    /// Number of free points.
    pub n_pts: usize,
    /// Observations of each free point made by free keyframes (CSR).
    pt_start: Vec<usize>,
    pt_obs: Vec<u32>,
    /// Per observation: `W_i` (zero when inactive or behind the camera) and `Y_i = W_i V*⁻¹`.
    wblk: Vec<Matrix6x3<f64>>,
    yblk: Vec<Matrix6x3<f64>>,
    u: Vec<Matrix6<f64>>,
    bc: Vec<Vector6<f64>>,
    v: Vec<Matrix3<f64>>,
    bp: Vec<Vector3<f64>>,
    vinv: Vec<Matrix3<f64>>,
    /// Whether `V*_p` could be inverted in the current step.
    pt_ok: Vec<bool>,
    /// Camera increments (solution of the reduced system) and point increments.
    pub dc: Vec<Vector6<f64>>,
    pub dp: Vec<Vector3<f64>>,
    /// The reduced camera system (one 6x6 block row per free keyframe).
    rcs: BlockSparseSystem,
    /// Scratch for the block pattern and the CSR fill.
    pairs: Vec<(u32, u32)>,
    cursor: Vec<usize>,
    /// Reduced-system block of each visited observation pair (see `setup`).
    pair_blk: Vec<u32>,
}

impl Default for NormalEquations {
    fn default() -> Self {
        Self {
            cam_of_kf: Vec::new(),
            pt_of_point: Vec::new(),
            n_pts: 0,
            pt_start: Vec::new(),
            pt_obs: Vec::new(),
            wblk: Vec::new(),
            yblk: Vec::new(),
            u: Vec::new(),
            bc: Vec::new(),
            v: Vec::new(),
            bp: Vec::new(),
            vinv: Vec::new(),
            pt_ok: Vec::new(),
            dc: Vec::new(),
            dp: Vec::new(),
            rcs: BlockSparseSystem::new("ba"),
            pairs: Vec::new(),
            cursor: Vec::new(),
            pair_blk: Vec::new(),
        }
    }
}

#[inline]
fn damp(h: f64, lambda: f64) -> f64 {
    lambda * h.clamp(MIN_DIAG, MAX_DIAG)
}

impl NormalEquations {
    /// Index maps, per-point observation lists, block pattern and linear-solver workspace.
    /// `fixed_kf(k)` says whether keyframe `k` is held constant. Returns the number of free
    /// keyframes. Allocates only when the problem outgrows earlier ones.
    pub fn setup(
        &mut self,
        problem: &BaProblem,
        fixed_kf: impl Fn(usize) -> bool,
        sparse_above: usize,
        force: Option<bool>,
    ) -> Result<(usize, bool), CoreError> {
        let n_obs = problem.observations.len();
        self.cam_of_kf.clear();
        let mut n_cams = 0u32;
        for k in 0..problem.keyframes.len() {
            if fixed_kf(k) {
                self.cam_of_kf.push(NONE);
            } else {
                self.cam_of_kf.push(n_cams);
                n_cams += 1;
            }
        }
        // Free points: not fixed and observed at least once.
        self.pt_of_point.clear();
        self.pt_of_point.resize(problem.points.len(), NONE);
        for o in &problem.observations {
            if !problem.points[o.point].fixed {
                self.pt_of_point[o.point] = 0;
            }
        }
        let mut n_pts = 0u32;
        for p in self.pt_of_point.iter_mut() {
            if *p != NONE {
                *p = n_pts;
                n_pts += 1;
            }
        }
        self.n_pts = n_pts as usize;
        // CSR of coupled observations (free point, free keyframe) per free point.
        self.pt_start.clear();
        self.pt_start.resize(self.n_pts + 1, 0);
        for o in &problem.observations {
            let (c, p) = (self.cam_of_kf[o.keyframe], self.pt_of_point[o.point]);
            if c != NONE && p != NONE {
                self.pt_start[p as usize + 1] += 1;
            }
        }
        for p in 0..self.n_pts {
            self.pt_start[p + 1] += self.pt_start[p];
        }
        self.pt_obs.clear();
        self.pt_obs.resize(self.pt_start[self.n_pts], 0);
        self.pairs.clear();
        self.cursor.clear();
        self.cursor.extend_from_slice(&self.pt_start[..self.n_pts]);
        for (i, o) in problem.observations.iter().enumerate() {
            let (c, p) = (self.cam_of_kf[o.keyframe], self.pt_of_point[o.point]);
            if c != NONE && p != NONE {
                self.pt_obs[self.cursor[p as usize]] = i as u32;
                self.cursor[p as usize] += 1;
            }
        }
        for p in 0..self.n_pts {
            let list = &self.pt_obs[self.pt_start[p]..self.pt_start[p + 1]];
            for &a in list {
                for &b in list {
                    let ca = self.cam_of_kf[problem.observations[a as usize].keyframe];
                    let cb = self.cam_of_kf[problem.observations[b as usize].keyframe];
                    if ca < cb {
                        self.pairs.push((ca, cb));
                    }
                }
            }
            // Keep the scratch bounded on huge problems.
            if self.pairs.len() > (1 << 20) {
                self.pairs.sort_unstable();
                self.pairs.dedup();
            }
        }
        let n_c = n_cams as usize;
        let sparse = force.unwrap_or(n_c > sparse_above);
        let mut pairs = std::mem::take(&mut self.pairs);
        let factorization = if sparse {
            Factorization::SparseScalarAmd
        } else {
            Factorization::Dense
        };
        let res = self.rcs.setup_uniform(n_c, 6, 1, &mut pairs, factorization);
        self.pairs = pairs;
        res?;
        // Block index of every (a, b) pair of each point's coupled observations with
        // cam(a) <= cam(b), in the order `solve_step` visits them.
        self.pair_blk.clear();
        for p in 0..self.n_pts {
            let list = &self.pt_obs[self.pt_start[p]..self.pt_start[p + 1]];
            for &a in list {
                let ca = self.cam_of_kf[problem.observations[a as usize].keyframe];
                for &b in list {
                    let cb = self.cam_of_kf[problem.observations[b as usize].keyframe];
                    if ca <= cb {
                        let k =
                            self.rcs
                                .block_index(ca as usize, cb as usize)
                                .ok_or_else(|| {
                                    CoreError::Degenerate("ba: block pattern is incomplete".into())
                                })?;
                        self.pair_blk.push(k as u32);
                    }
                }
            }
        }
        let z63 = Matrix6x3::zeros();
        self.wblk.clear();
        self.wblk.resize(n_obs, z63);
        self.yblk.clear();
        self.yblk.resize(n_obs, z63);
        self.u.clear();
        self.u.resize(n_c, Matrix6::zeros());
        self.bc.clear();
        self.bc.resize(n_c, Vector6::zeros());
        self.dc.clear();
        self.dc.resize(n_c, Vector6::zeros());
        self.v.clear();
        self.v.resize(self.n_pts, Matrix3::zeros());
        self.vinv.clear();
        self.vinv.resize(self.n_pts, Matrix3::zeros());
        self.bp.clear();
        self.bp.resize(self.n_pts, Vector3::zeros());
        self.dp.clear();
        self.dp.resize(self.n_pts, Vector3::zeros());
        self.pt_ok.clear();
        self.pt_ok.resize(self.n_pts, false);
        Ok((n_c, sparse))
    }

    /// Accumulates `U, V, W, b` at the state (`poses`, `points`) over the `active`
    /// observations. Observations behind the camera contribute nothing.
    pub fn linearize(
        &mut self,
        problem: &BaProblem,
        poses: &[Isometry3<f64>],
        points: &[Vector3<f64>],
        active: &[bool],
        kernel: &RobustKernel,
    ) {
        self.u.iter_mut().for_each(|m| *m = Matrix6::zeros());
        self.bc.iter_mut().for_each(|m| *m = Vector6::zeros());
        self.v.iter_mut().for_each(|m| *m = Matrix3::zeros());
        self.bp.iter_mut().for_each(|m| *m = Vector3::zeros());
        for (i, o) in problem.observations.iter().enumerate() {
            self.wblk[i] = Matrix6x3::zeros();
            let (c, p) = (self.cam_of_kf[o.keyframe], self.pt_of_point[o.point]);
            if !active[i] || (c == NONE && p == NONE) {
                continue;
            }
            let kf = &problem.keyframes[o.keyframe];
            let Some(l) =
                linearize_reprojection(&kf.camera, &poses[o.keyframe], &points[o.point], &o.pixel)
            else {
                continue;
            };
            let chi2 = l.residual.norm_squared() * o.inv_sigma2;
            let w = o.inv_sigma2 * kernel.weight(chi2);
            let wr = l.residual * w;
            if c != NONE {
                let c = c as usize;
                self.u[c] += l.d_pose.tr_mul(&l.d_pose) * w;
                self.bc[c] += l.d_pose.tr_mul(&wr);
            }
            if p != NONE {
                let p = p as usize;
                self.v[p] += l.d_point.tr_mul(&l.d_point) * w;
                self.bp[p] += l.d_point.tr_mul(&wr);
                if c != NONE {
                    self.wblk[i] = l.d_pose.tr_mul(&l.d_point) * w;
                }
            }
        }
    }

    /// Damps with `lambda`, forms and solves the reduced camera system, back-substitutes the
    /// points. Fills [`Self::dc`] and [`Self::dp`]. A point whose damped block cannot be
    /// inverted is held for this step. Errors when the reduced system is not positive
    /// definite (the caller raises `lambda`).
    pub fn solve_step(&mut self, problem: &BaProblem, lambda: f64) -> Result<(), CoreError> {
        self.rcs.clear();
        for c in 0..self.rcs.n() {
            let mut blk = self.u[c];
            for k in 0..6 {
                blk[(k, k)] += damp(blk[(k, k)], lambda);
            }
            let d = self.rcs.diag_index(c);
            self.rcs.block_mut::<6, 6>(d).copy_from(&blk);
            self.rcs.rhs_block_mut::<6>(c).copy_from(&(-self.bc[c]));
        }
        let mut pair = 0usize;
        for p in 0..self.n_pts {
            let (s, e) = (self.pt_start[p], self.pt_start[p + 1]);
            let mut vd = self.v[p];
            for k in 0..3 {
                vd[(k, k)] += damp(vd[(k, k)], lambda);
            }
            let inv = inverse_spd3(&vd);
            self.pt_ok[p] = inv.is_some();
            let Some(vinv) = inv else {
                pair += self.pairs_of(problem, s, e);
                continue;
            };
            self.vinv[p] = vinv;
            let bp = self.bp[p];
            for &i in &self.pt_obs[s..e] {
                let i = i as usize;
                let y = self.wblk[i] * vinv;
                self.yblk[i] = y;
                let c = self.cam_of_kf[problem.observations[i].keyframe] as usize;
                let mut rhs = self.rcs.rhs_block_mut::<6>(c);
                rhs += y * bp;
            }
            for &a in &self.pt_obs[s..e] {
                let a = a as usize;
                let ca = self.cam_of_kf[problem.observations[a].keyframe];
                for &b in &self.pt_obs[s..e] {
                    let b = b as usize;
                    let cb = self.cam_of_kf[problem.observations[b].keyframe];
                    if ca > cb {
                        continue;
                    }
                    let k = self.pair_blk[pair] as usize;
                    pair += 1;
                    sub_y_wt(self.rcs.block_values_mut(k), &self.yblk[a], &self.wblk[b]);
                }
            }
        }
        self.rcs.solve()?;
        for (c, dc) in self.dc.iter_mut().enumerate() {
            *dc = self.rcs.x_block::<6>(c);
        }
        for p in 0..self.n_pts {
            if !self.pt_ok[p] {
                self.dp[p] = Vector3::zeros();
                continue;
            }
            let mut t = -self.bp[p];
            for &i in &self.pt_obs[self.pt_start[p]..self.pt_start[p + 1]] {
                let i = i as usize;
                let c = self.cam_of_kf[problem.observations[i].keyframe] as usize;
                t -= self.wblk[i].tr_mul(&self.dc[c]);
            }
            self.dp[p] = self.vinv[p] * t;
        }
        Ok(())
    }

    /// Number of visited pairs of the coupled observations `pt_obs[s..e]` of one point.
    #[inline]
    fn pairs_of(&self, problem: &BaProblem, s: usize, e: usize) -> usize {
        let list = &self.pt_obs[s..e];
        let mut n = 0;
        for &a in list {
            let ca = self.cam_of_kf[problem.observations[a as usize].keyframe];
            for &b in list {
                n += usize::from(ca <= self.cam_of_kf[problem.observations[b as usize].keyframe]);
            }
        }
        n
    }

    /// Reduction of `½ Σ ρ` predicted by the linear model for the last step:
    /// `½ δᵀ (λ D δ - b)` summed over cameras and points.
    pub fn predicted_reduction(&self, lambda: f64) -> f64 {
        let mut s = 0.0;
        for c in 0..self.dc.len() {
            let d = &self.dc[c];
            for k in 0..6 {
                s += d[k] * (damp(self.u[c][(k, k)], lambda) * d[k] - self.bc[c][k]);
            }
        }
        for p in 0..self.n_pts {
            let d = &self.dp[p];
            for k in 0..3 {
                s += d[k] * (damp(self.v[p][(k, k)], lambda) * d[k] - self.bp[p][k]);
            }
        }
        0.5 * s
    }
}

/// `blk -= y wᵀ` for 6x3 factors (`blk`: a 6x6 block, column-major): three rank-one
/// column updates (vectorises well).
#[inline]
fn sub_y_wt(blk: &mut [f64], y: &Matrix6x3<f64>, w: &Matrix6x3<f64>) {
    let blk = &mut blk[..36];
    for c in 0..6 {
        let (w0, w1, w2) = (w[(c, 0)], w[(c, 1)], w[(c, 2)]);
        for r in 0..6 {
            blk[r + 6 * c] -= y[(r, 0)] * w0 + y[(r, 1)] * w1 + y[(r, 2)] * w2;
        }
    }
}

/// Inverse of a symmetric positive definite 3x3 matrix by cofactors; `None` when it is not
/// (numerically) positive definite.
#[inline]
fn inverse_spd3(m: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    let (a, b, c) = (m[(0, 0)], m[(0, 1)], m[(0, 2)]);
    let (d, e, f) = (m[(1, 1)], m[(1, 2)], m[(2, 2)]);
    let c00 = d * f - e * e;
    let c01 = c * e - b * f;
    let c02 = b * e - c * d;
    let det = a * c00 + b * c01 + c * c02;
    // Positive definite: positive leading minors (and a determinant not lost in rounding).
    if !(a > 0.0 && a * d - b * b > 0.0 && det > 1e-12 * a * d * f && det.is_finite()) {
        return None;
    }
    let c11 = a * f - c * c;
    let c12 = b * c - a * e;
    let c22 = a * d - b * b;
    let inv = 1.0 / det;
    Some(Matrix3::new(c00, c01, c02, c01, c11, c12, c02, c12, c22) * inv)
}
