//! Issue 19 through real processes: a visual-inertial and a monocular client on one server.
//! Every keyframe message of the visual-inertial client after its session's first carries
//! the IMU samples since the previous keyframe, borders interpolated (`VI_NOTES.md` §4,
//! Fig. 5.4); the segments of consecutive keyframes tile the time axis, as received (the
//! mapper's journal) and in the server map (`imu_segments_server_c0.txt`, after the
//! handler's discards and culling); the sample counts are the IMU stream's; the monocular
//! client's messages carry none.
mod common;

use std::path::Path;

use common::*;
use shm_schema::KeyframeHeader;
use shoal_runtime::journal::{read_journal, Entry};

/// Wire records of a segment over `[t0, t1]`: the stream's samples strictly inside, and the
/// two interpolated borders.
fn expected_records(stamps: &[i64], t0: i64, t1: i64) -> usize {
    stamps.iter().filter(|t| **t > t0 && **t < t1).count() + 2
}

/// The keyframe headers and IMU record times of client `c` in the mapper's journal, in the
/// order they were applied.
fn journaled(out: &Path, c: u32) -> Vec<(KeyframeHeader, Vec<i64>)> {
    let j = read_journal(&out.join("mapper_journal.bin")).expect("journal");
    j.entries
        .into_iter()
        .filter_map(|e| match e {
            Entry::Keyframe {
                client,
                header,
                imu,
                ..
            } if client == c => Some((*header, imu.iter().map(|r| r.t_ns).collect())),
            _ => None,
        })
        .collect()
}

/// The visual-inertial client's messages: a session's first keyframe has no segment, every
/// other one starts where the previous one ended (no gap, no overlap), its records are the
/// stream's samples inside plus the two borders, and the segments cover the session's span.
fn check_messages(kfs: &[(KeyframeHeader, Vec<i64>)], stamps: &[i64]) -> usize {
    let mut with_segment = 0;
    let mut session_start: Option<(u32, i64)> = None;
    let mut covered = 0i64;
    let mut prev: Option<&KeyframeHeader> = None;
    for (h, times) in kfs {
        assert_eq!(h.has_imu, 1, "keyframe {}", h.keyframe_id);
        assert_eq!(times.len(), h.n_imu as usize);
        let same_session = prev.is_some_and(|p| p.meta.session_id == h.meta.session_id);
        if !same_session {
            assert_eq!(h.n_imu, 0, "a session's first keyframe {}", h.keyframe_id);
            session_start = Some((h.meta.session_id, h.imu_t1_ns));
            covered = 0;
            prev = Some(h);
            continue;
        }
        let p = prev.expect("same session");
        assert!(h.n_imu > 0, "keyframe {} without a segment", h.keyframe_id);
        assert_eq!(
            h.imu_t0_ns, p.imu_t1_ns,
            "keyframe {}: tiles",
            h.keyframe_id
        );
        assert_eq!(
            (times[0], times[times.len() - 1]),
            (h.imu_t0_ns, h.imu_t1_ns),
            "borders exact"
        );
        assert!(times.windows(2).all(|w| w[0] < w[1]));
        let inside = &times[1..times.len() - 1];
        assert!(inside.iter().all(|t| stamps.binary_search(t).is_ok()));
        assert_eq!(
            times.len(),
            expected_records(stamps, h.imu_t0_ns, h.imu_t1_ns),
            "keyframe {}: every sample of the stream",
            h.keyframe_id
        );
        covered += h.imu_t1_ns - h.imu_t0_ns;
        let (_, t_start) = session_start.expect("session");
        assert_eq!(covered, h.imu_t1_ns - t_start, "segments cover the span");
        with_segment += 1;
        prev = Some(h);
    }
    with_segment
}

