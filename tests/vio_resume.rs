//! A SIGKILLed visual-inertial tracker's successor resumes its session (issue 17): a real
//! tracker child process is SIGKILLed by the launcher (`--kill tracker:0@f150`) after the
//! inertial initialisation, restarted, and its successor rebuilds the client map from the
//! keyframe spool and continues the same session in the same metric, gravity-aligned
//! world, instead of starting a new session that would have to initialise again (seconds of
//! motion, a new scale). Checked against the synthetic ground truth: no second
//! initialisation (no world move after the kill), one session and one server map, every
//! frame posed, the frames after the kill metric (Sim(3) scale ≈ 1) and in the world of the
//! frames before it (the rigid alignment of the frames before the kill fits those after),
//! the successor's keyframes carrying the same biases and a right velocity.
mod common;

use std::path::Path;

use common::*;
use nalgebra::{Isometry3, Vector3};
use slam_core::metrics::{align, Alignment};
use tracker::core::TrackerCounters;

/// 12 s of the `drone` scenario (aggressive 6-DoF flight, global shutter) at 20 Hz.
const FRAMES: usize = 240;
/// The kill, in frames with a pose: 7.5 s, after the initialisation (2.8 s) and its first
/// refinement (5 s of keyframes).
const KILL_AT: usize = 150;
/// Frames after [`KILL_AT`] that the predecessor may still have posed before the SIGKILL
/// landed: the successor's frames are counted from `KILL_AT + MARGIN` on.
const MARGIN: usize = 3;

#[test]
fn a_killed_vio_tracker_resumes_its_session_in_the_same_metric_world() {
    let tmp = tempdir();
    let ds = synthetic(tmp.path(), "drone", FRAMES, None);
    let out = tmp.path().join("out");
    let kill = format!("tracker:0@f{KILL_AT}");
    let args = [
        "--lockstep",
        "--mode",
        "vio",
        "--set",
        "tracker.window=10",
        "--kill",
        &kill,
    ];
    let res = run_pipeline(&[&ds[0]], &out, "vio_resume", &args);
    assert!(res.status.success(), "shoal run failed");
    let rep = report(&out);
    check_resumed(&rep);
    check_one_session(&rep);
    let (gt, est) = trajectories(&ds[0], &out);
    check_metric_in_one_world(&gt, &est);
    check_keyframe_states(&out, &gt, est[KILL_AT].0);
}

/// The tracker was killed once and restarted; its successor resumed the session (the
/// report says from which keyframe, and how soon it tracked again) and did not initialise
/// again: no world move after the kill, no spooled keyframe sent at the start.
fn check_resumed(rep: &serde_json::Value) {
    let faults = rep["faults"].as_array().expect("faults");
    assert_eq!(faults.len(), 1, "{faults:?}");
    let f = &faults[0];
    assert_eq!(f["service"], "tracker:0");
    assert!(f["recovery_s"].as_f64().is_some(), "{f}");
    let before: TrackerCounters = counters_at_restart(f);
    let after: TrackerCounters = service_counters(rep, "tracker:0");
    assert!(before.world_moves >= 1, "initialised before the kill: {f}");
    assert_eq!(
        after.world_moves, before.world_moves,
        "a world move after the kill"
    );
    assert_eq!(after.vio_resumes, 1, "{after:?}");
    assert!(after.keyframes_resumed >= 5, "{after:?}");
    assert_eq!(
        after.keyframes_recovered, 0,
        "the spool was resumed, not sent"
    );
    let c = &rep["clients"][0];
    let vio = &c["vio"];
    assert_eq!(vio["status"], "initialised", "{vio}");
    assert_eq!(vio["resumed"], 1, "{vio}");
    assert!(vio["resume_refused"].is_null(), "{vio}");
    assert!(vio["resumed_from_keyframe"].as_u64().is_some(), "{vio}");
    let frames = vio["resumed_after_frames"].as_u64().expect("re-tracked");
    assert!(frames <= 3, "{frames} frames until vision posed one again");
    eprintln!(
        "resumed from keyframe {} ({} keyframes, {} points rebuilt), gap {} s; vision posed \
         its frame {frames}, {} ms after the spool read; recovery {} s",
        vio["resumed_from_keyframe"],
        vio["resumed_keyframes"],
        vio["resumed_points"],
        vio["resumed_gap_s"],
        vio["resumed_after_ms"],
        f["recovery_s"]
    );
    assert_eq!(error_count(rep, "tracker:0", ErrorKind::VioResume), 0);
}

