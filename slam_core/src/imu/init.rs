//! Inertial initialisation from the first seconds of monocular tracking (seed ch. 5;
//! `VI_NOTES.md` §4 "VI initialisation"): metric scale, gravity direction, keyframe
//! velocities and IMU biases, with the camera poses of the monocular map held fixed.
//!
//! Three steps, each a pure function of the keyframe poses and the IMU preintegrated
//! between consecutive keyframes ([`Preintegrated`]):
//! 1. **Gyro bias** from rotation consistency (VINS-Mono): the bias that makes the
//!    preintegrated rotations agree with the visual ones, `min Σ ‖r_R‖²_Σ` over `b_g`
//!    (Gauss-Newton, first-order bias update of the deltas).
//! 2. **Linear alignment** for scale `s`, gravity `g` (3-vector, any norm) and velocities
//!    `v_k`, with `b_a = 0`: per keyframe pair `i, j`, with `R_k = R_wc,k R_cb`,
//!    ```text
//!    v_j - v_i - g Δt                            = R_i Δv_ij
//!    s (p_wc,j - p_wc,i) - v_i Δt - ½ g Δt²      = R_i Δp_ij - (R_wc,j - R_wc,i) p_cb
//!    ```
//!    (the position of the body is `p_wb = s p_wc + R_wc p_cb`, `p_cb` metric).
//! 3. **Inertial-only MAP** (ORB-SLAM3's inertial-only optimisation): Levenberg-Marquardt on
//!    the preintegration residuals (rotation, velocity, position rows of
//!    [`Preintegrated::residual`], weighted by their covariance) over
//!    `[v_0..v_n-1, δg (2), log s, b_g, b_a]`, gravity on the sphere `|g| = 9.81`
//!    (`g = R_wg Exp([δx, δy, 0]) (0, 0, -9.81)`), with Gaussian priors on both biases. The
//!    deltas follow bias changes to first order (no re-integration: the biases move little
//!    from step 1's).
//!
//! The result says how well the data determined it: the 1σ of `log s` and of the gravity
//! direction from the inverse of the final normal matrix. A caller accepts the
//! initialisation only when both are small (enough acceleration), else waits for more
//! keyframes; a straight constant-velocity motion leaves the scale unobservable and
//! [`initialize`] says so.
use nalgebra::{DMatrix, DVector, Isometry3, Matrix3, Rotation3, Vector3};

use super::preint::{Matrix9, NavState, Preintegrated};
use super::{ImuBiases, GRAVITY};
use crate::lie::{skew, so3_exp, so3_log};

/// Settings of [`initialize`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InitParams {
    /// Prior 1σ of the gyro bias around zero, rad/s.
    pub prior_gyro_bias: f64,
    /// Prior 1σ of the accelerometer bias around zero, m/s².
    pub prior_accel_bias: f64,
    /// Most Levenberg-Marquardt iterations of step 3.
    pub max_iterations: usize,
    /// Largest accepted 1σ of `log s` (relative scale uncertainty).
    pub max_scale_sigma: f64,
    /// Largest accepted 1σ of the gravity direction, rad.
    pub max_gravity_sigma: f64,
    /// 1σ of a keyframe position of the monocular map, metres at the true scale (its noise
    /// enters the weights: without it the result claims more than the poses hold).
    pub pose_sigma_m: f64,
    /// 1σ of a keyframe orientation of the monocular map, rad.
    pub pose_sigma_rad: f64,
}

impl Default for InitParams {
    fn default() -> Self {
        Self {
            prior_gyro_bias: 0.05,
            prior_accel_bias: 0.2,
            max_iterations: 30,
            max_scale_sigma: 0.05,
            max_gravity_sigma: 0.02,
            pose_sigma_m: 0.001,
            pose_sigma_rad: 0.001,
        }
    }
}

/// What the inertial initialisation found.
#[derive(Debug, Clone, PartialEq)]
pub struct InertialInit {
    /// Metric scale of the monocular map: metric positions are `scale · p_wc`.
    pub scale: f64,
    /// Rotation from the monocular map's world frame to the gravity-aligned world (z up,
    /// gravity `(0, 0, -9.81)`), the smallest one (no yaw added).
    pub r_gw: Rotation3<f64>,
    /// Gravity in the monocular map's world frame, m/s².
    pub gravity_w: Vector3<f64>,
    /// Body velocity at each keyframe in the monocular map's world frame, m/s (metric).
    pub velocities_w: Vec<Vector3<f64>>,
    /// Effective IMU biases.
    pub biases: ImuBiases,
    /// 1σ of `log scale`.
    pub scale_sigma: f64,
    /// 1σ of the gravity direction (larger axis), rad.
    pub gravity_sigma: f64,
    /// Scale of the linear alignment (step 2), for diagnostics.
    pub linear_scale: f64,
    /// Norm of the linear alignment's free gravity, m/s² (near 9.81 when the motion is
    /// informative).
    pub linear_gravity_norm: f64,
    /// Weighted squared residual after step 3.
    pub cost: f64,
    /// Levenberg-Marquardt iterations run.
    pub iterations: usize,
}

