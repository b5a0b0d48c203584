//! The sliding-window visual-inertial optimisation (`slam_core::imu::window`) on the `drone`
//! world: keyframes every 0.25 s, IMU from the world (exact or with the ADIS16448 noise of
//! the scenario), landmarks spawned in each keyframe's view (depth 2-8 m, seen from the
//! keyframes within ±3 s of their birth, no occlusion), pixels with 1 px noise.
//!
//! 1. From the truth perturbed (0.1 m, 2°, 0.2 m/s, biases zeroed, points 5 cm): back to the
//!    truth (exact IMU), to errors of the order of the noise (noisy IMU).
//! 2. From a 5 % wrong scale: the IMU factors bring it back to metric.
//! 3. A 10-keyframe window slid over 25 s: bounded window, trajectory error (SE(3)-aligned)
//!    and gravity (roll/pitch) error against the truth.
//! 4. A second `optimize` on a window of the same size allocates nothing.
//!
//! Figures are printed (`--nocapture`); times are printed, never asserted.

use std::time::Instant;

// The counting allocator of slam_core's no-allocation tests (one copy).
#[path = "../../slam_core/tests/common/mod.rs"]
mod common;
use common::allocations;

use datasets::sim::{Scenario, SimParams, SimWorld};
use nalgebra::{Isometry3, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3};
use slam_core::imu::init::{initialize, InitParams};
use slam_core::imu::preint::Vector15;
use slam_core::imu::window::{
    gauge_prior, point_from_init, reprojection_jacobians, states_from_init, ViKeyframe,
    ViObservation, ViParams, ViReport, ViSolver, ViWindow,
};
use slam_core::imu::{
    gravity_w, ImuBiases, ImuNoise, NavState, Preintegrated, PreintegrationParams,
};
use slam_core::lie::{so3_exp, so3_log};
use slam_core::metrics::{evaluate_by_index, Alignment, EvalParams};

const KF_STEP_NS: i64 = 250_000_000;
const IMU_STEP_NS: i64 = 5_000_000;
const PX_SIGMA: f64 = 1.0;
/// Landmarks spawned per keyframe.
const PER_KF: usize = 40;
/// A landmark is seen from keyframes within this many keyframes of its birth.
const VIS_KFS: usize = 12;
/// Free keyframes of the sliding window (plus the fixed one before them).
const WINDOW: usize = 10;

/// CPU time of the current thread, ms (Linux `/proc/thread-self/schedstat`; 0 elsewhere):
/// the machine is shared, so wall time says little.
fn cpu_ms() -> f64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse::<f64>().ok())
        .map_or(0.0, |ns| ns * 1e-6)
}

/// Deterministic generator (SplitMix64, Box-Muller).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next()
    }
    fn normal(&mut self) -> f64 {
        let (u, v) = (self.next().max(1e-300), self.next());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
    fn vec3(&mut self, sigma: f64) -> Vector3<f64> {
        Vector3::new(self.normal(), self.normal(), self.normal()) * sigma
    }
}

/// The `drone` world, its keyframes, landmarks and noisy observations.
struct Sim {
    world: SimWorld,
    kf_ns: Vec<i64>,
    truth: Vec<NavState>,
    landmarks: Vec<Vector3<f64>>,
    birth: Vec<usize>,
    /// Per keyframe: (landmark, noisy pixel).
    obs: Vec<Vec<(u32, Vector2<f64>)>>,
    params: PreintegrationParams,
}

