//! The frame navigator of the visual-inertial client: the body state at the last frame,
//! propagated with the IMU to the next frame (`VI_NOTES.md` §4, preintegration), and
//! corrected by the visual pose once the frame is tracked.
//!
//! **Prediction.** `x_j = predict(x_i)` with the samples between the two frames'
//! (IMU-clock) times, preintegrated at the current biases ([`Preintegrated::predict`]):
//! `R_j = R_i ΔR`, `v_j = v_i + g Δt + R_i Δv`, `p_j = p_i + v_i Δt + ½ g Δt² + R_i Δp`.
//!
//! **Velocity: a linear Kalman filter on `[p_wb; v_wb]`** (world frame), driven by the
//! preintegrated accelerations and updated by the visual position of each tracked frame.
//! Why not ORB-SLAM3's per-frame pose-velocity-bias optimisation: the orientation from
//! vision is already better than the gyro's over a frame, the biases come from the
//! initialisation and then from local mapping's visual-inertial window at every keyframe
//! ([`Navigator::adopt_keyframe`], `crate::vo::vi_window`), so the only state left to
//! estimate per frame is the velocity,
//! which is linear in the positions given the rotations: a 6-state filter does it exactly,
//! in constant time and with no allocation, and its covariance is the translation part of
//! the pose prior. Differencing two visual positions instead (`v = (p_j - p_i)/Δt - ...`)
//! would carry their noise divided by a 50 ms `Δt`; the filter smooths it.
//! - Process: `F = [I IΔt; 0 I]`, `Q` = the preintegration's `(δp, δv)` covariance rotated
//!   to the world, plus a white acceleration error [`NavParams::accel_error_sigma`] held over
//!   the interval (the accelerometer bias and the orientation error, `9.81 δθ`, which the
//!   preintegration covariance does not hold).
//! - Update: `z = p_wb` from vision, `H = [I 0]`, `R = σ_vis² I`
//!   ([`NavParams::visual_position_sigma_m`]).
use nalgebra::{Isometry3, Matrix3, Matrix6, Vector3};

use crate::imu::{gravity_w, ImuMeasurement, NavState, Preintegrated, PreintegrationParams};
use crate::optim::{centre_covariance, PosePrior, Velocity};

/// Settings of [`Navigator`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NavParams {
    /// 1σ of a visual camera position (the filter's measurement noise), m.
    pub visual_position_sigma_m: f64,
    /// 1σ of a visual orientation (floor of the pose prior's rotation), rad.
    pub visual_rotation_sigma_rad: f64,
    /// White acceleration error not in the preintegration covariance, m/s².
    pub accel_error_sigma: f64,
    /// 1σ of the gyro bias after the initialisation (grows the rotation prior with `Δt`),
    /// rad/s.
    pub gyro_bias_sigma: f64,
    /// The prior's centre 1σ is the filter's times this (1: the filter's own; larger, a
    /// weaker translation prior).
    pub position_prior_inflation: f64,
    /// 1σ of the initial velocity, m/s.
    pub initial_velocity_sigma: f64,
    /// Acceleration the velocity may have had over an interval the IMU does not cover
    /// (an IMU gap, a restarted tracker's first frames): its 1σ grows by this times the
    /// interval ([`Navigator::reset_to`]), m/s².
    pub unmodelled_accel: f64,
}

impl Default for NavParams {
    fn default() -> Self {
        Self {
            visual_position_sigma_m: 0.005,
            visual_rotation_sigma_rad: 1e-3,
            accel_error_sigma: 0.1,
            gyro_bias_sigma: 2e-3,
            position_prior_inflation: 1.0,
            initial_velocity_sigma: 0.05,
            unmodelled_accel: 3.0,
        }
    }
}

/// A predicted frame state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Prediction {
    /// The body state at the frame's time.
    pub nav: NavState,
    /// The camera pose, world to camera.
    pub t_cw: Isometry3<f64>,
    /// The camera twist (camera frame) for the rolling-shutter model.
    pub velocity: Velocity,
    /// The pose prior for the pose optimisation.
    pub prior: PosePrior,
    /// `[p; v]` covariance after the prediction.
    cov: Matrix6<f64>,
    /// The frame's IMU time, ns.
    t_ns: i64,
}

/// The body state at the last frame and its `[p; v]` covariance (module docs).
#[derive(Debug, Clone)]
pub struct Navigator {
    params: NavParams,
    preint: PreintegrationParams,
    t_bc: Isometry3<f64>,
    nav: NavState,
    t_ns: i64,
    cov: Matrix6<f64>,
}

