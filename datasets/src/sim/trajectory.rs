//! Smooth analytic trajectories: every coordinate is a sum of sinusoids plus a linear term,
//! so position, velocity, acceleration and angular velocity are exact (no numerical
//! differentiation), and the IMU synthesised from them integrates back to the ground truth.
//!
//! The body (IMU) position `p_WB(t)` is analytic; the orientation is given as the camera's
//! viewing direction by yaw / pitch / roll angles (`R_WC = Rz(yaw) Ry(pitch) Rx(roll) R_0`,
//! where `R_0` makes the camera look along world +x with image "down" along world -z).
//! The body orientation follows from the fixed camera-in-body transform:
//! `R_WB = R_WC R_BS^T`, `p_WC = p_WB + R_WB t_BS`.

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// One sinusoid `amp · sin(omega · t + phase)` (t in seconds, omega in rad/s).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sine {
    /// Amplitude.
    pub amp: f64,
    /// Angular frequency, rad/s.
    pub omega: f64,
    /// Phase, rad.
    pub phase: f64,
}

impl Sine {
    /// A sinusoid of `amp` with period `period_s` seconds and `phase`.
    pub fn with_period(amp: f64, period_s: f64, phase: f64) -> Self {
        Self {
            amp,
            omega: std::f64::consts::TAU / period_s,
            phase,
        }
    }
}

/// A scalar signal `offset + rate · t + Σ sines` with exact derivatives.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Signal {
    /// Constant term.
    pub offset: f64,
    /// Linear rate (units per second).
    pub rate: f64,
    /// Sinusoidal terms.
    pub sines: Vec<Sine>,
}

impl Signal {
    /// A signal `offset + rate · t + Σ sines`.
    pub fn new(offset: f64, rate: f64, sines: Vec<Sine>) -> Self {
        Self {
            offset,
            rate,
            sines,
        }
    }

    /// Value at `t` seconds.
    pub fn value(&self, t: f64) -> f64 {
        self.sines
            .iter()
            .fold(self.offset + self.rate * t, |acc, s| {
                acc + s.amp * (s.omega * t + s.phase).sin()
            })
    }

    /// First derivative at `t`.
    pub fn d1(&self, t: f64) -> f64 {
        self.sines.iter().fold(self.rate, |acc, s| {
            acc + s.amp * s.omega * (s.omega * t + s.phase).cos()
        })
    }

    /// Second derivative at `t`.
    pub fn d2(&self, t: f64) -> f64 {
        self.sines.iter().fold(0.0, |acc, s| {
            acc - s.amp * s.omega * s.omega * (s.omega * t + s.phase).sin()
        })
    }
}

/// The full kinematic state of the body (IMU) frame at one instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BodyState {
    /// Position of the body in the world, m.
    pub p_wb: Vector3<f64>,
    /// Velocity in the world frame, m/s.
    pub v_w: Vector3<f64>,
    /// Acceleration in the world frame (without gravity), m/s².
    pub a_w: Vector3<f64>,
    /// Orientation `R_WB`.
    pub q_wb: UnitQuaternion<f64>,
    /// Angular velocity of the body in the body frame, rad/s.
    pub omega_b: Vector3<f64>,
}

/// `R_0`: camera axes (x right, y down, z forward) expressed in the "look along +x, z up"
/// frame: z_c -> +x, x_c -> -y, y_c -> -z.
fn r0() -> Matrix3<f64> {
    Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0)
}

/// An analytic body trajectory with a rigidly attached camera.
#[derive(Debug, Clone, PartialEq)]
pub struct AnalyticTrajectory {
    /// Body position `p_WB` components x, y, z (m).
    pub pos: [Signal; 3],
    /// Camera viewing yaw about world z (rad; 0 looks along +x).
    pub yaw: Signal,
    /// Camera pitch (rad, positive looks down).
    pub pitch: Signal,
    /// Camera roll about its viewing axis (rad).
    pub roll: Signal,
    /// Camera pose in the body frame `T_BS` (x_B = T_BS x_S).
    pub t_bs: Isometry3<f64>,
}

impl AnalyticTrajectory {
    fn ypr_rotation(&self, t: f64) -> Rotation3<f64> {
        Rotation3::from_euler_angles(self.roll.value(t), self.pitch.value(t), self.yaw.value(t))
    }

    /// Camera orientation `R_WC` at `t` seconds.
    pub fn rot_wc(&self, t: f64) -> Matrix3<f64> {
        self.ypr_rotation(t).matrix() * r0()
    }

