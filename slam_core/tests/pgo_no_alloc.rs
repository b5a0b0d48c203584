//! The pose-graph LM allocates only in its setup: a run with more iterations allocates
//! exactly as often as a run with one. Own test binary: it installs a counting global
//! allocator (`common`).

mod common;

use common::allocations;
use nalgebra::{Isometry3, Matrix6, Translation3, UnitQuaternion, Vector3};
use slam_core::lie::{Matrix7, Sim3};
use slam_core::pgo::{
    optimize_se3, optimize_sim3, Edge, LmParams, PgoMethod, PgoParams, Se3Graph, Sim3Graph, Vertex,
};

fn loop_graph() -> Se3Graph {
    let n = 40;
    let pose = |k: usize, bend: f64| {
        let a = k as f64 * std::f64::consts::TAU / n as f64;
        Isometry3::from_parts(
            Translation3::new(5.0 * a.cos(), 5.0 * a.sin() * bend, 0.3 * a.sin()),
            UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.05 * bend, a)),
        )
    };
    let mut g = Se3Graph::default();
    for k in 0..n {
        g.vertices.push(Vertex {
            id: k as u64,
            pose: pose(k, 1.0 + 0.01 * k as f64),
        });
    }
    for k in 0..n {
        for d in [1, 7] {
            let j = (k + d) % n;
            g.edges.push(Edge {
                i: k,
                j,
                measurement: pose(k, 1.0).inverse() * pose(j, 1.0),
                info: Matrix6::identity(),
            });
        }
    }
    g
}

fn params(iters: usize) -> PgoParams {
    PgoParams {
        lm: LmParams {
            max_iterations: iters,
            rel_tol: 0.0,
            abs_tol: 0.0,
            ..Default::default()
        },
        ..Default::default()
    }
}

#[test]
fn lm_iterations_do_not_allocate() {
    let count = |iters: usize| {
        let mut g = loop_graph();
        let before = allocations();
        let r = optimize_se3(&mut g, &params(iters)).expect("pgo");
        (allocations() - before, r.iterations)
    };
    count(1); // warm-up (lazy statics)
    let (a1, i1) = count(1);
    let (a4, i4) = count(4);
    assert_eq!((i1, i4), (1, 4));
    assert_eq!(
        a1, a4,
        "SE(3): {a1} allocations with 1 iteration, {a4} with 4"
    );

    let sim = |iters: usize| {
        let mut g = Sim3Graph::default();
        for v in loop_graph().vertices {
            g.vertices.push(Vertex {
                id: v.id,
                pose: Sim3::from_isometry(&v.pose, 1.0),
            });
        }
        for e in loop_graph().edges {
            g.edges.push(Edge {
                i: e.i,
                j: e.j,
                measurement: Sim3::from_isometry(&e.measurement, 1.1),
                info: Matrix7::identity(),
            });
        }
        let before = allocations();
        let r = optimize_sim3(&mut g, PgoMethod::Direct, &params(iters)).expect("pgo");
        (allocations() - before, r.iterations)
    };
    sim(1);
    let (s1, j1) = sim(1);
    let (s4, j4) = sim(4);
    assert_eq!((j1, j4), (1, 4));
    assert_eq!(
        s1, s4,
        "Sim(3): {s1} allocations with 1 iteration, {s4} with 4"
    );
}
