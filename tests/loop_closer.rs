//! The loop closer end to end (issue 5), real processes on synthetic `two-agents`: the
//! loop closer finds where the two cameras saw the same place, the mapper merges the two
//! clients' server maps into one, and the server keyframes of both agents, evaluated
//! together in that one map with a single Sim(3) alignment, are within 0.3% of the
//! distance travelled.
mod common;

use std::path::Path;

use common::*;
use loop_closer::LoopCloserCounters;
use mapper::MapperCounters;

fn u(v: &serde_json::Value) -> u64 {
    v.as_u64().unwrap_or_else(|| panic!("not a count: {v}"))
}

#[test]
fn two_agents_maps_merge_into_one_accurate_map() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "two-agents", 480, None);
    let out = dir.path().join("out");
    let o = run_pipeline(
        &[&ds[0], &ds[1]],
        &out,
        "loop_two_agents",
        &["--tracker-arg=--window=10"],
    );
    assert!(o.status.success(), "shoal run failed");
    let r = report(&out);
    let lc: LoopCloserCounters = service_counters(&r, "loop_closer");
    let mc: MapperCounters = service_counters(&r, "mapper");
    eprintln!("loop closer: {lc:?}");
    assert!(lc.merges >= 1, "no merge found: {lc:?}");
    assert_eq!(
        mc.corrections_applied_merge, lc.merges,
        "every merge the loop closer sent was applied: {mc:?}"
    );
    assert_eq!(mc.corrections_refused, 0, "{mc:?}");
    assert_eq!(u(&r["mapper"]["maps"]), 1, "one map after the merge");
    let map_id = |c| mc.client(c).map_id;
    assert!(map_id(0).is_some(), "{mc:?}");
    assert_eq!(
        map_id(0),
        map_id(1),
        "both clients continue in the same map"
    );
    let mut length = 0.0;
    let mut n_server = 0;
    for c in 0..2 {
        let cl = &r["clients"][c];
        let sent = u(&cl["keyframes_sent"]);
        assert_eq!(u(&cl["keyframes_applied"]), sent);
        assert_eq!(u(&cl["keyframes_acked"]), sent);
        let s = &cl["ate_server_keyframes"];
        length += s["path_length_m"].as_f64().expect("path length");
        n_server += u(&cl["server_keyframes"]) as usize;
        eprintln!(
            "client {c}: server keyframes ATE {:.4} m (alone), client keyframes {:.4} m",
            s["rmse_m"], cl["ate_client_keyframes"]["rmse_m"]
        );
    }
    let joint = joint_server_eval(&out, &ds, slam_core::metrics::Alignment::Sim3);
    let (rmse, n) = (joint.ape.rmse, joint.pairs.len());
    let percent = 100.0 * rmse / length;
    eprintln!(
        "both agents in one map: {n} server keyframes, ATE {rmse:.4} m = {percent:.3}% of {length:.1} m"
    );
    assert_eq!(n, n_server, "every server keyframe evaluated");
    assert!(percent <= 0.3, "joint server ATE {percent:.3}% > 0.3%");
}

/// ATE (m, Sim(3)-aligned) of a TUM file of keyframes against the ground truth of `ds`.
fn ate_of(ds: &Path, est: &Path) -> (f64, usize) {
    let gt = datasets::open(ds)
        .expect("dataset")
        .ground_truth
        .expect("ground truth");
    let est = datasets::trajectory::read_tum(est).expect("trajectory");
    let params = slam_core::metrics::EvalParams {
        alignment: slam_core::metrics::Alignment::Sim3,
        ..Default::default()
    };
    let r = slam_core::metrics::evaluate(
        &gt.iter().map(|g| g.t_ns).collect::<Vec<_>>(),
        &gt.iter().map(|g| g.pose).collect::<Vec<_>>(),
        &est.poses.iter().map(|p| p.t_ns).collect::<Vec<_>>(),
        &est.poses.iter().map(|p| p.pose).collect::<Vec<_>>(),
        &params,
    )
    .expect("ATE");
    (r.ape.rmse, r.pairs.len())
}