/// Why an initialisation was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InitError {
    /// Fewer than three keyframes, or preintegrations not one per consecutive pair.
    #[error("inertial initialisation needs ≥ 3 keyframes and one preintegration per pair ({keyframes} keyframes, {preints} preintegrations)")]
    BadInput {
        /// Keyframes given.
        keyframes: usize,
        /// Preintegrations given.
        preints: usize,
    },
    /// The linear system was singular or gave a non-positive scale.
    #[error("linear alignment failed: {0}")]
    Alignment(String),
    /// The data do not determine the scale or gravity well enough (too little
    /// acceleration): the 1σ found.
    #[error("not observable yet: scale {scale:.4} with 1σ {scale_sigma:.3} (of log scale), gravity 1σ {gravity_sigma_deg:.2}°")]
    NotObservable {
        /// The scale found.
        scale: f64,
        /// 1σ of `log scale`.
        scale_sigma: f64,
        /// 1σ of the gravity direction, degrees.
        gravity_sigma_deg: f64,
    },
}

/// Initialises scale, gravity, velocities and biases from keyframe poses `t_wc` (camera to
/// the monocular world, up to scale), the preintegrations between consecutive keyframes
/// (`preints[k]` from keyframe `k` to `k + 1`, linearised at zero bias) and the camera
/// pose in the body frame `t_bc` (metric).
pub fn initialize(
    t_wc: &[Isometry3<f64>],
    preints: &[Preintegrated],
    t_bc: &Isometry3<f64>,
    params: &InitParams,
) -> Result<InertialInit, InitError> {
    if t_wc.len() < 3 || preints.len() + 1 != t_wc.len() {
        return Err(InitError::BadInput {
            keyframes: t_wc.len(),
            preints: preints.len(),
        });
    }
    let frames = BodyFrames::new(t_wc, t_bc);
    let bg = gyro_bias(&frames, preints, params);
    let zero_ba = ImuBiases {
        gyro: bg,
        accel: Vector3::zeros(),
    };
    let lin = linear_alignment(&frames, preints, &zero_ba)?;
    let mut state = MapState {
        velocities: lin.velocities.clone(),
        r_wg: rotation_to_gravity(&lin.gravity),
        log_s: lin.scale.ln(),
        biases: zero_ba,
    };
    let (cost, iterations, sigmas) = refine(&frames, preints, &mut state, params);
    let (scale_sigma, gravity_sigma) = sigmas;
    if !(scale_sigma <= params.max_scale_sigma && gravity_sigma <= params.max_gravity_sigma) {
        return Err(InitError::NotObservable {
            scale: state.log_s.exp(),
            scale_sigma,
            gravity_sigma_deg: gravity_sigma.to_degrees(),
        });
    }
    Ok(InertialInit {
        scale: state.log_s.exp(),
        r_gw: state.r_wg.inverse(),
        gravity_w: state.gravity(),
        velocities_w: state.velocities,
        biases: state.biases,
        scale_sigma,
        gravity_sigma,
        linear_scale: lin.scale,
        linear_gravity_norm: lin.gravity.norm(),
        cost,
        iterations,
    })
}

/// Keyframe body orientations `R_k = R_wc,k R_cb` and what the body positions need.
struct BodyFrames {
    r_wb: Vec<Rotation3<f64>>,
    /// Camera positions `p_wc` (monocular scale).
    p_wc: Vec<Vector3<f64>>,
    /// `R_wc,k p_cb` (metric lever arm in the world frame).
    lever_w: Vec<Vector3<f64>>,
}

