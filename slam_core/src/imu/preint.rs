//! IMU preintegration on the manifold between two keyframes (Forster, Carlone, Dellaert &
//! Scaramuzza, "On-Manifold Preintegration for Real-Time Visual-Inertial Odometry", T-RO
//! 2017; `VI_NOTES.md` §4), with the seed's IMU model (eq. 2.53-2.56).
//!
//! **Deltas.** For IMU steps `k = i..j` of length `δt_k` with corrected rate `ω_k` and specific
//! force `a_k` (below), body frame at `i`:
//! ```text
//! ΔR_ij = Π ΔR_k,k+1,                               ΔR_k,k+1 = Exp(ω_k δt)
//! Δv_ij = Σ R_mid,k a_k δt,                         R_mid,k = ΔR_ik Exp(ω_k δt/2)
//! Δp_ij = Σ Δv_ik δt + ½ R_mid,k a_k δt²
//! ```
//! so that, with gravity `g` in the world frame and `Δt = Σ δt`,
//! `R_j = R_i ΔR_ij`, `v_j = v_i + g Δt + R_i Δv_ij`, `p_j = p_i + v_i Δt + ½ g Δt² + R_i Δp_ij`.
//!
//! **Integration scheme: midpoint.** A step holds `ω`, `a` constant (they should be the
//! interval's mean, which is what [`Preintegrated::integrate_window`] passes: the mean of the
//! two bracketing samples, i.e. of the linearly interpolated signal), and rotates `a` by the
//! orientation at the middle of the step, `R_mid`, instead of the step's start (Forster's
//! Euler form, first order). The scheme is second order in the sample period: noise-free
//! samples of the sim's `loop` path (200 Hz) give the exact motion to ~1e-6 (rad, m/s, m)
//! over 0.1-2 s; fast motion costs more (`fast-rs` with its 3-6 Hz shake: 1.5e-3 m/s at
//! 200 Hz, 6e-5 at 1000 Hz), the interpolation of the samples being the limit. Feeding raw
//! samples one by one to
//! [`Preintegrated::integrate`] (`dt` = time to the next sample) is a zero-order hold, first
//! order.
//!
//! **Intrinsics.** Measurements are corrected first (T fixed, `VI_NOTES.md` §4):
//! `ã = T_a⁻¹ a_m`, `ω̃ = T_g⁻¹ (ω_m - T_s ã)`, then `a = ã - b_a`, `ω = ω̃ - b_g` with the
//! **effective** biases `b'_a = T_a⁻¹ b_a`, `b'_g = T_g⁻¹ (b_g - T_s b'_a)`
//! ([`MeasurementCorrection::effective_biases`]). Every bias in this module is effective;
//! with ideal intrinsics (`T_a = T_g = I`, `T_s = 0`) effective and raw biases are the same.
//! The white noise is mapped the same way, `ñ_a = T_a⁻¹ n_a`,
//! `ñ_g = T_g⁻¹ (n_g - T_s T_a⁻¹ n_a)`, cross-covariance included.
//!
//! **Covariance** of the deltas, 9x9, order `[δφ; δv; δp]` (rotation first), with
//! `ΔR̂ = ΔR Exp(δφ)`, `Δv̂ = Δv + δv`, `Δp̂ = Δp + δp` (estimate from noisy samples vs
//! truth). Per step `Σ ← A Σ Aᵀ + B Q_c/δt Bᵀ`, `Q_c = diag(σ_g² I, σ_a² I)` (continuous
//! densities, mapped through the intrinsics) and, with `E = Exp(ω δt)`, `E_h = Exp(ω δt/2)`,
//! `J = Jr(ω δt)`, `J_h = Jr(ω δt/2)`, `[·]` = skew:
//! ```text
//! A = [ Eᵀ                   0     0 ]     B = [ J δt                     0             ]
//!     [ -ΔR [E_h a] δt       I     0 ]         [ -R_mid [a] J_h δt²/2     R_mid δt      ]
//!     [ -ΔR [E_h a] δt²/2    I δt  I ]         [ -R_mid [a] J_h δt³/4     R_mid δt²/2   ]
//! ```
//! (`ΔR` before the step). The 9x6 bias Jacobian `∂[φ; v; p]/∂[b_g; b_a]` follows
//! `J_b ← A J_b - B` (a bias change is a constant negative noise); `∂φ/∂b_a = 0`.
//!
//! **First-order bias update** ([`Preintegrated::corrected`]), `δb = b - b̄` (b̄ = the
//! linearisation biases): `ΔR(b) ≈ ΔR Exp(J^R_g δb_g)`, `Δv(b) ≈ Δv + J^v_g δb_g + J^v_a δb_a`,
//! `Δp(b) ≈ Δp + J^p_g δb_g + J^p_a δb_a`. Re-integrate when `δb` grows large.
//!
//! **Residual** between navigation states ([`Preintegrated::residual`]), 15 rows
//! `[r_R; r_v; r_p; r_bg; r_ba]`, using the biases of state `i`:
//! ```text
//! r_R = Log(ΔR(b_i)ᵀ R_iᵀ R_j)
//! r_v = R_iᵀ (v_j - v_i - g Δt) - Δv(b_i)
//! r_p = R_iᵀ (p_j - p_i - v_i Δt - ½ g Δt²) - Δp(b_i)
//! r_bg = b_g,j - b_g,i,   r_ba = b_a,j - b_a,i      (bias random walk)
//! ```
//! with covariance [`Preintegrated::residual_covariance`] = `diag(Σ, σ_bg² Δt I, σ_ba² Δt I)`.
//! Jacobians are with respect to each state's 15-vector `[δθ; δp; δv; δb_g; δb_a]` as
//! applied by [`NavState::retract`]: `R ← R Exp(δθ)` (right, body frame), `p ← p + δp`,
//! `v ← v + δv` (world frame), `b ← b + δb` (the VINS-Mono convention).

