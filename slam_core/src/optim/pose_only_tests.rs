//! Tests of [`super::pose_only`] on synthetic scenes.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector2, Vector3, Vector6};

use super::pose_only::*;
use crate::camera::PinholeRadtan;
use crate::lie::se3_exp;
use crate::rolling_shutter::row_offset_s;
use crate::twoview::synth::{box_point, Rng};
use crate::CoreError;

fn true_pose() -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(0.3, -0.2, 1.0),
        UnitQuaternion::from_euler_angles(0.1, -0.3, 0.05),
    )
}

/// Observations of random points (octaves 0..4, noise σ = scale_factor^octave px), a fraction
/// `outliers` moved to random pixels. With a velocity, pixels follow the rolling-shutter
/// model with readout `readout_ns` and `dt` of the observed row.
fn scene(
    rng: &mut Rng,
    cam: &PinholeRadtan,
    t_cw: &Isometry3<f64>,
    n: usize,
    outliers: f64,
    vel: Option<(&Velocity, i64)>,
) -> (Vec<PoseObservation>, Vec<bool>) {
    let t_wc = t_cw.inverse();
    let mut obs = Vec::new();
    let mut is_out = Vec::new();
    while obs.len() < n {
        let p_w = (t_wc * Point3::from(box_point(rng))).coords;
        let octave = (rng.0.next_f64() * 4.0) as u32;
        let sigma = crate::features::ORB_SCALE_FACTOR.powi(octave as i32);
        let (uv, dt) = match vel {
            None => match cam.project(&(t_cw * Point3::from(p_w)).coords) {
                Some(uv) => (uv, 0.0),
                None => continue,
            },
            Some((v, readout)) => {
                let xi = v.twist();
                let mut dt = 0.0;
                let mut uv = Vector2::zeros();
                let mut ok = true;
                for _ in 0..8 {
                    let p = se3_exp(&(xi * -dt)) * (t_cw * Point3::from(p_w));
                    match cam.project(&p.coords) {
                        Some(u) => uv = u,
                        None => ok = false,
                    }
                    dt = row_offset_s(readout, uv.y, cam.height);
                }
                if !ok {
                    continue;
                }
                (uv, dt)
            }
        };
        if !cam.contains(&uv) {
            continue;
        }
        let out = rng.0.next_f64() < outliers;
        let pixel = if out {
            Vector2::new(rng.uniform(0.0, 752.0), rng.uniform(0.0, 480.0))
        } else {
            uv + rng.normal2(sigma)
        };
        obs.push(PoseObservation {
            point_w: p_w,
            pixel,
            inv_sigma2: 1.0 / (sigma * sigma),
            dt,
        });
        is_out.push(out);
    }
    (obs, is_out)
}

fn perturb(t: &Isometry3<f64>, deg: f64, metres: f64) -> Isometry3<f64> {
    let axis = Vector3::new(0.3, -0.8, 0.5).normalize();
    let dir = Vector3::new(-0.6, 0.2, 0.77).normalize();
    Isometry3::from_parts(
        Translation3::from(dir * metres),
        UnitQuaternion::from_scaled_axis(axis * deg.to_radians()),
    ) * t
}

fn pose_error(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    let d = a.inverse() * b;
    (
        d.rotation.angle().to_degrees(),
        (a.inverse().translation.vector - b.inverse().translation.vector).norm(),
    )
}