impl Sim {
    /// `n_kf` keyframes from `t0_s` on, IMU noise `noise` in the world.
    fn new(noise: ImuNoise, n_kf: usize, t0_s: f64, seed: u64) -> Self {
        let mut p = SimParams::new(Scenario::Drone);
        p.seed = seed;
        p.noise = noise;
        p.frames = Some(((t0_s + n_kf as f64 * 0.25 + 2.0) * 20.0) as usize);
        let world = SimWorld::new(p).expect("world");
        let start = world.params().start_ns;
        let t0 = start + (t0_s * 200.0).round() as i64 * IMU_STEP_NS;
        let kf_ns: Vec<i64> = (0..n_kf as i64).map(|k| t0 + k * KF_STEP_NS).collect();
        let gt = world.ground_truth_states();
        let truth = kf_ns
            .iter()
            .map(|&t| {
                let s = &gt[((t - gt[0].t_ns) / IMU_STEP_NS) as usize];
                assert_eq!(s.t_ns, t, "keyframes on the IMU grid");
                NavState {
                    r: s.q_wb.to_rotation_matrix(),
                    p: s.p_wb,
                    v: s.v_w,
                    biases: s.biases,
                }
            })
            .collect();
        let mut sim = Self {
            params: PreintegrationParams::new(&ImuNoise::default(), &Default::default())
                .expect("params"),
            world,
            kf_ns,
            truth,
            landmarks: Vec::new(),
            birth: Vec::new(),
            obs: Vec::new(),
        };
        sim.spawn_and_observe(&mut Rng(seed * 7 + 1));
        sim
    }

    fn t_bc(&self) -> Isometry3<f64> {
        self.world.calib().t_bs
    }

    fn t_wc(&self, s: &NavState) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::from(s.p),
            UnitQuaternion::from_rotation_matrix(&s.r),
        ) * self.t_bc()
    }

    fn spawn_and_observe(&mut self, rng: &mut Rng) {
        let cam = *self.world.camera();
        let (w, h) = (f64::from(cam.width), f64::from(cam.height));
        for k in 0..self.kf_ns.len() {
            let t_wc = self.t_wc(&self.truth[k]);
            for _ in 0..PER_KF {
                let uv = Vector2::new(rng.uniform(20.0, w - 20.0), rng.uniform(20.0, h - 20.0));
                let d = rng.uniform(2.0, 8.0);
                self.landmarks.push(
                    t_wc.transform_point(&(cam.unproject(&uv) * d).into())
                        .coords,
                );
                self.birth.push(k);
            }
        }
        let t_bc = self.t_bc();
        for k in 0..self.kf_ns.len() {
            let mut v = Vec::new();
            for (i, p) in self.landmarks.iter().enumerate() {
                if self.birth[i].abs_diff(k) > VIS_KFS {
                    continue;
                }
                if let Some((uv, _, _)) =
                    reprojection_jacobians(&cam, &t_bc, &self.truth[k], p, 0.0)
                {
                    if cam.contains(&uv) {
                        let n = Vector2::new(rng.normal(), rng.normal()) * PX_SIGMA;
                        v.push((i as u32, uv + n));
                    }
                }
            }
            self.obs.push(v);
        }
    }

    /// IMU preintegration from keyframe `k` to `k + 1`, linearised at `bias_lin`.
    fn preint(&self, k: usize, bias_lin: ImuBiases) -> Preintegrated {
        Preintegrated::from_window(
            self.world.imu_samples(),
            self.kf_ns[k],
            self.kf_ns[k + 1],
            bias_lin,
            self.params,
        )
        .expect("IMU brackets the keyframes")
    }

    /// The window over keyframes `first..=last` (the first fixed) at the estimates `states`
    /// and `points` (landmarks without an estimate are left out); returns it with the
    /// landmark of each window point.
    fn window(
        &self,
        first: usize,
        last: usize,
        states: &[NavState],
        points: &[Option<Vector3<f64>>],
    ) -> (ViWindow, Vec<u32>) {
        let mut slot = vec![u32::MAX; self.landmarks.len()];
        let mut ids = Vec::new();
        let mut points_w = Vec::new();
        let mut observations = Vec::new();
        for k in first..=last {
            for &(i, uv) in &self.obs[k] {
                let Some(p) = points[i as usize] else {
                    continue;
                };
                if slot[i as usize] == u32::MAX {
                    slot[i as usize] = ids.len() as u32;
                    ids.push(i);
                    points_w.push(p);
                }
                observations.push(ViObservation {
                    kf: (k - first) as u32,
                    point: slot[i as usize],
                    uv,
                    sigma_px: PX_SIGMA,
                    dt_s: 0.0,
                });
            }
        }
        let w = ViWindow {
            keyframes: (first..=last)
                .map(|k| ViKeyframe {
                    rig: 0,
                    t_ns: self.kf_ns[k],
                    state: states[k],
                    fixed: k == first,
                })
                .collect(),
            n_visual: 0,
            preints: (first..last)
                .map(|k| self.preint(k, states[k].biases))
                .collect(),
            points_w,
            observations,
            t_bc: self.t_bc(),
            camera: *self.world.camera(),
            gravity_w: gravity_w(),
            prior: None,
            ..ViWindow::empty()
        };
        (w, ids)
    }
}