use nalgebra::{
    Isometry3, Matrix3, Rotation3, SMatrix, SVector, Translation3, UnitQuaternion, Vector3,
};

use super::{ImuBiases, ImuIntrinsics, ImuNoise};
use crate::lie::{skew, so3_exp, so3_jr, so3_jr_inv, so3_log};
use crate::CoreError;

/// 9x9 matrix (covariance of `[δφ; δv; δp]`).
pub type Matrix9 = SMatrix<f64, 9, 9>;
/// 15x15 matrix (residual covariance, Jacobians w.r.t. a navigation state).
pub type Matrix15 = SMatrix<f64, 15, 15>;
/// 6x6 matrix (noise of `[gyro; accel]`).
pub type Matrix6 = SMatrix<f64, 6, 6>;
/// 9x6 matrix (bias Jacobian `∂[φ; v; p]/∂[b_g; b_a]`).
pub type Matrix9x6 = SMatrix<f64, 9, 6>;
/// 9-vector `[φ; v; p]`.
pub type Vector9 = SVector<f64, 9>;
/// 15-vector (residual `[r_R; r_v; r_p; r_bg; r_ba]` or state tangent `[θ; p; v; b_g; b_a]`).
pub type Vector15 = SVector<f64, 15>;

/// An IMU sample with its time on the IMU clock, as read by [`Preintegrated::integrate_window`].
pub trait TimedImuSample {
    /// Time, ns on the IMU clock.
    fn t_ns(&self) -> i64;
    /// Raw angular rate `ω_m`, rad/s.
    fn gyro(&self) -> Vector3<f64>;
    /// Raw specific force `a_m`, m/s².
    fn accel(&self) -> Vector3<f64>;
}

/// A plain timestamped IMU measurement.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct ImuMeasurement {
    /// Time, ns on the IMU clock.
    pub t_ns: i64,
    /// Raw angular rate `ω_m`, rad/s.
    pub gyro: Vector3<f64>,
    /// Raw specific force `a_m`, m/s².
    pub accel: Vector3<f64>,
}