/// A drifting client on `loop` (5-keyframe window, 400 features: its VO drifts ~1%) with
/// the mapper's revisit search off, so that closing the loop is left to the loop closer:
/// when lap 2 comes back to the start, a loop is detected within the one map, the pose
/// graph correction is applied, and the server keyframes right after it (correction +
/// global BA) have at most half the ATE they had right before it.
#[test]
fn loop_closure_halves_the_server_map_error() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "loop", 900, None);
    let out = dir.path().join("out");
    let o = run_pipeline(
        &[&ds[0]],
        &out,
        "loop_drift",
        &[
            "--tracker-arg=--window=5",
            "--tracker-arg=--features=400",
            "--mapper-arg=--spatial-keyframes=0",
        ],
    );
    assert!(o.status.success(), "shoal run failed");
    let r = report(&out);
    let lc: LoopCloserCounters = service_counters(&r, "loop_closer");
    let mc: MapperCounters = service_counters(&r, "mapper");
    eprintln!("loop closer: {lc:?}");
    assert!(lc.loops >= 1, "no loop detected: {lc:?}");
    assert!(mc.corrections_applied_pose_graph >= 1, "{mc:?}");
    let (before, n0) = ate_of(&ds[0], &out.join("correction_1_before.txt"));
    let (after, n1) = ate_of(&ds[0], &out.join("correction_1_after.txt"));
    eprintln!(
        "server keyframes ({n0}): ATE {before:.4} m before the loop correction, {after:.4} m after"
    );
    assert_eq!(n0, n1);
    assert!(
        after <= 0.5 * before,
        "{after:.4} m after vs {before:.4} m before"
    );
}

/// Issue 6's tracker kill: a tracker SIGKILLed a third of the way through a lap; its
/// successor sends the keyframes of the dead VO window from the spool (nothing lost), then
/// starts a new VO session with its own server map; the loop closer matches the new
/// session's first keyframes with the old one's last (session continuation) or, failing
/// that, finds lap 2 coming back to where the first session began, and the mapper merges
/// the two maps. The run ends with one map holding both sessions, globally consistent (server
/// keyframe ATE ≤ 0.5% of the path). The "within 20% of a fault-free run" is
/// asserted on the shorter run of `kill_each.rs::kill_tracker`, where run-to-run spread is
/// small; on this 900-frame loop the spread is 2× between runs (BENCHMARKS.md, "Loop closing
/// and map merging", measured over 6 runs each), so no fault-free run is made here. The
/// merge usually happens right after the restart (session continuation), else at lap 2.
#[test]
fn killed_tracker_session_is_merged_back() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "loop", 900, None);
    let run = |name: &str, extra: &[&str]| {
        let out = dir.path().join(name);
        let mut args = vec!["--lockstep", "--tracker-arg=--window=10"];
        args.extend_from_slice(extra);
        let o = run_pipeline(&[&ds[0]], &out, name, &args);
        assert!(o.status.success(), "{name}: shoal run failed");
        report(&out)
    };
    let r = run("merge_back_kill", &["--kill", "tracker:0@f250"]);
    let tracker = &r["services"]["tracker:0"];
    assert!(u(&tracker["restarts"]) >= 1, "{tracker}");
    let c = &r["clients"][0];
    assert!(u(&c["server_maps"]) >= 2, "the new session got its own map");
    assert!(
        u(&r["merges"]) >= 1,
        "no merge: {}",
        r["services"]["loop_closer"]
    );
    assert_eq!(u(&r["mapper"]["maps"]), 1, "one map after the merge");
    assert_eq!(u(&c["keyframes_applied"]), u(&c["keyframes_sent"]));
    assert!(
        u(&c["keyframes_recovered"]) >= 1,
        "the dead tracker's window came from the spool: {c:#}"
    );
    let a = c["ate_server_keyframes"]["rmse_m"]
        .as_f64()
        .expect("server ATE");
    eprintln!(
        "tracker kill: merged map ATE {a:.4} m over {} keyframes of both sessions",
        u(&c["server_keyframes"]),
    );
    let path = c["ate_server_keyframes"]["path_length_m"]
        .as_f64()
        .expect("path length");
    assert!(
        a <= 0.005 * path,
        "merged map ATE {a} m over {path} m: the merge did not give one consistent map"
    );
}