impl BodyFrames {
    fn new(t_wc: &[Isometry3<f64>], t_bc: &Isometry3<f64>) -> Self {
        let t_cb = t_bc.inverse();
        let r_cb = t_cb.rotation.to_rotation_matrix();
        let p_cb = t_cb.translation.vector;
        Self {
            r_wb: t_wc
                .iter()
                .map(|t| t.rotation.to_rotation_matrix() * r_cb)
                .collect(),
            p_wc: t_wc.iter().map(|t| t.translation.vector).collect(),
            lever_w: t_wc.iter().map(|t| t.rotation * p_cb).collect(),
        }
    }

    /// The body's navigation state at keyframe `k` for scale `s`.
    fn nav(&self, k: usize, s: f64, v: Vector3<f64>, biases: ImuBiases) -> NavState {
        NavState {
            r: self.r_wb[k],
            p: self.p_wc[k] * s + self.lever_w[k],
            v,
            biases,
        }
    }
}

/// Step 1: the gyro bias that makes the preintegrated rotations agree with the visual ones
/// (Gauss-Newton on the rotation rows of the residual, three iterations).
fn gyro_bias(frames: &BodyFrames, preints: &[Preintegrated], params: &InitParams) -> Vector3<f64> {
    let mut bg = Vector3::zeros();
    for _ in 0..3 {
        let (mut h, mut b) = (Matrix3::zeros(), Vector3::zeros());
        for (k, pre) in preints.iter().enumerate() {
            let biases = ImuBiases {
                gyro: bg,
                accel: Vector3::zeros(),
            };
            let (dr, _, _) = pre.corrected(&biases);
            let e = so3_log(&(dr.inverse() * frames.r_wb[k].inverse() * frames.r_wb[k + 1]));
            // ∂e/∂b_g ≈ -J^R_g (small residual); weight: the rotation block's information.
            let j = -pre.d_r_d_bg();
            let cov = pre.covariance().fixed_view::<3, 3>(0, 0).into_owned()
                + Matrix3::identity() * (2.0 * params.pose_sigma_rad.powi(2));
            let info = cov.try_inverse().unwrap_or_else(Matrix3::identity);
            h += j.transpose() * info * j;
            b += j.transpose() * info * e;
        }
        match h.try_inverse() {
            Some(hi) => bg -= hi * b,
            None => break,
        }
    }
    bg
}

/// Step 2's result.
struct Linear {
    scale: f64,
    gravity: Vector3<f64>,
    velocities: Vec<Vector3<f64>>,
}

/// Step 2: the linear alignment (module docs), solved by SVD; unknowns
/// `[v_0..v_n-1, g, s]`.
fn linear_alignment(
    frames: &BodyFrames,
    preints: &[Preintegrated],
    biases: &ImuBiases,
) -> Result<Linear, InitError> {
    let n = frames.r_wb.len();
    let (cols, rows) = (3 * n + 4, 6 * preints.len());
    let (mut a, mut rhs) = (DMatrix::zeros(rows, cols), DVector::zeros(rows));
    let (ig, is) = (3 * n, 3 * n + 3);
    for (k, pre) in preints.iter().enumerate() {
        let (_, dv, dp) = pre.corrected(biases);
        let (t, ri, r0) = (pre.delta_t(), frames.r_wb[k], 6 * k);
        let eye = Matrix3::identity();
        // Velocity rows: v_j - v_i - g Δt = R_i Δv.
        a.fixed_view_mut::<3, 3>(r0, 3 * (k + 1)).copy_from(&eye);
        a.fixed_view_mut::<3, 3>(r0, 3 * k).copy_from(&(-eye));
        a.fixed_view_mut::<3, 3>(r0, ig).copy_from(&(-eye * t));
        rhs.fixed_rows_mut::<3>(r0).copy_from(&(ri * dv));
        // Position rows: s Δp_wc - v_i Δt - ½ g Δt² = R_i Δp - Δ(lever).
        let p1 = r0 + 3;
        a.fixed_view_mut::<3, 3>(p1, 3 * k).copy_from(&(-eye * t));
        a.fixed_view_mut::<3, 3>(p1, ig)
            .copy_from(&(-eye * (0.5 * t * t)));
        a.fixed_view_mut::<3, 1>(p1, is)
            .copy_from(&(frames.p_wc[k + 1] - frames.p_wc[k]));
        let lever = frames.lever_w[k + 1] - frames.lever_w[k];
        rhs.fixed_rows_mut::<3>(p1).copy_from(&(ri * dp - lever));
    }
    let x = a
        .svd(true, true)
        .solve(&rhs, 1e-12)
        .map_err(|e| InitError::Alignment(e.to_string()))?;
    let scale = x[is];
    let gravity = Vector3::new(x[ig], x[ig + 1], x[ig + 2]);
    if !(scale > 0.0 && scale.is_finite() && gravity.norm() > 1e-3) {
        return Err(InitError::Alignment(format!(
            "scale {scale:.4}, gravity norm {:.3} m/s²",
            gravity.norm()
        )));
    }
    let velocities = (0..n)
        .map(|k| Vector3::new(x[3 * k], x[3 * k + 1], x[3 * k + 2]))
        .collect();
    Ok(Linear {
        scale,
        gravity,
        velocities,
    })
}

