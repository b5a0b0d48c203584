//! Per-call timings of the geometry kernels (ignored by default; run with
//! `cargo test -p slam_core --release --lib geometry_timings -- --ignored --nocapture`).

use std::time::Instant;

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector2};

use super::synth::{box_point, two_view_scene, Rng};
use super::{initialize, TwoViewParams};
use crate::camera::PinholeRadtan;
use crate::optim::{PoseObservation, PoseOptParams, PoseOptimizer};
use crate::pnp::{solve_pnp_ransac_with, PnpParams, PnpSolver};

fn time<F: FnMut()>(name: &str, reps: usize, mut f: F) {
    f();
    let t0 = Instant::now();
    for _ in 0..reps {
        f();
    }
    let us = t0.elapsed().as_secs_f64() * 1e6 / reps as f64;
    eprintln!("{name}: {us:.1} us per call ({reps} calls)");
}

#[test]
#[ignore = "timing report, run in release"]
fn geometry_timings() {
    let cam = PinholeRadtan::euroc_cam0();
    let pin = PinholeRadtan::pinhole(752, 480, 458.0, 458.0, 376.0, 240.0);
    let motion = Isometry3::from_parts(
        Translation3::new(-0.5, 0.25, 0.4),
        UnitQuaternion::from_euler_angles(0.03, -0.08, 0.02),
    );
    let mut rng = Rng::new(1);
    let s = two_view_scene(&mut rng, &pin, &motion, 500, 1.0, 0.2, box_point);
    let params = TwoViewParams::for_camera(&pin);
    time("two-view init, 500 matches (20% outliers)", 50, || {
        let r = initialize(&s.x1, &s.x2, &params);
        assert!(r.is_ok());
    });

    // Pose-only: 300 observations, 20% outliers, 5 deg / 10 cm initial error.
    let t_cw = Isometry3::from_parts(
        Translation3::new(0.3, -0.2, 1.0),
        UnitQuaternion::from_euler_angles(0.1, -0.3, 0.05),
    );
    let t_wc = t_cw.inverse();
    let mut obs = Vec::new();
    while obs.len() < 300 {
        let p_w = (t_wc * Point3::from(box_point(&mut rng))).coords;
        let Some(uv) = cam.project(&(t_cw * Point3::from(p_w)).coords) else {
            continue;
        };
        if !cam.contains(&uv) {
            continue;
        }
        let pixel = if rng.0.next_f64() < 0.2 {
            Vector2::new(rng.uniform(0.0, 752.0), rng.uniform(0.0, 480.0))
        } else {
            uv + rng.normal2(1.0)
        };
        obs.push(PoseObservation {
            point_w: p_w,
            pixel,
            inv_sigma2: 1.0,
            dt: 0.0,
        });
    }
    let init = Isometry3::from_parts(
        Translation3::new(0.06, -0.05, 0.06),
        UnitQuaternion::from_scaled_axis(nalgebra::Vector3::new(0.05, -0.06, 0.03)),
    ) * t_cw;
    let mut opt = PoseOptimizer::with_capacity(300);
    let mut inl = vec![false; 300];
    let p = PoseOptParams::default();
    time("pose-only LM, 300 observations (4 rounds)", 500, || {
        let r = opt.optimize(&cam, &init, &obs, None, &p, &mut inl);
        assert!(r.is_ok());
    });

    // PnP: 200 correspondences, 30% outliers.
    let mut pw = Vec::new();
    let mut xn = Vec::new();
    while pw.len() < 200 {
        let pc = box_point(&mut rng);
        pw.push((t_wc * Point3::from(pc)).coords);
        xn.push(if rng.0.next_f64() < 0.3 {
            Vector2::new(rng.uniform(-0.8, 0.8), rng.uniform(-0.5, 0.5))
        } else {
            Vector2::new(pc.x / pc.z, pc.y / pc.z) + rng.normal2(1.0 / 458.0)
        });
    }
    let w = vec![1.0; 200];
    let pp = PnpParams {
        pixel_scale: 458.0,
        ..PnpParams::default()
    };
    let mut solver = PnpSolver::new();
    time(
        "EPnP + RANSAC + refinement, 200 points (30% outliers)",
        200,
        || {
            let r = solve_pnp_ransac_with(&mut solver, &pw, &xn, &w, &pp);
            assert!(r.is_ok());
        },
    );
}
