//! IMU synthesis from an analytic trajectory (seed eq. 2.53-2.56): exact specific force and
//! body rate, then biases (random walk), white noise and optional intrinsics.

use nalgebra::{UnitQuaternion, Vector3};
use slam_core::imu::{self, ImuBiases, ImuIntrinsics, ImuNoise};

use super::rng::Rng;
use super::trajectory::AnalyticTrajectory;
use crate::ImuSample;

/// Ground-truth body state at one IMU sample (the EuRoC `state_groundtruth_estimate0` row).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GtState {
    /// Time, ns (true clock = IMU clock).
    pub t_ns: i64,
    /// Body position in the world, m.
    pub p_wb: Vector3<f64>,
    /// Body orientation `q_WB`.
    pub q_wb: UnitQuaternion<f64>,
    /// Body velocity in the world, m/s.
    pub v_w: Vector3<f64>,
    /// Biases in effect for this sample's measurement.
    pub biases: ImuBiases,
}

impl GtState {
    /// The true navigation state with `biases` (the preintegration's residuals take it).
    pub fn nav_state(&self, biases: ImuBiases) -> slam_core::imu::NavState {
        slam_core::imu::NavState {
            r: self.q_wb.to_rotation_matrix(),
            p: self.p_wb,
            v: self.v_w,
            biases,
        }
    }
}

/// How to synthesise the IMU stream.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuSynthesis {
    /// Time (ns) of trajectory time 0 and of the first sample.
    pub start_ns: i64,
    /// Sample period, ns.
    pub period_ns: i64,
    /// Number of samples.
    pub n_samples: usize,
    /// Noise densities (use [`ImuNoise::zero`] for exact measurements).
    pub noise: ImuNoise,
    /// Intrinsics `T_a`, `T_g`, `T_s`.
    pub intrinsics: ImuIntrinsics,
    /// Biases at the first sample.
    pub initial_biases: ImuBiases,
    /// Seed of the noise stream.
    pub seed: u64,
}

/// Synthesises IMU samples and the matching ground-truth states (same timestamps).
pub fn synthesize(traj: &AnalyticTrajectory, cfg: &ImuSynthesis) -> (Vec<ImuSample>, Vec<GtState>) {
    let mut rng = Rng::new(cfg.seed);
    let dt = cfg.period_ns as f64 * 1e-9;
    let mut biases = cfg.initial_biases;
    let mut samples = Vec::with_capacity(cfg.n_samples);
    let mut states = Vec::with_capacity(cfg.n_samples);
    for i in 0..cfg.n_samples {
        let offset_ns = i as i64 * cfg.period_ns;
        let t_ns = cfg.start_ns + offset_ns;
        let s = traj.body_state(offset_ns as f64 * 1e-9);
        let f_b = imu::specific_force_b(s.q_wb.to_rotation_matrix().matrix(), &s.a_w);
        let normals = rng.normals6();
        let (a_m, w_m) = imu::measure_noisy(
            &f_b,
            &s.omega_b,
            &biases,
            &cfg.intrinsics,
            &cfg.noise,
            dt,
            &normals,
        );
        samples.push(ImuSample {
            t_ns,
            gyro: [w_m.x, w_m.y, w_m.z],
            accel: [a_m.x, a_m.y, a_m.z],
        });
        states.push(GtState {
            t_ns,
            p_wb: s.p_wb,
            q_wb: s.q_wb,
            v_w: s.v_w,
            biases,
        });
        let walk = rng.normals6();
        imu::bias_random_walk_step(&mut biases, &cfg.noise, dt, &walk);
    }
    (samples, states)
}
