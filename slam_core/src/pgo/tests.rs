//! Unit tests of the optimisers on small graphs.

use nalgebra::{Isometry3, Matrix6, Translation3, UnitQuaternion, Vector3, Vector6};

use super::*;
use crate::lie::{se3_exp, Matrix7};

fn iso(t: [f64; 3], w: [f64; 3]) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(t[0], t[1], t[2]),
        UnitQuaternion::from_scaled_axis(Vector3::new(w[0], w[1], w[2])),
    )
}

#[test]
fn point_follows_its_keyframe() {
    let old = Sim3::from_isometry(&iso([1.0, 2.0, 0.5], [0.1, -0.2, 0.3]), 1.0);
    let new = Sim3::new(
        UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.3, 0.1)),
        Vector3::new(-1.0, 0.0, 2.0),
        2.5,
    );
    let p_k = Vector3::new(0.3, -0.4, 3.0);
    let p_w = old.transform_point(&p_k);
    let moved = correct_point(&p_w, &old, &new);
    assert!((moved - new.transform_point(&p_k)).norm() < 1e-12);
    // The seed's form (world-to-camera): p ← [p + R_rgᵀ(t_old - t_new)] / s_r, with
    // S_rg = new⁻¹ and T_rg = old⁻¹ when old has unit scale.
    let t_old = old.inverse();
    let s_new = new.inverse();
    let r_rg = t_old.r.to_rotation_matrix(); // the rotation is kept by the seed's step 2
    let s_ng = Sim3::new(t_old.r, s_new.t, s_new.s);
    let seed = (p_w + r_rg.inverse() * (t_old.t - s_ng.t)) / s_ng.s;
    let expect = s_ng.inverse().transform_point(&t_old.transform_point(&p_w));
    assert!((seed - expect).norm() < 1e-12);
    assert!((correct_point_se3(&p_w, &old.to_isometry(), &new) - moved).norm() < 1e-12);
}

fn noisy_loop_se3() -> Se3Graph {
    let mut g = Se3Graph::default();
    let n = 12;
    let truth: Vec<Isometry3<f64>> = (0..n)
        .map(|k| {
            let a = k as f64 * std::f64::consts::TAU / n as f64;
            iso(
                [3.0 * a.cos(), 3.0 * a.sin(), 0.2 * a.sin()],
                [0.0, 0.0, a + 1.57],
            )
        })
        .collect();
    for (k, t) in truth.iter().enumerate() {
        // drifted initial values
        let d = iso(
            [0.05 * k as f64, -0.03 * k as f64, 0.0],
            [0.0, 0.02 * k as f64, 0.01],
        );
        g.vertices.push(Vertex {
            id: k as u64,
            pose: t * d,
        });
    }
    for k in 0..n {
        let j = (k + 1) % n;
        let z = truth[k].inverse() * truth[j] * iso([0.01, -0.01, 0.0], [0.002, 0.0, -0.003]);
        g.edges.push(Edge {
            i: k,
            j,
            measurement: z,
            info: Matrix6::identity() * 100.0,
        });
    }
    g
}

#[test]
fn se3_lm_reaches_a_stationary_point_and_chordal_agrees() {
    let mut a = noisy_loop_se3();
    let ra = optimize_se3(&mut a, &PgoParams::default()).unwrap();
    assert!(ra.final_cost < ra.initial_cost * 1e-2, "{ra:?}");
    let mut b = noisy_loop_se3();
    let params = PgoParams {
        init: PgoInit::Chordal,
        ..Default::default()
    };
    let rb = optimize_se3(&mut b, &params).unwrap();
    assert!(
        (ra.final_cost - rb.final_cost).abs() < 1e-6 * ra.final_cost,
        "{ra:?}\n{rb:?}"
    );
    // Tight tolerances converge to the same minimum: gradient (finite differences) ~ 0.
    let tight = PgoParams {
        lm: LmParams {
            rel_tol: 1e-14,
            abs_tol: 1e-14,
            ..Default::default()
        },
        ..Default::default()
    };
    optimize_se3(&mut a, &tight).unwrap();
    let prior = gtsam_prior(&noisy_loop_se3());
    let e0 = se3_cost(&a, prior.as_ref());
    for v in 0..a.vertices.len() {
        for k in 0..6 {
            let mut d = Vector6::zeros();
            d[k] = 1e-6;
            let mut p = a.clone();
            p.vertices[v].pose = a.vertices[v].pose * se3_exp(&d);
            let mut m = a.clone();
            m.vertices[v].pose = a.vertices[v].pose * se3_exp(&-d);
            let g = (se3_cost(&p, prior.as_ref()) - se3_cost(&m, prior.as_ref())) / 2e-6;
            assert!(
                g.abs() < 1e-5 * (1.0 + e0),
                "vertex {v} coord {k}: gradient {g}"
            );
        }
    }
}

#[test]
fn fixed_vertices_do_not_move() {
    let mut g = noisy_loop_se3();
    g.fixed = vec![0, 5];
    let before = (g.vertices[0].pose, g.vertices[5].pose);
    optimize_se3(&mut g, &PgoParams::default()).unwrap();
    assert_eq!((g.vertices[0].pose, g.vertices[5].pose), before);
}

#[test]
fn sim3_methods_recover_a_consistent_graph() {
    // A chain of 6 keyframes whose relative Sim(3) are consistent, initial values off.
    let truth: Vec<Sim3> = (0..6)
        .map(|k| {
            let k = k as f64;
            Sim3::new(
                UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.0, 0.3 * k)),
                Vector3::new(k, 0.5 * k * k, 0.0),
                1.2f64.powf(k),
            )
        })
        .collect();
    let mut g = Sim3Graph::default();
    for (k, t) in truth.iter().enumerate() {
        g.vertices.push(Vertex {
            id: k as u64,
            pose: if k == 0 {
                *t
            } else {
                Sim3::new(t.r, t.t * 1.3, 1.0)
            },
        });
    }
    for (i, j) in [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0), (1, 4)] {
        g.edges.push(Edge {
            i,
            j,
            measurement: truth[i].inverse() * truth[j],
            info: Matrix7::identity(),
        });
    }
    for method in [
        PgoMethod::Direct,
        PgoMethod::Stepwise,
        PgoMethod::StepwiseDirect,
    ] {
        let mut h = g.clone();
        let r = optimize_sim3(&mut h, method, &PgoParams::default()).unwrap();
        assert!(r.final_cost < 1e-10, "{method:?}: {r:?}");
        for (v, t) in h.vertices.iter().zip(&truth) {
            assert!((v.pose.t - t.t).norm() < 1e-4, "{method:?}");
            assert!((v.pose.s - t.s).abs() < 1e-4, "{method:?}");
        }
    }
}
