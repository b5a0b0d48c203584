//! Four-degree-of-freedom pose graph optimisation (`VI_NOTES.md` §4 "Loops and merges";
//! VINS-Mono's loop graph, Qin et al. 2018, from the paper): in a metric, gravity-aligned
//! map the drift of a visual-inertial system is in x, y, z and yaw only (the IMU observes
//! roll, pitch and scale), so each vertex keeps its roll and pitch and the optimisation moves
//! its position `p_k` and yaw `ψ_k`.
//!
//! With `R_k(ψ) = R_z(ψ) R̄_k`, where `R̄_k = R_z(-ψ_k⁰) R_k⁰` is the vertex's initial tilt
//! (`R⁰ = R_z(ψ⁰) R_y(θ) R_x(φ)`, yaw `ψ = atan2(R₁₀, R₀₀)`), an edge `(i, j)` measuring the
//! relative pose `Z_ij ≈ T_i⁻¹ T_j` has the residual
//! ```text
//! r_p = R_i(ψ_i)ᵀ (p_j - p_i) - t(Z_ij)                (3, in vertex i's frame)
//! r_ψ = wrap(ψ_j - ψ_i - ψ̂_ij),  ψ̂_ij = yaw(R_i⁰ R(Z_ij)) - ψ_i⁰
//! ∂r_p/∂p_i = -R_iᵀ,  ∂r_p/∂p_j = R_iᵀ,  ∂r_p/∂ψ_i = -R̄_iᵀ [e_z]x R_z(-ψ_i) (p_j - p_i)
//! ∂r_ψ/∂ψ_i = -1,  ∂r_ψ/∂ψ_j = 1
//! ```
//! and the cost `½ Σ w ‖r‖²`. Levenberg-Marquardt on 4x4 blocks, assembled in the crate's
//! [`BlockSparseSystem`] and solved with its sparse Cholesky (the loop graphs of the server
//! maps have hundreds to thousands of keyframes).
use std::time::Instant;

use nalgebra::{Isometry3, Matrix3, Matrix4, Rotation3, SMatrix, UnitQuaternion, Vector3, Vector4};

use super::{PgoParams, PgoReport, StageReport};
use crate::lie::skew;
use crate::optim::block_sparse::{BlockSparseSystem, Factorization};
use crate::CoreError;

/// An edge of a 4-DoF graph: `measurement ≈ T_i⁻¹ T_j`, weight `w` of its cost.
#[derive(Debug, Clone, Copy)]
pub struct FourDofEdge {
    /// First vertex (index).
    pub i: usize,
    /// Second vertex (index).
    pub j: usize,
    /// Relative pose measured.
    pub measurement: Isometry3<f64>,
    /// Weight of the edge's squared residual.
    pub weight: f64,
}

/// Yaw of a rotation, `atan2(R₁₀, R₀₀)` (z-y-x Euler angles).
pub fn yaw(r: &Rotation3<f64>) -> f64 {
    let m = r.matrix();
    m[(1, 0)].atan2(m[(0, 0)])
}

fn wrap(a: f64) -> f64 {
    let two_pi = std::f64::consts::TAU;
    a - two_pi * ((a + std::f64::consts::PI) / two_pi).floor()
}

fn rz(psi: f64) -> Rotation3<f64> {
    Rotation3::from_axis_angle(&Vector3::z_axis(), psi)
}

/// An edge with what stays constant: measured translation and yaw, vertex blocks.
struct Slot {
    i: usize,
    j: usize,
    t_ij: Vector3<f64>,
    yaw_ij: f64,
    w: f64,
    vi: Option<usize>,
    vj: Option<usize>,
}

/// The state: position and yaw per vertex, tilt fixed.
#[derive(Clone)]
struct State {
    p: Vec<Vector3<f64>>,
    psi: Vec<f64>,
}

struct Problem {
    tilt: Vec<Rotation3<f64>>,
    slots: Vec<Slot>,
}