impl Navigator {
    /// A navigator at state `nav` at IMU time `t_ns`, for a camera at `t_bc` in the body.
    pub fn new(
        nav: NavState,
        t_ns: i64,
        t_bc: Isometry3<f64>,
        preint: PreintegrationParams,
        params: NavParams,
    ) -> Self {
        let (sp, sv) = (
            params.visual_position_sigma_m,
            params.initial_velocity_sigma,
        );
        let mut cov = Matrix6::zeros();
        cov.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(Matrix3::identity() * (sp * sp)));
        cov.fixed_view_mut::<3, 3>(3, 3)
            .copy_from(&(Matrix3::identity() * (sv * sv)));
        Self {
            params,
            preint,
            t_bc,
            nav,
            t_ns,
            cov,
        }
    }

    /// The state at the last frame.
    pub fn state(&self) -> &NavState {
        &self.nav
    }

    /// The last frame's IMU time, ns.
    pub fn t_ns(&self) -> i64 {
        self.t_ns
    }

    /// The camera pose `T_cw` of body state `nav`.
    pub fn camera_pose(&self, nav: &NavState) -> Isometry3<f64> {
        nav.camera_pose(&self.t_bc)
    }

    /// The state predicted at IMU time `t_ns` from `samples` (`None` when they do not
    /// bracket the interval). `gyro_at_frame_b` is the raw gyro over the frame's readout
    /// (e.g. [`crate::imu::mean_rate`]), for the camera twist.
    pub fn predict(
        &self,
        samples: &[ImuMeasurement],
        t_ns: i64,
        gyro_at_frame_b: &Vector3<f64>,
    ) -> Option<Prediction> {
        let pre =
            Preintegrated::from_window(samples, self.t_ns, t_ns, self.nav.biases, self.preint)?;
        let nav = pre.predict(&self.nav, &gravity_w());
        let dt = pre.delta_t();
        let cov = self.propagate_cov(&pre);
        let t_cw = self.camera_pose(&nav);
        let velocity = self.camera_twist(&nav, gyro_at_frame_b);
        let prior = self.prior(&pre, &cov, t_cw, dt);
        Some(Prediction {
            nav,
            t_cw,
            velocity,
            prior,
            cov,
            t_ns,
        })
    }

    /// `F P Fᵀ + Q` (module docs).
    fn propagate_cov(&self, pre: &Preintegrated) -> Matrix6<f64> {
        let dt = pre.delta_t();
        let mut f = Matrix6::identity();
        f.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&(Matrix3::identity() * dt));
        let r = self.nav.r.matrix();
        let c = pre.covariance();
        // Preintegration order [φ, v, p] → ours [p, v].
        let mut q = Matrix6::zeros();
        let blk = |i: usize, j: usize| r * c.fixed_view::<3, 3>(i, j).into_owned() * r.transpose();
        q.fixed_view_mut::<3, 3>(0, 0).copy_from(&blk(6, 6));
        q.fixed_view_mut::<3, 3>(0, 3).copy_from(&blk(6, 3));
        q.fixed_view_mut::<3, 3>(3, 0).copy_from(&blk(3, 6));
        q.fixed_view_mut::<3, 3>(3, 3).copy_from(&blk(3, 3));
        // A white acceleration error held over the interval: [½Δt²; Δt] σ² [½Δt²; Δt]ᵀ.
        let sa2 = self.params.accel_error_sigma.powi(2);
        let (gp, gv) = (0.5 * dt * dt, dt);
        for k in 0..3 {
            q[(k, k)] += gp * gp * sa2;
            q[(k, k + 3)] += gp * gv * sa2;
            q[(k + 3, k)] += gp * gv * sa2;
            q[(k + 3, k + 3)] += gv * gv * sa2;
        }
        f * self.cov * f.transpose() + q
    }

    /// The camera twist in the camera frame: `ω_c = R_cb ω_b`,
    /// `v_c = R_cw (v_wb + R_wb (ω_b × p_bc))` (the camera centre's velocity).
    fn camera_twist(&self, nav: &NavState, gyro_b: &Vector3<f64>) -> Velocity {
        let (w_corr, _) = self.preint.correction.apply(gyro_b, &Vector3::zeros());
        let w_b = w_corr - nav.biases.gyro;
        let r_bc = self.t_bc.rotation.to_rotation_matrix();
        let r_wc = nav.r * r_bc;
        let v_wc = nav.v + nav.r * w_b.cross(&self.t_bc.translation.vector);
        Velocity {
            angular: r_bc.inverse() * w_b,
            linear: r_wc.inverse() * v_wc,
        }
    }

    /// The pose prior: rotation 1σ from the visual floor, the preintegrated rotation's
    /// covariance and the gyro bias over `dt` (isotropic); the centre's information is the
    /// inverse of the filter's position covariance (full 3x3; the lever arm's share of the
    /// rotation uncertainty is neglected) over [`NavParams::position_prior_inflation`]².
    fn prior(
        &self,
        pre: &Preintegrated,
        cov: &Matrix6<f64>,
        t_cw: Isometry3<f64>,
        dt: f64,
    ) -> PosePrior {
        let p = &self.params;
        let rot_var = p.visual_rotation_sigma_rad.powi(2)
            + pre.covariance().fixed_view::<3, 3>(0, 0).trace() / 3.0
            + (p.gyro_bias_sigma * dt).powi(2);
        let pos_cov = cov.fixed_view::<3, 3>(0, 0) * p.position_prior_inflation.powi(2);
        let pos_info = pos_cov
            .try_inverse()
            .unwrap_or_else(|| Matrix3::identity() / (pos_cov.trace() / 3.0).max(1e-12));
        let mut information = Matrix6::zeros();
        information
            .fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(Matrix3::identity() / rot_var));
        information
            .fixed_view_mut::<3, 3>(3, 3)
            .copy_from(&pos_info);
        PosePrior { t_cw, information }
    }

    /// Takes the prediction as the new state without a visual correction (coasting).
    pub fn coast(&mut self, pred: &Prediction) {
        self.nav = pred.nav;
        self.cov = pred.cov;
        self.t_ns = pred.t_ns;
    }

    /// Corrects the prediction with the tracked camera pose `t_cw` and the information of
    /// its pose optimisation (module docs, "Update"): orientation from vision; position and
    /// velocity by the Kalman update with the centre covariance of the reprojections'
    /// information (with `prior_included`, the prediction's prior taken out of it again,
    /// [`PosePrior::information_at`]) plus the floor [`NavParams::visual_position_sigma_m`]
    /// (the map points' own errors are not in that information). Without `information`,
    /// the floor alone. Measured: conditioning on the optimised pose as the posterior
    /// instead (no floor) made the velocity follow vision's noise; the in-process
    /// `blackout` then missed its rejoin after 2 s of coasting.
    pub fn correct(
        &mut self,
        pred: &Prediction,
        t_cw: &Isometry3<f64>,
        information: Option<&Matrix6<f64>>,
        prior_included: bool,
    ) {
        let t_wb = t_cw.inverse() * self.t_bc.inverse();
        let z = t_wb.translation.vector;
        let vision = information.map(|h| match prior_included {
            true => h - pred.prior.information_at(t_cw),
            false => *h,
        });
        let sigma_c = vision.and_then(|h| centre_covariance(t_cw, &h));
        let floor = Matrix3::identity() * self.params.visual_position_sigma_m.powi(2);
        let updated = kalman_position_update(&pred.cov, &(sigma_c.unwrap_or_default() + floor));
        let Some((gain_v, cov)) = updated else {
            self.reset_to(t_cw, pred.t_ns);
            return;
        };
        let mut nav = pred.nav;
        nav.v += gain_v * (z - pred.nav.p);
        nav.r = t_wb.rotation.to_rotation_matrix();
        // The pose stays vision's (the next prediction starts from the tracked frame, as
        // ORB-SLAM3's); the filter gives the velocity.
        nav.p = z;
        self.cov = cov;
        self.nav = nav;
        self.t_ns = pred.t_ns;
    }

    /// Re-anchors the pose at a visual `t_cw` at IMU time `t_ns` with no prediction (the
    /// IMU did not cover the interval): velocity and biases kept, position uncertainty
    /// reset, velocity uncertainty at least its initial value and grown by
    /// [`NavParams::unmodelled_accel`] over the interval, so that the next visual positions
    /// correct a velocity that went stale (e.g. a resumed session's, taken from a keyframe
    /// before the gap).
    pub fn reset_to(&mut self, t_cw: &Isometry3<f64>, t_ns: i64) {
        let dt = (t_ns - self.t_ns).max(0) as f64 * 1e-9;
        let var_v = self.cov.fixed_view::<3, 3>(3, 3).trace() / 3.0;
        let var_v = var_v.max(self.params.initial_velocity_sigma.powi(2))
            + (self.params.unmodelled_accel * dt).powi(2);
        let mut nav = self.nav;
        let t_wb = t_cw.inverse() * self.t_bc.inverse();
        nav.r = t_wb.rotation.to_rotation_matrix();
        nav.p = t_wb.translation.vector;
        *self = Self::new(nav, t_ns, self.t_bc, self.preint, self.params);
        self.cov
            .fixed_view_mut::<3, 3>(3, 3)
            .copy_from(&(Matrix3::identity() * var_v));
    }

    /// The 1σ of the velocity (mean over the axes), m/s.
    pub fn velocity_sigma(&self) -> f64 {
        (self.cov.fixed_view::<3, 3>(3, 3).trace() / 3.0).sqrt()
    }

    /// Takes a keyframe's state `kf` at IMU time `t_kf_ns` as local mapping's
    /// visual-inertial window left it (`imu::window`): its biases, and its velocity carried
    /// to this state's time with the IMU, `v = v_kf + g Δt + R_kf Δv` (the pose stays
    /// vision's). Only the biases when `samples` do not cover the interval.
    pub fn adopt_keyframe(&mut self, samples: &[ImuMeasurement], kf: &NavState, t_kf_ns: i64) {
        self.nav.biases = kf.biases;
        if t_kf_ns > self.t_ns {
            return;
        }
        if let Some(pre) =
            Preintegrated::from_window(samples, t_kf_ns, self.t_ns, kf.biases, self.preint)
        {
            self.nav.v = pre.predict(kf, &gravity_w()).v;
        }
    }

    /// Sets the velocity and biases (an initialisation's refinement).
    pub fn set_velocity_biases(&mut self, v_wb: Vector3<f64>, biases: crate::imu::ImuBiases) {
        self.nav.v = v_wb;
        self.nav.biases = biases;
    }

    /// Moves the state as the world moved, `x' = s R x + t`: `p' = s R p + t`,
    /// `v' = s R v`, `R_wb' = R R_wb`; covariance scaled and rotated alike.
    pub fn transform_world(&mut self, w: &crate::lie::Sim3) {
        let (s, rm) = (w.s, w.r.to_rotation_matrix());
        self.nav.p = w.transform_point(&self.nav.p);
        self.nav.v = rm * (self.nav.v * s);
        self.nav.r = rm * self.nav.r;
        let mut m = Matrix6::zeros();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&(rm.matrix() * s));
        m.fixed_view_mut::<3, 3>(3, 3).copy_from(&(rm.matrix() * s));
        self.cov = m * self.cov * m.transpose();
    }
}

