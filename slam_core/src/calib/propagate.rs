//! IMU propagation of the calibration filter (`VI_NOTES.md` §2 and §3 "Propagation"; seed
//! 4.2, Li et al. ICRA 2014 for the T-model).
//!
//! Per step of `dt` with corrected `ω̂ = T̂_g⁻¹(ω_m - T̂_s â_s - b̂_g)` and
//! `â_s = T̂_a⁻¹(a_m - b̂_a)` held constant (mid-point of the raw samples), the nominal state
//! moves by [`NavState::step`] and the error by `dx_{k+1} = Φ dx_k + G n`. Only the rows of
//! `dθ, dp, dv` differ from the identity (biases are random walks, the calibration is
//! constant), so [`Transition`] holds those 9 rows of Φ and the filter applies them to the
//! whole covariance, clone cross terms included.
//!
//! **Error dynamics** (global rotation error `R = Exp(dθ) R̂`):
//! ```text
//! da_s = -T̂_a⁻¹ (δT_a â_s + db_a + n_a)            δT x = (I ⊗ xᵀ) vec(δT), row-major
//! dω   = -T̂_g⁻¹ (δT_g ω̂ + δT_s â_s + T̂_s da_s + db_g + n_g)
//! dθ_{k+1} = dθ_k + R̂_{k+1} Jr(ω̂ dt) dt dω
//! dv_{k+1} = dv_k - [v̂_{k+1} - v̂_k - g dt]x dθ_k + R̂_mid dt da_s + W dt²/2 dω
//! dp_{k+1} = dp_k + dt dv_k - [p̂_{k+1} - p̂_k - v̂_k dt - ½ g dt²]x dθ_k
//!            + R̂_mid dt²/2 da_s + W dt³/4 dω,      W = -[R̂_mid â_s]x R̂_mid Jr(ω̂ dt/2)
//! ```
//! These are the exact derivatives of the mid-point rule of [`NavState::step`] (the
//! continuous-time model gives dt³/6 for the last term; the difference is O(dt³)).
//! **FEJ** (Li & Mourikis, IJRR 2013): the `dθ` columns of the `dp` and `dv` rows, the only
//! places p̂ and v̂ enter Φ, use the **first estimates** `p̂_k, v̂_k` (the propagated values
//! before any update at step k, [`FirstEstimates`]) and the propagated `p̂_{k+1}, v̂_{k+1}`, so
//! that products of Φ telescope and the yaw/position null space is kept. Everything else
//! (R̂, â_s, ω̂, T̂) is linearised at the current estimate.
//!
//! **Noise.** `n_g, n_a` are the mean white noise over the step, variances `σ²/dt` per axis
//! (densities of [`ImuNoise`]); the biases take `σ_b² dt`. `Q_d = G diag(σ²/dt) Gᵀ` with G
//! the noise columns of the same discrete map (`VI_NOTES.md` §3 `Q_d ≈ Φ G Q_c Gᵀ Φᵀ Δt`
//! to first order in dt).

use nalgebra::{Matrix3, SMatrix, Vector3};

use super::state::{CalibState, NavState};
use super::{CORE_DIM, IDX_BA, IDX_BG, IDX_P, IDX_TA, IDX_TG, IDX_THETA, IDX_TS, IDX_V};
use crate::imu::{gravity_w, ImuNoise};
use crate::lie::{skew, so3_exp, so3_jr};

/// Rows `dθ, dp, dv` of Φ over the whole core error state.
pub type PhiTop = SMatrix<f64, 9, CORE_DIM>;

/// First estimates of the IMU position and velocity (FEJ): the propagated values, never the
/// updated ones.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FirstEstimates {
    /// First estimate of `p_gb`.
    pub p: Vector3<f64>,
    /// First estimate of `v_gb`.
    pub v: Vector3<f64>,
}

impl FirstEstimates {
    /// First estimates equal to the current state (the start, and after augmentation).
    pub fn of(nav: &NavState) -> Self {
        Self {
            p: nav.p_gb,
            v: nav.v_gb,
        }
    }
}

/// One step's discrete transition: Φ's top rows and the process noise.
#[derive(Debug, Clone, PartialEq)]
pub struct Transition {
    /// Rows `dθ, dp, dv` of Φ (identity elsewhere).
    pub phi: PhiTop,
    /// Process noise of `dθ, dp, dv` (9x9).
    pub q_nav: SMatrix<f64, 9, 9>,
    /// Bias random-walk variances added over the step: `(σ_bg² dt, σ_ba² dt)`.
    pub q_bias: (f64, f64),
}

