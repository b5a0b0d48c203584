//! Test support: a synthetic calibration scenario after the seed's Fig. 4.4 and
//! `VI_NOTES.md` §3 "Simulation": a body turning ≥ 1 rad/s about every axis with varied
//! attitude to gravity, landmarks on the faces of a box around it, a rolling-shutter camera
//! with radtan distortion and a T-model IMU with noise and biases. Everything is in closed
//! form: `R_gb(t) = Exp(φ(t))` with sinusoidal `φ`, so `ω_b = Jr(φ) φ̇`, and a sinusoidal
//! position.

use std::f64::consts::TAU;

use nalgebra::{Matrix3, Rotation3, Vector2, Vector3};

use super::state::{CalibState, NavState};
use super::{ImuSample, Observation, TrackId};
use crate::camera::PinholeRadtan;
use crate::imu::{gravity_w, measure, ImuBiases, ImuIntrinsics, ImuNoise};
use crate::lie::{so3_exp, so3_jr};

/// SplitMix64 with Box-Muller normals: deterministic, no dependency.
pub(crate) struct Rng(u64);

impl Rng {
    pub(crate) fn new(seed: u64) -> Self {
        Self(seed ^ 0x9E37_79B9_7F4A_7C15)
    }

    pub(crate) fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }

    pub(crate) fn normal(&mut self) -> f64 {
        let u = self.uniform().max(1e-300);
        (-2.0 * u.ln()).sqrt() * (TAU * self.uniform()).cos()
    }

    pub(crate) fn sign(&mut self) -> f64 {
        if self.uniform() < 0.5 {
            -1.0
        } else {
            1.0
        }
    }

    pub(crate) fn vec3(&mut self, s: f64) -> Vector3<f64> {
        Vector3::new(self.normal(), self.normal(), self.normal()) * s
    }
}

/// Sinusoidal motion: `φ(t) = φ0 + A_i sin(2π f_i t + ψ_i)`, `p(t)` likewise.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Motion {
    pub rot_offset: Vector3<f64>,
    pub rot_amp: Vector3<f64>,
    pub rot_freq: Vector3<f64>,
    pub rot_phase: Vector3<f64>,
    pub pos_amp: Vector3<f64>,
    pub pos_freq: Vector3<f64>,
    pub pos_phase: Vector3<f64>,
}

/// True body state at time `t` (s): the state, the body rate and the world acceleration.
pub(crate) struct BodyTruth {
    pub nav: NavState,
    pub omega_b: Vector3<f64>,
    pub accel_w: Vector3<f64>,
}

impl Motion {
    /// The Fig. 4.4-like motion: ~1.3-1.6 rad/s peaks about every axis, ~2 m/s² peaks.
    pub(crate) fn calib() -> Self {
        Self {
            rot_offset: Vector3::new(0.2, -0.3, 0.1),
            rot_amp: Vector3::new(1.0, 0.9, 1.1),
            rot_freq: Vector3::new(0.23, 0.27, 0.19),
            rot_phase: Vector3::new(0.0, 1.0, 2.0),
            pos_amp: Vector3::new(0.5, 0.45, 0.4),
            pos_freq: Vector3::new(0.33, 0.29, 0.37),
            pos_phase: Vector3::new(0.5, 1.5, 2.5),
        }
    }

    /// At rest at the attitude `rot_offset`.
    pub(crate) fn still() -> Self {
        Self {
            rot_amp: Vector3::zeros(),
            pos_amp: Vector3::zeros(),
            ..Self::calib()
        }
    }

    pub(crate) fn at(&self, t: f64) -> BodyTruth {
        let (mut phi, mut phi_d) = (self.rot_offset, Vector3::zeros());
        let (mut p, mut v, mut a) = (Vector3::zeros(), Vector3::zeros(), Vector3::zeros());
        for i in 0..3 {
            let w = TAU * self.rot_freq[i];
            let arg = w * t + self.rot_phase[i];
            phi[i] += self.rot_amp[i] * arg.sin();
            phi_d[i] = self.rot_amp[i] * w * arg.cos();
            let u = TAU * self.pos_freq[i];
            let arg = u * t + self.pos_phase[i];
            p[i] = self.pos_amp[i] * arg.sin();
            v[i] = self.pos_amp[i] * u * arg.cos();
            a[i] = -self.pos_amp[i] * u * u * arg.sin();
        }
        BodyTruth {
            nav: NavState {
                r_gb: so3_exp(&phi),
                p_gb: p,
                v_gb: v,
            },
            omega_b: so3_jr(&phi) * phi_d,
            accel_w: a,
        }
    }
}