impl TimedImuSample for ImuMeasurement {
    fn t_ns(&self) -> i64 {
        self.t_ns
    }
    fn gyro(&self) -> Vector3<f64> {
        self.gyro
    }
    fn accel(&self) -> Vector3<f64> {
        self.accel
    }
}

/// The inverted IMU intrinsics applied to every measurement:
/// `ã = T_a⁻¹ a_m`, `ω̃ = T_g⁻¹ (ω_m - T_s ã)`.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct MeasurementCorrection {
    t_a_inv: Matrix3<f64>,
    t_g_inv: Matrix3<f64>,
    t_s: Matrix3<f64>,
    ideal: bool,
}

impl MeasurementCorrection {
    /// Inverts `T_a` and `T_g`. Fails when either is singular or not finite.
    pub fn new(k: &ImuIntrinsics) -> Result<Self, CoreError> {
        let finite = k
            .t_a
            .iter()
            .chain(k.t_g.iter())
            .chain(k.t_s.iter())
            .all(|v| v.is_finite());
        let inv = |m: &Matrix3<f64>, name: &str| {
            m.try_inverse()
                .filter(|i| finite && i.iter().all(|v| v.is_finite()))
                .ok_or_else(|| {
                    CoreError::InvalidArgument(format!(
                        "IMU intrinsics: {name} is singular or not finite"
                    ))
                })
        };
        Ok(Self {
            t_a_inv: inv(&k.t_a, "T_a")?,
            t_g_inv: inv(&k.t_g, "T_g")?,
            t_s: k.t_s,
            ideal: k.is_ideal(),
        })
    }

    /// The corrected `(ω̃, ã)` of a raw measurement `(ω_m, a_m)`.
    #[inline]
    pub fn apply(&self, gyro: &Vector3<f64>, accel: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
        if self.ideal {
            return (*gyro, *accel);
        }
        let a = self.t_a_inv * accel;
        (self.t_g_inv * (gyro - self.t_s * a), a)
    }

    /// The effective biases of raw model biases: `b'_a = T_a⁻¹ b_a`,
    /// `b'_g = T_g⁻¹ (b_g - T_s b'_a)`, so that `ω = ω̃ - b'_g`, `a_s = ã - b'_a`.
    pub fn effective_biases(&self, raw: &ImuBiases) -> ImuBiases {
        let (gyro, accel) = self.apply(&raw.gyro, &raw.accel);
        ImuBiases { gyro, accel }
    }

    /// The raw model biases of effective ones (inverse of [`Self::effective_biases`]):
    /// `b_a = T_a b'_a`, `b_g = T_g b'_g + T_s b'_a`.
    pub fn raw_biases(&self, eff: &ImuBiases) -> ImuBiases {
        if self.ideal {
            return *eff;
        }
        let t_a = self.t_a_inv.try_inverse().unwrap_or_else(Matrix3::identity);
        let t_g = self.t_g_inv.try_inverse().unwrap_or_else(Matrix3::identity);
        ImuBiases {
            gyro: t_g * eff.gyro + self.t_s * eff.accel,
            accel: t_a * eff.accel,
        }
    }

    /// The linear map of raw `[n_g; n_a]` to corrected `[ñ_g; ñ_a]`.
    fn noise_map(&self) -> Matrix6 {
        let mut c = Matrix6::zeros();
        c.fixed_view_mut::<3, 3>(0, 0).copy_from(&self.t_g_inv);
        c.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&(-self.t_g_inv * self.t_s * self.t_a_inv));
        c.fixed_view_mut::<3, 3>(3, 3).copy_from(&self.t_a_inv);
        c
    }
}

/// Fixed settings of a preintegration: noise densities and the intrinsics correction.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct PreintegrationParams {
    /// The measurement correction (inverted intrinsics).
    pub correction: MeasurementCorrection,
    /// Continuous-time white-noise covariance of the corrected `[ω̃; ã]`, per second.
    pub noise_cov: Matrix6,
    /// Bias random-walk densities `(σ_bg, σ_ba)` (rad/s²/√Hz, m/s³/√Hz).
    pub bias_walk: (f64, f64),
    /// The noise densities these settings were made from (a keyframe message carries them
    /// so that the server builds the same settings, `VI_NOTES.md` §4 "Server").
    pub noise: ImuNoise,
    /// The intrinsics these settings were made from (idem).
    pub intrinsics: ImuIntrinsics,
}

