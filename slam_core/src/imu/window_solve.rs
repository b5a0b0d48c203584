//! Linearisation, Schur complement and step of [`super::ViSolver`] (module docs of
//! [`super`]).

use nalgebra::{Matrix3, Vector3};

use super::{
    prior_residual, reprojection_jacobians, ImuLin, Linearization, Matrix15, Matrix9, Matrix9x3,
    NavState, ObsLin, Vector15, ViChi2, ViParams, ViSolver, ViWindow,
};
use crate::CoreError;

/// Largest `|x/z|`, `|y/z|` of a valid observation (about ±63°).
const MAX_TAN: f64 = 2.0;

/// The 95 % gate of χ²(2).
const CHI2_2DOF_95: f64 = 5.991;

/// Evaluates every factor at `states`, `points`: the χ² of each family and the robust cost;
/// with `lin`, also stores the whitened residuals and Jacobians. Allocates nothing.
#[allow(clippy::too_many_arguments)]
fn evaluate(
    w: &ViWindow,
    states: &[NavState],
    points: &[Vector3<f64>],
    p: &ViParams,
    sqrt_info: &[Matrix15],
    links: &[u32],
    mut lin: Option<&mut Linearization>,
) -> ViChi2 {
    let mut chi = ViChi2::default();
    for (k, o) in w.observations.iter().enumerate() {
        let st = &states[o.kf as usize];
        let pt = &points[o.point as usize];
        let (camera, t_bc) = w.rig(o.kf as usize);
        let proj = reprojection_jacobians(camera, t_bc, st, pt, o.dt_s);
        let Some((uv, j_x, j_p)) = proj.filter(|_| in_view(t_bc, st, pt, o.dt_s, p.min_depth_m))
        else {
            chi.behind += 1;
            if let Some(l) = lin.as_deref_mut() {
                l.obs[k].valid = false;
            }
            continue;
        };
        let s = 1.0 / o.sigma_px;
        let r = (uv - o.uv) * s;
        let e2 = r.norm_squared();
        chi.reprojection += e2;
        chi.reprojection_outliers += usize::from(e2 > CHI2_2DOF_95);
        chi.cost += p.kernel.cost(e2);
        if let Some(l) = lin.as_deref_mut() {
            l.obs[k] = ObsLin {
                valid: true,
                w: p.kernel.weight(e2),
                r,
                j_x: j_x * s,
                j_p: j_p * s,
            };
        }
    }
    for (k, (pre, &i)) in w.preints.iter().zip(links).enumerate() {
        let i = i as usize;
        let res = pre.residual(&states[i], &states[i + 1], &w.gravity_w);
        let l_inv = &sqrt_info[k];
        let r = l_inv * res.r;
        let e_pre = r.fixed_rows::<9>(0).norm_squared();
        let e_bias = r.fixed_rows::<6>(9).norm_squared();
        chi.imu += e_pre;
        chi.bias_walk += e_bias;
        chi.cost += e_pre + e_bias;
        if let Some(l) = lin.as_deref_mut() {
            l.imu[k] = ImuLin {
                r,
                j_i: l_inv * res.jac_i,
                j_j: l_inv * res.jac_j,
            };
        }
    }
    if let Some(pr) = &w.prior {
        let (r, j) = prior_residual(&pr.mean, &states[pr.kf]);
        let e = r.dot(&(pr.info * r));
        chi.prior = e;
        chi.cost += e;
        if let Some(l) = lin {
            l.prior = (r, j);
        }
    }
    chi
}

/// Whether `p_w` lies in the camera of body state `st` at a depth of at least `min_depth`
/// and within the normalised field `|x/z|, |y/z| ≤ MAX_TAN` (beyond it the distortion
/// polynomial is meaningless and its Jacobian explodes).
#[inline]
fn in_view(
    t_bc: &nalgebra::Isometry3<f64>,
    st: &NavState,
    p_w: &Vector3<f64>,
    dt_s: f64,
    min_depth: f64,
) -> bool {
    let p_b = st.r.inverse() * (p_w - st.p - st.v * dt_s);
    let p_c = t_bc.rotation.inverse() * (p_b - t_bc.translation.vector);
    p_c.z >= min_depth && p_c.x.abs() <= MAX_TAN * p_c.z && p_c.y.abs() <= MAX_TAN * p_c.z
}

/// Adds the 9x9 `m` (or its transpose) to the top-left corner of a 15x15 column-major block.
#[inline]
fn add9(blk: &mut [f64], m: &Matrix9, transpose: bool) {
    for c in 0..9 {
        for r in 0..9 {
            blk[r + 15 * c] += if transpose { m[(c, r)] } else { m[(r, c)] };
        }
    }
}