/// RMS errors of the window's free keyframes against the truth: position m, rotation °,
/// velocity m/s, gyro bias rad/s, accel bias m/s².
fn rms_errors(w: &ViWindow, truth: &[NavState]) -> [f64; 5] {
    let mut e = [0.0f64; 5];
    let mut n = 0.0;
    for (kf, t) in w.keyframes.iter().zip(truth).filter(|(k, _)| !k.fixed) {
        let s = &kf.state;
        e[0] += (s.p - t.p).norm_squared();
        e[1] += so3_log(&(t.r.inverse() * s.r)).norm().to_degrees().powi(2);
        e[2] += (s.v - t.v).norm_squared();
        e[3] += (s.biases.gyro - t.biases.gyro).norm_squared();
        e[4] += (s.biases.accel - t.biases.accel).norm_squared();
        n += 1.0;
    }
    e.map(|x| (x / n).sqrt())
}

fn print_report(label: &str, r: &ViReport, secs: f64) {
    eprintln!(
        "{label}: {} iterations ({} solves), cost {:.1} -> {:.1}; final χ² reprojection {:.1} \
         ({} above 5.991), IMU {:.2}, bias walk {:.2}; {:.1} ms",
        r.iterations,
        r.solves,
        r.initial.cost,
        r.last.cost,
        r.last.reprojection,
        r.last.reprojection_outliers,
        r.last.imu,
        r.last.bias_walk,
        secs * 1e3
    );
}

/// Window of 11 keyframes at 5 s, truth perturbed; optimised. Returns the errors before and
/// after, the window and its report.
fn perturbed_window(noise: ImuNoise, seed: u64) -> ([f64; 5], [f64; 5], ViWindow, ViReport, f64) {
    let sim = Sim::new(noise, WINDOW + 1, 5.0, seed);
    let mut rng = Rng(seed + 100);
    let mut states = sim.truth.clone();
    for s in states.iter_mut().skip(1) {
        s.r *= so3_exp(&(rng.vec3(1.0).normalize() * 2f64.to_radians()));
        s.p += rng.vec3(0.1 / 3f64.sqrt());
        s.v += rng.vec3(0.2 / 3f64.sqrt());
        s.biases = ImuBiases::default();
    }
    let points: Vec<_> = sim
        .landmarks
        .iter()
        .map(|p| Some(p + rng.vec3(0.05)))
        .collect();
    let (mut w, _) = sim.window(0, WINDOW, &states, &points);
    let before = rms_errors(&w, &sim.truth);
    let mut solver = ViSolver::new();
    let (t, c) = (Instant::now(), cpu_ms());
    let rep = solver
        .optimize(&mut w, &ViParams::default())
        .expect("optimised");
    let secs = t.elapsed().as_secs_f64();
    print_report(&format!("perturbed window {noise:?}"), &rep, secs);
    eprintln!("  CPU {:.1} ms (first call on this solver)", cpu_ms() - c);
    eprintln!(
        "  {} keyframes, {} points, {} observations",
        w.keyframes.len(),
        w.points_w.len(),
        w.observations.len()
    );
    let nees = nees(&mut solver, &w, &sim.truth);
    eprintln!(
        "  NEES (15 dof, against the window's marginal covariances) mean {:.1}, max {:.1}; \
         last keyframe σ_p {:.4} m, σ_v {:.4} m/s",
        nees.0, nees.1, nees.2, nees.3
    );
    (before, rms_errors(&w, &sim.truth), w, rep, nees.0)
}

