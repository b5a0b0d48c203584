//! Synthetic calibration scenarios (pure: no IO, threads or clocks) and the Monte-Carlo
//! trial of `shoal bench calibrate` ([`run_trial`], in `sim/trial.rs`).
//!
//! - `calib`: the seed's Fig. 4.4 and `VI_NOTES.md` §3 "Simulation": a body turning ≥ 1 rad/s
//!   about every axis with varied attitude to gravity, landmarks on the faces of a box around
//!   it ([`Motion::calib`], [`Scenario::calib`]);
//! - `phone`: a hand-held phone carried at walking pace (1.4 m/s) on a 5 m circle in a room,
//!   step bob and sway at 1-2 Hz, small rotations (~0.3-0.5 rad/s), upright, camera looking
//!   ahead ([`Motion::phone`]); it excites the calibration less.
//!
//! Both share the sensors: a 640x480 rolling-shutter camera with radtan distortion and a
//! 200 Hz T-model IMU with noise and bias random walk. Everything is in closed form:
//! `R_gb(t) = Rz(ψ(t)) Exp(φ(t)) R0` with a constant heading rate `ψ̇` and sinusoidal `φ`,
//! so `ω_b = R0ᵀ (Exp(φ)ᵀ ẑ ψ̇ + Jr(φ) φ̇)`, and `p(t) = c(t) + Rz(ψ) s(t)` with `c` a
//! circle (or nothing) and `s` sinusoidal (the `calib` motion has `ψ̇ = 0`, `R0 = I`).

use std::f64::consts::TAU;

use nalgebra::{Matrix3, Rotation3, Vector2, Vector3};

use super::params::CalibPriors;
use super::state::{CalibState, NavState};
use super::{ImuSample, Observation, TrackId, CORE_DIM, IDX_BG, IDX_TR};
use crate::camera::PinholeRadtan;
use crate::imu::{gravity_w, measure, ImuBiases, ImuIntrinsics, ImuNoise};
use crate::lie::{so3_exp, so3_jr};

mod trial;

pub use trial::{
    body_start, nominal_start, prior_sigma, run_trial, Epoch, FrameStep, MotionKind, Trial,
    TrialConfig, TrialTrace, CALIB_DIM, CALIB_FIRST,
};

/// SplitMix64 with Box-Muller normals: deterministic, no dependency.
pub struct Rng(u64);

impl Rng {
    /// A generator from a seed.
    pub fn new(seed: u64) -> Self {
        Self(seed ^ 0x9E37_79B9_7F4A_7C15)
    }

    /// Uniform in `[0, 1)`.
    pub fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Standard normal.
    pub fn normal(&mut self) -> f64 {
        let u = self.uniform().max(1e-300);
        (-2.0 * u.ln()).sqrt() * (TAU * self.uniform()).cos()
    }

    /// ±1 with equal odds.
    pub fn sign(&mut self) -> f64 {
        if self.uniform() < 0.5 {
            -1.0
        } else {
            1.0
        }
    }

    /// Three independent normals of σ `s`.
    pub fn vec3(&mut self, s: f64) -> Vector3<f64> {
        Vector3::new(self.normal(), self.normal(), self.normal()) * s
    }
}

/// Motion in closed form (module doc): `φ(t) = φ0 + A_i sin(2π f_i t + ψ_i)` and `s(t)`
/// likewise, in the walker frame `Rz(ψ)` (x ahead, z up) when `heading_rate ≠ 0`.
#[derive(Debug, Clone, Copy)]
pub struct Motion {
    /// `φ0`, rad.
    pub rot_offset: Vector3<f64>,
    /// Amplitudes of `φ`, rad.
    pub rot_amp: Vector3<f64>,
    /// Frequencies of `φ`, Hz.
    pub rot_freq: Vector3<f64>,
    /// Phases of `φ`, rad.
    pub rot_phase: Vector3<f64>,
    /// Amplitudes of `s`, m.
    pub pos_amp: Vector3<f64>,
    /// Frequencies of `s`, Hz.
    pub pos_freq: Vector3<f64>,
    /// Phases of `s`, rad.
    pub pos_phase: Vector3<f64>,
    /// `ψ̇`, rad/s: the heading turns at this rate (0: no heading, no path).
    pub heading_rate: f64,
    /// Speed along the path `c(t)`, m/s (a circle of radius `speed / ψ̇`; a straight line
    /// along x when `ψ̇ = 0`).
    pub walk_speed: f64,
    /// `R0`: body to walker frame.
    pub base: Rotation3<f64>,
}