#[test]
fn converges_from_perturbation_and_flags_outliers() {
    let cam = PinholeRadtan::euroc_cam0();
    let truth = true_pose();
    let mut opt = PoseOptimizer::new();
    for seed in 1..=5 {
        let mut rng = Rng::new(seed);
        let (obs, is_out) = scene(&mut rng, &cam, &truth, 300, 0.2, None);
        let init = perturb(&truth, 5.0, 0.1);
        let mut inl = vec![false; obs.len()];
        let res = opt
            .optimize(&cam, &init, &obs, None, &PoseOptParams::default(), &mut inl)
            .expect("optimised");
        let (r_err, t_err) = pose_error(&res.t_cw, &truth);
        let missed = (0..obs.len()).filter(|&i| is_out[i] && inl[i]).count();
        let lost = (0..obs.len()).filter(|&i| !is_out[i] && !inl[i]).count();
        let n_out = is_out.iter().filter(|&&b| b).count();
        eprintln!(
            "seed {seed}: R err {r_err:.4} deg, t err {:.2} mm, {} iters, outliers kept {missed}/{n_out}, inliers lost {lost}",
            t_err * 1e3,
            res.iterations
        );
        assert!(r_err < 0.1, "rotation error {r_err}");
        assert!(t_err < 0.01, "position error {t_err}");
        assert!(missed * 50 <= n_out, "{missed} of {n_out} outliers kept");
        // ~5% of true inliers exceed chi2(2) at 95% by definition.
        assert!(lost * 10 <= obs.len() - n_out, "{lost} inliers lost");
        assert_eq!(res.n_inliers, inl.iter().filter(|&&b| b).count());
        assert!(res.final_cost.is_finite());
    }
}

#[test]
fn jacobian_matches_finite_differences() {
    let cam = PinholeRadtan::euroc_cam0();
    let truth = true_pose();
    let mut rng = Rng::new(9);
    let v = Velocity {
        linear: Vector3::new(0.5, -0.2, 0.3),
        angular: Vector3::new(0.4, 1.2, -0.3),
    };
    let (obs, _) = scene(&mut rng, &cam, &truth, 20, 0.0, Some((&v, 30_000_000)));
    let mut opt = PoseOptimizer::new();
    let mut inl = vec![true; obs.len()];
    // Zero rounds: only sets up the shutter buffers.
    let p = PoseOptParams {
        rounds: 0,
        ..PoseOptParams::default()
    };
    opt.optimize(&cam, &truth, &obs, Some(&v), &p, &mut inl)
        .expect("setup");
    for (i, o) in obs.iter().enumerate() {
        let (r0, j) = opt.test_linearise(&cam, &truth, i, o).expect("visible");
        for k in 0..6 {
            let mut d = Vector6::zeros();
            d[k] = 1e-6;
            let rp = opt
                .test_linearise(&cam, &(se3_exp(&d) * truth), i, o)
                .expect("visible")
                .0;
            let rm = opt
                .test_linearise(&cam, &(se3_exp(&(-d)) * truth), i, o)
                .expect("visible")
                .0;
            let num = (rp - rm) / 2e-6;
            assert!(
                (num - j.column(k)).norm() < 1e-4 * (1.0 + num.norm()),
                "obs {i} col {k}: {num} vs {}",
                j.column(k)
            );
        }
        assert!(r0.norm() < 10.0);
    }
}

#[test]
fn rolling_shutter_model_recovers_the_pose_and_global_shutter_does_not() {
    let cam = PinholeRadtan::euroc_cam0();
    let truth = true_pose();
    let v = Velocity {
        linear: Vector3::new(0.8, 0.1, -0.3),
        angular: Vector3::new(0.3, 1.5, 0.2),
    };
    let readout = 30_000_000; // 30 ms
    let mut rng = Rng::new(21);
    let (obs, _) = scene(&mut rng, &cam, &truth, 300, 0.1, Some((&v, readout)));
    let init = perturb(&truth, 3.0, 0.05);
    let mut opt = PoseOptimizer::with_capacity(300);
    let mut inl = vec![false; obs.len()];
    let rs = opt
        .optimize(
            &cam,
            &init,
            &obs,
            Some(&v),
            &PoseOptParams::default(),
            &mut inl,
        )
        .expect("rs");
    let rs_inliers = rs.n_inliers;
    let gs = opt
        .optimize(&cam, &init, &obs, None, &PoseOptParams::default(), &mut inl)
        .expect("gs");
    let (rs_r, rs_t) = pose_error(&rs.t_cw, &truth);
    let (gs_r, gs_t) = pose_error(&gs.t_cw, &truth);
    eprintln!(
        "RS: {rs_r:.4} deg {:.2} mm, {rs_inliers} inliers, cost {:.1}; GS: {gs_r:.4} deg {:.2} mm, {} inliers, cost {:.1}",
        rs_t * 1e3,
        rs.final_cost,
        gs_t * 1e3,
        gs.n_inliers,
        gs.final_cost
    );
    assert!(
        rs_r < 0.15 && rs_t < 0.01,
        "rolling-shutter model error {rs_r} deg {rs_t} m"
    );
    assert!(
        gs_r > 5.0 * rs_r || gs_t > 5.0 * rs_t,
        "global-shutter error not clearly larger"
    );
    assert!(rs_inliers > gs.n_inliers);
    // dt = 0 everywhere is the global-shutter case, whatever the velocity.
    let gs_obs: Vec<_> = obs
        .iter()
        .map(|o| PoseObservation { dt: 0.0, ..*o })
        .collect();
    let a = opt
        .optimize(
            &cam,
            &init,
            &gs_obs,
            Some(&v),
            &PoseOptParams::default(),
            &mut inl,
        )
        .expect("a");
    let b = opt
        .optimize(
            &cam,
            &init,
            &gs_obs,
            None,
            &PoseOptParams::default(),
            &mut inl,
        )
        .expect("b");
    assert_eq!(a, b);
}