impl Problem {
    /// `(r, J_i, J_j)` of slot `s` at `x` (J over `[p; ψ]` of each vertex).
    fn linearize(&self, s: &Slot, x: &State) -> (Vector4<f64>, Matrix4<f64>, Matrix4<f64>) {
        let d = x.p[s.j] - x.p[s.i];
        let rz_inv = rz(-x.psi[s.i]);
        let tilt_t = self.tilt[s.i].transpose();
        let a: Matrix3<f64> = (tilt_t * rz_inv).into_inner();
        let rp = a * d - s.t_ij;
        let rpsi = wrap(x.psi[s.j] - x.psi[s.i] - s.yaw_ij);
        let mut ji = Matrix4::zeros();
        let mut jj = Matrix4::zeros();
        ji.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-a));
        jj.fixed_view_mut::<3, 3>(0, 0).copy_from(&a);
        let dpsi = -(tilt_t.matrix() * skew(&Vector3::z()) * (rz_inv * d));
        ji.fixed_view_mut::<3, 1>(0, 3).copy_from(&dpsi);
        ji[(3, 3)] = -1.0;
        jj[(3, 3)] = 1.0;
        (Vector4::new(rp.x, rp.y, rp.z, rpsi), ji, jj)
    }

    fn cost(&self, x: &State) -> f64 {
        self.slots
            .iter()
            .map(|s| 0.5 * s.w * self.linearize(s, x).0.norm_squared())
            .sum()
    }

    /// Assembles `H` and `-g` into `sys`.
    fn assemble(&self, x: &State, sys: &mut BlockSparseSystem) {
        sys.clear();
        for s in &self.slots {
            let (r, ji, jj) = self.linearize(s, x);
            let blocks = [(s.vi, ji), (s.vj, jj)];
            for (va, ja) in &blocks {
                let Some(a) = *va else { continue };
                sys.add_rhs(a, 0, (-(ja.transpose() * r) * s.w).as_slice());
                for (vb, jb) in &blocks {
                    let Some(b) = *vb else { continue };
                    if a > b {
                        continue;
                    }
                    let h: SMatrix<f64, 4, 4> = ja.transpose() * jb * s.w;
                    if let Some(k) = sys.block_index(a, b) {
                        sys.add_block(k, h.as_slice(), false);
                    }
                }
            }
        }
    }
}

/// Optimises `poses` (camera → world, gravity-aligned world) over x, y, z and yaw with the
/// `edges`, vertices with `fixed[v]` held (at least one: the 4 directions are the gauge).
/// Roll and pitch of every vertex are kept. Errors (and leaves `poses` unchanged) on bad
/// indices, no fixed or no free vertex, or a failed factorisation at the first step.
pub fn optimize_four_dof(
    poses: &mut [Isometry3<f64>],
    edges: &[FourDofEdge],
    fixed: &[bool],
    params: &PgoParams,
) -> Result<PgoReport, CoreError> {
    let t0 = Instant::now();
    let n = poses.len();
    if fixed.len() != n || !fixed.iter().any(|f| *f) {
        return Err(CoreError::InvalidArgument(
            "4-dof pgo: the fixed mask must name at least one vertex".into(),
        ));
    }
    let (var, nv) = super::lm::free_vertices(fixed, "4-dof pgo")?;
    let rot = |p: &Isometry3<f64>| p.rotation.to_rotation_matrix();
    let psi0: Vec<f64> = poses.iter().map(|p| yaw(&rot(p))).collect();
    let tilt: Vec<Rotation3<f64>> = poses
        .iter()
        .zip(&psi0)
        .map(|(p, y)| rz(-y) * rot(p))
        .collect();
    let mut pairs = Vec::with_capacity(edges.len());
    let mut slots = Vec::with_capacity(edges.len());
    for e in edges {
        if e.i >= n || e.j >= n || e.i == e.j || !(e.weight.is_finite() && e.weight > 0.0) {
            return Err(CoreError::InvalidArgument(format!(
                "4-dof pgo: bad edge ({}, {}) weight {}",
                e.i, e.j, e.weight
            )));
        }
        let (vi, vj) = (var[e.i], var[e.j]);
        if let (Some(a), Some(b)) = (vi, vj) {
            pairs.push((a as u32, b as u32));
        }
        let r_j = rot(&poses[e.i]) * e.measurement.rotation.to_rotation_matrix();
        slots.push(Slot {
            i: e.i,
            j: e.j,
            t_ij: e.measurement.translation.vector,
            yaw_ij: wrap(yaw(&r_j) - psi0[e.i]),
            w: e.weight,
            vi,
            vj,
        });
    }
    let mut sys = BlockSparseSystem::new("4-dof pgo");
    sys.setup_uniform(nv, 4, 1, &mut pairs, Factorization::SparseBlockAmd)?;
    let problem = Problem { tilt, slots };
    let mut x = State {
        p: poses.iter().map(|p| p.translation.vector).collect(),
        psi: psi0,
    };
    let initial_cost = problem.cost(&x);
    let (cost, iterations, converged) =
        levenberg_marquardt(&problem, &mut x, &var, &mut sys, params)?;
    for (k, pose) in poses.iter_mut().enumerate() {
        let r = rz(x.psi[k]) * problem.tilt[k];
        *pose = Isometry3::from_parts(x.p[k].into(), UnitQuaternion::from_rotation_matrix(&r));
    }
    let time_s = t0.elapsed().as_secs_f64();
    Ok(PgoReport {
        iterations,
        initial_cost,
        final_cost: cost,
        solve_time_s: time_s,
        stages: vec![StageReport {
            name: "lm_four_dof",
            iterations,
            initial_cost,
            final_cost: cost,
            time_s,
            converged,
        }],
        repaired_information: 0,
    })
}

