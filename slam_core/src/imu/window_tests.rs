//! Tests of the window optimiser: factor Jacobians against central differences, and a
//! window consistent with its own preintegrations (states from [`Preintegrated::predict`],
//! exact pixels) recovered from a perturbed start.

use nalgebra::{Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

use super::*;
use crate::imu::{gravity_w, ImuBiases, ImuNoise, PreintegrationParams};
use crate::lie::so3_exp;
use crate::twoview::synth::Rng;

pub(crate) fn rand3(rng: &mut Rng, s: f64) -> Vector3<f64> {
    Vector3::new(rng.uniform(-s, s), rng.uniform(-s, s), rng.uniform(-s, s))
}

/// Camera z along body x, a small lever arm.
pub(crate) fn t_bc() -> Isometry3<f64> {
    let r_bc = Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0);
    Isometry3::from_parts(
        Translation3::new(0.05, 0.01, -0.02),
        UnitQuaternion::from_matrix(&r_bc),
    )
}

pub(crate) fn true_biases() -> ImuBiases {
    ImuBiases {
        gyro: Vector3::new(0.002, -0.003, 0.001),
        accel: Vector3::new(0.03, -0.02, 0.04),
    }
}

/// `n` keyframes 0.25 s apart, states chained by their own preintegrations (so the IMU
/// residuals are exactly zero), points seen from the keyframes, exact pixels. Keyframe 0 is
/// fixed.
fn consistent_window(n: usize, seed: u64) -> ViWindow {
    let params = PreintegrationParams::new(&ImuNoise::default(), &Default::default()).unwrap();
    let g = gravity_w();
    let b = true_biases();
    let mut state = NavState {
        r: Rotation3::from_scaled_axis(Vector3::new(0.02, -0.03, 0.4)),
        p: Vector3::new(0.0, 0.0, 1.0),
        v: Vector3::new(1.0, 0.2, 0.1),
        biases: b,
    };
    let mut keyframes = Vec::new();
    let mut preints = Vec::new();
    for k in 0..n {
        keyframes.push(ViKeyframe {
            rig: 0,
            t_ns: k as i64 * 250_000_000,
            state,
            fixed: k == 0,
        });
        if k + 1 == n {
            break;
        }
        let mut pre = Preintegrated::new(b, params);
        for s in 0..50 {
            let t = k as f64 * 0.25 + s as f64 * 0.005;
            let w = Vector3::new(0.3 * (2.0 * t).sin(), 0.2 * (3.0 * t).cos(), 0.3);
            let a = Vector3::new(0.8 * (1.5 * t).sin(), 0.5 * (2.5 * t).cos(), 9.81);
            pre.integrate(0.005, &(w + b.gyro), &(a + b.accel));
        }
        state = pre.predict(&state, &g);
        preints.push(pre);
    }
    let camera = PinholeRadtan::euroc_cam0();
    let t_bc = t_bc();
    let mut rng = Rng::new(seed);
    let mut points_w = Vec::new();
    for kf in &keyframes {
        let t_wc = Isometry3::from_parts(
            Translation3::from(kf.state.p),
            UnitQuaternion::from_rotation_matrix(&kf.state.r),
        ) * t_bc;
        for _ in 0..25 {
            let uv = Vector2::new(rng.uniform(40.0, 710.0), rng.uniform(40.0, 440.0));
            let depth = rng.uniform(3.0, 8.0);
            points_w.push(
                t_wc.transform_point(&(camera.unproject(&uv) * depth).into())
                    .coords,
            );
        }
    }
    let mut observations = Vec::new();
    for (k, kf) in keyframes.iter().enumerate() {
        for (i, p) in points_w.iter().enumerate() {
            if let Some((uv, _, _)) = reprojection_jacobians(&camera, &t_bc, &kf.state, p, 0.0) {
                if camera.contains(&uv) {
                    observations.push(ViObservation {
                        kf: k as u32,
                        point: i as u32,
                        uv,
                        sigma_px: 1.0,
                        dt_s: 0.0,
                    });
                }
            }
        }
    }
    ViWindow {
        keyframes,
        n_visual: 0,
        preints,
        points_w,
        observations,
        t_bc,
        camera,
        gravity_w: g,
        prior: None,
        ..ViWindow::empty()
    }
}