/// True body state at time `t` (s): the state, the body rate and the world acceleration.
pub struct BodyTruth {
    /// Pose and velocity.
    pub nav: NavState,
    /// Angular rate in the body frame, rad/s.
    pub omega_b: Vector3<f64>,
    /// Acceleration in the global frame (gravity excluded), m/s².
    pub accel_w: Vector3<f64>,
}

/// The camera's fixed orientation `R_cb` in every scenario.
pub fn nominal_r_cb() -> Rotation3<f64> {
    Rotation3::from_scaled_axis(Vector3::new(1.2, -1.2, 1.2))
}

impl Motion {
    /// The Fig. 4.4-like motion: ~1.3-1.6 rad/s peaks about every axis, ~2 m/s² peaks.
    pub fn calib() -> Self {
        Self {
            rot_offset: Vector3::new(0.2, -0.3, 0.1),
            rot_amp: Vector3::new(1.0, 0.9, 1.1),
            rot_freq: Vector3::new(0.23, 0.27, 0.19),
            rot_phase: Vector3::new(0.0, 1.0, 2.0),
            pos_amp: Vector3::new(0.5, 0.45, 0.4),
            pos_freq: Vector3::new(0.33, 0.29, 0.37),
            pos_phase: Vector3::new(0.5, 1.5, 2.5),
            heading_rate: 0.0,
            walk_speed: 0.0,
            base: Rotation3::identity(),
        }
    }

    /// At rest at the attitude `rot_offset`.
    pub fn still() -> Self {
        Self {
            rot_amp: Vector3::zeros(),
            pos_amp: Vector3::zeros(),
            ..Self::calib()
        }
    }

    /// A phone held ahead while walking 1.4 m/s on a 5 m circle (heading 0.28 rad/s, a lap
    /// in 22 s), camera looking ahead 0.15 rad down; roll 0.04 rad at 1 Hz, pitch 0.025 rad
    /// at 2 Hz, yaw 0.05 rad at 1 Hz (peaks ~0.25-0.6 rad/s with the heading); surge 1.5 cm
    /// and bob 2.5 cm at 2 Hz (step), sway 3 cm at 1 Hz (peaks 2.4, 3.9, 1.2 m/s²).
    pub fn phone() -> Self {
        // Camera axes (x right, y down, z ahead) in the walker frame (x ahead, z up).
        let r_wc = Rotation3::from_matrix_unchecked(Matrix3::new(
            0.0, 0.0, 1.0, //
            -1.0, 0.0, 0.0, //
            0.0, -1.0, 0.0,
        ));
        Self {
            rot_offset: Vector3::new(0.0, 0.15, 0.0),
            rot_amp: Vector3::new(0.04, 0.025, 0.05),
            rot_freq: Vector3::new(1.0, 2.0, 1.0),
            rot_phase: Vector3::new(0.3, 0.0, 1.2),
            pos_amp: Vector3::new(0.015, 0.03, 0.025),
            pos_freq: Vector3::new(2.0, 1.0, 2.0),
            pos_phase: Vector3::new(0.5, 0.0, 1.5),
            heading_rate: 1.4 / 5.0,
            walk_speed: 1.4,
            base: r_wc * nominal_r_cb(),
        }
    }

    /// A phone held still in the hand (the real 0.8 s clip of `data/phone_honorv10`): tremor
    /// and drift of 0.02-0.04 rad at 0.4-0.9 Hz (peaks ~0.05-0.2 rad/s) and 3-6 mm of
    /// translation: almost no parallax on a scene 2-4 m away.
    pub fn handheld() -> Self {
        Self {
            rot_offset: Vector3::new(0.2, -0.3, 0.1),
            rot_amp: Vector3::new(0.03, 0.04, 0.02),
            rot_freq: Vector3::new(0.6, 0.4, 0.9),
            rot_phase: Vector3::new(0.0, 1.0, 2.0),
            pos_amp: Vector3::new(0.005, 0.006, 0.003),
            pos_freq: Vector3::new(0.7, 0.5, 0.9),
            pos_phase: Vector3::new(0.5, 1.5, 2.5),
            heading_rate: 0.0,
            walk_speed: 0.0,
            base: Rotation3::identity(),
        }
    }