/// A non-ideal state for Jacobian tests (distortion, lever arm, T-model, biases, t_d, t_r).
pub(crate) fn test_state() -> CalibState {
    let mut imu = ImuIntrinsics::default();
    imu.t_g += Matrix3::new(4e-3, -2e-3, 1e-3, 3e-3, -5e-3, 2e-3, -1e-3, 4e-3, 3e-3);
    imu.t_a += Matrix3::new(-3e-3, 1e-3, 2e-3, 4e-3, 5e-3, -2e-3, 1e-3, -4e-3, 2e-3);
    imu.t_s = Matrix3::new(1e-3, -5e-4, 2e-4, 3e-4, 8e-4, -6e-4, -2e-4, 4e-4, -9e-4);
    CalibState {
        t_ns: 0,
        nav: NavState {
            r_gb: Rotation3::from_scaled_axis(Vector3::new(0.4, -0.6, 0.9)),
            p_gb: Vector3::new(0.3, -0.2, 1.1),
            v_gb: Vector3::new(0.7, 0.4, -0.3),
        },
        biases: ImuBiases {
            gyro: Vector3::new(0.01, -0.02, 0.015),
            accel: Vector3::new(0.1, -0.05, 0.08),
        },
        imu,
        r_cb: Rotation3::from_scaled_axis(Vector3::new(1.2, -0.3, 0.5)),
        p_cb: Vector3::new(0.04, -0.03, 0.02),
        camera: PinholeRadtan::from_coefficients(
            640,
            480,
            [452.0, 448.0, 318.0, 243.0],
            [-0.27, 0.075, 8e-4, -6e-4, 0.0],
        ),
        t_d: 0.012,
        t_r: 0.024,
    }
}

/// A whole scenario: motion, true calibration, sensors and landmarks.
pub(crate) struct Scenario {
    pub motion: Motion,
    /// True calibration (its `nav`, `t_ns` are unused; biases are the initial ones).
    pub truth: CalibState,
    pub noise: ImuNoise,
    pub pixel_sigma: f64,
    pub imu_period_ns: i64,
    pub frame_period_ns: i64,
    pub landmarks: Vec<Vector3<f64>>,
}

impl Scenario {
    /// 640x480 at 30 Hz, t_r = 25 ms, t_d = 30 ms, radtan; 200 Hz IMU (EuRoC densities) with
    /// T errors of the prior's size; landmarks on a 8 m box.
    pub(crate) fn calib(motion: Motion, rng: &mut Rng) -> Self {
        let mut imu = ImuIntrinsics::default();
        for r in 0..3 {
            for c in 0..3 {
                imu.t_g[(r, c)] += 5e-3 * rng.sign();
                imu.t_a[(r, c)] += 5e-3 * rng.sign();
                imu.t_s[(r, c)] = 1e-3 * rng.sign();
            }
        }
        let truth = CalibState {
            t_ns: 0,
            nav: motion.at(0.0).nav,
            biases: ImuBiases {
                gyro: rng.vec3(0.01),
                accel: rng.vec3(0.05),
            },
            imu,
            r_cb: Rotation3::from_scaled_axis(Vector3::new(1.2, -1.2, 1.2)),
            p_cb: Vector3::new(0.05, -0.03, 0.02),
            camera: PinholeRadtan::from_coefficients(
                640,
                480,
                [450.0, 452.0, 322.0, 238.0],
                [-0.28, 0.08, 1e-3, -5e-4, 0.0],
            ),
            t_d: 0.030,
            t_r: 0.025,
        };
        Self {
            motion,
            truth,
            noise: ImuNoise::default(),
            pixel_sigma: 0.5,
            imu_period_ns: 5_000_000,
            frame_period_ns: 33_333_333,
            landmarks: box_landmarks(4.0, 350, rng),
        }
    }