impl PreintegrationParams {
    /// Settings for noise densities `noise` and intrinsics `intrinsics` (fails when `T_a`
    /// or `T_g` is singular, or a noise density is negative or not finite).
    pub fn new(noise: &ImuNoise, intrinsics: &ImuIntrinsics) -> Result<Self, CoreError> {
        let d = [
            noise.gyro_noise_density,
            noise.accel_noise_density,
            noise.gyro_bias_rw,
            noise.accel_bias_rw,
        ];
        if !d.iter().all(|v| v.is_finite() && *v >= 0.0) {
            return Err(CoreError::InvalidArgument(format!(
                "IMU noise densities {d:?}"
            )));
        }
        let correction = MeasurementCorrection::new(intrinsics)?;
        let (sg2, sa2) = (d[0] * d[0], d[1] * d[1]);
        let raw = Matrix6::from_diagonal(&SVector::<f64, 6>::new(sg2, sg2, sg2, sa2, sa2, sa2));
        let c = correction.noise_map();
        Ok(Self {
            correction,
            noise_cov: c * raw * c.transpose(),
            bias_walk: (d[2], d[3]),
            noise: *noise,
            intrinsics: *intrinsics,
        })
    }
}

/// Preintegrated IMU deltas between two times, with covariance and bias Jacobians (see the
/// module docs for the equations and conventions).
#[derive(Debug, Clone, PartialEq)]
pub struct Preintegrated {
    params: PreintegrationParams,
    bias_lin: ImuBiases,
    delta_r: Matrix3<f64>,
    delta_v: Vector3<f64>,
    delta_p: Vector3<f64>,
    dt: f64,
    cov: Matrix9,
    jac_bias: Matrix9x6,
}

/// A navigation state: orientation `R_gb`, position `p_gb`, velocity `v_gb` (world frame) and
/// effective IMU biases.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NavState {
    /// Orientation `R_gb` (body to world).
    pub r: Rotation3<f64>,
    /// Position of the body in the world, m.
    pub p: Vector3<f64>,
    /// Velocity of the body in the world, m/s.
    pub v: Vector3<f64>,
    /// Effective biases (equal to the raw biases with ideal intrinsics).
    pub biases: ImuBiases,
}

impl NavState {
    /// The body state of a camera pose `t_cw` (world to camera) for a camera at `t_bc` in
    /// the body (`p_b = T_bc p_c`): `T_wb = T_cw⁻¹ T_bc⁻¹`, velocity `v_wb`, `biases`.
    pub fn from_camera(
        t_cw: &Isometry3<f64>,
        t_bc: &Isometry3<f64>,
        v_wb: Vector3<f64>,
        biases: ImuBiases,
    ) -> NavState {
        let t_wb = t_cw.inverse() * t_bc.inverse();
        NavState {
            r: Rotation3::from(t_wb.rotation),
            p: t_wb.translation.vector,
            v: v_wb,
            biases,
        }
    }

    /// The body pose `T_wb`.
    pub fn body_pose(&self) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::from(self.p),
            UnitQuaternion::from_rotation_matrix(&self.r),
        )
    }

    /// The camera pose `T_cw` (world to camera) of a camera at `t_bc` in the body.
    pub fn camera_pose(&self, t_bc: &Isometry3<f64>) -> Isometry3<f64> {
        (self.body_pose() * t_bc).inverse()
    }

    /// The state moved by a tangent `d = [δθ; δp; δv; δb_g; δb_a]`: `R Exp(δθ)`, `p + δp`,
    /// `v + δv`, `b + δb` (the perturbation of the residual Jacobians).
    pub fn retract(&self, d: &Vector15) -> NavState {
        let seg = |k: usize| Vector3::new(d[k], d[k + 1], d[k + 2]);
        NavState {
            r: self.r * so3_exp(&seg(0)),
            p: self.p + seg(3),
            v: self.v + seg(6),
            biases: ImuBiases {
                gyro: self.biases.gyro + seg(9),
                accel: self.biases.accel + seg(12),
            },
        }
    }
}

