//! Faults: real SIGKILLs of real child processes, restarts by the launcher, and a consumer
//! that dies while the ingest keeps publishing.
mod common;

use std::time::Duration;

use camera_ingest::CameraCounters;
use common::*;
use tracker::core::TrackerCounters;

/// Real-time replay; the tracker (the frame consumer) is SIGKILLed mid-stream. The camera
/// keeps publishing on schedule (safe overflow: a dead subscriber never blocks it), the
/// launcher restarts the tracker, and the restarted tracker resumes taking frames.
#[test]
fn killed_consumer_never_blocks_the_ingest_and_resumes() {
    let dir = tempdir();
    let agents = synthetic(dir.path(), "loop", 120, None); // 6 s at 20 Hz
    let out = tempdir();
    let mut child = spawn_pipeline(
        &agents[0],
        out.path(),
        "kill",
        &["--rate", "1.0", "--tracker-arg=--no-vo"],
    );
    let st = wait_counters(
        out.path(),
        "tracker_c0",
        "20 frames",
        |c: &TrackerCounters| c.frames_received >= 20,
    );
    let before = st.counters_as::<TrackerCounters>().frames_received;
    sigkill(st.pid.into());
    let status = child.wait().unwrap();
    assert!(status.success());
    let rep = report(out.path());
    let c = &rep["clients"][0];
    // The camera published every frame on time: nothing was late, nothing blocked.
    let cam: CameraCounters = service_counters(&rep, "camera_ingest:0");
    assert_eq!(
        c["frames_published"], 120,
        "{cam:?} {}",
        rep["services"]["camera_ingest:0"]
    );
    assert_eq!(cam.frames_skipped_late, 0, "{cam:?}");
    assert_eq!(
        rep["services"]["tracker:0"]["restarts"], 1,
        "the launcher restarted the tracker"
    );
    assert_eq!(rep["services"]["tracker:0"]["outcome"], "done");
    let received = c["frames_received"].as_u64().unwrap();
    assert!(
        received > before + 20,
        "the restarted tracker resumed ({before} -> {received})"
    );
    // What was lost while it was down is counted, not hidden.
    assert_eq!(c["frames_dropped"].as_u64().unwrap(), 120 - received);
    assert!(
        rep["services"]["tracker:0"]["recovery_s"][0]
            .as_f64()
            .unwrap()
            > 0.0
    );
}

/// Lock-step replay; the camera ingest is SIGKILLed mid-stream, restarted by the launcher,
/// and resumes where it stopped: every frame still arrives, in order, exactly once.
#[test]
fn killed_ingest_is_restarted_and_resumes() {
    let dir = tempdir();
    let agents = synthetic(dir.path(), "loop", 80, None);
    let out = tempdir();
    let log = out.path().join("frames_c{c}.log");
    let mut child = spawn_pipeline(
        &agents[0],
        out.path(),
        "killcam",
        &[
            "--lockstep",
            &format!("--tracker-arg=--frame-log={}", log.display()),
            "--tracker-arg=--work-ms=20",
            "--tracker-arg=--no-vo",
        ],
    );
    let st = wait_counters(
        out.path(),
        "camera_ingest_c0",
        "15 frames",
        |c: &CameraCounters| c.frames_published >= 15,
    );
    sigkill(st.pid.into());
    assert!(child.wait().unwrap().success());
    let rep = report(out.path());
    assert_eq!(rep["services"]["camera_ingest:0"]["restarts"], 1);
    let (frames, _) = frame_log(&out.path().join("frames_c0.log"));
    assert_frames_match(&agents[0], &frames);
    assert_eq!(rep["clients"][0]["frames_dropped"], 0);
}

/// A run left behind by SIGKILL of every process (stale shared memory, stale node files)
/// does not stop the next run on the same prefix: it cleans up and starts, and nothing of
/// either run is left in /dev/shm after it.
#[test]
fn stale_state_of_a_killed_run_does_not_stop_the_next() {
    let dir = tempdir();
    let agents = synthetic(dir.path(), "loop", 60, None);
    let out = tempdir();
    // Same prefix ("stale") for both runs.
    let mut child = spawn_pipeline(&agents[0], out.path(), "stale", &["--rate", "1.0"]);
    wait_counters(
        out.path(),
        "tracker_c0",
        "5 frames",
        |c: &TrackerCounters| c.frames_received >= 5,
    );
    let mut pids = vec![];
    for f in [
        "camera_ingest_c0",
        "imu_ingest_c0",
        "tracker_c0",
        "mapper",
        "loop_closer",
    ] {
        let v: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(out.path().join("status").join(format!("{f}.json"))).unwrap(),
        )
        .unwrap();
        pids.push(v["pid"].as_u64().unwrap());
    }
    // Children first (so the launcher cannot restart them), then the launcher.
    for p in &pids {
        sigkill(*p);
    }
    sigkill(child.id() as u64);
    let _ = child.wait();
    std::thread::sleep(Duration::from_millis(200));
    let out2 = tempdir();
    let res = run_pipeline(&[&agents[0]], out2.path(), "stale", &["--lockstep"]);
    assert!(
        res.status.success(),
        "the next run starts despite the stale state"
    );
    assert_eq!(report(out2.path())["clients"][0]["frames_received"], 60);
    // The next run removed what the killed one left in shared memory, and left nothing.
    assert_eq!(shm_entries("stale"), Vec::<String>::new());
}

