//! The bundle adjuster allocates nothing once its workspace has seen a problem of the same
//! shape (dense reduced-system path), so its LM loop cannot allocate either. Own test binary:
//! it installs a counting global allocator.

mod common;

use common::allocations;
use slam_core::optim::ba::synth::{synthetic_scene, SyntheticBaConfig};
use slam_core::optim::ba::{BaParams, BundleAdjuster, LinearSolverKind};

#[test]
fn warm_local_ba_does_not_allocate() {
    let scene = synthetic_scene(&SyntheticBaConfig::default()).expect("scene");
    let params = BaParams {
        solver: LinearSolverKind::Dense,
        ..BaParams::local()
    };
    let mut ba = BundleAdjuster::new();
    let mut first = scene.problem.clone();
    ba.optimize(&mut first, &params).expect("warm-up");
    let mut second = scene.problem.clone();
    let before = allocations();
    let report = ba.optimize(&mut second, &params).expect("ba");
    let n = allocations() - before;
    assert!(report.iterations > 5);
    assert_eq!(first, second);
    assert_eq!(n, 0, "{n} allocations in a warm local BA");
}