/// An IMU residual and its Jacobians (see [`Preintegrated::residual`]).
#[derive(Debug, Clone, PartialEq)]
pub struct ImuResidual {
    /// `[r_R; r_v; r_p; r_bg; r_ba]`.
    pub r: Vector15,
    /// `∂r/∂[δθ_i; δp_i; δv_i; δb_g,i; δb_a,i]`.
    pub jac_i: Matrix15,
    /// `∂r/∂[δθ_j; δp_j; δv_j; δb_g,j; δb_a,j]`.
    pub jac_j: Matrix15,
}

#[inline]
fn block3(m: &Matrix9x6, r: usize, c: usize) -> Matrix3<f64> {
    m.fixed_view::<3, 3>(r, c).into_owned()
}

/// Linear interpolation of a sample pair at `t` (ns); `a.t_ns < b.t_ns` is not required.
/// The sample linearly interpolated between `a` and `b` at `t_ns` (`VI_NOTES.md` §4,
/// Fig. 5.4: `y(t) = y_a + (t - t_a)/(t_b - t_a) (y_b - y_a)`; `y_a` when both share a
/// time), computed as [`Preintegrated::integrate_window`] does at a window's borders.
pub fn interpolate<S: TimedImuSample>(a: &S, b: &S, t_ns: i64) -> ImuMeasurement {
    let (gyro, accel) = lerp(a, b, t_ns);
    ImuMeasurement { t_ns, gyro, accel }
}

fn lerp<S: TimedImuSample>(a: &S, b: &S, t: i64) -> (Vector3<f64>, Vector3<f64>) {
    let span = b.t_ns() - a.t_ns();
    let s = if span > 0 {
        (t - a.t_ns()) as f64 / span as f64
    } else {
        0.0
    };
    let (ga, aa) = (a.gyro(), a.accel());
    (ga + (b.gyro() - ga) * s, aa + (b.accel() - aa) * s)
}

impl Preintegrated {
    /// An empty preintegration (identity deltas, zero covariance) linearised at the
    /// effective biases `bias_lin`.
    pub fn new(bias_lin: ImuBiases, params: PreintegrationParams) -> Self {
        Self {
            params,
            bias_lin,
            delta_r: Matrix3::identity(),
            delta_v: Vector3::zeros(),
            delta_p: Vector3::zeros(),
            dt: 0.0,
            cov: Matrix9::zeros(),
            jac_bias: Matrix9x6::zeros(),
        }
    }