/// The smallest rotation `R_wg` with `R_wg (0, 0, -1) = g / |g|`.
fn rotation_to_gravity(g: &Vector3<f64>) -> Rotation3<f64> {
    let down = Vector3::new(0.0, 0.0, -1.0);
    Rotation3::rotation_between(&down, &g.normalize())
        .unwrap_or_else(|| Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI))
}

/// Step 3's unknowns.
struct MapState {
    velocities: Vec<Vector3<f64>>,
    r_wg: Rotation3<f64>,
    log_s: f64,
    biases: ImuBiases,
}

/// Gravity in the gravity-aligned frame.
fn g0() -> Vector3<f64> {
    Vector3::new(0.0, 0.0, -GRAVITY)
}

impl MapState {
    fn gravity(&self) -> Vector3<f64> {
        self.r_wg * g0()
    }

    /// The state moved by the step `d` = `[δv (3n), δg (2), δ log s, δb_g, δb_a]`.
    fn moved(&self, d: &DVector<f64>) -> MapState {
        let n = self.velocities.len();
        let at = |k: usize| Vector3::new(d[k], d[k + 1], d[k + 2]);
        let o = 3 * n;
        MapState {
            velocities: (0..n).map(|k| self.velocities[k] + at(3 * k)).collect(),
            r_wg: self.r_wg * so3_exp(&Vector3::new(d[o], d[o + 1], 0.0)),
            log_s: self.log_s + d[o + 2],
            biases: ImuBiases {
                gyro: self.biases.gyro + at(o + 3),
                accel: self.biases.accel + at(o + 6),
            },
        }
    }
}

/// The normal equations `(H, b)` of step 3 at `st` and its cost.
fn normal_equations(
    frames: &BodyFrames,
    preints: &[Preintegrated],
    st: &MapState,
    params: &InitParams,
) -> (DMatrix<f64>, DVector<f64>, f64) {
    let n = st.velocities.len();
    let o = 3 * n;
    let dim = o + 9;
    let (mut h, mut b, mut cost) = (DMatrix::zeros(dim, dim), DVector::zeros(dim), 0.0);
    let (s, g) = (st.log_s.exp(), st.gravity());
    // ∂g/∂δ: g = R_wg Exp(δ) g0 ≈ R_wg (g0 - [g0]× δ), δ = (δx, δy, 0).
    let dg = -(st.r_wg.matrix() * skew(&g0()));
    for (k, pre) in preints.iter().enumerate() {
        let ni = frames.nav(k, s, st.velocities[k], st.biases);
        let nj = frames.nav(k + 1, s, st.velocities[k + 1], st.biases);
        let res = pre.residual(&ni, &nj, &g);
        let mut jac = DMatrix::<f64>::zeros(9, dim);
        let (ji, jj, t) = (&res.jac_i, &res.jac_j, pre.delta_t());
        jac.view_mut((0, 3 * k), (9, 3))
            .copy_from(&ji.fixed_view::<9, 3>(0, 6));
        jac.view_mut((0, 3 * (k + 1)), (9, 3))
            .copy_from(&jj.fixed_view::<9, 3>(0, 6));
        let rit = ni.r.matrix().transpose();
        let dr_dg_v = -rit * t * dg;
        let dr_dg_p = -rit * (0.5 * t * t) * dg;
        jac.view_mut((3, o), (3, 2))
            .copy_from(&dr_dg_v.fixed_view::<3, 2>(0, 0));
        jac.view_mut((6, o), (3, 2))
            .copy_from(&dr_dg_p.fixed_view::<3, 2>(0, 0));
        let ds = ji.fixed_view::<9, 3>(0, 3) * (frames.p_wc[k] * s)
            + jj.fixed_view::<9, 3>(0, 3) * (frames.p_wc[k + 1] * s);
        jac.view_mut((0, o + 2), (9, 1)).copy_from(&ds);
        jac.view_mut((0, o + 3), (9, 6))
            .copy_from(&ji.fixed_view::<9, 6>(0, 9));
        let info = information(pre, params);
        let r9 = res.r.fixed_rows::<9>(0).into_owned();
        let jt_info = jac.transpose() * DMatrix::from_column_slice(9, 9, info.as_slice());
        h += &jt_info * &jac;
        b += &jt_info * DVector::from_column_slice(r9.as_slice());
        cost += (r9.transpose() * info * r9)[0];
    }
    add_bias_priors(&mut h, &mut b, &mut cost, st, o + 3, params);
    (h, b, cost)
}