/// NEES of the free keyframes' 15-dof errors under their marginal covariances: (mean, max,
/// last keyframe's position σ (m), velocity σ (m/s)).
fn nees(solver: &mut ViSolver, w: &ViWindow, truth: &[NavState]) -> (f64, f64, f64, f64) {
    let (mut sum, mut max, mut n) = (0.0, 0.0f64, 0.0);
    let mut sig = (0.0, 0.0);
    for (k, (kf, t)) in w.keyframes.iter().zip(truth).enumerate().skip(1) {
        let cov = solver
            .keyframe_covariance(w, &ViParams::default(), k)
            .expect("covariance");
        let s = &kf.state;
        let mut e = Vector15::zeros();
        e.fixed_rows_mut::<3>(0)
            .copy_from(&so3_log(&(t.r.inverse() * s.r)));
        e.fixed_rows_mut::<3>(3).copy_from(&(s.p - t.p));
        e.fixed_rows_mut::<3>(6).copy_from(&(s.v - t.v));
        e.fixed_rows_mut::<3>(9)
            .copy_from(&(s.biases.gyro - t.biases.gyro));
        e.fixed_rows_mut::<3>(12)
            .copy_from(&(s.biases.accel - t.biases.accel));
        let v = e.dot(&(cov.try_inverse().expect("invertible") * e));
        (sum, max, n) = (sum + v, max.max(v), n + 1.0);
        sig = (
            cov.fixed_view::<3, 3>(3, 3).trace().sqrt(),
            cov.fixed_view::<3, 3>(6, 6).trace().sqrt(),
        );
    }
    (sum / n, max, sig.0, sig.1)
}

fn print_errors(label: &str, e: &[f64; 5]) {
    eprintln!(
        "  {label}: p {:.4} m, R {:.4}°, v {:.4} m/s, b_g {:.2e} rad/s, b_a {:.4} m/s²",
        e[0], e[1], e[2], e[3], e[4]
    );
}

/// Exact IMU, 1 px pixels: the perturbed window goes back to the truth.
#[test]
fn perturbed_window_converges_exact_imu() {
    let (before, after, _, rep, _) = perturbed_window(ImuNoise::zero(), 3);
    print_errors("before", &before);
    print_errors("after", &after);
    assert!(
        rep.converged && rep.last.cost < 0.01 * rep.initial.cost,
        "{rep:?}"
    );
    assert!(
        after[0] < 0.01 && after[1] < 0.1 && after[2] < 0.01,
        "{after:?}"
    );
    assert!(after[3] < 1e-3 && after[4] < 0.05, "{after:?}");
}

/// ADIS16448 noise in the IMU: errors of the order of what the noise allows.
#[test]
fn perturbed_window_converges_noisy_imu() {
    let (before, after, _, rep, nees) = perturbed_window(ImuNoise::default(), 4);
    print_errors("before", &before);
    print_errors("after", &after);
    // Consistent errors: mean NEES of 15-dof states near 15 (loose: the keyframes are
    // correlated and one run is one sample).
    assert!(nees < 45.0, "NEES {nees}");
    assert!(rep.last.cost < 0.01 * rep.initial.cost, "{rep:?}");
    assert!(
        after[0] < 0.02 && after[1] < 0.2 && after[2] < 0.02,
        "{after:?}"
    );
    assert!(after[3] < 2e-3 && after[4] < 0.1, "{after:?}");
}