/// `I_3 ⊗ xᵀ`: the 3x9 map with `δT x = (I ⊗ xᵀ) vec(δT)` for row-major `vec`.
pub fn kron_row(x: &Vector3<f64>) -> SMatrix<f64, 3, 9> {
    let mut m = SMatrix::<f64, 3, 9>::zeros();
    for r in 0..3 {
        for c in 0..3 {
            m[(r, 3 * r + c)] = x[c];
        }
    }
    m
}

/// Jacobians of `da_s` and `dω` with respect to the core error state (3x55 each), at the
/// corrected rate `w` and specific force `a`.
pub fn rate_jacobians(
    state: &CalibState,
    w: &Vector3<f64>,
    a: &Vector3<f64>,
) -> (SMatrix<f64, 3, CORE_DIM>, SMatrix<f64, 3, CORE_DIM>) {
    let (ta_inv, tg_inv) = state.imu_inverses();
    let mut ja = SMatrix::<f64, 3, CORE_DIM>::zeros();
    ja.fixed_view_mut::<3, 3>(0, IDX_BA).copy_from(&(-ta_inv));
    ja.fixed_view_mut::<3, 9>(0, IDX_TA)
        .copy_from(&(-ta_inv * kron_row(a)));
    let mut jw = -(tg_inv * state.imu.t_s) * ja;
    let mut add = |col: usize, m: SMatrix<f64, 3, 9>| {
        let mut v = jw.fixed_view_mut::<3, 9>(0, col);
        v += m;
    };
    add(IDX_TG, -tg_inv * kron_row(w));
    add(IDX_TS, -tg_inv * kron_row(a));
    let mut b = jw.fixed_view_mut::<3, 3>(0, IDX_BG);
    b -= tg_inv;
    (ja, jw)
}

/// Propagates `state` over one step of `dt` s with raw `(gyro, accel)` (already the
/// mid-point values) and returns the discrete [`Transition`]. `fej` holds the first
/// estimates at the step's start and is moved to the propagated values.
pub fn propagate_step(
    state: &mut CalibState,
    fej: &mut FirstEstimates,
    gyro: &Vector3<f64>,
    accel: &Vector3<f64>,
    dt: f64,
    noise: &ImuNoise,
) -> Transition {
    let (w, a) = state.correct(gyro, accel);
    let r_mid = (state.nav.r_gb * so3_exp(&(w * (0.5 * dt)))).into_inner();
    let (ja, jw) = rate_jacobians(state, &w, &a);
    state.nav.step(&w, &a, dt);
    state.t_ns += (dt * 1e9).round() as i64;
    let r_next = state.nav.r_gb.into_inner();
    let g = gravity_w();
    let ra = skew(&(r_mid * a));
    let g_tw = r_next * so3_jr(&(w * dt)) * dt;
    // dω turns R_mid by R_mid Jr(ω dt/2) dω dt/2 (the mid-point rule of NavState::step).
    let turn = -ra * r_mid * so3_jr(&(w * (0.5 * dt)));
    let (g_va, g_vw) = (r_mid * dt, turn * (0.5 * dt * dt));
    let (g_pa, g_pw) = (r_mid * (0.5 * dt * dt), turn * (0.25 * dt * dt * dt));
    let dv = state.nav.v_gb - fej.v - g * dt;
    let dp = state.nav.p_gb - fej.p - fej.v * dt - g * (0.5 * dt * dt);
    let mut phi = PhiTop::zeros();
    phi.fixed_view_mut::<3, CORE_DIM>(0, 0)
        .copy_from(&(g_tw * jw));
    phi.fixed_view_mut::<3, CORE_DIM>(3, 0)
        .copy_from(&(g_pa * ja + g_pw * jw));
    phi.fixed_view_mut::<3, CORE_DIM>(6, 0)
        .copy_from(&(g_va * ja + g_vw * jw));
    for k in 0..9 {
        phi[(k, k)] += 1.0;
    }
    phi.fixed_view_mut::<3, 3>(3, IDX_THETA)
        .copy_from(&(-skew(&dp)));
    phi.fixed_view_mut::<3, 3>(6, IDX_THETA)
        .copy_from(&(-skew(&dv)));
    phi.fixed_view_mut::<3, 3>(3, IDX_V)
        .copy_from(&(Matrix3::identity() * dt));
    debug_assert_eq!(IDX_P, 3);
    *fej = FirstEstimates::of(&state.nav);
    Transition {
        phi,
        q_nav: process_noise(state, [g_tw, g_pw, g_vw], [g_pa, g_va], dt, noise),
        q_bias: (
            noise.gyro_bias_rw.powi(2) * dt.abs(),
            noise.accel_bias_rw.powi(2) * dt.abs(),
        ),
    }
}

