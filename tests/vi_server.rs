//! The visual-inertial server end to end (issue 19), real processes on the synthetic
//! `four-agents` (hand-held cameras with IMUs): two visual-inertial clients whose paths
//! overlap end in one metric, gravity-aligned server map, merged by yaw and translation only
//! (4 degrees of freedom), its local BAs visual-inertial, and their server keyframes
//! together in that map within 0.1% of the distance travelled with a rigid (SE(3))
//! alignment (no scale to fit), their scale within 1%.
//!
//! One lap each (640 frames): measured 0.0274-0.0296 m over 61.8 m (0.044-0.048%; two runs
//! of the test profile differ: each client is locked to its own stream, not to the
//! other's), Sim(3) scale 1.005-1.006 (the visual global BA after the merge lets the scale
//! move; BENCHMARKS.md, issue 19). On half a lap (320 frames) the two maps merged in one
//! run and not in the next.
mod common;

use common::*;
use loop_closer::LoopCloserCounters;
use mapper::MapperCounters;

#[test]
fn two_visual_inertial_clients_merge_into_one_metric_map() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "four-agents", 640, None);
    let out = dir.path().join("out");
    let o = run_pipeline(
        &[&ds[0], &ds[1]],
        &out,
        "vi_server",
        &["--lockstep", "--mode", "vio"],
    );
    assert!(o.status.success(), "shoal run failed");
    let r = report(&out);
    let lc: LoopCloserCounters = service_counters(&r, "loop_closer");
    let mc: MapperCounters = service_counters(&r, "mapper");
    eprintln!("loop closer: {lc:?}");
    assert!(lc.merges >= 1, "no merge: {lc:?}");
    assert_eq!(lc.merges_four_dof, lc.merges, "every merge 4-DoF: {lc:?}");
    assert_eq!(lc.loops_four_dof, lc.loops, "every loop 4-DoF: {lc:?}");
    assert_eq!(mc.corrections_refused, 0, "{mc:?}");
    check_one_metric_map(&r, &[0, 1]);
    let mut length = 0.0;
    for c in 0..2 {
        let windows = mc.client(c as u32).vi_windows;
        assert!(
            windows >= 3,
            "client {c}: {windows} visual-inertial local BAs"
        );
        let cl = &r["clients"][c];
        assert_eq!(cl["keyframes_applied"], cl["keyframes_sent"]);
        // The distance the client travelled (its frames' ground truth).
        length += cl["ate_se3"]["path_length_m"]
            .as_f64()
            .expect("path length");
    }
    let e = joint_server_eval(&out, &ds[..2], slam_core::metrics::Alignment::Se3);
    let scale = joint_server_eval(&out, &ds[..2], slam_core::metrics::Alignment::Sim3)
        .alignment
        .scale;
    let percent = 100.0 * e.ape.rmse / length;
    eprintln!(
        "both clients in one metric map: {} server keyframes, SE(3) ATE {:.4} m = {percent:.3}% \
         of {length:.1} m, Sim(3) scale {scale:.4}",
        e.pairs.len(),
        e.ape.rmse
    );
    assert!((scale - 1.0).abs() < 0.01, "merged map scale {scale}");
    assert!(percent <= 0.1, "joint server ATE {percent:.3}% > 0.1%");
}

/// A visual-inertial client anchors its world to its metric, gravity-aligned server map
/// (issue 19, feedback; `slam_core::vio::anchor`): with keyframes sent as they leave a
/// 10-keyframe window, the server's feedback moves the client's world (yaw and translation)
/// so that each frame's pose as tracked and its server-map pose agree to a centimetre or
/// two, where without anchoring they drift apart by a decimetre and more; the rigid moves
/// leave the recorded trajectory what it was (lock-step, one client: the same run).
/// Measured: gap p50/p90 7.7/15.9 mm anchored, 93/154 mm not, SE(3) ATE 0.0448 m both;
/// with the whole-session windows (final code, test profile) 14.1/20.7 and 89.5/120.8 mm.
#[test]
fn a_visual_inertial_client_tracks_in_its_server_map_frame() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "four-agents", 320, None);
    let run = |name: &str, extra: &[&str]| {
        let out = dir.path().join(name);
        let mut args = vec!["--lockstep", "--mode", "vio", "--tracker-arg=--window=10"];
        args.extend_from_slice(extra);
        let o = run_pipeline(&[&ds[0]], &out, name, &args);
        assert!(o.status.success(), "shoal run {name} failed");
        report(&out)["clients"][0].clone()
    };
    let anchored = run("anchored", &[]);
    let plain = run("plain", &["--tracker-arg=--no-anchor"]);
    let gap = |c: &serde_json::Value, q: &str| c["live_server_gap_mm"][q].as_f64().expect(q);
    let a = &anchored["vio"]["anchor"];
    eprintln!(
        "anchors {a}; live pose to server pose p50/p90 {:.1}/{:.1} mm anchored, \
         {:.1}/{:.1} mm not",
        gap(&anchored, "p50"),
        gap(&anchored, "p90"),
        gap(&plain, "p50"),
        gap(&plain, "p90")
    );
    assert!(a["applied"].as_u64().unwrap_or(0) >= 5, "{a}");
    assert_eq!(a["dropped"], 0, "{a}");
    assert!(plain["vio"]["anchor"].is_null());
    assert!(gap(&anchored, "n") >= 150.0, "frames with a server pose");
    assert!(gap(&anchored, "p90") < 40.0);
    assert!(gap(&plain, "p90") > 3.0 * gap(&anchored, "p90"));
    let ate = |c: &serde_json::Value| c["ate_se3"]["rmse_m"].as_f64().expect("ate_se3");
    assert!(
        (ate(&anchored) - ate(&plain)).abs() < 1e-3,
        "trajectory {} vs {} m",
        ate(&anchored),
        ate(&plain)
    );
}