    /// Adds one step of `dt` seconds with the raw measurement `(gyro, accel)` held over it
    /// (ideally the step's mean; see the module docs). Corrects the intrinsics, subtracts the
    /// linearisation biases, and propagates deltas, covariance and bias Jacobians (midpoint
    /// rule). `dt <= 0` (or not finite) is a no-op. Allocates nothing.
    pub fn integrate(&mut self, dt: f64, gyro: &Vector3<f64>, accel: &Vector3<f64>) {
        if !(dt > 0.0 && dt.is_finite()) {
            return;
        }
        let (w_c, a_c) = self.params.correction.apply(gyro, accel);
        let w = w_c - self.bias_lin.gyro;
        let a = a_c - self.bias_lin.accel;
        let th = w * dt;
        let e = *so3_exp(&th).matrix();
        let e_h = *so3_exp(&(th * 0.5)).matrix();
        let jr = so3_jr(&th);
        let jr_h = so3_jr(&(th * 0.5));
        let dr = self.delta_r;
        let r_mid = dr * e_h;
        let acc = r_mid * a;
        let (dt2, dt3) = (dt * dt, dt * dt * dt);

        // A (9x9) and B (9x6) of the module docs, with the pre-step ΔR.
        let a_vphi = -dr * skew(&(e_h * a)) * dt;
        let r_mid_ax_jh = r_mid * skew(&a) * jr_h;
        let mut am = Matrix9::identity();
        am.fixed_view_mut::<3, 3>(0, 0).copy_from(&e.transpose());
        am.fixed_view_mut::<3, 3>(3, 0).copy_from(&a_vphi);
        am.fixed_view_mut::<3, 3>(6, 0)
            .copy_from(&(a_vphi * (0.5 * dt)));
        am.fixed_view_mut::<3, 3>(6, 3)
            .copy_from(&(Matrix3::identity() * dt));
        let mut bm = Matrix9x6::zeros();
        bm.fixed_view_mut::<3, 3>(0, 0).copy_from(&(jr * dt));
        bm.fixed_view_mut::<3, 3>(3, 0)
            .copy_from(&(r_mid_ax_jh * (-0.5 * dt2)));
        bm.fixed_view_mut::<3, 3>(6, 0)
            .copy_from(&(r_mid_ax_jh * (-0.25 * dt3)));
        bm.fixed_view_mut::<3, 3>(3, 3).copy_from(&(r_mid * dt));
        bm.fixed_view_mut::<3, 3>(6, 3)
            .copy_from(&(r_mid * (0.5 * dt2)));

        self.cov = am * self.cov * am.transpose()
            + bm * (self.params.noise_cov * (1.0 / dt)) * bm.transpose();
        // Keep it exactly symmetric.
        self.cov = (self.cov + self.cov.transpose()) * 0.5;
        self.jac_bias = am * self.jac_bias - bm;

        self.delta_p += self.delta_v * dt + acc * (0.5 * dt2);
        self.delta_v += acc * dt;
        self.delta_r = dr * e;
        self.dt += dt;
    }

    /// Integrates the samples of `samples` (sorted by time) over `[t0_ns, t1_ns]`: the
    /// signal is the linear interpolation of the samples, the window's ends are
    /// interpolated from their two bracketing samples (`VI_NOTES.md` §4, Fig. 5.4), and each
    /// step between consecutive points uses the mean of its two end values (midpoint).
    /// Consecutive windows sharing a border integrate the signal once, without gap or
    /// overlap. Returns `false` (and changes nothing) when the samples do not bracket the
    /// window or `t1_ns < t0_ns`. Allocates nothing.
    pub fn integrate_window<S: TimedImuSample>(
        &mut self,
        samples: &[S],
        t0_ns: i64,
        t1_ns: i64,
    ) -> bool {
        let n = samples.len();
        if t1_ns < t0_ns || n == 0 || samples[0].t_ns() > t0_ns || samples[n - 1].t_ns() < t1_ns {
            return false;
        }
        if t1_ns == t0_ns {
            return true;
        }
        // First sample strictly after t0 (exists: the last sample is >= t1 > t0).
        let mut k = samples.partition_point(|s| s.t_ns() <= t0_ns);
        let (mut t_prev, (mut g_prev, mut a_prev)) =
            (t0_ns, lerp(&samples[k - 1], &samples[k], t0_ns));
        loop {
            let (t, g, a) = if samples[k].t_ns() < t1_ns {
                (samples[k].t_ns(), samples[k].gyro(), samples[k].accel())
            } else {
                let (g, a) = lerp(&samples[k - 1], &samples[k], t1_ns);
                (t1_ns, g, a)
            };
            let dt = (t - t_prev) as f64 * 1e-9;
            self.integrate(dt, &((g_prev + g) * 0.5), &((a_prev + a) * 0.5));
            if t == t1_ns {
                return true;
            }
            (t_prev, g_prev, a_prev) = (t, g, a);
            k += 1;
        }
    }

    /// Preintegrates `samples` over `[t0_ns, t1_ns]` (see [`Self::integrate_window`]);
    /// `None` when the samples do not bracket the window.
    pub fn from_window<S: TimedImuSample>(
        samples: &[S],
        t0_ns: i64,
        t1_ns: i64,
        bias_lin: ImuBiases,
        params: PreintegrationParams,
    ) -> Option<Self> {
        let mut p = Self::new(bias_lin, params);
        p.integrate_window(samples, t0_ns, t1_ns).then_some(p)
    }