/// LM on the problem: `(cost, iterations, converged)`.
fn levenberg_marquardt(
    problem: &Problem,
    x: &mut State,
    var: &[Option<usize>],
    sys: &mut BlockSparseSystem,
    params: &PgoParams,
) -> Result<(f64, usize, bool), CoreError> {
    let lm = &params.lm;
    let mut cost = problem.cost(x);
    let mut lambda = lm.lambda_initial;
    let mut iterations = 0;
    while iterations < lm.max_iterations {
        iterations += 1;
        problem.assemble(x, sys);
        let mut accepted = false;
        while lambda <= lm.lambda_upper {
            if sys.solve_shifted(Some(lambda)).is_err() {
                lambda *= lm.lambda_factor;
                continue;
            }
            let mut cand = x.clone();
            for (k, v) in var.iter().enumerate() {
                if let Some(v) = v {
                    let d: Vector4<f64> = sys.x_block(*v);
                    cand.p[k] += d.xyz();
                    cand.psi[k] = wrap(cand.psi[k] + d.w);
                }
            }
            let c = problem.cost(&cand);
            if c.is_finite() && c < cost {
                let decrease = cost - c;
                let done = decrease <= lm.abs_tol || decrease <= lm.rel_tol * cost;
                *x = cand;
                cost = c;
                lambda = (lambda / lm.lambda_factor).max(1e-12);
                accepted = true;
                if done {
                    return Ok((cost, iterations, true));
                }
                break;
            }
            lambda *= lm.lambda_factor;
        }
        if !accepted {
            // No step lowers the cost: at a minimum (or stuck).
            return Ok((cost, iterations, cost <= lm.abs_tol));
        }
    }
    Ok((cost, iterations, false))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lie::Sim3;
    use crate::pgo::LoopGraphParams;
    use crate::pgo::{correct_loop, correct_loop_four_dof, GraphKeyframe, LoopConstraint};

    /// A tilted camera on a circle (gravity-aligned world); its odometry drifts in yaw
    /// (0.3° per step) and along x (2 mm per step), as a visual-inertial client drifts.
    fn drifted_circle(n: usize) -> (Vec<Isometry3<f64>>, Vec<Isometry3<f64>>) {
        let tilt = UnitQuaternion::from_euler_angles(0.2, -0.1, 0.0);
        let truth: Vec<Isometry3<f64>> = (0..n)
            .map(|k| {
                let a = std::f64::consts::TAU * k as f64 / n as f64;
                Isometry3::from_parts(
                    Vector3::new(10.0 * a.cos(), 10.0 * a.sin(), 0.3 * (3.0 * a).sin()).into(),
                    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), a) * tilt,
                )
            })
            .collect();
        let mut est = vec![truth[0]];
        let drift = Isometry3::from_parts(
            Vector3::new(0.002, 0.0, 0.0).into(),
            UnitQuaternion::identity(),
        );
        for k in 1..n {
            let rel = truth[k - 1].inverse() * truth[k];
            // Yaw drift about the world vertical, applied to the whole chain from here.
            let world_yaw = Isometry3::from_parts(
                Vector3::zeros().into(),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.3f64.to_radians()),
            );
            let next = drift * est[k - 1] * rel;
            let c = est[k - 1].translation.vector;
            let about = Isometry3::translation(c.x, c.y, c.z)
                * world_yaw
                * Isometry3::translation(-c.x, -c.y, -c.z);
            est.push(about * next);
        }
        (truth, est)
    }

    /// Angle between the vertical as two camera poses see it (their roll and pitch).
    fn tilt_change(a: &Isometry3<f64>, b: &Isometry3<f64>) -> f64 {
        let za = a.rotation.inverse() * Vector3::z();
        let zb = b.rotation.inverse() * Vector3::z();
        za.angle(&zb)
    }

    /// The loop edge pulls the drifted end back onto the truth; roll and pitch of every
    /// vertex are unchanged (each camera sees the vertical where it saw it); the 4-DoF
    /// correction beats a 7-DoF Sim(3) one on the same graph, which tilts the map.
    #[test]
    fn a_yaw_and_position_drift_is_removed_and_the_map_stays_level() {
        let n = 60;
        let (truth, est) = drifted_circle(n);
        let kfs: Vec<GraphKeyframe> = est
            .iter()
            .enumerate()
            .map(|(k, t)| GraphKeyframe {
                id: k as u64,
                t_wk: *t,
                covisible: Vec::new(),
            })
            .collect();
        let rel = truth[n - 1].inverse() * truth[0];
        let loops = [LoopConstraint {
            query: (n - 1) as u64,
            matched: 0,
            s_qm: Sim3::from_isometry(&rel, 1.0),
        }];
        let p = LoopGraphParams::default();
        let four = correct_loop_four_dof(&kfs, &loops, 0, &p).unwrap();
        let seven = correct_loop(&kfs, &loops, 0, &p).unwrap();
        let rmse = |c: &crate::pgo::LoopCorrection| {
            let s: f64 = (0..n)
                .map(|k| (c.poses[&(k as u64)].t - truth[k].translation.vector).norm_squared())
                .sum();
            (s / n as f64).sqrt()
        };
        let before: f64 = ((0..n)
            .map(|k| (est[k].translation.vector - truth[k].translation.vector).norm_squared())
            .sum::<f64>()
            / n as f64)
            .sqrt();
        let (e4, e7) = (rmse(&four), rmse(&seven));
        let tilt4 = (0..n)
            .map(|k| tilt_change(&four.poses[&(k as u64)].to_isometry(), &est[k]))
            .fold(0.0, f64::max);
        println!(
            "drifted {before:.4} m; 4-dof {e4:.4} m ({:.2} ms, {} it); sim3 {e7:.4} m ({:.2} ms)",
            four.report.solve_time_s * 1e3,
            four.report.iterations,
            seven.report.solve_time_s * 1e3
        );
        assert!(e4 < 0.2 * before, "4-dof {e4} vs {before} before");
        let tilt7 = (0..n)
            .map(|k| tilt_change(&seven.poses[&(k as u64)].to_isometry(), &est[k]))
            .fold(0.0, f64::max);
        println!("largest roll/pitch change: 4-dof {tilt4:.2e} rad, sim3 {tilt7:.2e} rad");
        assert!(e4 < e7, "4-dof {e4} vs 7-dof {e7}");
        assert!(tilt4 < 1e-9, "roll/pitch moved by {tilt4} rad");
        assert!(four.deltas.values().all(|d| (d.s - 1.0).abs() < 1e-12));
        let first = four.poses[&0].to_isometry();
        assert!((first.translation.vector - est[0].translation.vector).norm() < 1e-12);
    }

    /// Gauge and input errors are refused.
    #[test]
    fn bad_graphs_are_refused() {
        let mut poses = vec![Isometry3::identity(); 3];
        let e = |i, j| FourDofEdge {
            i,
            j,
            measurement: Isometry3::identity(),
            weight: 1.0,
        };
        let p = PgoParams::default();
        assert!(optimize_four_dof(&mut poses, &[e(0, 1)], &[false; 3], &p).is_err());
        assert!(optimize_four_dof(&mut poses, &[e(0, 5)], &[true, false, false], &p).is_err());
        assert!(optimize_four_dof(&mut poses, &[e(0, 1)], &[true; 3], &p).is_err());
        let ok = optimize_four_dof(&mut poses, &[e(0, 1), e(1, 2)], &[true, false, false], &p);
        assert!(ok.unwrap().final_cost < 1e-20);
    }
}