/// `Q_d = G diag(σ_g²/dt, σ_a²/dt) Gᵀ` for the rows `dθ, dp, dv`, with the noise columns
/// `dω = -T_g⁻¹ n_g + T_g⁻¹ T_s T_a⁻¹ n_a`, `da_s = -T_a⁻¹ n_a` pushed through the step.
fn process_noise(
    state: &CalibState,
    g_w: [Matrix3<f64>; 3],
    g_a: [Matrix3<f64>; 2],
    dt: f64,
    noise: &ImuNoise,
) -> SMatrix<f64, 9, 9> {
    if dt <= 0.0 {
        return SMatrix::zeros();
    }
    let (ta_inv, tg_inv) = state.imu_inverses();
    let w_ng = -tg_inv;
    let w_na = tg_inv * state.imu.t_s * ta_inv;
    let a_na = -ta_inv;
    let mut gn = SMatrix::<f64, 9, 6>::zeros();
    gn.fixed_view_mut::<3, 3>(0, 0).copy_from(&(g_w[0] * w_ng));
    gn.fixed_view_mut::<3, 3>(0, 3).copy_from(&(g_w[0] * w_na));
    gn.fixed_view_mut::<3, 3>(3, 0).copy_from(&(g_w[1] * w_ng));
    gn.fixed_view_mut::<3, 3>(3, 3)
        .copy_from(&(g_a[0] * a_na + g_w[1] * w_na));
    gn.fixed_view_mut::<3, 3>(6, 0).copy_from(&(g_w[2] * w_ng));
    gn.fixed_view_mut::<3, 3>(6, 3)
        .copy_from(&(g_a[1] * a_na + g_w[2] * w_na));
    let sg = noise.gyro_noise_density.powi(2) / dt;
    let sa = noise.accel_noise_density.powi(2) / dt;
    let d = SMatrix::<f64, 6, 6>::from_diagonal(&nalgebra::Vector6::new(sg, sg, sg, sa, sa, sa));
    gn * d * gn.transpose()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::sim::test_state;
    use crate::lie::so3_log;
    use nalgebra::DVector;

    /// The error `(dθ, dp, dv)` of `a` relative to `b`: `R_a = Exp(dθ) R_b`.
    fn nav_error(a: &NavState, b: &NavState) -> SMatrix<f64, 9, 1> {
        let mut e = SMatrix::<f64, 9, 1>::zeros();
        e.fixed_rows_mut::<3>(0)
            .copy_from(&so3_log(&(a.r_gb * b.r_gb.inverse())));
        e.fixed_rows_mut::<3>(3).copy_from(&(a.p_gb - b.p_gb));
        e.fixed_rows_mut::<3>(6).copy_from(&(a.v_gb - b.v_gb));
        e
    }

    #[test]
    fn transition_matches_finite_differences() {
        let base = test_state();
        let (gyro, accel) = (Vector3::new(0.9, -1.3, 0.6), Vector3::new(1.5, -0.7, 9.2));
        let dt = 0.01;
        let noise = ImuNoise::default();
        let run = |s: &CalibState| {
            let mut s = *s;
            let mut f = FirstEstimates::of(&s.nav);
            let t = propagate_step(&mut s, &mut f, &gyro, &accel, dt, &noise);
            (s, t)
        };
        let (end, tr) = run(&base);
        let h = 1e-6;
        for col in 0..CORE_DIM {
            let mut dx = DVector::zeros(CORE_DIM);
            dx[col] = h;
            let mut plus = base;
            plus.retract(&dx);
            let mut minus = base;
            minus.retract(&(-dx));
            let num = (nav_error(&run(&plus).0.nav, &end.nav)
                - nav_error(&run(&minus).0.nav, &end.nav))
                / (2.0 * h);
            let ana = tr.phi.column(col);
            let err = (num - ana).norm();
            assert!(
                err < 1e-6 * (1.0 + num.norm()),
                "column {col}: {err}\n{num}\n{ana}"
            );
        }
        assert!(tr.q_nav.symmetric_eigenvalues().min() >= -1e-18);
    }
}