/// Positions (about the fixed keyframe), velocities and points 5 % too large: the IMU
/// factors restore the metric scale.
#[test]
fn wrong_scale_is_pulled_back_to_metric() {
    let sim = Sim::new(ImuNoise::default(), WINDOW + 1, 8.0, 6);
    let s0 = 1.05;
    let o = sim.truth[0].p;
    let mut states = sim.truth.clone();
    for s in states.iter_mut().skip(1) {
        s.p = o + (s.p - o) * s0;
        s.v *= s0;
    }
    let points: Vec<_> = sim
        .landmarks
        .iter()
        .map(|p| Some(o + (p - o) * s0))
        .collect();
    let (mut w, _) = sim.window(0, WINDOW, &states, &points);
    let scale = |w: &ViWindow| {
        let num: f64 = w.keyframes.iter().map(|k| (k.state.p - o).norm()).sum();
        let den: f64 = sim.truth.iter().map(|t| (t.p - o).norm()).sum();
        num / den
    };
    let before = scale(&w);
    let t = Instant::now();
    let rep = ViSolver::new()
        .optimize(&mut w, &ViParams::default())
        .expect("optimised");
    print_report("wrong scale", &rep, t.elapsed().as_secs_f64());
    let after = scale(&w);
    eprintln!("  scale {before:.4} -> {after:.5} (path {:.2} m)", {
        sim.truth
            .windows(2)
            .map(|p| (p[1].p - p[0].p).norm())
            .sum::<f64>()
    });
    print_errors("after", &rms_errors(&w, &sim.truth));
    assert!((before - 1.05).abs() < 1e-9);
    assert!((after - 1.0).abs() < 0.01, "scale {after}");
}

/// Tilt (roll/pitch) error, °: the angle between the estimated and true gravity direction
/// in the body frame.
fn tilt_deg(est: &NavState, truth: &NavState) -> f64 {
    let z = Vector3::z();
    (est.r.inverse() * z)
        .angle(&(truth.r.inverse() * z))
        .to_degrees()
}

fn iso(s: &NavState) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::from(s.p),
        UnitQuaternion::from_rotation_matrix(&s.r),
    )
}

/// Initial estimate of the landmarks born at keyframe `k`: the first noisy pixel back-
/// projected from the *estimated* keyframe pose at the true depth with 5 % noise (a stand-in
/// for the local mapper's triangulation).
fn init_points(
    sim: &Sim,
    k: usize,
    est: &NavState,
    points: &mut [Option<Vector3<f64>>],
    rng: &mut Rng,
) {
    let t_wc_true = sim.t_wc(&sim.truth[k]);
    let t_wc = sim.t_wc(est);
    for &(i, uv) in &sim.obs[k] {
        if sim.birth[i as usize] != k {
            continue;
        }
        let d = (sim.landmarks[i as usize] - t_wc_true.translation.vector).norm();
        let b = sim.world.camera().unproject(&uv);
        points[i as usize] = Some(
            t_wc.transform_point(&(b * d * (1.0 + 0.05 * rng.normal())).into())
                .coords,
        );
    }
}

/// The window slid over 25 s of the drone flight (noisy IMU, 1 px), its first window at
/// the truth or at the inertial initialisation's output (then all free with a 4-DoF gauge
/// prior); returns the keyframe estimates, the truth and per-window (wall ms, CPU ms,
/// iterations, χ²/observation, points).
fn sliding_run(from_init: bool) -> (Vec<NavState>, Vec<NavState>, Vec<[f64; 5]>) {
    let n_kf = 101;
    let sim = Sim::new(ImuNoise::default(), n_kf, 2.0, 8);
    let mut rng = Rng(77);
    let g = gravity_w();
    let mut est = sim.truth.clone();
    let mut points = vec![None; sim.landmarks.len()];
    if from_init {
        let (states, pts) = init_from_vo(&sim, WINDOW + 1, &mut rng);
        est[..=WINDOW].copy_from_slice(&states);
        points = pts;
    } else {
        for (k, s) in est.iter().enumerate().take(WINDOW + 1) {
            init_points(&sim, k, s, &mut points, &mut rng);
        }
    }
    let mut solver = ViSolver::new();
    let mut stats = Vec::new();
    for n in WINDOW..n_kf {
        if n > WINDOW {
            est[n] = sim
                .preint(n - 1, est[n - 1].biases)
                .predict(&est[n - 1], &g);
            init_points(&sim, n, &est[n], &mut points, &mut rng);
        }
        let first = n - WINDOW;
        let (mut w, ids) = sim.window(first, n, &est, &points);
        assert_eq!(w.keyframes.len(), WINDOW + 1);
        if from_init && n == WINDOW {
            w.keyframes[0].fixed = false;
            w.prior = Some(gauge_prior(0, &est[0], 0.001, 0.001));
        }
        let (t, c) = (Instant::now(), cpu_ms());
        let rep = solver
            .optimize(&mut w, &ViParams::default())
            .expect("optimised");
        stats.push([
            t.elapsed().as_secs_f64() * 1e3,
            cpu_ms() - c,
            rep.iterations as f64,
            rep.last.reprojection / w.observations.len() as f64,
            w.points_w.len() as f64,
        ]);
        for (k, kf) in w.keyframes.iter().enumerate() {
            est[first + k] = kf.state;
        }
        for (i, p) in ids.iter().zip(&w.points_w) {
            points[*i as usize] = Some(*p);
        }
    }
    (est, sim.truth, stats)
}

