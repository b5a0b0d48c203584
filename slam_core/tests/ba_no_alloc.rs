//! The bundle adjuster allocates nothing once its workspace has seen a problem of the same
//! shape (dense reduced-system path), so its LM loop cannot allocate either. Own test binary:
//! it installs a counting global allocator.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use slam_core::optim::ba::synth::{synthetic_scene, SyntheticBaConfig};
use slam_core::optim::ba::{BaParams, BundleAdjuster, LinearSolverKind};

struct Counting;

thread_local! {
    static ALLOCS: Cell<usize> = const { Cell::new(0) };
}

// SAFETY: forwards to the system allocator; only counts calls of the current thread.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let _ = ALLOCS.try_with(|c| c.set(c.get() + 1));
        // SAFETY: same contract as the caller's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: same contract as the caller's.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let _ = ALLOCS.try_with(|c| c.set(c.get() + 1));
        // SAFETY: same contract as the caller's.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn allocations() -> usize {
    ALLOCS.with(|c| c.get())
}

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
