//! Criterion benchmark of the bundle adjustment on synthetic scenes: ORB-SLAM-sized local BA
//! (10 keyframes, 1000 points, ~5000 observations, 5% outliers), dense against sparse
//! reduced-system solvers, and a larger global BA.

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, BatchSize, Criterion};
use slam_core::optim::ba::synth::{synthetic_scene, SyntheticBaConfig};
use slam_core::optim::ba::{BaParams, BundleAdjuster, LinearSolverKind};

fn bench_ba(c: &mut Criterion) {
    let cases = [
        ("local_10kf_1000pts", 10, 1000, 2, BaParams::local(), false),
        ("local_30kf_3000pts", 30, 3000, 2, BaParams::local(), false),
        (
            "global_100kf_10000pts",
            100,
            10000,
            0,
            BaParams::global(),
            true,
        ),
    ];
    for (name, n_keyframes, n_points, n_fixed, base, global) in cases {
        let Ok(scene) = synthetic_scene(&SyntheticBaConfig {
            n_keyframes,
            n_points,
            n_fixed,
            outlier_ratio: if global { 0.0 } else { 0.05 },
            ..SyntheticBaConfig::default()
        }) else {
            eprintln!("{name}: could not build the scene");
            continue;
        };
        eprintln!(
            "{name}: {} keyframes, {} points, {} observations",
            scene.problem.keyframes.len(),
            scene.problem.points.len(),
            scene.problem.observations.len()
        );
        for solver in [LinearSolverKind::Dense, LinearSolverKind::Sparse] {
            let params = BaParams { solver, ..base };
            let mut ba = BundleAdjuster::new();
            let id = format!("ba/{name}/{solver:?}");
            c.bench_function(&id, |b| {
                b.iter_batched_ref(
                    || scene.problem.clone(),
                    |p| {
                        let r = if global {
                            ba.optimize_global(p, &params, None)
                        } else {
                            ba.optimize(p, &params)
                        };
                        black_box(r.ok())
                    },
                    BatchSize::LargeInput,
                )
            });
        }
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10);
    targets = bench_ba
}
criterion_main!(benches);