impl ViSolver {
    /// Linearises every factor at the window's current estimate.
    pub(super) fn linearize(&mut self, w: &ViWindow, p: &ViParams) -> ViChi2 {
        for (s, kf) in self.cur_states.iter_mut().zip(&w.keyframes) {
            *s = kf.state;
        }
        evaluate(
            w,
            &self.cur_states,
            &w.points_w,
            p,
            &self.imu_sqrt_info,
            &self.links,
            Some(&mut self.lin),
        )
    }

    /// The factors at the candidate estimate, linearised into `lin_cand`.
    pub(super) fn evaluate_candidate(&mut self, w: &ViWindow, p: &ViParams) -> ViChi2 {
        evaluate(
            w,
            &self.cand_states,
            &self.cand_points,
            p,
            &self.imu_sqrt_info,
            &self.links,
            Some(&mut self.lin_cand),
        )
    }

    /// The candidate estimate: the current one moved by the last step.
    pub(super) fn make_candidate(&mut self, w: &ViWindow) {
        let x = self.sys.x();
        for (k, kf) in w.keyframes.iter().enumerate() {
            let v = self.var_of_kf[k];
            self.cand_states[k] = if v == u32::MAX {
                kf.state
            } else {
                let o = v as usize * 15;
                kf.state
                    .retract(&Vector15::from_column_slice(&x[o..o + 15]))
            };
        }
        for ((c, p), d) in self.cand_points.iter_mut().zip(&w.points_w).zip(&self.dp) {
            *c = p + d;
        }
    }

    /// Assembles the keyframe factors (IMU, prior, reprojection pose blocks) into the
    /// system's `H` and `-g`; the velocity and biases of a free keyframe without IMU factor
    /// are held by [`super::UNLINKED_STIFFNESS`].
    fn assemble_keyframe_factors(&mut self, w: &ViWindow) -> Result<(), CoreError> {
        self.sys.clear();
        for (k, &linked) in self.linked.iter().enumerate() {
            let a = self.var_of_kf[k];
            if !linked && a != u32::MAX {
                let di = self.sys.diag_index(a as usize);
                let blk = self.sys.block_values_mut(di);
                for d in 6..15 {
                    blk[d + 15 * d] += super::UNLINKED_STIFFNESS;
                }
            }
        }
        for (l, &i) in self.lin.imu.iter().zip(&self.links) {
            let i = i as usize;
            let (a, b) = (self.var_of_kf[i], self.var_of_kf[i + 1]);
            if a != u32::MAX {
                self.sys
                    .add_to_block(a as usize, a as usize, &(l.j_i.transpose() * l.j_i))?;
                let g = l.j_i.transpose() * l.r;
                self.sys.add_rhs(a as usize, 0, (-g).as_slice());
            }
            if b != u32::MAX {
                self.sys
                    .add_to_block(b as usize, b as usize, &(l.j_j.transpose() * l.j_j))?;
                let g = l.j_j.transpose() * l.r;
                self.sys.add_rhs(b as usize, 0, (-g).as_slice());
            }
            if a != u32::MAX && b != u32::MAX {
                self.sys
                    .add_to_block(a as usize, b as usize, &(l.j_i.transpose() * l.j_j))?;
            }
        }
        if let Some(pr) = &w.prior {
            let a = self.var_of_kf[pr.kf];
            if a != u32::MAX {
                let (r, j) = &self.lin.prior;
                let jt_info = j.transpose() * pr.info;
                self.sys
                    .add_to_block(a as usize, a as usize, &(jt_info * j))?;
                self.sys.add_rhs(a as usize, 0, (-(jt_info * r)).as_slice());
            }
        }
        for (o, l) in w.observations.iter().zip(&self.lin.obs) {
            let a = self.var_of_kf[o.kf as usize];
            if !l.valid || a == u32::MAX {
                continue;
            }
            let h = l.j_x.transpose() * l.j_x * l.w;
            let di = self.sys.diag_index(a as usize);
            add9(self.sys.block_values_mut(di), &h, false);
            let g = l.j_x.transpose() * l.r * l.w;
            for (d, v) in self.sys.rhs_mut(a as usize, 0).iter_mut().zip(g.iter()) {
                *d -= v;
            }
        }
        Ok(())
    }