/// The Jacobians of a rolling-shutter row 12 ms after the keyframe (the velocity column
/// included) against central differences.
#[test]
fn reprojection_jacobians_match_finite_differences() {
    let w = consistent_window(3, 1);
    let (h, dt) = (1e-6, 0.012);
    for o in w.observations.iter().step_by(7).take(20) {
        let st = w.keyframes[o.kf as usize].state;
        let p = w.points_w[o.point as usize] + Vector3::new(0.01, -0.02, 0.015);
        let (_, j_x, j_p) = reprojection_jacobians(&w.camera, &w.t_bc, &st, &p, dt).unwrap();
        let uv = |s: &NavState, p: &Vector3<f64>| {
            reprojection_jacobians(&w.camera, &w.t_bc, s, p, dt)
                .unwrap()
                .0
        };
        for c in 0..15 {
            let mut d = Vector15::zeros();
            d[c] = h;
            let num = (uv(&st.retract(&d), &p) - uv(&st.retract(&-d), &p)) / (2.0 * h);
            let ana = if c < 9 {
                j_x.column(c).into_owned()
            } else {
                Vector2::zeros()
            };
            let e = (num - ana).norm();
            assert!(
                e < 1e-5 * (1.0 + num.norm()),
                "∂uv/∂x col {c}: {num} vs {ana}"
            );
        }
        for c in 0..3 {
            let mut d = Vector3::zeros();
            d[c] = h;
            let num = (uv(&st, &(p + d)) - uv(&st, &(p - d))) / (2.0 * h);
            let e = (num - j_p.column(c)).norm();
            assert!(e < 1e-5 * (1.0 + num.norm()), "∂uv/∂p col {c}: {e}");
        }
    }
}

#[test]
fn prior_jacobian_matches_finite_differences() {
    let mut rng = Rng::new(3);
    let mean = consistent_window(2, 2).keyframes[1].state;
    let st = mean.retract(&Vector15::from_fn(|_, _| rng.uniform(-0.2, 0.2)));
    let (r0, j) = prior_residual(&mean, &st);
    assert!(prior_residual(&mean, &mean).0.norm() < 1e-12);
    assert!(r0.norm() > 0.1);
    let h = 1e-6;
    for c in 0..15 {
        let mut d = Vector15::zeros();
        d[c] = h;
        let num = (prior_residual(&mean, &st.retract(&d)).0
            - prior_residual(&mean, &st.retract(&-d)).0)
            / (2.0 * h);
        let e = (num - j.column(c)).norm();
        assert!(e < 1e-7, "∂r/∂x col {c}: {e}");
    }
}

/// Errors of the window against `truth`: max position (m), rotation (rad), velocity (m/s),
/// gyro bias, accel bias, point seen by ≥ 2 keyframes (m; a single view leaves the depth
/// free).
fn errors(w: &ViWindow, truth: &ViWindow) -> [f64; 6] {
    let mut views = vec![0usize; w.points_w.len()];
    for o in &w.observations {
        views[o.point as usize] += 1;
    }
    let mut e = [0.0f64; 6];
    for (a, b) in w.keyframes.iter().zip(&truth.keyframes) {
        let (s, t) = (&a.state, &b.state);
        e[0] = e[0].max((s.p - t.p).norm());
        e[1] = e[1].max(so3_log(&(t.r.inverse() * s.r)).norm());
        e[2] = e[2].max((s.v - t.v).norm());
        e[3] = e[3].max((s.biases.gyro - t.biases.gyro).norm());
        e[4] = e[4].max((s.biases.accel - t.biases.accel).norm());
    }
    for ((a, b), n) in w.points_w.iter().zip(&truth.points_w).zip(&views) {
        if *n >= 2 {
            e[5] = e[5].max((a - b).norm());
        }
    }
    e
}

/// From a perturbed start (0.1 m, ~2°, 0.2 m/s, biases, points 5 cm) the optimiser returns to
/// the exactly consistent truth; a prior at the truth keeps it there; bad input is refused.
#[test]
fn consistent_window_is_recovered() {
    let truth = consistent_window(8, 4);
    let mut w = truth.clone();
    let mut rng = Rng::new(9);
    for kf in w.keyframes.iter_mut().filter(|k| !k.fixed) {
        let s = &mut kf.state;
        s.r *= so3_exp(&rand3(&mut rng, 0.035));
        s.p += rand3(&mut rng, 0.1);
        s.v += rand3(&mut rng, 0.2);
        s.biases.gyro += rand3(&mut rng, 0.002);
        s.biases.accel += rand3(&mut rng, 0.05);
    }
    for p in &mut w.points_w {
        *p += rand3(&mut rng, 0.05);
    }
    let before = errors(&w, &truth);
    let mut solver = ViSolver::new();
    let params = ViParams {
        max_iterations: 50,
        ..Default::default()
    };
    let rep = solver.optimize(&mut w, &params).unwrap();
    let after = errors(&w, &truth);
    eprintln!("consistent window: {rep:?}\nerrors before {before:?}\nafter {after:?}");
    assert!(rep.initial.cost > 1e3 && rep.last.cost < 1e-6, "{rep:?}");
    assert!(
        after[0] < 1e-5 && after[1] < 1e-6 && after[2] < 1e-5,
        "{after:?}"
    );
    assert!(
        after[3] < 1e-6 && after[4] < 1e-4 && after[5] < 1e-5,
        "{after:?}"
    );

    // A prior at the truth on the last keyframe: zero cost, still at the truth.
    let last = w.keyframes.len() - 1;
    w.prior = Some(StatePrior {
        kf: last,
        mean: truth.keyframes[last].state,
        info: Matrix15::identity() * 100.0,
    });
    let rep = solver.optimize(&mut w, &params).unwrap();
    assert!(
        rep.last.prior < 1e-9 && errors(&w, &truth)[0] < 1e-5,
        "{rep:?}"
    );

    let mut bad = truth.clone();
    bad.preints.pop();
    assert!(solver.optimize(&mut bad, &params).is_err());
    let mut bad = truth.clone();
    bad.keyframes.iter_mut().for_each(|k| k.fixed = true);
    assert!(solver.optimize(&mut bad, &params).is_err());
}

