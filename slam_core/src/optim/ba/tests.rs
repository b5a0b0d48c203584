//! Tests of the bundle adjustment: Jacobians against finite differences, synthetic scenes
//! (accuracy, outliers, gauge), dense/sparse agreement, degenerate input.

use std::sync::atomic::AtomicBool;

use nalgebra::{Isometry3, Vector2, Vector3, Vector6};

use super::synth::{synthetic_scene, SyntheticBa, SyntheticBaConfig};
use super::*;
use crate::camera::PinholeRadtan;
use crate::geometry::umeyama;
use crate::lie::se3_exp;

fn centre(t_cw: &Isometry3<f64>) -> Vector3<f64> {
    t_cw.inverse().translation.vector
}

/// Mean camera-centre error of the free keyframes.
fn mean_position_error(est: &BaProblem, truth: &BaProblem) -> f64 {
    let (mut s, mut n) = (0.0, 0);
    for (e, t) in est.keyframes.iter().zip(&truth.keyframes) {
        if !t.fixed {
            s += (centre(&e.t_cw) - centre(&t.t_cw)).norm();
            n += 1;
        }
    }
    s / n.max(1) as f64
}

fn scene(n_kf: usize, n_pts: usize, seed: u64) -> SyntheticBa {
    synthetic_scene(&SyntheticBaConfig {
        n_keyframes: n_kf,
        n_points: n_pts,
        seed,
        ..SyntheticBaConfig::default()
    })
    .expect("scene")
}

#[test]
fn jacobians_match_finite_differences() {
    let cam = PinholeRadtan::euroc_cam0();
    let t_cw = Isometry3::new(Vector3::new(0.2, -0.1, 0.3), Vector3::new(0.1, -0.2, 0.05));
    let p_w = Vector3::new(0.8, -0.5, 3.0);
    let pixel = Vector2::new(300.0, 200.0);
    let l = linearize_reprojection(&cam, &t_cw, &p_w, &pixel).expect("in front");
    let r0 = reprojection_residual(&cam, &t_cw, &p_w, &pixel).expect("in front");
    assert!((l.residual - r0).norm() < 1e-12);
    let h = 1e-6;
    for k in 0..6 {
        let mut d = Vector6::zeros();
        d[k] = h;
        let rp = reprojection_residual(&cam, &(se3_exp(&d) * t_cw), &p_w, &pixel).expect("p");
        let rm = reprojection_residual(&cam, &(se3_exp(&-d) * t_cw), &p_w, &pixel).expect("m");
        let num = (rp - rm) / (2.0 * h);
        let err = (num - l.d_pose.column(k)).norm();
        assert!(err < 1e-5 * (1.0 + num.norm()), "pose column {k}: {err}");
    }
    for k in 0..3 {
        let mut d = Vector3::zeros();
        d[k] = h;
        let rp = reprojection_residual(&cam, &t_cw, &(p_w + d), &pixel).expect("p");
        let rm = reprojection_residual(&cam, &t_cw, &(p_w - d), &pixel).expect("m");
        let num = (rp - rm) / (2.0 * h);
        let err = (num - l.d_point.column(k)).norm();
        assert!(err < 1e-5 * (1.0 + num.norm()), "point column {k}: {err}");
    }
    // Behind the camera: no linearisation.
    assert!(linearize_reprojection(&cam, &t_cw, &Vector3::new(0.0, 0.0, -5.0), &pixel).is_none());
}

/// Camera centres of `est` aligned onto `truth` by a similarity; RMS of the residuals.
fn aligned_ate(est: &BaProblem, truth: &BaProblem) -> f64 {
    let e: Vec<_> = est.keyframes.iter().map(|k| centre(&k.t_cw)).collect();
    let t: Vec<_> = truth.keyframes.iter().map(|k| centre(&k.t_cw)).collect();
    let sim = umeyama(&e, &t, true).expect("align");
    let ss: f64 = e
        .iter()
        .zip(&t)
        .map(|(a, b)| (sim.transform_point(a) - b).norm_squared())
        .sum();
    (ss / e.len() as f64).sqrt()
}

