//! End-to-end replay through shared memory: camera_ingest + imu_ingest + the tracker (as the
//! consumer) run as separate processes under the launcher; the consumer logs what it read
//! from shared memory and we compare it with the dataset on disk.
mod common;

use common::*;

fn replay_and_check(dataset: &std::path::Path, test: &str, expect_imu: bool) {
    let out = tempdir();
    let log = out.path().join("frames_c{c}.log");
    let arg = format!("--tracker-arg=--frame-log={}", log.display());
    let res = run_pipeline(&[dataset], out.path(), test, &["--lockstep", &arg]);
    assert!(res.status.success(), "shoal run failed");
    let (frames, imu) = frame_log(&out.path().join("frames_c0.log"));
    assert_frames_match(dataset, &frames);
    let ds = datasets::open(dataset).unwrap();
    if expect_imu {
        assert_eq!(imu.len(), ds.imu.len(), "every IMU sample arrived");
        for (k, (seq, t)) in imu.iter().enumerate() {
            assert_eq!(*seq, k as u64, "IMU sequence number");
            assert_eq!(*t, ds.imu[k].t_ns, "IMU sample {k} in order with its time");
        }
    }
    let rep = report(out.path());
    let c = &rep["clients"][0];
    assert_eq!(c["frames_published"], ds.frames.len() as u64);
    assert_eq!(c["frames_dropped"], 0, "lock-step drops nothing");
    assert_eq!(c["imu_samples_published"], ds.imu.len() as u64);
    assert_eq!(
        rep["latency_ms"]["publish_to_pose"]["n"],
        ds.frames.len() as u64
    );
    for svc in ["camera_ingest:0", "imu_ingest:0", "tracker:0"] {
        assert_eq!(
            rep["services"][svc]["outcome"], "done",
            "{svc} ended at the end of data"
        );
        assert_eq!(rep["services"][svc]["restarts"], 0);
    }
}

#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/kitti07 (set SHOAL_DATA)"
)]
#[test]
fn kitti07_lockstep_replay_is_exact() {
    let ds = shared_dataset("kitti07");
    replay_and_check(&ds, "kitti", false);
}

#[test]
fn synthetic_lockstep_replay_is_exact() {
    let dir = tempdir();
    let agents = synthetic(dir.path(), "fast-rs", 40, None);
    replay_and_check(&agents[0], "synth", true);
    // fast-rs is a rolling-shutter sequence: the readout time travels with every frame.
    let ds = datasets::open(&agents[0]).unwrap();
    assert!(ds.frames.iter().all(|f| f.readout_ns == 30_000_000));
}

#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/phone_honorv10 (set SHOAL_DATA)"
)]
#[test]
fn phone_frames_carry_rolling_shutter_readout() {
    let ds = shared_dataset("phone_honorv10");
    let out = tempdir();
    let log = out.path().join("frames_c{c}.log");
    let arg = format!("--tracker-arg=--frame-log={}", log.display());
    let res = run_pipeline(&[&ds], out.path(), "phone", &[&arg]);
    assert!(res.status.success());
    let (frames, imu) = frame_log(&out.path().join("frames_c0.log"));
    assert_eq!(frames.len(), 25);
    assert!(
        frames.iter().all(|f| f.readout_ns == 20_733_000),
        "t_r = 20.733 ms on every frame"
    );
    assert!(frames.iter().all(|f| (f.width, f.height) == (720, 1280)));
    assert!(!imu.is_empty() && imu.windows(2).all(|w| w[1].1 > w[0].1));
    assert_frames_match(&ds, &frames);
}

#[test]
fn two_clients_run_side_by_side() {
    let dir = tempdir();
    let agents = synthetic(dir.path(), "two-agents", 15, None);
    assert_eq!(agents.len(), 2);
    let out = tempdir();
    let res = run_pipeline(&[&agents[0], &agents[1]], out.path(), "two", &[]);
    assert!(res.status.success());
    let rep = report(out.path());
    for c in 0..2 {
        assert_eq!(rep["clients"][c]["frames_received"], 15, "client {c}");
        assert_eq!(rep["services"][format!("tracker:{c}")]["outcome"], "done");
    }
}