/// `imu_segments_server_c0.txt`: every keyframe of the server map either starts a session
/// or links the one before it; the linked segments cover the span between their keyframes
/// and hold the stream's samples.
fn check_server_map(out: &Path, stamps: &[i64]) -> usize {
    let text = std::fs::read_to_string(out.join("imu_segments_server_c0.txt")).expect("file");
    let rows: Vec<Vec<i64>> = text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split(' ').map(|v| v.parse().expect("number")).collect())
        .collect();
    let mut linked = 0;
    for w in rows.windows(2) {
        let (a, b) = (&w[0], &w[1]);
        if b[1] == -1 {
            continue;
        }
        assert_eq!(b[6], 1, "server keyframe at {} not linked: {text}", b[0]);
        assert_eq!(b[1], a[2], "starts where the previous one ends");
        assert_eq!((b[4], b[5]), (b[1], b[2]), "borders exact");
        assert_eq!(b[3] as usize, expected_records(stamps, b[1], b[2]));
        linked += 1;
    }
    linked
}

/// A visual-inertial `drone` client and a monocular `loop` client (`--mode` once per
/// dataset; both datasets have an IMU stream) in one lock-step run: the visual-inertial
/// client's server map is metric and gravity-aligned, the monocular one's is neither.
#[test]
fn keyframes_carry_tiling_imu_segments_and_mono_ones_none() {
    let tmp = tempdir();
    let vi = synthetic(&tmp.path().join("drone"), "drone", 100, None);
    let mono = synthetic(&tmp.path().join("loop"), "loop", 60, None);
    let out = tmp.path().join("out");
    let res = run_pipeline(
        &[&vi[0], &mono[0]],
        &out,
        "imu_segments",
        &["--lockstep", "--mode", "vio", "--mode", "mono"],
    );
    assert!(res.status.success());
    let rep = report(&out);
    let (c0, c1) = (&rep["clients"][0], &rep["clients"][1]);
    assert_eq!(c0["client_mode"], "vio", "{}", c0["client_mode_reason"]);
    assert_eq!(c1["client_mode"], "mono", "{}", c1["client_mode_reason"]);
    let stamps = imu_stamps(&vi[0]);
    let kfs = journaled(&out, 0);
    assert!(kfs.len() >= 4, "{} keyframes applied", kfs.len());
    let with_segment = check_messages(&kfs, &stamps);
    assert!(
        with_segment + 2 >= kfs.len(),
        "{with_segment} of {}",
        kfs.len()
    );
    assert_eq!(c0["keyframes_with_imu"], with_segment as u64);
    assert_eq!(c0["imu_segments_refused"], 0);
    let linked = check_server_map(&out, &stamps);
    assert!(linked >= 2, "{linked} linked server keyframes");
    // The monocular client: keyframes as before, no IMU part.
    let mono_kfs = journaled(&out, 1);
    assert!(!mono_kfs.is_empty());
    for (h, times) in &mono_kfs {
        assert_eq!((h.has_imu, h.n_imu, times.len()), (0, 0, 0));
    }
    assert_eq!(c1["keyframes_with_imu"], 0);
    assert!(!out.join("imu_segments_server_c1.txt").exists());
    for c in [c0, c1] {
        let mean = c["keyframe_bytes_mean"].as_f64().expect("bytes");
        assert!(
            mean > std::mem::size_of::<KeyframeHeader>() as f64,
            "{mean}"
        );
        assert!(c["keyframes_per_s"].as_f64().expect("rate") > 0.0);
    }
    let errors = rep["error_counts"].as_object().expect("error_counts");
    assert!(errors.is_empty(), "{errors:?}");
    // report.json `maps`: one map per client (no overlap, no merge), flagged by kind.
    let maps = rep["maps"].as_array().expect("maps");
    let map_of = |c: u64| {
        maps.iter()
            .find(|m| m["clients"] == serde_json::json!([c]))
            .unwrap_or_else(|| panic!("no map of client {c}: {maps:?}"))
    };
    assert_eq!(map_of(0)["metric"], true, "{maps:?}");
    assert_eq!(map_of(0)["gravity_aligned"], true, "{maps:?}");
    assert_eq!(map_of(1)["metric"], false, "{maps:?}");
    assert_eq!(map_of(1)["gravity_aligned"], false, "{maps:?}");
    let vi = &rep["services"]["mapper"]["counters"]["c0.vi_windows"];
    assert!(
        vi.as_u64().is_some_and(|n| n >= 1),
        "visual-inertial local BAs: {vi}"
    );
}
