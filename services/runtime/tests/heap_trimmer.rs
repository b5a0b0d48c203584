//! The allocator statistics and [`HeapTrimmer`] against the resident size of the process.
//!
//! Both are process-wide figures, so this binary holds a single test: as a unit test it ran
//! beside the crate's other tests in parallel threads, whose allocations moved the heap and
//! the resident size between two readings. Keep it one test per binary.
#![cfg(all(target_os = "linux", target_env = "gnu"))]

use shoal_runtime::{heap_in_use_bytes, HeapTrimmer};

fn rss_bytes() -> u64 {
    let statm = std::fs::read_to_string("/proc/self/statm").expect("statm");
    let pages: u64 = statm
        .split_whitespace()
        .nth(1)
        .and_then(|p| p.parse().ok())
        .expect("resident pages");
    // SAFETY: sysconf has no preconditions.
    let page = unsafe { libc::sysconf(libc::_SC_PAGESIZE) } as u64;
    pages * page
}

/// `heap_in_use_bytes` follows a 16 MB allocation; then 80 MB of 4 KB blocks freed except the
/// last one (which keeps the heap top in use, so `free` cannot shrink the heap) stay resident
/// until trimmed, and the trimmer gives them back.
#[test]
fn heap_in_use_follows_allocations_and_trimmer_gives_free_heap_back() {
    let before = heap_in_use_bytes().expect("mallinfo2");
    let block = vec![1u8; 16 << 20];
    let during = heap_in_use_bytes().expect("mallinfo2");
    assert!(during >= before + (16 << 20) - 4096, "{before} -> {during}");
    drop(std::hint::black_box(block));
    let after = heap_in_use_bytes().expect("mallinfo2");
    assert!(after + (15 << 20) < during, "{during} -> {after}");

    let mut blocks: Vec<Vec<u8>> = (0..20_000).map(|_| vec![7u8; 4000]).collect();
    let last = blocks.pop();
    let full = rss_bytes();
    let held = heap_in_use_bytes().expect("mallinfo2");
    drop(std::hint::black_box(blocks));
    let freed = rss_bytes();
    let released = heap_in_use_bytes().expect("mallinfo2");
    // The program gave the 80 MB back to the allocator, which keeps them resident.
    assert!(
        released + (70 << 20) < held,
        "heap in use {held} -> {released}"
    );
    assert!(
        freed + (20 << 20) > full,
        "resident {full} -> freed {freed}"
    );
    let mut t = HeapTrimmer::new(std::time::Duration::ZERO);
    assert!(t.maybe_trim());
    let trimmed = rss_bytes();
    drop(last);
    assert!(
        trimmed + (40 << 20) < freed,
        "resident {full} -> freed {freed} -> trimmed {trimmed}"
    );
    let mut slow = HeapTrimmer::new(std::time::Duration::from_secs(3600));
    assert!(!slow.maybe_trim());
}