    /// The true body state at `t` (s).
    pub fn at(&self, t: f64) -> BodyTruth {
        let (mut phi, mut phi_d) = (self.rot_offset, Vector3::zeros());
        let (mut s, mut s_d, mut s_dd) = (Vector3::zeros(), Vector3::zeros(), Vector3::zeros());
        for i in 0..3 {
            let w = TAU * self.rot_freq[i];
            let arg = w * t + self.rot_phase[i];
            phi[i] += self.rot_amp[i] * arg.sin();
            phi_d[i] = self.rot_amp[i] * w * arg.cos();
            let u = TAU * self.pos_freq[i];
            let arg = u * t + self.pos_phase[i];
            s[i] = self.pos_amp[i] * arg.sin();
            s_d[i] = self.pos_amp[i] * u * arg.cos();
            s_dd[i] = -self.pos_amp[i] * u * u * arg.sin();
        }
        let (psi_d, z) = (self.heading_rate, Vector3::z());
        let heading = Rotation3::from_axis_angle(&Vector3::z_axis(), psi_d * t);
        let e = so3_exp(&phi);
        let (c, c_d, c_dd) = self.path(t);
        let zs = z.cross(&s);
        BodyTruth {
            nav: NavState {
                r_gb: heading * e * self.base,
                p_gb: c + heading * s,
                v_gb: c_d + heading * (s_d + psi_d * zs),
            },
            omega_b: self.base.inverse() * (e.inverse() * z * psi_d + so3_jr(&phi) * phi_d),
            accel_w: c_dd
                + heading * (s_dd + 2.0 * psi_d * z.cross(&s_d) + psi_d * psi_d * z.cross(&zs)),
        }
    }

    /// The path `c(t)` and its first two derivatives: a circle of radius `speed / ψ̇`
    /// starting at the origin heading along x, turning left; a line along x when `ψ̇ = 0`.
    fn path(&self, t: f64) -> (Vector3<f64>, Vector3<f64>, Vector3<f64>) {
        let (v, w) = (self.walk_speed, self.heading_rate);
        if w == 0.0 {
            return (
                Vector3::new(v * t, 0.0, 0.0),
                Vector3::new(v, 0.0, 0.0),
                Vector3::zeros(),
            );
        }
        let (sn, cs) = (w * t).sin_cos();
        let r = v / w;
        (
            Vector3::new(r * sn, r * (1.0 - cs), 0.0),
            Vector3::new(v * cs, v * sn, 0.0),
            Vector3::new(-v * w * sn, v * w * cs, 0.0),
        )
    }
}

/// A non-ideal state for Jacobian tests (distortion, lever arm, T-model, biases, t_d, t_r).
#[cfg(test)]
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

/// The nominal calibration (what the filter starts from in a Monte-Carlo trial): ideal
/// IMU (`T_g = T_a = I`, `T_s = 0`, zero biases), 640x480 radtan camera, `t_d` 30 ms,
/// `t_r` 25 ms; the body at `nav`.
pub fn nominal_calibration(nav: NavState) -> CalibState {
    CalibState {
        t_ns: 0,
        nav,
        biases: ImuBiases::default(),
        imu: ImuIntrinsics::default(),
        r_cb: nominal_r_cb(),
        p_cb: Vector3::new(0.05, -0.03, 0.02),
        camera: PinholeRadtan::from_coefficients(
            640,
            480,
            [450.0, 452.0, 322.0, 238.0],
            [-0.28, 0.08, 1e-3, -5e-4, 0.0],
        ),
        t_d: 0.030,
        t_r: 0.025,
    }
}

/// A whole scenario: motion, true calibration, sensors and landmarks.
pub struct Scenario {
    /// The body's motion.
    pub motion: Motion,
    /// True calibration (its `nav`, `t_ns` are unused; biases are the initial ones).
    pub truth: CalibState,
    /// IMU noise densities.
    pub noise: ImuNoise,
    /// Pixel noise σ per coordinate, px.
    pub pixel_sigma: f64,
    /// Diagnostic: `Some(0)` zeroes the noise on u (column), `Some(1)` on v (row).
    pub zero_noise_axis: Option<usize>,
    /// IMU sample period, ns.
    pub imu_period_ns: i64,
    /// Frame period, ns.
    pub frame_period_ns: i64,
    /// World points.
    pub landmarks: Vec<Vector3<f64>>,
}