/// One VO session across the kill (the recorder's and the mapper's), every frame posed,
/// every keyframe applied, no map merge needed.
fn check_one_session(rep: &serde_json::Value) {
    let c = &rep["clients"][0];
    let sessions = c["sessions"]["sessions"].as_array().expect("sessions");
    assert_eq!(sessions.len(), 1, "{sessions:?}");
    assert_eq!(sessions[0]["frames"], FRAMES as u64);
    assert_eq!(c["sessions"]["frames_reexpressed"], 0, "raw tracker poses");
    assert_eq!(c["frames_posed"], FRAMES as u64, "{c:#}");
    assert_eq!(c["server_maps"], 1);
    assert_eq!(rep["merges"], 0);
    assert_eq!(c["keyframes_sent"], c["keyframes_applied"], "{c:#}");
}

/// Ground truth and estimate, index-aligned over the frames of both (`(t_ns, T_wc)`).
type Traj = Vec<(i64, Isometry3<f64>)>;

fn trajectories(dataset: &Path, out: &Path) -> (Traj, Traj) {
    let read = |p: &Path| {
        let t = datasets::trajectory::read_tum(p).expect("trajectory");
        t.poses
            .into_iter()
            .map(|p| (p.t_ns, p.pose))
            .collect::<Traj>()
    };
    let gt = read(&dataset.join("groundtruth_cam0.txt"));
    let est = read(&out.join("trajectory_c0.txt"));
    assert_eq!(est.len(), FRAMES);
    let gt: Traj = est
        .iter()
        .map(|(t, _)| {
            *gt.iter()
                .find(|g| g.0 == *t)
                .expect("ground truth of a frame")
        })
        .collect();
    (gt, est)
}

/// Sim(3) scale and RMSE of `est` against `gt` (each aligned on its own).
fn sim3(gt: &[(i64, Isometry3<f64>)], est: &[(i64, Isometry3<f64>)]) -> (f64, f64) {
    let (g, e) = poses(gt, est);
    let s = align(&g, &e, Alignment::Sim3).expect("alignment");
    (s.scale, rmse(&g, &e, |p| s.transform_pose(p)))
}

fn poses(
    gt: &[(i64, Isometry3<f64>)],
    est: &[(i64, Isometry3<f64>)],
) -> (Vec<Isometry3<f64>>, Vec<Isometry3<f64>>) {
    (
        gt.iter().map(|p| p.1).collect(),
        est.iter().map(|p| p.1).collect(),
    )
}

fn rmse(
    gt: &[Isometry3<f64>],
    est: &[Isometry3<f64>],
    f: impl Fn(&Isometry3<f64>) -> Isometry3<f64>,
) -> f64 {
    let sse: f64 = gt
        .iter()
        .zip(est)
        .map(|(g, e)| (f(e).translation.vector - g.translation.vector).norm_squared())
        .sum();
    (sse / gt.len() as f64).sqrt()
}

/// The frames before the kill and those after are each metric, and the rigid alignment
/// fitted on the frames before the kill fits those after it: one world across the kill.
fn check_metric_in_one_world(gt: &Traj, est: &Traj) {
    let after0 = KILL_AT + MARGIN;
    let (s_before, ate_before) = sim3(&gt[..KILL_AT], &est[..KILL_AT]);
    let (s_after, ate_after) = sim3(&gt[after0..], &est[after0..]);
    let (g, e) = poses(gt, est);
    let rigid = align(&g[..KILL_AT], &e[..KILL_AT], Alignment::Se3).expect("alignment");
    let carried = rmse(&g[after0..], &e[after0..], |p| rigid.transform_pose(p));
    let whole = align(&g, &e, Alignment::Se3).expect("alignment");
    let ate_se3 = rmse(&g, &e, |p| whole.transform_pose(p));
    eprintln!(
        "before the kill: Sim(3) scale {s_before:.4}, ATE {ate_before:.4} m; after: scale \
         {s_after:.4}, ATE {ate_after:.4} m; after in the before-kill alignment {carried:.4} \
         m; whole run SE(3) ATE {ate_se3:.4} m"
    );
    for s in [s_before, s_after] {
        assert!((s - 1.0).abs() < 0.03, "Sim(3) scale {s}: not metric");
    }
    assert!(ate_after < 0.05, "ATE after the kill {ate_after} m");
    assert!(
        carried < 0.05,
        "after the kill {carried} m off the world before it"
    );
    assert!(ate_se3 < 0.05, "SE(3) ATE {ate_se3} m");
}