    /// `ΔR_ij` at the linearisation biases.
    pub fn delta_r(&self) -> Rotation3<f64> {
        Rotation3::from_matrix_unchecked(self.delta_r)
    }
    /// `Δv_ij` at the linearisation biases (body frame at i), m/s.
    pub fn delta_v(&self) -> Vector3<f64> {
        self.delta_v
    }
    /// `Δp_ij` at the linearisation biases (body frame at i), m.
    pub fn delta_p(&self) -> Vector3<f64> {
        self.delta_p
    }
    /// Integrated time `Δt`, s.
    pub fn delta_t(&self) -> f64 {
        self.dt
    }
    /// Covariance of `[δφ; δv; δp]`.
    pub fn covariance(&self) -> &Matrix9 {
        &self.cov
    }
    /// The 9x6 bias Jacobian `∂[φ; v; p]/∂[b_g; b_a]`.
    pub fn bias_jacobian(&self) -> &Matrix9x6 {
        &self.jac_bias
    }
    /// `∂φ/∂b_g` (`J^R_g`).
    pub fn d_r_d_bg(&self) -> Matrix3<f64> {
        block3(&self.jac_bias, 0, 0)
    }
    /// `∂v/∂b_g` (`J^v_g`).
    pub fn d_v_d_bg(&self) -> Matrix3<f64> {
        block3(&self.jac_bias, 3, 0)
    }
    /// `∂v/∂b_a` (`J^v_a`).
    pub fn d_v_d_ba(&self) -> Matrix3<f64> {
        block3(&self.jac_bias, 3, 3)
    }
    /// `∂p/∂b_g` (`J^p_g`).
    pub fn d_p_d_bg(&self) -> Matrix3<f64> {
        block3(&self.jac_bias, 6, 0)
    }
    /// `∂p/∂b_a` (`J^p_a`).
    pub fn d_p_d_ba(&self) -> Matrix3<f64> {
        block3(&self.jac_bias, 6, 3)
    }
    /// The (effective) biases the deltas were integrated with.
    pub fn linearisation_biases(&self) -> &ImuBiases {
        &self.bias_lin
    }
    /// The settings.
    pub fn params(&self) -> &PreintegrationParams {
        &self.params
    }

    /// The deltas `(ΔR, Δv, Δp)` for other (effective) biases, to first order (module docs).
    pub fn corrected(&self, biases: &ImuBiases) -> (Rotation3<f64>, Vector3<f64>, Vector3<f64>) {
        let dbg = biases.gyro - self.bias_lin.gyro;
        let dba = biases.accel - self.bias_lin.accel;
        let r = self.delta_r * so3_exp(&(self.d_r_d_bg() * dbg)).matrix();
        (
            Rotation3::from_matrix_unchecked(r),
            self.delta_v + self.d_v_d_bg() * dbg + self.d_v_d_ba() * dba,
            self.delta_p + self.d_p_d_bg() * dbg + self.d_p_d_ba() * dba,
        )
    }

    /// State `j` predicted from state `i` (biases kept): `R_j = R_i ΔR`,
    /// `v_j = v_i + g Δt + R_i Δv`, `p_j = p_i + v_i Δt + ½ g Δt² + R_i Δp`, deltas corrected
    /// to `i`'s biases.
    pub fn predict(&self, i: &NavState, gravity: &Vector3<f64>) -> NavState {
        let (dr, dv, dp) = self.corrected(&i.biases);
        let t = self.dt;
        NavState {
            r: i.r * dr,
            v: i.v + gravity * t + i.r * dv,
            p: i.p + i.v * t + gravity * (0.5 * t * t) + i.r * dp,
            biases: i.biases,
        }
    }