impl Scenario {
    /// 640x480 at 30 Hz, t_r = 25 ms, t_d = 30 ms, radtan; 200 Hz IMU (EuRoC densities) with
    /// T errors of the prior's size (±5e-3, ±1e-3 per element); landmarks on a 8 m box.
    pub fn calib(motion: Motion, rng: &mut Rng) -> Self {
        let mut truth = nominal_calibration(motion.at(0.0).nav);
        let imu = &mut truth.imu;
        for r in 0..3 {
            for c in 0..3 {
                imu.t_g[(r, c)] += 5e-3 * rng.sign();
                imu.t_a[(r, c)] += 5e-3 * rng.sign();
                imu.t_s[(r, c)] = 1e-3 * rng.sign();
            }
        }
        truth.biases = ImuBiases {
            gyro: rng.vec3(0.01),
            accel: rng.vec3(0.05),
        };
        Self::with_truth(motion, truth, box_landmarks(4.0, 350, rng))
    }

    /// A Monte-Carlo draw: the true biases and calibration `T_g .. t_r` drawn around
    /// [`nominal_calibration`] with the 1σ of `priors` (the seed's Table 4.3 caption);
    /// landmarks on an 8 m box (`calib`-like motions) or the walls, floor and ceiling of a
    /// 20 m x 20 m x 3 m room around the circle ([`Motion::phone`]).
    pub fn monte_carlo(motion: Motion, priors: &CalibPriors, rng: &mut Rng) -> Self {
        let mut truth = nominal_calibration(motion.at(0.0).nav);
        let sigma2 = priors.covariance().diagonal();
        let mut dx = nalgebra::DVector::zeros(CORE_DIM);
        for i in IDX_BG..=IDX_TR {
            dx[i] = rng.normal() * sigma2[i].sqrt();
        }
        truth.retract(&dx);
        let landmarks = if motion.heading_rate == 0.0 {
            box_landmarks(4.0, 350, rng)
        } else {
            let r = motion.walk_speed / motion.heading_rate;
            let centre = Vector3::new(0.0, r, 0.1);
            room_landmarks(&centre, &Vector3::new(2.0 * r, 2.0 * r, 1.5), 6.0, rng)
        };
        Self::with_truth(motion, truth, landmarks)
    }

    fn with_truth(motion: Motion, truth: CalibState, landmarks: Vec<Vector3<f64>>) -> Self {
        Self {
            motion,
            truth,
            noise: ImuNoise::default(),
            pixel_sigma: 0.5,
            zero_noise_axis: None,
            imu_period_ns: 5_000_000,
            frame_period_ns: 33_333_333,
            landmarks,
        }
    }