    /// IMU sample number `k` (time `k · period`); `biases` walk one step first.
    pub(crate) fn imu_sample(&self, k: i64, biases: &mut ImuBiases, rng: &mut Rng) -> ImuSample {
        let t_ns = k * self.imu_period_ns;
        let dt = self.imu_period_ns as f64 * 1e-9;
        let b = self.motion.at(t_ns as f64 * 1e-9);
        let n: [f64; 6] = std::array::from_fn(|_| rng.normal());
        crate::imu::bias_random_walk_step(biases, &self.noise, dt, &n);
        let a_s = b.nav.r_gb.inverse() * (b.accel_w - gravity_w());
        let (a, g) = measure(&a_s, &b.omega_b, biases, &self.truth.imu);
        let (sg, sa) = self.noise.discrete_white_sigma(dt);
        ImuSample {
            t_ns,
            gyro: g + rng.vec3(sg),
            accel: a + rng.vec3(sa),
        }
    }

    /// The observations of the frame stamped `t_mid_ns` (camera clock): every landmark at
    /// its rolling-shutter row (fixed point of `v = π(pose(t_mid + t_d + (v/N - ½) t_r))`),
    /// inside the image (before noise), with pixel noise.
    pub(crate) fn frame(&self, t_mid_ns: i64, rng: &mut Rng) -> Vec<Observation> {
        let tr = &self.truth;
        let n_rows = f64::from(tr.camera.height);
        let t_mid = t_mid_ns as f64 * 1e-9 + tr.t_d;
        let mid = self.motion.at(t_mid).nav;
        let mut out = Vec::new();
        for (id, x) in self.landmarks.iter().enumerate() {
            let pc = tr.r_cb * (mid.r_gb.inverse() * (x - mid.p_gb)) + tr.p_cb;
            if pc.z < 0.2 || pc.x.abs() > 1.0 * pc.z || pc.y.abs() > 0.8 * pc.z {
                continue;
            }
            let Some(uv) = self.rolling_pixel(x, t_mid, n_rows) else {
                continue;
            };
            // Kept by the true pixel: cutting by the noisy one would bias the noise of the
            // last observation of every track leaving the image (against its motion), which
            // the filter reads as readout time.
            let mut n = Vector2::new(rng.normal(), rng.normal()) * self.pixel_sigma;
            if let Ok(axis) = std::env::var("CALIB_NOISE_AXIS") {
                n[if axis == "u" { 1 } else { 0 }] = 0.0;
            }
            let noisy = uv + n;
            out.push(Observation {
                track: TrackId(id as u64),
                uv: noisy,
            });
        }
        out
    }

    fn rolling_pixel(&self, x: &Vector3<f64>, t_mid: f64, n_rows: f64) -> Option<Vector2<f64>> {
        let tr = &self.truth;
        let mut v = 0.5 * n_rows;
        for _ in 0..10 {
            let nav = self.motion.at(t_mid + (v / n_rows - 0.5) * tr.t_r).nav;
            let pc = tr.r_cb * (nav.r_gb.inverse() * (x - nav.p_gb)) + tr.p_cb;
            if pc.z < 0.2 {
                return None;
            }
            let uv = tr.camera.project(&pc)?;
            if (uv.y - v).abs() < 1e-7 {
                return tr.camera.contains(&uv).then_some(uv);
            }
            v = uv.y;
        }
        None
    }
}

/// `per_face` random points on each face of the cube `[-h, h]³`.
fn box_landmarks(h: f64, per_face: usize, rng: &mut Rng) -> Vec<Vector3<f64>> {
    let mut out = Vec::with_capacity(6 * per_face);
    for axis in 0..3 {
        for side in [-h, h] {
            for _ in 0..per_face {
                let mut p = Vector3::new(
                    (2.0 * rng.uniform() - 1.0) * h,
                    (2.0 * rng.uniform() - 1.0) * h,
                    (2.0 * rng.uniform() - 1.0) * h,
                );
                p[axis] = side;
                out.push(p);
            }
        }
    }
    out
}