/// Information of the rotation, velocity and position rows of `pre`'s residual: its
/// covariance plus the keyframe poses' noise (two poses: `2σ_θ²` on the rotation rows,
/// `2σ_p²` plus the rotated delta's `(σ_θ |Δ|)²` on the position and velocity rows).
fn information(pre: &Preintegrated, params: &InitParams) -> Matrix9 {
    let mut cov = *pre.covariance();
    let (sp2, sr2) = (params.pose_sigma_m.powi(2), params.pose_sigma_rad.powi(2));
    let (dv2, dp2) = (pre.delta_v().norm_squared(), pre.delta_p().norm_squared());
    for i in 0..3 {
        cov[(i, i)] += 2.0 * sr2;
        cov[(3 + i, 3 + i)] += sr2 * dv2;
        cov[(6 + i, 6 + i)] += 2.0 * sp2 + sr2 * dp2;
    }
    cov.try_inverse().unwrap_or_else(Matrix9::identity)
}

/// Gaussian priors around zero on the biases (columns `c..c + 6`).
fn add_bias_priors(
    h: &mut DMatrix<f64>,
    b: &mut DVector<f64>,
    cost: &mut f64,
    st: &MapState,
    c: usize,
    params: &InitParams,
) {
    let wg = 1.0 / (params.prior_gyro_bias * params.prior_gyro_bias);
    let wa = 1.0 / (params.prior_accel_bias * params.prior_accel_bias);
    for i in 0..3 {
        h[(c + i, c + i)] += wg;
        b[c + i] += wg * st.biases.gyro[i];
        h[(c + 3 + i, c + 3 + i)] += wa;
        b[c + 3 + i] += wa * st.biases.accel[i];
    }
    *cost += wg * st.biases.gyro.norm_squared() + wa * st.biases.accel.norm_squared();
}

/// Step 3: Levenberg-Marquardt; returns the cost, the iterations and the 1σ of `log s` and
/// of the gravity direction.
fn refine(
    frames: &BodyFrames,
    preints: &[Preintegrated],
    st: &mut MapState,
    params: &InitParams,
) -> (f64, usize, (f64, f64)) {
    let (mut h, mut b, mut cost) = normal_equations(frames, preints, st, params);
    let mut lambda = 1e-4;
    let mut it = 0;
    while it < params.max_iterations {
        it += 1;
        let mut hd = h.clone();
        for i in 0..hd.nrows() {
            hd[(i, i)] *= 1.0 + lambda;
        }
        let Some(chol) = hd.cholesky() else {
            lambda *= 10.0;
            continue;
        };
        let step = -chol.solve(&b);
        let cand = st.moved(&step);
        let (h2, b2, c2) = normal_equations(frames, preints, &cand, params);
        if c2 < cost {
            let small = step.norm() < 1e-10 || (cost - c2) < 1e-12 * cost.max(1.0);
            (*st, h, b, cost) = (cand, h2, b2, c2);
            lambda = (lambda * 0.3).max(1e-9);
            if small {
                break;
            }
        } else {
            lambda *= 10.0;
            if lambda > 1e8 {
                break;
            }
        }
    }
    (cost, it, sigmas(&h, st.velocities.len()))
}

/// 1σ of `log s` and of the gravity direction (larger axis) from the normal matrix `h`.
fn sigmas(h: &DMatrix<f64>, n: usize) -> (f64, f64) {
    let Some(cov) = h.clone().try_inverse() else {
        return (f64::INFINITY, f64::INFINITY);
    };
    let o = 3 * n;
    let s = cov[(o + 2, o + 2)].max(0.0).sqrt();
    let g = nalgebra::Matrix2::new(
        cov[(o, o)],
        cov[(o, o + 1)],
        cov[(o + 1, o)],
        cov[(o + 1, o + 1)],
    );
    let gmax = g.symmetric_eigenvalues().max().max(0.0).sqrt();
    (s, gmax)
}