    /// IMU sample number `k` (time `k · period`); `biases` walk one step first.
    pub fn imu_sample(&self, k: i64, biases: &mut ImuBiases, rng: &mut Rng) -> ImuSample {
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
    /// inside the image (before noise) and where the lens is one-to-one, with pixel noise.
    pub fn frame(&self, t_mid_ns: i64, rng: &mut Rng) -> Vec<Observation> {
        let tr = &self.truth;
        let t_mid = t_mid_ns as f64 * 1e-9 + tr.t_d;
        let mid = self.motion.at(t_mid).nav;
        let mut out = Vec::new();
        for (id, x) in self.landmarks.iter().enumerate() {
            let pc = tr.r_cb * (mid.r_gb.inverse() * (x - mid.p_gb)) + tr.p_cb;
            if pc.z < 0.2 || pc.x.abs() > 1.0 * pc.z || pc.y.abs() > 0.8 * pc.z {
                continue;
            }
            if !radially_monotone(&tr.camera, (pc.x / pc.z).hypot(pc.y / pc.z)) {
                continue;
            }
            let Some(uv) = self.rolling_pixel(x, t_mid) else {
                continue;
            };
            // Kept by the true pixel: cutting by the noisy one would bias the noise of the
            // last observation of every track leaving the image (against its motion), which
            // the filter reads as readout time.
            let mut n = Vector2::new(rng.normal(), rng.normal()) * self.pixel_sigma;
            if let Some(axis) = self.zero_noise_axis {
                n[axis] = 0.0;
            }
            out.push(Observation {
                track: TrackId(id as u64),
                uv: uv + n,
            });
        }
        out
    }

    /// The pixel of `x` read at its own line time: the fixed point of
    /// `l = line(π(pose(t_mid + (l/N - ½) t_r)))` ([`PinholeRadtan::readout_line`]), from the
    /// middle line.
    fn rolling_pixel(&self, x: &Vector3<f64>, t_mid: f64) -> Option<Vector2<f64>> {
        let tr = &self.truth;
        let n = f64::from(tr.camera.readout_line(&Vector2::zeros()).1);
        let mut line = 0.5 * n;
        for _ in 0..10 {
            let nav = self.motion.at(t_mid + (line / n - 0.5) * tr.t_r).nav;
            let pc = tr.r_cb * (nav.r_gb.inverse() * (x - nav.p_gb)) + tr.p_cb;
            if pc.z < 0.2 {
                return None;
            }
            let uv = tr.camera.project(&pc)?;
            let next = tr.camera.readout_line(&uv).0;
            if (next - line).abs() < 1e-7 {
                return tr.camera.contains(&uv).then_some(uv);
            }
            line = next;
        }
        None
    }
}

/// True when the radial distortion `r (1 + k1 r² + k2 r⁴)` still grows at the normalised
/// radius `r` (with a margin): beyond, a drawn lens could fold far points into the image.
fn radially_monotone(camera: &PinholeRadtan, r: f64) -> bool {
    let r2 = r * r;
    1.0 + 3.0 * camera.k1 * r2 + 5.0 * camera.k2 * r2 * r2 > 0.2
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

/// Random points on the six faces of the box `centre ± half`, `per_m2` per square metre.
fn room_landmarks(
    centre: &Vector3<f64>,
    half: &Vector3<f64>,
    per_m2: f64,
    rng: &mut Rng,
) -> Vec<Vector3<f64>> {
    let mut out = Vec::new();
    for axis in 0..3 {
        let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
        let n = (4.0 * half[a] * half[b] * per_m2).round() as usize;
        for side in [-1.0, 1.0] {
            for _ in 0..n {
                let mut p = Vector3::zeros();
                p[axis] = side * half[axis];
                p[a] = (2.0 * rng.uniform() - 1.0) * half[a];
                p[b] = (2.0 * rng.uniform() - 1.0) * half[b];
                out.push(centre + p);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lie::so3_log;

    /// The closed-form rate, velocity and acceleration of both motions match central
    /// differences of the pose.
    #[test]
    fn motion_derivatives_match_finite_differences() {
        let h = 1e-5;
        for m in [Motion::calib(), Motion::phone()] {
            for t in [0.0, 0.37, 3.1, 17.9] {
                let (b, lo, hi) = (m.at(t), m.at(t - h).nav, m.at(t + h).nav);
                let w = so3_log(&(lo.r_gb.inverse() * hi.r_gb)) / (2.0 * h);
                let v = (hi.p_gb - lo.p_gb) / (2.0 * h);
                let a = (m.at(t + h).nav.v_gb - m.at(t - h).nav.v_gb) / (2.0 * h);
                assert!((w - b.omega_b).norm() < 1e-6, "ω {w} vs {}", b.omega_b);
                assert!((v - b.nav.v_gb).norm() < 1e-6, "v {v} vs {}", b.nav.v_gb);
                assert!((a - b.accel_w).norm() < 1e-4, "a {a} vs {}", b.accel_w);
            }
        }
    }

    /// The phone motion: upright (camera axis within 0.3 rad of horizontal), walking pace,
    /// rates well below the `calib` motion's.
    #[test]
    fn phone_motion_is_a_slow_upright_walk() {
        let (phone, calib) = (Motion::phone(), Motion::calib());
        let rms = |m: &Motion| {
            let s: f64 = (0..2000)
                .map(|k| m.at(k as f64 * 0.01).omega_b.norm_squared())
                .sum();
            (s / 2000.0).sqrt()
        };
        let (w_phone, w_calib) = (rms(&phone), rms(&calib));
        eprintln!("rms rate: phone {w_phone:.2} rad/s, calib {w_calib:.2} rad/s");
        assert!((0.25..0.6).contains(&w_phone) && w_calib > 1.0);
        for k in 0..200 {
            let b = phone.at(k as f64 * 0.1);
            let axis_w = b.nav.r_gb * (nominal_r_cb().inverse() * Vector3::z());
            assert!(axis_w.z.abs() < 0.3, "camera axis {axis_w}");
            assert!((b.nav.v_gb.norm() - 1.4).abs() < 0.5);
        }
    }
}