    /// Covariance of [`Self::residual`]: `diag(Σ, σ_bg² Δt I, σ_ba² Δt I)`.
    pub fn residual_covariance(&self) -> Matrix15 {
        let mut c = Matrix15::zeros();
        c.fixed_view_mut::<9, 9>(0, 0).copy_from(&self.cov);
        let (bg, ba) = self.params.bias_walk;
        for k in 0..3 {
            c[(9 + k, 9 + k)] = bg * bg * self.dt;
            c[(12 + k, 12 + k)] = ba * ba * self.dt;
        }
        c
    }

    /// The residual `[r_R; r_v; r_p; r_bg; r_ba]` between states `i` and `j` and its
    /// Jacobians w.r.t. both states' tangents (module docs), for gravity `gravity` in the
    /// world frame (e.g. [`super::gravity_w`]).
    pub fn residual(&self, i: &NavState, j: &NavState, gravity: &Vector3<f64>) -> ImuResidual {
        let dbg = i.biases.gyro - self.bias_lin.gyro;
        let dba = i.biases.accel - self.bias_lin.accel;
        let jrg = self.d_r_d_bg();
        let phi_b = jrg * dbg;
        let dr_c = self.delta_r * so3_exp(&phi_b).matrix();
        let dv_c = self.delta_v + self.d_v_d_bg() * dbg + self.d_v_d_ba() * dba;
        let dp_c = self.delta_p + self.d_p_d_bg() * dbg + self.d_p_d_ba() * dba;
        let (ri, rj) = (i.r.matrix(), j.r.matrix());
        let rit = ri.transpose();
        let t = self.dt;
        let e = dr_c.transpose() * rit * rj;
        let r_r = so3_log(&Rotation3::from_matrix_unchecked(e));
        let u = rit * (j.v - i.v - gravity * t);
        let w = rit * (j.p - i.p - i.v * t - gravity * (0.5 * t * t));
        let r_v = u - dv_c;
        let r_p = w - dp_c;

        let mut r = Vector15::zeros();
        r.fixed_rows_mut::<3>(0).copy_from(&r_r);
        r.fixed_rows_mut::<3>(3).copy_from(&r_v);
        r.fixed_rows_mut::<3>(6).copy_from(&r_p);
        r.fixed_rows_mut::<3>(9)
            .copy_from(&(j.biases.gyro - i.biases.gyro));
        r.fixed_rows_mut::<3>(12)
            .copy_from(&(j.biases.accel - i.biases.accel));

        let jri = so3_jr_inv(&r_r);
        let eye = Matrix3::identity();
        // State tangent columns: θ 0, p 3, v 6, b_g 9, b_a 12. Residual rows: R 0, v 3, p 6,
        // b_g 9, b_a 12.
        let mut ji = Matrix15::zeros();
        let mut jj = Matrix15::zeros();
        let set = |m: &mut Matrix15, row: usize, col: usize, b: Matrix3<f64>| {
            m.fixed_view_mut::<3, 3>(row, col).copy_from(&b);
        };
        set(&mut ji, 0, 0, -jri * rj.transpose() * ri);
        set(&mut ji, 0, 9, -jri * e.transpose() * so3_jr(&phi_b) * jrg);
        set(&mut ji, 3, 0, skew(&u));
        set(&mut ji, 3, 6, -rit);
        set(&mut ji, 3, 9, -self.d_v_d_bg());
        set(&mut ji, 3, 12, -self.d_v_d_ba());
        set(&mut ji, 6, 0, skew(&w));
        set(&mut ji, 6, 3, -rit);
        set(&mut ji, 6, 6, -rit * t);
        set(&mut ji, 6, 9, -self.d_p_d_bg());
        set(&mut ji, 6, 12, -self.d_p_d_ba());
        set(&mut ji, 9, 9, -eye);
        set(&mut ji, 12, 12, -eye);
        set(&mut jj, 0, 0, jri);
        set(&mut jj, 3, 6, rit);
        set(&mut jj, 6, 3, rit);
        set(&mut jj, 9, 9, eye);
        set(&mut jj, 12, 12, eye);
        ImuResidual {
            r,
            jac_i: ji,
            jac_j: jj,
        }
    }
}

#[cfg(test)]
#[path = "preint_tests.rs"]
mod tests;