    /// Body pose `T_WB` at `t` seconds.
    pub fn pose_body(&self, t: f64) -> Isometry3<f64> {
        let r_wb = self.rot_wc(t) * self.t_bs.rotation.to_rotation_matrix().matrix().transpose();
        let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r_wb));
        let p = Vector3::new(
            self.pos[0].value(t),
            self.pos[1].value(t),
            self.pos[2].value(t),
        );
        Isometry3::from_parts(Translation3::from(p), q)
    }

    /// Camera pose `T_WC` (camera-to-world) at `t` seconds: `T_WB T_BS`.
    pub fn pose_cam(&self, t: f64) -> Isometry3<f64> {
        self.pose_body(t) * self.t_bs
    }

    /// Exact body state (position, velocity, acceleration, orientation, body rate) at `t`.
    pub fn body_state(&self, t: f64) -> BodyState {
        let pose = self.pose_body(t);
        let v_w = Vector3::new(self.pos[0].d1(t), self.pos[1].d1(t), self.pos[2].d1(t));
        let a_w = Vector3::new(self.pos[0].d2(t), self.pos[1].d2(t), self.pos[2].d2(t));
        // ZYX Euler rates -> angular velocity in the rotated (local) frame.
        let (phi, theta) = (self.roll.value(t), self.pitch.value(t));
        let (dphi, dtheta, dpsi) = (self.roll.d1(t), self.pitch.d1(t), self.yaw.d1(t));
        let (sphi, cphi) = phi.sin_cos();
        let (sth, cth) = theta.sin_cos();
        let omega_l = Vector3::new(
            dphi - dpsi * sth,
            dtheta * cphi + dpsi * cth * sphi,
            dpsi * cth * cphi - dtheta * sphi,
        );
        let omega_c = r0().transpose() * omega_l;
        let omega_b = self.t_bs.rotation * omega_c;
        BodyState {
            p_wb: pose.translation.vector,
            v_w,
            a_w,
            q_wb: pose.rotation,
            omega_b,
        }
    }
}

/// The EuRoC MAV `cam0` extrinsics `T_BS` (camera in the IMU body frame), re-orthonormalised.
pub fn euroc_t_bs() -> Isometry3<f64> {
    let m = Matrix3::new(
        0.0148655429818,
        -0.999880929698,
        0.00414029679422,
        0.999557249008,
        0.0149672133247,
        0.025715529948,
        -0.0257744366974,
        0.00375618835797,
        0.999660727178,
    );
    let r = Rotation3::from_matrix_eps(&m, 1e-15, 100, Rotation3::identity());
    Isometry3::from_parts(
        Translation3::new(-0.0216401454975, -0.064676986768, 0.00981073058949),
        UnitQuaternion::from_rotation_matrix(&r),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn traj() -> AnalyticTrajectory {
        let w = std::f64::consts::TAU / 32.0;
        AnalyticTrajectory {
            pos: [
                Signal::new(
                    0.0,
                    0.0,
                    vec![Sine {
                        amp: 6.0,
                        omega: w,
                        phase: 1.57,
                    }],
                ),
                Signal::new(
                    0.0,
                    0.0,
                    vec![Sine {
                        amp: 4.0,
                        omega: w,
                        phase: 0.0,
                    }],
                ),
                Signal::new(1.5, 0.0, vec![Sine::with_period(0.2, 5.0, 0.3)]),
            ],
            yaw: Signal::new(0.1, w, vec![Sine::with_period(0.5, 1.25, 0.0)]),
            pitch: Signal::new(0.05, 0.0, vec![Sine::with_period(0.04, 0.3, 0.2)]),
            roll: Signal::new(0.0, 0.0, vec![Sine::with_period(0.04, 0.25, 0.5)]),
            t_bs: euroc_t_bs(),
        }
    }

    #[test]
    fn derivatives_match_central_differences() {
        let tr = traj();
        let h = 1e-5;
        for t in [0.0, 1.3, 17.77] {
            let s = tr.body_state(t);
            let p = |t| tr.pose_body(t).translation.vector;
            let v_num = (p(t + h) - p(t - h)) / (2.0 * h);
            assert!((v_num - s.v_w).norm() < 1e-7);
            let a_num = (p(t + 1e-3) - 2.0 * p(t) + p(t - 1e-3)) / 1e-6;
            assert!((a_num - s.a_w).norm() < 1e-4);
            let q0 = tr.pose_body(t - h).rotation;
            let q1 = tr.pose_body(t + h).rotation;
            let w_num = (q0.inverse() * q1).scaled_axis() / (2.0 * h);
            assert!(
                (w_num - s.omega_b).norm() < 1e-6,
                "{w_num} vs {}",
                s.omega_b
            );
        }
    }

    #[test]
    fn camera_looks_along_yaw_direction() {
        let mut tr = traj();
        tr.pitch = Signal::default();
        tr.roll = Signal::default();
        tr.yaw = Signal::new(0.0, 0.0, vec![]);
        let r = tr.rot_wc(0.0);
        assert!((r * Vector3::z() - Vector3::x()).norm() < 1e-12);
        let t_bs = euroc_t_bs();
        let r_bs = t_bs.rotation.to_rotation_matrix();
        assert!((r_bs.matrix() * r_bs.matrix().transpose() - Matrix3::identity()).norm() < 1e-12);
    }
}
