//! Replaying an MCAP file through the whole pipeline (issue 21): a synthetic EuRoC-layout
//! sequence and the MCAP file `shoal convert --to mcap` writes of it give byte-identical
//! lock-step trajectories (client frames, server frames, server keyframes) in the
//! visual-inertial mode, so the file carries the frames, the IMU, the times and the
//! calibration exactly; and the run's report counts the same frames and no error.
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
    let extra = ["--lockstep", "--mode", "vio"];
    assert!(run_pipeline(&[&agents[0]], &a, "mcap_replay_a", &extra)
        .status
        .success());
    assert!(run_pipeline(&[&mcap], &b, "mcap_replay_b", &extra)
        .status
        .success());
    for file in [
        "trajectory_c0.txt",
        "trajectory_server_c0.txt",
        "keyframes_server_c0.txt",
    ] {
        let (x, y) = (
            std::fs::read(a.join(file)).expect(file),
            std::fs::read(b.join(file)).expect(file),
        );
        assert!(!x.is_empty(), "{file} is empty");
        assert!(x == y, "{file} differs between the folder and its MCAP");
    }
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