/// Median and max of column `c` of the per-window statistics.
fn median_max(stats: &[[f64; 5]], c: usize) -> (f64, f64) {
    let mut v: Vec<f64> = stats.iter().map(|s| s[c]).collect();
    v.sort_by(f64::total_cmp);
    (v[v.len() / 2], v[v.len() - 1])
}

/// The sliding run from the truth and from the inertial initialisation: bounded window,
/// trajectory error (SE(3)-aligned) and gravity (roll/pitch) error against the truth.
#[test]
fn sliding_window_over_the_drone_flight() {
    for from_init in [false, true] {
        let (est, truth, stats) = sliding_run(from_init);
        let m = sliding_metrics(&est, &truth, &stats, from_init);
        assert!(m.0 < 0.1, "ATE {}", m.0);
        assert!(m.1 < 0.5, "tilt {}°", m.1);
        assert!(m.2 < 0.05, "velocity rmse {}", m.2);
        // 1 px noise: χ²/observation ≤ 2 at the optimum (2 rows, less the absorbed dof).
        assert!(m.3 < 2.0 && m.4 < 5.0, "χ²/observation {} {}", m.3, m.4);
    }
}

/// Prints the figures of a sliding run; returns (ATE rmse m, max tilt °, body-velocity rmse
/// m/s, median and max χ²/observation).
fn sliding_metrics(
    est: &[NavState],
    truth: &[NavState],
    stats: &[[f64; 5]],
    from_init: bool,
) -> (f64, f64, f64, f64, f64) {
    let n_kf = est.len();
    let g = gauge_free_errors(est, truth);
    let reference: Vec<_> = truth.iter().map(iso).collect();
    let estimate: Vec<_> = est.iter().map(iso).collect();
    let params = |alignment| EvalParams {
        alignment,
        ..Default::default()
    };
    let ate = evaluate_by_index(&reference, &estimate, &params(Alignment::Se3)).expect("ate");
    let raw = evaluate_by_index(&reference, &estimate, &params(Alignment::None)).expect("ape");
    let tilt_last = tilt_deg(&est[n_kf - 1], &truth[n_kf - 1]);
    let ((wall_med, wall_max), (cpu_med, cpu_max)) = (median_max(stats, 0), median_max(stats, 1));
    let (it_med, _) = median_max(stats, 2);
    let (chi_med, chi_max) = median_max(stats, 3);
    let (_, pts_max) = median_max(stats, 4);
    eprintln!(
        "sliding from {}: {} windows of {} keyframes over {:.1} s ({:.1} m), ≤ {pts_max} points; \
         iterations/window median {it_med}; wall median {wall_med:.1} ms, max {wall_max:.1} ms; \
         CPU median {cpu_med:.1} ms, max {cpu_max:.1} ms",
        if from_init {
            "the inertial initialisation"
        } else {
            "the truth"
        },
        stats.len(),
        WINDOW + 1,
        (n_kf - 1) as f64 * 0.25,
        ate.ref_path_length_m,
    );
    eprintln!(
        "  ATE (SE(3)-aligned) rmse {:.4} m, max {:.4} m; unaligned rmse {:.4} m, max {:.4} m; \
         scale (path ratio) {:.4}",
        ate.ape.rmse, ate.ape.max, raw.ape.rmse, raw.ape.max, g.0
    );
    eprintln!(
        "  tilt (roll/pitch) error max {:.4}°, last {tilt_last:.4}°; body-velocity rmse {:.4} m/s; \
         final b_g error {:.2e}, b_a error {:.4}; reprojection χ²/observation median {chi_med:.2}, max {chi_max:.2}",
        g.1, g.2, g.3, g.4
    );
    (ate.ape.rmse, g.1, g.2, chi_med, chi_max)
}