    /// Eliminates point `pt` (Schur complement, damping `lambda` on its 3x3 block): stores
    /// `(V + λI)⁻¹`, `g_p` and the `W` blocks, updates the reduced right-hand side and adds
    /// `-W V⁻¹ Wᵀ` per keyframe pair into the 9x9 pose-velocity corners of their blocks.
    fn eliminate_point(&mut self, w: &ViWindow, pt: usize, lambda: f64) -> Result<(), CoreError> {
        let (s, e) = (
            self.point_start[pt] as usize,
            self.point_start[pt + 1] as usize,
        );
        let mut v = Matrix3::identity() * lambda;
        let mut g = Vector3::zeros();
        let mut n_valid = 0;
        for &oi in &self.obs_order[s..e] {
            let l = &self.lin.obs[oi as usize];
            if l.valid {
                v += l.j_p.transpose() * l.j_p * l.w;
                g += l.j_p.transpose() * l.r * l.w;
                n_valid += 1;
            }
        }
        // A point seen once has no depth information: it is held fixed (a known landmark
        // for its keyframe): no step, no Schur term.
        let v_inv = if n_valid >= 2 {
            v.try_inverse().unwrap_or_else(Matrix3::zeros)
        } else {
            g = Vector3::zeros();
            Matrix3::zeros()
        };
        self.v_inv[pt] = v_inv;
        self.g_p[pt] = g;
        let vg = v_inv * g;
        for &oi in &self.obs_order[s..e] {
            let (o, l) = (&w.observations[oi as usize], &self.lin.obs[oi as usize]);
            let a = self.var_of_kf[o.kf as usize];
            self.w_blk[oi as usize] = if l.valid && a != u32::MAX && n_valid >= 2 {
                l.j_x.transpose() * l.j_p * l.w
            } else {
                Matrix9x3::zeros()
            };
            if a != u32::MAX {
                let wvg = self.w_blk[oi as usize] * vg;
                let rhs = self.sys.rhs_mut(a as usize, 0);
                for (d, x) in rhs.iter_mut().zip(wvg.iter()) {
                    *d += x;
                }
            }
        }
        if n_valid < 2 {
            return Ok(());
        }
        for x in s..e {
            let ox = self.obs_order[x] as usize;
            let a = self.var_of_kf[w.observations[ox].kf as usize];
            if a == u32::MAX {
                continue;
            }
            let wv = self.w_blk[ox] * v_inv;
            for y in x..e {
                let oy = self.obs_order[y] as usize;
                let b = self.var_of_kf[w.observations[oy].kf as usize];
                if b == u32::MAX {
                    continue;
                }
                let m = -(wv * self.w_blk[oy].transpose());
                self.add_pair(a as usize, b as usize, &m, x != y)?;
            }
        }
        Ok(())
    }

    /// Adds the 9x9 Schur term `m` of keyframe variables `(a, b)` to `H_ab` (and its
    /// transpose to `H_ba`: on the diagonal, when `both` the two observations differ).
    #[inline]
    fn add_pair(&mut self, a: usize, b: usize, m: &Matrix9, both: bool) -> Result<(), CoreError> {
        let (i, j, t) = if a <= b { (a, b, false) } else { (b, a, true) };
        let k = self
            .sys
            .block_index(i, j)
            .ok_or_else(|| CoreError::Degenerate("vi window: pattern".into()))?;
        let blk = self.sys.block_values_mut(k);
        add9(blk, m, t);
        if a == b && both {
            add9(blk, m, true);
        }
        Ok(())
    }

    /// Assembles the reduced keyframe system (points eliminated with damping `lambda` on
    /// their blocks; the keyframe blocks are not damped here).
    pub(super) fn assemble_reduced(&mut self, w: &ViWindow, lambda: f64) -> Result<(), CoreError> {
        self.assemble_keyframe_factors(w)?;
        for pt in 0..w.points_w.len() {
            self.eliminate_point(w, pt, lambda)?;
        }
        Ok(())
    }

    /// Solves the damped normal equations for the keyframe step (into the system's `x`) and
    /// the point steps (`dp`). Returns the largest step component.
    pub(super) fn solve_step(&mut self, w: &ViWindow, lambda: f64) -> Result<f64, CoreError> {
        self.assemble_reduced(w, lambda)?;
        self.sys.solve_shifted(Some(lambda))?;
        let x = self.sys.x();
        let mut step_max = x.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for pt in 0..w.points_w.len() {
            let mut rhs = -self.g_p[pt];
            for &oi in
                &self.obs_order[self.point_start[pt] as usize..self.point_start[pt + 1] as usize]
            {
                let a = self.var_of_kf[w.observations[oi as usize].kf as usize];
                if a != u32::MAX {
                    let o = a as usize * 15;
                    let dx9 = nalgebra::SVector::<f64, 9>::from_column_slice(&x[o..o + 9]);
                    rhs -= self.w_blk[oi as usize].transpose() * dx9;
                }
            }
            self.dp[pt] = self.v_inv[pt] * rhs;
            step_max = step_max.max(self.dp[pt].amax());
        }
        if !step_max.is_finite() {
            return Err(CoreError::Degenerate("vi window: step not finite".into()));
        }
        Ok(step_max)
    }
}