#[test]
fn local_ba_recovers_a_perturbed_scene_and_flags_outliers() {
    let s = scene(12, 600, 7);
    let mut problem = s.problem.clone();
    let pos_before = mean_position_error(&problem, &s.truth);
    let ate_before = aligned_ate(&problem, &s.truth);
    let mut ba = BundleAdjuster::new();
    let report = ba.optimize(&mut problem, &BaParams::local()).expect("ba");
    let flags = ba.inliers().to_vec();
    let pos_after = mean_position_error(&problem, &s.truth);
    let ate_after = aligned_ate(&problem, &s.truth);
    // Reference: the same BA started from the true state reaches the noise-limited optimum.
    let mut from_truth = s.truth.clone();
    let r_ref = BundleAdjuster::new()
        .optimize(&mut from_truth, &BaParams::local())
        .expect("ba from truth");
    let truth_rmse = s.truth.reprojection_rmse(Some(&flags)).expect("rmse");
    eprintln!(
        "{report:?}\nposition {pos_before:.4} -> {pos_after:.4} m (from truth {:.4}), \
         aligned ATE {ate_before:.4} -> {ate_after:.4} m, rmse at truth {truth_rmse:.3} px",
        mean_position_error(&from_truth, &s.truth)
    );
    assert_eq!(report.solver, LinearSolverKind::Dense);
    assert_eq!(report.free_keyframes, 10);
    assert!(report.final_cost < report.initial_cost);
    // Inlier residuals at the noise level: no worse than the true state's.
    assert!(
        report.final_rmse <= truth_rmse,
        "{} vs {truth_rmse}",
        report.final_rmse
    );
    assert!(report.initial_rmse > 3.0 * report.final_rmse);
    // Same optimum as from the truth (to well below the noise-limited error), far below
    // the perturbation.
    assert!((report.final_cost - r_ref.final_cost).abs() < 0.02 * r_ref.final_cost);
    let gap = problem
        .keyframes
        .iter()
        .zip(&from_truth.keyframes)
        .map(|(a, b)| (centre(&a.t_cw) - centre(&b.t_cw)).norm())
        .fold(0.0, f64::max);
    assert!(gap < 5e-3, "largest gap to the BA from the truth {gap}");
    assert!(pos_after < 0.4 * pos_before, "{pos_before} -> {pos_after}");
    assert!(ate_after < 0.1 * ate_before, "{ate_before} -> {ate_after}");
    // Outliers: every gross outlier flagged, few true inliers lost (χ² 95%: ~5% expected).
    let n_out = s.outlier.iter().filter(|&&o| o).count();
    let caught = s
        .outlier
        .iter()
        .zip(&flags)
        .filter(|(&o, &i)| o && !i)
        .count();
    let lost = s
        .outlier
        .iter()
        .zip(&flags)
        .filter(|(&o, &i)| !o && !i)
        .count();
    let n_in = s.outlier.len() - n_out;
    eprintln!("outliers caught {caught}/{n_out}, inliers lost {lost}/{n_in}");
    assert!(n_out > 50);
    assert!(
        caught as f64 >= 0.98 * n_out as f64,
        "caught {caught} of {n_out}"
    );
    assert!(
        (lost as f64) < 0.08 * n_in as f64,
        "lost {lost} of {n_in} inliers"
    );
    // Fixed keyframes are bit-for-bit unchanged.
    for (e, t) in problem.keyframes.iter().zip(&s.problem.keyframes) {
        if t.fixed {
            assert_eq!(e.t_cw, t.t_cw);
        }
    }
}

#[test]
fn dense_and_sparse_solvers_agree() {
    let s = scene(10, 300, 3);
    let mut results = Vec::new();
    for solver in [LinearSolverKind::Dense, LinearSolverKind::Sparse] {
        let mut p = s.problem.clone();
        let params = BaParams {
            solver,
            ..BaParams::local()
        };
        let r = BundleAdjuster::new().optimize(&mut p, &params).expect("ba");
        assert_eq!(r.solver, solver);
        results.push((p, r));
    }
    let (a, b) = (&results[0], &results[1]);
    assert!((a.1.final_cost - b.1.final_cost).abs() < 1e-6 * a.1.final_cost.max(1.0));
    for (x, y) in a.0.keyframes.iter().zip(&b.0.keyframes) {
        assert!((centre(&x.t_cw) - centre(&y.t_cw)).norm() < 1e-7);
    }
    for (x, y) in a.0.points.iter().zip(&b.0.points) {
        assert!((x.p_w - y.p_w).norm() < 1e-6);
    }
}

