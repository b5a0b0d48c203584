//! The nominal state of the calibration filter and its retraction (`VI_NOTES.md` §0, §3
//! "State"): `R = Exp(dθ) R̂`, every other entry additive.

use nalgebra::{DVector, Matrix3, Rotation3, Vector3};

use super::{
    CLONE_DIM, CORE_DIM, IDX_BA, IDX_BG, IDX_DIST, IDX_INTR, IDX_PCB, IDX_TA, IDX_TD, IDX_TG,
    IDX_THETA, IDX_TR, IDX_TS,
};
use crate::camera::PinholeRadtan;
use crate::imu::{gravity_w, ImuBiases, ImuIntrinsics};
use crate::lie::so3_exp;

/// A body state `(R_gb, p_gb, v_gb)`: the IMU part of the state and of every clone.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NavState {
    /// Orientation of the body in the global frame.
    pub r_gb: Rotation3<f64>,
    /// Position of the body in the global frame, m.
    pub p_gb: Vector3<f64>,
    /// Velocity of the body in the global frame, m/s.
    pub v_gb: Vector3<f64>,
}

impl NavState {
    /// One integration step over `dt` seconds (negative integrates backwards) with body rate
    /// `omega` and specific force `a_s`, both constant over the step (mid-point rule):
    /// `R_mid = R Exp(ω dt/2)`, `v += (R_mid a_s + g) dt`,
    /// `p += v dt + ½ (R_mid a_s + g) dt²`, `R = R Exp(ω dt)` (`VI_NOTES.md` §3).
    pub fn step(&mut self, omega: &Vector3<f64>, a_s: &Vector3<f64>, dt: f64) {
        let r_mid = self.r_gb * so3_exp(&(omega * (0.5 * dt)));
        let acc = r_mid * a_s + gravity_w();
        self.p_gb += self.v_gb * dt + acc * (0.5 * dt * dt);
        self.v_gb += acc * dt;
        self.r_gb *= so3_exp(&(omega * dt));
    }

    /// The error `(dθ, dp, dv)` taking `other` to `self`: `R_self = Exp(dθ) R_other`.
    pub fn boxminus(&self, other: &NavState) -> nalgebra::SVector<f64, 9> {
        let mut e = nalgebra::SVector::<f64, 9>::zeros();
        e.fixed_rows_mut::<3>(0)
            .copy_from(&crate::lie::so3_log(&(self.r_gb * other.r_gb.inverse())));
        e.fixed_rows_mut::<3>(3)
            .copy_from(&(self.p_gb - other.p_gb));
        e.fixed_rows_mut::<3>(6)
            .copy_from(&(self.v_gb - other.v_gb));
        e
    }

    /// Applies a 9-vector error `(dθ, dp, dv)` starting at `dx[at]`.
    pub fn retract(&mut self, dx: &DVector<f64>, at: usize) {
        let dth = Vector3::new(dx[at], dx[at + 1], dx[at + 2]);
        self.r_gb = so3_exp(&dth) * self.r_gb;
        self.r_gb.renormalize();
        self.p_gb += Vector3::new(dx[at + 3], dx[at + 4], dx[at + 5]);
        self.v_gb += Vector3::new(dx[at + 6], dx[at + 7], dx[at + 8]);
    }
}

/// A cloned body state of image j (`VI_NOTES.md` §3 "Augmentation").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CloneState {
    /// Unique id of the clone (frame counter).
    pub id: u64,
    /// Clone time `τ_j = t_mid,j + t̂_d` (ns, IMU clock), rounded.
    pub tau_ns: i64,
    /// `t̂_d` (s) when the clone was taken (`t̂_d,j`).
    pub t_d_at_clone: f64,
    /// The cloned body state (updated by the filter).
    pub nav: NavState,
    /// First estimates of position and velocity (FEJ, the values at augmentation).
    pub p_fej: Vector3<f64>,
    /// First estimate of the velocity.
    pub v_fej: Vector3<f64>,
}

/// The nominal state of [`super::CalibFilter`] without clones.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CalibState {
    /// Time of the state, ns, IMU clock.
    pub t_ns: i64,
    /// The IMU body state.
    pub nav: NavState,
    /// Gyro and accelerometer biases.
    pub biases: ImuBiases,
    /// `T_g`, `T_s`, `T_a` (seed eq. 2.55-2.56).
    pub imu: ImuIntrinsics,
    /// Camera-from-body rotation `R_cb`, fixed (`VI_NOTES.md` §0).
    pub r_cb: Rotation3<f64>,
    /// Body origin in the camera frame: `p^c = R_cb p^b + p_cb`, m.
    pub p_cb: Vector3<f64>,
    /// Camera: `fx fy cx cy k1 k2 p1 p2` are estimated, `k3` and the size are fixed.
    pub camera: PinholeRadtan,
    /// Residual time offset `t_d` (s): a row's IMU-clock time is `t_mid + t_d + (v/N - ½) t_r`.
    pub t_d: f64,
    /// Rolling-shutter readout time `t_r` (s), 0 for a global shutter.
    pub t_r: f64,
}