#[test]
fn bad_input_is_refused() {
    let cam = PinholeRadtan::euroc_cam0();
    let truth = true_pose();
    let mut rng = Rng::new(2);
    let (mut obs, _) = scene(&mut rng, &cam, &truth, 10, 0.0, None);
    let mut opt = PoseOptimizer::new();
    let p = PoseOptParams::default();
    let mut inl = vec![false; 9];
    assert!(matches!(
        opt.optimize(&cam, &truth, &obs, None, &p, &mut inl),
        Err(CoreError::InvalidArgument(_))
    ));
    let mut inl = vec![false; 2];
    assert!(matches!(
        opt.optimize(&cam, &truth, &obs[..2], None, &p, &mut inl),
        Err(CoreError::NotEnoughData(_))
    ));
    let mut inl = vec![false; 10];
    obs[3].inv_sigma2 = 0.0;
    assert!(opt
        .optimize(&cam, &truth, &obs, None, &p, &mut inl)
        .is_err());
    obs[3].inv_sigma2 = 1.0;
    obs[4].pixel.x = f64::NAN;
    assert!(opt
        .optimize(&cam, &truth, &obs, None, &p, &mut inl)
        .is_err());
    obs[4].pixel.x = 10.0;
    // All points behind the camera: no panic, everything an outlier.
    let flipped = Isometry3::from_parts(
        Translation3::identity(),
        UnitQuaternion::from_euler_angles(0.0, std::f64::consts::PI, 0.0),
    ) * truth;
    let r = opt
        .optimize(&cam, &flipped, &obs, None, &p, &mut inl)
        .expect("runs");
    assert_eq!(r.n_inliers, 0);
}