/// Adds the exact observations of points `pts` in keyframes `kfs` of `w` (each keyframe's
/// own rig), where they fall in the image.
fn observe(w: &mut ViWindow, kfs: std::ops::Range<usize>, pts: std::ops::Range<usize>) {
    for k in kfs {
        let (camera, t_bc) = w.rig(k);
        let (camera, t_bc) = (*camera, *t_bc);
        for i in pts.clone() {
            let proj =
                reprojection_jacobians(&camera, &t_bc, &w.keyframes[k].state, &w.points_w[i], 0.0);
            if let Some((uv, _, _)) = proj.filter(|(uv, _, _)| camera.contains(uv)) {
                w.observations.push(ViObservation {
                    kf: k as u32,
                    point: i as u32,
                    uv,
                    sigma_px: 1.0,
                    dt_s: 0.0,
                });
            }
        }
    }
}

/// A global BA's problem (`VI_NOTES.md` §4, "global BA = all"): two IMU chains, the second
/// with its own camera and `t_bc`, and a keyframe without any IMU factor (a monocular
/// client's), 59 free keyframes (the sparse factorisation). From a perturbed start the
/// solver returns to the truth; the unlinked keyframe's pose is recovered and its velocity
/// and biases, which nothing observes, stay where they were.
#[test]
fn several_chains_with_their_own_cameras_are_recovered() {
    let (a, b) = (consistent_window(30, 4), consistent_window(30, 5));
    let mut truth = a.clone();
    let mut camera_b = PinholeRadtan::euroc_cam0();
    camera_b.fx *= 1.1;
    truth.extra_rigs.push(ViRig {
        camera: camera_b,
        t_bc: t_bc() * Isometry3::new(Vector3::new(0.02, 0.0, 0.01), Vector3::new(0.0, 0.1, 0.0)),
    });
    let n_a = a.points_w.len();
    truth.chain_starts.push(30);
    truth
        .keyframes
        .extend(b.keyframes.iter().map(|k| ViKeyframe { rig: 1, ..*k }));
    truth.preints.extend(b.preints.iter().cloned());
    truth.points_w.extend(&b.points_w);
    let n = truth.points_w.len();
    observe(&mut truth, 30..60, n_a..n);
    let mut lone = a.keyframes[3];
    lone.t_ns += 1;
    lone.state.v = Vector3::zeros();
    lone.state.biases = ImuBiases::default();
    truth.chain_starts.push(60);
    truth.keyframes.push(lone);
    observe(&mut truth, 60..61, 0..n_a);

    let mut w = truth.clone();
    let mut rng = Rng::new(11);
    for (k, kf) in w.keyframes.iter_mut().enumerate().filter(|(_, k)| !k.fixed) {
        let s = &mut kf.state;
        s.r *= so3_exp(&rand3(&mut rng, 0.02));
        s.p += rand3(&mut rng, 0.05);
        if k < 60 {
            s.v += rand3(&mut rng, 0.1);
            s.biases.accel += rand3(&mut rng, 0.03);
        }
    }
    // Points seen once are held (no depth): perturbed, they would pull their keyframe.
    let mut views = vec![0; w.points_w.len()];
    w.observations
        .iter()
        .for_each(|o| views[o.point as usize] += 1);
    for (p, n) in w.points_w.iter_mut().zip(&views) {
        *p += rand3(&mut rng, 0.03) * f64::from(u8::from(*n >= 2));
    }
    let params = ViParams {
        max_iterations: 50,
        ..Default::default()
    };
    let rep = ViSolver::new().optimize(&mut w, &params).unwrap();
    let after = errors(&w, &truth);
    eprintln!("two chains and a lone keyframe: {rep:?}\nerrors {after:?}");
    assert!(rep.initial.cost > 1e3 && rep.last.cost < 1e-6, "{rep:?}");
    assert!(
        after[0] < 1e-5 && after[1] < 1e-6 && after[2] < 1e-5 && after[5] < 1e-5,
        "{after:?}"
    );
    assert!(after[3] < 1e-6 && after[4] < 1e-4, "{after:?}");

    let mut bad = truth.clone();
    bad.chain_starts = vec![60, 30];
    assert!(ViSolver::new().optimize(&mut bad, &params).is_err());
    let mut bad = truth.clone();
    bad.keyframes[5].rig = 2;
    assert!(ViSolver::new().optimize(&mut bad, &params).is_err());
}