/// The Kalman update of `[p; v]` (covariance `p`) by a position measurement of covariance
/// `r`: the velocity gain `K_v` (applied to the innovation `z - p⁻`) and the updated
/// covariance. `None` when `P_pp + R` is singular.
fn kalman_position_update(
    p: &Matrix6<f64>,
    r: &Matrix3<f64>,
) -> Option<(Matrix3<f64>, Matrix6<f64>)> {
    let s_inv = (p.fixed_view::<3, 3>(0, 0) + r).try_inverse()?;
    let k = p.fixed_view::<6, 3>(0, 0) * s_inv;
    let mut ikh = Matrix6::<f64>::identity();
    for r in 0..6 {
        for c in 0..3 {
            ikh[(r, c)] -= k[(r, c)];
        }
    }
    let cov = ikh * p;
    Some((
        k.fixed_view::<3, 3>(3, 0).into_owned(),
        (cov + cov.transpose()) * 0.5,
    ))
}

/// `T_wb` of a navigation state ([`NavState::body_pose`]).
pub fn body_pose(nav: &NavState) -> Isometry3<f64> {
    nav.body_pose()
}

/// The body state of camera pose `t_cw` (camera at `t_bc` in the body), velocity `v_wb`
/// ([`NavState::from_camera`]).
pub fn nav_from_camera(
    t_cw: &Isometry3<f64>,
    t_bc: &Isometry3<f64>,
    v_wb: Vector3<f64>,
    biases: crate::imu::ImuBiases,
) -> NavState {
    NavState::from_camera(t_cw, t_bc, v_wb, biases)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

    /// With an informative measurement the velocity follows the position's innovation over
    /// the prediction interval; a measurement of huge covariance leaves it alone.
    #[test]
    fn the_velocity_gain_follows_the_measurement_noise() {
        let nav = NavState {
            r: Rotation3::identity(),
            p: Vector3::zeros(),
            v: Vector3::zeros(),
            biases: Default::default(),
        };
        let preint = PreintegrationParams::new(
            &crate::imu::ImuNoise::default(),
            &crate::imu::ImuIntrinsics::default(),
        )
        .expect("preint");
        let n = Navigator::new(nav, 0, Isometry3::identity(), preint, NavParams::default());
        let mut p = n.cov;
        // One 50 ms constant-velocity step of process noise.
        let mut f = Matrix6::identity();
        f.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&(Matrix3::identity() * 0.05));
        p = f * p * f.transpose() + Matrix6::identity() * 1e-6;
        let (k_tight, _) = kalman_position_update(&p, &(Matrix3::identity() * 1e-8)).expect("kf");
        let (k_loose, _) = kalman_position_update(&p, &(Matrix3::identity() * 1e2)).expect("kf");
        assert!(k_tight[(0, 0)] > 1.0, "gain {}", k_tight[(0, 0)]);
        assert!(k_loose.norm() < 1e-3);
    }
}