#[test]
fn global_ba_recovers_the_trajectory_up_to_a_similarity() {
    // Outlier-free map (the global BA runs on a map the local BAs have already cleaned):
    // ORB-SLAM's global BA as is. With 5% gross outliers: the same with outlier rejection
    // (Huber alone is not redescending: its optimum is biased by gross outliers).
    for (outlier_ratio, remove_outliers) in [(0.0, false), (0.05, true)] {
        let s = synthetic_scene(&SyntheticBaConfig {
            n_keyframes: 20,
            n_points: 1000,
            n_fixed: 0,
            outlier_ratio,
            seed: 11,
            ..SyntheticBaConfig::default()
        })
        .expect("scene");
        let mut problem = s.problem.clone();
        let mut ba = BundleAdjuster::new();
        let params = BaParams {
            remove_outliers,
            solver: LinearSolverKind::Sparse,
            ..BaParams::global()
        };
        let report = ba
            .optimize_global(&mut problem, &params, None)
            .expect("global ba");
        let ate_before = aligned_ate(&s.problem, &s.truth);
        let ate = aligned_ate(&problem, &s.truth);
        eprintln!("{report:?}\naligned ATE {ate_before:.5} -> {ate:.5} m");
        assert_eq!(report.free_keyframes, 19);
        assert_eq!(problem.keyframes[0].t_cw, s.problem.keyframes[0].t_cw);
        assert!(ate < 0.2 * ate_before, "ATE {ate_before} -> {ate}");
        assert!(report.final_rmse < 1.5, "rmse {}", report.final_rmse);
    }
}

#[test]
fn fixed_points_stay_fixed_and_reuse_across_sizes_is_clean() {
    let big = scene(14, 500, 5);
    let mut small = scene(8, 200, 6);
    for p in small.problem.points.iter_mut().step_by(3) {
        p.fixed = true;
    }
    let mut reused = BundleAdjuster::new();
    let mut p_big = big.problem.clone();
    reused
        .optimize(&mut p_big, &BaParams::local())
        .expect("big");
    let mut p1 = small.problem.clone();
    let r1 = reused.optimize(&mut p1, &BaParams::local()).expect("small");
    let mut p2 = small.problem.clone();
    let r2 = BundleAdjuster::new()
        .optimize(&mut p2, &BaParams::local())
        .expect("fresh");
    assert_eq!(r1.final_cost, r2.final_cost);
    assert_eq!(p1, p2);
    for (a, b) in p1.points.iter().zip(&small.problem.points) {
        if b.fixed {
            assert_eq!(a.p_w, b.p_w);
        }
    }
}

#[test]
fn degenerate_inputs_do_not_panic() {
    let cam = PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0);
    let mut ba = BundleAdjuster::new();
    // Empty problem.
    let r = ba
        .optimize(&mut BaProblem::new(), &BaParams::local())
        .expect("empty");
    assert_eq!((r.n_inliers, r.iterations), (0, 0));
    // Bad indices and non-finite values are errors.
    let mut p = BaProblem::new();
    let k = p.add_keyframe(Isometry3::identity(), cam, false);
    let j = p.add_point(Vector3::new(0.0, 0.0, 2.0), false);
    p.add_observation(k, j + 1, Vector2::new(320.0, 240.0), 1.0);
    assert!(ba.optimize(&mut p, &BaParams::local()).is_err());
    p.observations[0].point = j;
    p.observations[0].inv_sigma2 = 0.0;
    assert!(ba.optimize(&mut p, &BaParams::local()).is_err());
    p.observations[0].inv_sigma2 = 1.0;
    p.points[0].p_w.x = f64::NAN;
    assert!(ba.optimize(&mut p, &BaParams::local()).is_err());
    // Points behind the camera, a single free keyframe with one observation: no panic,
    // finite state.
    p.points[0].p_w = Vector3::new(0.0, 0.0, -2.0);
    let r = ba.optimize(&mut p, &BaParams::local()).expect("behind");
    assert_eq!(r.n_inliers, 0);
    assert!(p.points[0].p_w.iter().all(|v| v.is_finite()));
    // Everything fixed: unchanged.
    let s = scene(4, 50, 9);
    let mut all_fixed = s.problem.clone();
    all_fixed.keyframes.iter_mut().for_each(|k| k.fixed = true);
    all_fixed.points.iter_mut().for_each(|p| p.fixed = true);
    let before = all_fixed.clone();
    let r = ba
        .optimize(&mut all_fixed, &BaParams::local())
        .expect("fixed");
    assert_eq!(all_fixed, before);
    assert_eq!(r.iterations, 0);
    // Abort before the first iteration: state untouched, flagged.
    let mut q = s.problem.clone();
    let r = ba
        .optimize_with_abort(&mut q, &BaParams::local(), &AtomicBool::new(true))
        .expect("abort");
    assert!(r.aborted && r.iterations == 0);
    assert_eq!(q, s.problem);
}