/// The keyframes the mapper applied: after the kill all inertial, their biases going on
/// from the last keyframe's before it, and a velocity as right as before the kill (speed vs the
/// ground truth's, m/s RMS).
fn check_keyframe_states(out: &Path, gt: &Traj, t_kill_ns: i64) {
    let states = keyframe_states(out);
    let (before, after): (Vec<&KeyframeState>, Vec<&KeyframeState>) =
        states.iter().partition(|k| k.0 < t_kill_ns);
    let last = before
        .iter()
        .rev()
        .find(|k| k.1.is_some())
        .expect("inertial before");
    assert!(after.len() >= 5, "{} keyframes after the kill", after.len());
    // The biases go on from the last keyframe before the kill: the first keyframe after it
    // carries them (its state is the resumed navigator's), later ones as local mapping's
    // window refines them from there; never reset to zero or estimated anew.
    let [g0, a0] = last.1.expect("biases").1;
    for (i, k) in after.iter().enumerate() {
        let (_, [g, a]) = k.1.expect("inertial keyframe after the kill");
        let (dg, da) = (
            (Vector3::from(g) - Vector3::from(g0)).norm(),
            (Vector3::from(a) - Vector3::from(a0)).norm(),
        );
        let (max_g, max_a) = if i == 0 { (1e-3, 0.01) } else { (5e-3, 0.05) };
        assert!(
            dg < max_g && da < max_a,
            "keyframe {i} after the resume: biases moved by {dg} rad/s, {da} m/s²"
        );
    }
    let speed_err = |ks: &[&KeyframeState]| {
        let e: Vec<f64> = ks
            .iter()
            .filter_map(|k| Some((k.0, k.1?.0)))
            .map(|(t, v)| v.norm() - gt_speed(gt, t))
            .collect();
        (e.iter().map(|x| x * x).sum::<f64>() / e.len().max(1) as f64).sqrt()
    };
    let (eb, ea) = (speed_err(&before), speed_err(&after));
    eprintln!("keyframe speed error vs truth: {eb:.3} m/s before the kill, {ea:.3} m/s after");
    assert!(
        ea < 0.2 && ea < 3.0 * eb.max(0.02),
        "speed error {ea} m/s after, {eb} before"
    );
}

/// A keyframe's time and, when inertial, its velocity and `[gyro, accel]` biases.
type KeyframeState = (i64, Option<(Vector3<f64>, [[f64; 3]; 2])>);

/// The keyframe states of client 0 in the mapper's journal, in time order.
fn keyframe_states(out: &Path) -> Vec<KeyframeState> {
    let j = shoal_runtime::journal::read_journal(&out.join("mapper_journal.bin")).expect("journal");
    let mut v: Vec<KeyframeState> = j
        .entries
        .iter()
        .filter_map(|e| match e {
            shoal_runtime::journal::Entry::Keyframe {
                client: 0, header, ..
            } => Some(header),
            _ => None,
        })
        .map(|h| {
            let state = (h.inertial != 0)
                .then(|| (Vector3::from(h.velocity_w), [h.gyro_bias, h.accel_bias]));
            (h.t_ns, state)
        })
        .collect();
    v.sort_by_key(|k| k.0);
    v
}

/// The ground truth camera's speed at `t_ns` (central difference over ±50 ms), m/s.
fn gt_speed(gt: &Traj, t_ns: i64) -> f64 {
    let i = gt.partition_point(|g| g.0 < t_ns).clamp(1, gt.len() - 2);
    let (a, b) = (&gt[i - 1], &gt[i + 1]);
    (b.1.translation.vector - a.1.translation.vector).norm() / ((b.0 - a.0) as f64 * 1e-9)
}