/// A second `optimize` on a window of the same size (another window of the flight)
/// allocates nothing.
#[test]
fn second_optimize_allocates_nothing() {
    let sim = Sim::new(ImuNoise::default(), 2 * WINDOW + 2, 4.0, 9);
    let points: Vec<_> = sim.landmarks.iter().map(|p| Some(*p)).collect();
    let (mut w1, _) = sim.window(0, WINDOW, &sim.truth, &points);
    let mut solver = ViSolver::new();
    let p = ViParams::default();
    solver.optimize(&mut w1, &p).expect("first");
    // The same window again, from a perturbed start.
    for kf in w1.keyframes.iter_mut().skip(1) {
        kf.state.p += Vector3::new(0.02, -0.01, 0.01);
        kf.state.r *= Rotation3::from_scaled_axis(Vector3::new(0.005, 0.0, -0.005));
    }
    let a0 = allocations();
    let rep = solver.optimize(&mut w1, &p).expect("second");
    let n = allocations() - a0;
    eprintln!(
        "second optimize: {} iterations, {} solves, {n} allocations ({} observations)",
        rep.iterations,
        rep.solves,
        w1.observations.len()
    );
    assert!(rep.iterations >= 2, "{rep:?}");
    assert_eq!(n, 0, "allocations in the second optimize");
}

/// (scale, tilt °, body velocity m/s, gyro bias, accel bias) errors.
type GaugeFree = (f64, f64, f64, f64, f64);

/// Gauge-free errors of keyframe states against the truth: (scale of the path, max tilt °,
/// RMS body-frame velocity m/s, gyro bias, accel bias of the last keyframe).
fn gauge_free_errors(est: &[NavState], truth: &[NavState]) -> GaugeFree {
    let path = |s: &[NavState]| s.windows(2).map(|p| (p[1].p - p[0].p).norm()).sum::<f64>();
    let tilt = est
        .iter()
        .zip(truth)
        .map(|(e, t)| tilt_deg(e, t))
        .fold(0.0, f64::max);
    let v2: f64 = est
        .iter()
        .zip(truth)
        .map(|(e, t)| (e.r.inverse() * e.v - t.r.inverse() * t.v).norm_squared())
        .sum();
    let (e, t) = (est[est.len() - 1].biases, truth[truth.len() - 1].biases);
    (
        path(est) / path(truth),
        tilt,
        (v2 / est.len() as f64).sqrt(),
        (e.gyro - t.gyro).norm(),
        (e.accel - t.accel).norm(),
    )
}