/// Without a prior (or with a zero-information one) the result is bit-identical to the
/// plain optimisation; a strong prior pulls a poorly observed pose to itself, a weak one
/// changes it little, and the centre part of the prior does not move the rotation.
#[test]
fn pose_prior_is_neutral_when_absent_and_pulls_when_present() {
    let cam = PinholeRadtan::euroc_cam0();
    let truth = true_pose();
    let mut rng = Rng::new(7);
    let (obs, _) = scene(&mut rng, &cam, &truth, 12, 0.0, None);
    let init = perturb(&truth, 2.0, 0.05);
    let run = |params: &PoseOptParams| {
        let mut inl = vec![true; obs.len()];
        PoseOptimizer::new()
            .optimize(&cam, &init, &obs, None, params, &mut inl)
            .expect("optimised")
    };
    let plain = run(&PoseOptParams::default());
    let zero = run(&PoseOptParams {
        prior: Some(PosePrior {
            t_cw: perturb(&truth, 3.0, 0.2),
            information: nalgebra::Matrix6::zeros(),
        }),
        ..PoseOptParams::default()
    });
    assert_eq!(plain, zero, "a zero-information prior changed the result");
    // A strong prior 1 cm and 0.5° from the truth: the 12 noisy points are outweighed.
    let target = perturb(&truth, 0.5, 0.01);
    let strong = run(&PoseOptParams {
        prior: Some(PosePrior::isotropic(target, 1e-5, 1e-5)),
        ..PoseOptParams::default()
    });
    let (r_t, t_t) = pose_error(&strong.t_cw, &target);
    let (r_p, t_p) = pose_error(&plain.t_cw, &target);
    eprintln!(
        "to the prior: plain {r_p:.4}° {:.2} mm, strong prior {r_t:.5}° {:.3} mm",
        t_p * 1e3,
        t_t * 1e3
    );
    assert!(r_t < 0.01 && t_t < 2e-4, "strong prior not followed");
    assert!(
        r_p > 0.2 && t_p > 5e-3,
        "the test needs a prior away from the data"
    );
    // Weak prior (10°, 1 m): within 0.1 mm and 0.01° of the plain result.
    let weak = run(&PoseOptParams {
        prior: Some(PosePrior::isotropic(target, 0.17, 1.0)),
        ..PoseOptParams::default()
    });
    let (r_w, t_w) = pose_error(&weak.t_cw, &plain.t_cw);
    assert!(r_w < 0.01 && t_w < 1e-4, "weak prior moved {r_w}° {t_w} m");
    // Centre-only prior: the centre follows it, the rotation stays near the data's.
    let centre_only = {
        let mut info = nalgebra::Matrix6::zeros();
        for k in 3..6 {
            info[(k, k)] = 1e10;
        }
        run(&PoseOptParams {
            prior: Some(PosePrior {
                t_cw: target,
                information: info,
            }),
            ..PoseOptParams::default()
        })
    };
    let (_, t_c) = pose_error(&centre_only.t_cw, &target);
    assert!(t_c < 2e-4, "centre not pulled: {t_c}");
}

/// The camera centre's covariance from [`PoseOptResult::information`] ([`centre_covariance`])
/// matches the spread of the optimised centres over noisy re-draws of the same points (200
/// trials, no outliers): the measurement the IMU navigator takes is as uncertain as it says.
#[test]
fn centre_covariance_matches_the_spread_of_the_estimates() {
    let cam = PinholeRadtan::euroc_cam0();
    let truth = true_pose();
    let mut opt = PoseOptimizer::new();
    let (points, _) = scene(&mut Rng::new(7), &cam, &truth, 60, 0.0, None);
    let c_true = truth.inverse().translation.vector;
    let (mut sum, mut predicted) = (nalgebra::Matrix3::zeros(), nalgebra::Matrix3::zeros());
    let trials = 200;
    for seed in 0..trials {
        let mut rng = Rng::new(1000 + seed);
        let obs: Vec<PoseObservation> = points
            .iter()
            .map(|o| {
                let uv = cam
                    .project(&(truth * Point3::from(o.point_w)).coords)
                    .expect("visible");
                PoseObservation {
                    pixel: uv + rng.normal2(1.0 / o.inv_sigma2.sqrt()),
                    ..*o
                }
            })
            .collect();
        let mut inl = vec![true; obs.len()];
        let res = opt
            .optimize(
                &cam,
                &truth,
                &obs,
                None,
                &PoseOptParams::default(),
                &mut inl,
            )
            .expect("optimised");
        let d = res.t_cw.inverse().translation.vector - c_true;
        sum += d * d.transpose();
        predicted += centre_covariance(&res.t_cw, &res.information).expect("covariance");
    }
    let (empirical, predicted) = (sum / trials as f64, predicted / trials as f64);
    let ratio = empirical.trace() / predicted.trace();
    eprintln!(
        "centre σ: empirical {:.2} mm, predicted {:.2} mm (trace ratio {ratio:.3})",
        empirical.trace().sqrt() * 1e3,
        predicted.trace().sqrt() * 1e3
    );
    // Chi-square 95% and 5% a little outside the 200-trial band; the robust rounds and
    // the inlier test make the estimate slightly less efficient than the bound.
    assert!((0.7..1.5).contains(&ratio), "ratio {ratio}");
    // A rotation-only increment leaves the centre where it was (first order).
    let dw = se3_exp(&Vector6::new(1e-6, -2e-6, 1.5e-6, 0.0, 0.0, 0.0)) * truth;
    let moved = (dw.inverse().translation.vector - c_true).norm();
    assert!(moved < 1e-10, "centre moved {moved}");
}