impl CalibState {
    /// Corrected body rate and specific force from raw `(ω_m, a_m)` (`VI_NOTES.md` §2):
    /// `a_s = T_a⁻¹ (a_m - b_a)`, `ω = T_g⁻¹ (ω_m - T_s a_s - b_g)`.
    pub fn correct(
        &self,
        gyro: &Vector3<f64>,
        accel: &Vector3<f64>,
    ) -> (Vector3<f64>, Vector3<f64>) {
        let (ta_inv, tg_inv) = self.imu_inverses();
        let a_s = ta_inv * (accel - self.biases.accel);
        let w = tg_inv * (gyro - self.imu.t_s * a_s - self.biases.gyro);
        (w, a_s)
    }

    /// `(T_a⁻¹, T_g⁻¹)`; identity if a matrix is singular (never near `I`).
    pub fn imu_inverses(&self) -> (Matrix3<f64>, Matrix3<f64>) {
        let ta = self.imu.t_a.try_inverse().unwrap_or_else(Matrix3::identity);
        let tg = self.imu.t_g.try_inverse().unwrap_or_else(Matrix3::identity);
        (ta, tg)
    }

    /// Applies the first [`CORE_DIM`] entries of an error-state correction.
    pub fn retract(&mut self, dx: &DVector<f64>) {
        self.nav.retract(dx, IDX_THETA);
        self.biases.gyro += dx.fixed_rows::<3>(IDX_BG);
        self.biases.accel += dx.fixed_rows::<3>(IDX_BA);
        add_row_major(&mut self.imu.t_g, dx, IDX_TG);
        add_row_major(&mut self.imu.t_s, dx, IDX_TS);
        add_row_major(&mut self.imu.t_a, dx, IDX_TA);
        self.p_cb += dx.fixed_rows::<3>(IDX_PCB);
        let c = &mut self.camera;
        c.fx += dx[IDX_INTR];
        c.fy += dx[IDX_INTR + 1];
        c.cx += dx[IDX_INTR + 2];
        c.cy += dx[IDX_INTR + 3];
        c.k1 += dx[IDX_DIST];
        c.k2 += dx[IDX_DIST + 1];
        c.p1 += dx[IDX_DIST + 2];
        c.p2 += dx[IDX_DIST + 3];
        self.t_d += dx[IDX_TD];
        self.t_r += dx[IDX_TR];
    }

    /// The core error taking `other` to `self` (inverse of [`CalibState::retract`] to first
    /// order in the rotation, exact elsewhere).
    pub fn boxminus(&self, other: &CalibState) -> DVector<f64> {
        let mut e = self.calib_vector() - other.calib_vector();
        e.fixed_rows_mut::<9>(IDX_THETA)
            .copy_from(&self.nav.boxminus(&other.nav));
        e
    }

    /// The calibration part `x[15..55]` as a vector in error-state order (for tests and
    /// reports: the difference of two of these is the calibration error).
    pub fn calib_vector(&self) -> DVector<f64> {
        let mut v = DVector::zeros(CORE_DIM);
        v.fixed_rows_mut::<3>(IDX_BG).copy_from(&self.biases.gyro);
        v.fixed_rows_mut::<3>(IDX_BA).copy_from(&self.biases.accel);
        for (at, m) in [
            (IDX_TG, &self.imu.t_g),
            (IDX_TS, &self.imu.t_s),
            (IDX_TA, &self.imu.t_a),
        ] {
            for r in 0..3 {
                for c in 0..3 {
                    v[at + 3 * r + c] = m[(r, c)];
                }
            }
        }
        v.fixed_rows_mut::<3>(IDX_PCB).copy_from(&self.p_cb);
        let c = &self.camera;
        for (k, x) in [c.fx, c.fy, c.cx, c.cy, c.k1, c.k2, c.p1, c.p2]
            .into_iter()
            .enumerate()
        {
            v[IDX_INTR + k] = x;
        }
        v[IDX_TD] = self.t_d;
        v[IDX_TR] = self.t_r;
        v
    }
}

/// `m += reshape(dx[at..at+9])`, row-major (`VI_NOTES.md` §2).
fn add_row_major(m: &mut Matrix3<f64>, dx: &DVector<f64>, at: usize) {
    for r in 0..3 {
        for c in 0..3 {
            m[(r, c)] += dx[at + 3 * r + c];
        }
    }
}

/// Error-state offset of clone number `i` (0 = oldest).
pub fn clone_offset(i: usize) -> usize {
    CORE_DIM + CLONE_DIM * i
}