/// The window started from the inertial initialisation of a monocular map (arbitrary frame,
/// scale 1/2.5, poses with 3 mm / 0.17° noise, noisy IMU), all keyframes free with a 4-DoF
/// gauge prior on the first: scale, gravity, velocities and biases refined. Returns the
/// gauge-free errors of the initialisation and of the window.
/// The inertial initialisation over keyframes `0..n_kf` of `sim` from a monocular map of
/// them (arbitrary frame, scale 1/2.5, poses with 3 mm / 0.17° noise): the keyframe states
/// and the landmarks born in those keyframes (3 cm noise) in its gravity-aligned world.
fn init_from_vo(
    sim: &Sim,
    n_kf: usize,
    rng: &mut Rng,
) -> (Vec<NavState>, Vec<Option<Vector3<f64>>>) {
    let (r_vw, t_vw, s_true) = (
        Rotation3::from_scaled_axis(Vector3::new(0.3, -0.5, 1.0)),
        Vector3::new(1.0, -2.0, 0.5),
        2.5,
    );
    let to_vo = |p: &Vector3<f64>| (r_vw * p + t_vw) / s_true;
    let vo: Vec<Isometry3<f64>> = sim.truth[..n_kf]
        .iter()
        .map(|t| {
            let t_wc = sim.t_wc(t);
            let p = t_wc.translation.vector + rng.vec3(0.003);
            let r = r_vw * t_wc.rotation.to_rotation_matrix() * so3_exp(&rng.vec3(0.003));
            Isometry3::from_parts(
                Translation3::from(to_vo(&p)),
                UnitQuaternion::from_rotation_matrix(&r),
            )
        })
        .collect();
    let preints: Vec<_> = (0..n_kf - 1)
        .map(|k| sim.preint(k, ImuBiases::default()))
        .collect();
    let params = InitParams {
        pose_sigma_m: 0.003,
        pose_sigma_rad: 0.003,
        ..Default::default()
    };
    let init = initialize(&vo, &preints, &sim.t_bc(), &params).expect("initialised");
    let points = sim
        .landmarks
        .iter()
        .zip(&sim.birth)
        .map(|(p, &b)| (b < n_kf).then(|| point_from_init(&init, &to_vo(&(p + rng.vec3(0.03))))))
        .collect();
    (states_from_init(&init, &vo, &sim.t_bc()), points)
}

fn from_inertial_init(n_kf: usize) -> (GaugeFree, GaugeFree) {
    let sim = Sim::new(ImuNoise::default(), n_kf, 5.0, 11);
    let (states, points) = init_from_vo(&sim, n_kf, &mut Rng(12));
    let (mut w, _) = sim.window(0, n_kf - 1, &states, &points);
    w.keyframes[0].fixed = false;
    w.prior = Some(gauge_prior(0, &states[0], 0.001, 0.001));
    let before = gauge_free_errors(&states, &sim.truth);
    let rep = ViSolver::new()
        .optimize(&mut w, &ViParams::default())
        .expect("optimised");
    print_report(
        &format!("{n_kf} keyframes from the inertial initialisation"),
        &rep,
        0.0,
    );
    let est: Vec<_> = w.keyframes.iter().map(|k| k.state).collect();
    let after = gauge_free_errors(&est, &sim.truth);
    let mut solver = ViSolver::new();
    let cov = solver
        .keyframe_covariance(&w, &ViParams::default(), n_kf - 1)
        .expect("covariance");
    let sd = |i: usize| cov.fixed_view::<3, 3>(i, i).trace().sqrt();
    eprintln!(
        "  last keyframe 1σ (marginal): θ {:.4}°, b_g {:.2e} rad/s, b_a {:.4} m/s²",
        sd(0).to_degrees(),
        sd(9),
        sd(12)
    );
    for (label, e) in [("init  ", before), ("window", after)] {
        eprintln!(
            "  {label}: scale {:.4}, tilt max {:.4}°, body velocity rmse {:.4} m/s, b_g error \
             {:.2e}, b_a error {:.4}",
            e.0, e.1, e.2, e.3, e.4
        );
    }
    (before, after)
}

/// From the inertial initialisation over 2.5 s (11 keyframes) and 5 s (21): the window
/// improves every gauge-free error; over 2.5 s the accelerometer bias and the tilt stay
/// confounded (b_a error ≈ g · tilt error), 5 s separate them better.
#[test]
fn window_refines_the_inertial_initialisation() {
    for n_kf in [WINDOW + 1, 2 * WINDOW + 1] {
        let (before, after) = from_inertial_init(n_kf);
        assert!((after.0 - 1.0).abs() < 0.02, "{n_kf}: scale {}", after.0);
        assert!(
            (after.0 - 1.0).abs() <= (before.0 - 1.0).abs(),
            "{n_kf}: scale"
        );
        assert!(
            after.1 < 0.5 && after.1 <= before.1,
            "{n_kf}: tilt {before:?} -> {after:?}"
        );
        assert!(after.2 < 0.03 && after.2 <= before.2, "{n_kf}: velocity");
        assert!(after.4 <= before.4, "{n_kf}: accel bias");
    }
}
