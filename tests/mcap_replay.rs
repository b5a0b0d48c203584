//! Replaying an MCAP file through the whole pipeline (issue 21): a synthetic EuRoC-layout
//! sequence and the MCAP file `shoal convert --to mcap` writes of it give byte-identical
//! lock-step trajectories (client frames, server frames, server keyframes) in the
//! visual-inertial mode, so the file carries the frames, the IMU, the times and the
//! calibration exactly; and the run's report counts the same frames and no error. The
//! folder's run also records what crossed shared memory (`--record`), and replaying that
//! recording gives the same trajectories again.
mod common;

use common::*;

const FRAMES: usize = 200;

#[test]
fn mcap_replay_matches_folder_in_lockstep() {
    let dir = tempdir();
    let agents = synthetic(&dir.path().join("sim"), "loop", FRAMES, Some(10.0));
    let mcap = dir.path().join("loop.mcap");
    let out = shoal()
        .args(["convert", "--to", "mcap"])
        .arg(&agents[0])
        .arg(&mcap)
        .output()
        .expect("run shoal convert");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (a, b) = (dir.path().join("folder"), dir.path().join("mcap"));
    let (recorded, c) = (dir.path().join("run.mcap"), dir.path().join("recorded"));
    let extra = ["--lockstep", "--mode", "vio"];
    let record = [&extra[..], &["--record", recorded.to_str().unwrap()]].concat();
    assert!(run_pipeline(&[&agents[0]], &a, "mcap_replay_a", &record)
        .status
        .success());
    assert!(run_pipeline(&[&mcap], &b, "mcap_replay_b", &extra)
        .status
        .success());
    assert!(run_pipeline(&[&recorded], &c, "mcap_replay_c", &extra)
        .status
        .success());
    for file in [
        "trajectory_c0.txt",
        "trajectory_server_c0.txt",
        "keyframes_server_c0.txt",
    ] {
        let x = std::fs::read(a.join(file)).expect(file);
        assert!(!x.is_empty(), "{file} is empty");
        for (run, what) in [(&b, "its MCAP"), (&c, "the run's recording")] {
            let y = std::fs::read(run.join(file)).expect(file);
            assert!(x == y, "{file} differs between the folder and {what}");
        }
    }
    let ra = report(&a);
    let rec = &ra["record"][0];
    assert_eq!(rec["frames"], FRAMES as u64, "{rec}");
    assert_eq!(rec["frames_missed"], 0, "{rec}");
    assert_eq!(
        rec["imu_samples"], ra["clients"][0]["imu_samples_published"],
        "{rec}"
    );
    assert_eq!(rec["poses"], ra["clients"][0]["frames_posed"], "{rec}");
    assert_eq!(
        rec["keyframes"], ra["clients"][0]["keyframes_sent"],
        "{rec}"
    );
    assert_eq!(rec["map_points"], ra["mapper"]["points"], "{rec}");
    assert!(rec["error"].is_null(), "{rec}");
    let (ra, rb) = (report(&a), report(&b));
    for key in [
        "frames_received",
        "keyframes_applied",
        "imu_samples_published",
    ] {
        assert_eq!(ra["clients"][0][key], rb["clients"][0][key], "{key}");
    }
    assert_eq!(rb["clients"][0]["frames_received"], FRAMES as u64);
    assert_eq!(
        rb["error_counts"],
        serde_json::json!({}),
        "{}",
        rb["error_counts"]
    );
    assert_eq!(rb["provenance"]["datasets"][0]["files"], 1);
}