/// `--kill` SIGKILLs the real child processes on schedule; each service is restarted, the
/// report's `faults` section lists every kill with its recovery time, the run completes
/// and no keyframe is lost between tracker and mapper.
#[test]
fn kill_schedule_kills_and_every_service_recovers() {
    let tmp = tempdir();
    let ds = synthetic(&tmp.path().join("seq"), "loop", 240, None);
    let out = tmp.path().join("out");
    let kills = [
        "loop_closer@0.8",
        "mapper@1.6",
        "tracker:0@2.4",
        "imu_ingest:0@3.2",
        "camera_ingest:0@4.0",
    ];
    let mut extra = vec!["--rate", "1.0"];
    for k in &kills {
        extra.push("--kill");
        extra.push(k);
    }
    let o = run_pipeline(&[&ds[0]], &out, "killsched", &extra);
    assert!(o.status.success(), "run failed");
    let rep = report(&out);
    let faults = rep["faults"].as_array().expect("faults section");
    assert_eq!(faults.len(), kills.len(), "every kill done: {faults:?}");
    for (f, k) in faults.iter().zip(kills) {
        let name = k.split('@').next().unwrap();
        assert_eq!(f["service"], name);
        let r = f["recovery_s"].as_f64();
        assert!(
            r.is_some_and(|r| r > 0.0 && r < 10.0),
            "{name} recovered: {f}"
        );
        assert!(
            rep["services"][name]["restarts"].as_u64().unwrap() >= 1,
            "{name} restarted"
        );
    }
    let c = &rep["clients"][0];
    assert_eq!(c["keyframes_sent"], c["keyframes_acked"], "{c}");
    assert_eq!(c["keyframes_sent"], c["keyframes_applied"], "{c}");
    assert!(c["keyframes_sent"].as_u64().unwrap() > 0);
}

/// Waits until `OUT/status/NAME.json` names a process other than `old_pid` (the restarted
/// service is up); returns its pid.
fn wait_new_pid(out: &std::path::Path, file: &str, old_pid: u64) -> u64 {
    let v = wait_status_until(out, file, "a new pid", |v| {
        v["pid"].as_u64().is_some_and(|p| p != old_pid)
    });
    v["pid"].as_u64().unwrap_or_default()
}

/// Real-time replay; the camera ingest is SIGKILLed four times in a row, each time as soon
/// as its successor is up, so the launcher's back-off for crashes in a row (100, 200, 400,
/// 800 ms) keeps it down for 0.8 s before its last restart. The restarted ingest resumes at
/// the frame due now: the frames due while it was down are never published late, nor
/// skipped silently: they are counted (`frames_skipped_late`) and reported as dropped, and
/// every frame of the sequence is either received by the tracker or counted as dropped.
#[test]
fn realtime_ingest_outage_counts_the_missed_frames_as_dropped() {
    const FRAMES: u64 = 140; // 7 s at 20 Hz
    let dir = tempdir();
    let agents = synthetic(dir.path(), "loop", FRAMES as usize, None);
    let out = tempdir();
    let mut child = spawn_pipeline(
        &agents[0],
        out.path(),
        "outage",
        &["--rate", "1.0", "--tracker-arg=--no-vo"],
    );
    let st = wait_counters(
        out.path(),
        "camera_ingest_c0",
        "20 frames",
        |c: &CameraCounters| c.frames_published >= 20,
    );
    let mut pid = u64::from(st.pid);
    for _ in 0..4 {
        sigkill(pid);
        pid = wait_new_pid(out.path(), "camera_ingest_c0", pid);
    }
    assert!(child.wait().unwrap().success());
    let rep = report(out.path());
    assert_eq!(rep["services"]["camera_ingest:0"]["restarts"], 4);
    assert_eq!(rep["services"]["camera_ingest:0"]["outcome"], "done");
    let c = &rep["clients"][0];
    let skipped = c["frames_skipped_late"].as_u64().unwrap();
    let dropped = c["frames_dropped"].as_u64().unwrap();
    let received = c["frames_received"].as_u64().unwrap();
    eprintln!("outage: {skipped} frames skipped late, {dropped} dropped, {received} received");
    // The last back-off alone (800 ms at 20 Hz, less the 250 ms a frame may be late before
    // it is given up) leaves ≥ 11 frames behind.
    assert!(skipped >= 11, "missed frames counted: {c:#}");
    assert!(
        dropped >= skipped,
        "skipped frames are dropped frames: {c:#}"
    );
    assert_eq!(
        received + dropped,
        FRAMES,
        "every frame accounted for: {c:#}"
    );
    // It resumed: frames after the outage reached the tracker.
    assert!(received > 40, "{c:#}");
}
