//! Bad input never crashes a service: a corrupt PNG, a truncated CSV line, non-monotonic
//! timestamps and a missing folder each give a clear error naming the file (and line),
//! counted in report.json, and the run goes on where it safely can.
mod common;

use std::fs;

use common::*;
use tracker::core::TrackerCounters;

fn errors_of(rep: &serde_json::Value, kind: ErrorKind) -> Vec<String> {
    rep["errors"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["kind"] == kind.as_str())
        .map(|e| e["detail"].as_str().unwrap().to_string())
        .collect()
}

#[test]
fn corrupt_image_truncated_csv_and_non_monotonic_stamps_are_reported_and_skipped() {
    let dir = tempdir();
    let agent = synthetic(dir.path(), "loop", 30, None).remove(0);
    let cam = agent.join("mav0/cam0");
    let ds = datasets::open(&agent).unwrap();
    // 1. Frame 5 becomes garbage bytes.
    let bad_png = ds.frames[5].path.clone();
    fs::write(&bad_png, b"\x89PNG\r\n\x1a\nthis is not an image").unwrap();
    // 2. Frame 12's stamp is moved before frame 11's (line 14 of data.csv: header + 0-based 12).
    let csv_path = cam.join("data.csv");
    let text = fs::read_to_string(&csv_path).unwrap();
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    let t11 = ds.frames[11].t_ns;
    let name12 = lines[13].split(',').nth(1).unwrap().to_string();
    lines[13] = format!("{},{}", t11 - 1000, name12);
    fs::write(&csv_path, lines.join("\n") + "\n").unwrap();
    // 3. The IMU file ends in a truncated line.
    let imu_path = agent.join("mav0/imu0/data.csv");
    let mut imu = fs::read_to_string(&imu_path).unwrap();
    let n_imu_lines = imu.lines().count();
    imu.push_str("1000200000000,0.1,0.2");
    fs::write(&imu_path, imu).unwrap();

    let out = tempdir();
    let res = run_pipeline(&[&agent], out.path(), "bad", &[]);
    assert!(res.status.success(), "the run goes on");
    let rep = report(out.path());
    let corrupt = errors_of(&rep, ErrorKind::CorruptImage);
    assert_eq!(corrupt.len(), 1, "{corrupt:?}");
    assert!(
        corrupt[0].contains(bad_png.file_name().unwrap().to_str().unwrap()),
        "{corrupt:?}"
    );
    let nm = errors_of(&rep, ErrorKind::NonMonotonic);
    assert_eq!(nm.len(), 1, "{nm:?}");
    assert!(
        nm[0].contains("cam0/data.csv:14"),
        "names file and line: {nm:?}"
    );
    let trunc = errors_of(&rep, ErrorKind::MalformedLine);
    assert_eq!(trunc.len(), 1, "{trunc:?}");
    assert!(
        trunc[0].contains(&format!("imu0/data.csv:{}", n_imu_lines + 1)),
        "{trunc:?}"
    );
    assert_eq!(
        error_count(&rep, "camera_ingest:0", ErrorKind::CorruptImage),
        1
    );
    assert_eq!(
        error_count(&rep, "imu_ingest:0", ErrorKind::MalformedLine),
        1
    );
    assert_eq!(
        rep["error_counts"]["camera_ingest:0/corrupt_image"], 1,
        "report.json keeps its error count keys"
    );
    // 30 frames - the non-monotonic one skipped by the reader - the corrupt one.
    assert_eq!(rep["clients"][0]["frames_published"], 28);
    assert_eq!(rep["clients"][0]["frames_received"], 28);
    assert_eq!(rep["services"]["camera_ingest:0"]["outcome"], "done");
}

#[test]
fn missing_folder_is_a_clear_error() {
    let out = tempdir();
    let missing = out.path().join("no_such_dataset");
    let res = run_pipeline(&[&missing], out.path(), "missing", &[]);
    assert!(!res.status.success());
    let stderr = String::from_utf8_lossy(&res.stderr);
    assert!(
        stderr.contains("no_such_dataset"),
        "names the folder: {stderr}"
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
    let rep = report(out.path());
    let errs = errors_of(&rep, ErrorKind::Dataset);
    assert_eq!(errs.len(), 1);
    assert!(errs[0].contains("no_such_dataset"));
}

#[test]
fn a_pipeline_of_another_schema_version_is_refused() {
    use iceoryx2::prelude::*;
    let prefix = prefix("schema");
    let config = shm_schema::topics::config_with_prefix(&prefix).unwrap();
    let node = NodeBuilder::new()
        .config(&config)
        .create::<ipc::Service>()
        .unwrap();
    let foreign = ServiceName::new("shoal/v999/c0/frames").unwrap();
    let _svc = node
        .service_builder(&foreign)
        .publish_subscribe::<u64>()
        .create()
        .unwrap();
    let out = tempdir();
    let res = shoal()
        .args([
            "service",
            "tracker",
            "--client",
            "0",
            "--ipc-prefix",
            &prefix,
        ])
        .output()
        .unwrap();
    assert!(!res.status.success());
    let stderr = String::from_utf8_lossy(&res.stderr);
    assert!(
        stderr.contains("schema version") && stderr.contains("v999"),
        "{stderr}"
    );
    drop(out);
    drop((_svc, node));
    remove_counter_segment(&prefix);
}

/// A message of another schema version in the middle of a running pipeline (a frame and an
/// IMU sample to the tracker, a keyframe to the mapper, from a foreign publisher on the same
/// services): each is refused with a clear error naming the service and both versions,
/// counted in report.json, and the run goes on: every real frame still gets through.
#[test]
fn messages_of_another_schema_version_are_counted_and_the_run_goes_on() {
    use iceoryx2::prelude::*;
    use shm_schema::topics;
    use shm_schema::{FrameHeader, ImuMsg, KeyframeHeader, MsgMeta, SCHEMA_VERSION};
    const FRAMES: u64 = 80;
    let dir = tempdir();
    let agent = synthetic(dir.path(), "loop", FRAMES as usize, None).remove(0);
    let out = tempdir();
    let mut child = spawn_pipeline(
        &agent,
        out.path(),
        "foreign",
        &[
            "--lockstep",
            "--tracker-arg=--no-vo",
            "--tracker-arg=--work-ms=40",
        ],
    );
    wait_status_written(out.path(), "mapper");
    wait_counters(
        out.path(),
        "tracker_c0",
        "10 frames",
        |c: &TrackerCounters| c.frames_received >= 10,
    );

    let foreign = {
        let mut m = MsgMeta::new(0, 77, 1_000_000, 0);
        m.schema_version = SCHEMA_VERSION + 1;
        m
    };
    let config = topics::config_with_prefix(&prefix("foreign")).unwrap();
    let node = NodeBuilder::new()
        .config(&config)
        .create::<ipc::Service>()
        .unwrap();
    // A frame.
    let frames = topics::frames_service(&node, 0).unwrap();
    let frame_pub = topics::frame_publisher(&frames, 64, 0).unwrap();
    let mut s = frame_pub.loan_slice(64).unwrap();
    *s.user_header_mut() = FrameHeader {
        meta: foreign,
        width: 8,
        height: 8,
        stride: 8,
        ..Default::default()
    };
    s.send().unwrap();
    // An IMU sample.
    let imu = topics::imu_service(&node, 0).unwrap();
    let imu_pub = topics::publisher(&imu).unwrap();
    imu_pub
        .send_copy(ImuMsg {
            meta: foreign,
            ..Default::default()
        })
        .unwrap();
    // A keyframe (no keypoints).
    let kfs = topics::keyframes_service(&node, 0).unwrap();
    let kf_pub = topics::keyframe_publisher(&kfs).unwrap();
    let mut s = kf_pub.loan_slice(0).unwrap();
    *s.user_header_mut() = KeyframeHeader {
        meta: foreign,
        keyframe_id: slam_core::ids::ClientKeyframeId::MAX + 1,
        ..Default::default()
    };
    s.send().unwrap();

    assert!(child.wait().unwrap().success(), "the run goes on");
    drop((frame_pub, imu_pub, kf_pub, frames, imu, kfs, node));
    remove_counter_segment(&prefix("foreign"));
    let rep = report(out.path());
    assert_eq!(
        error_count(&rep, "tracker:0", ErrorKind::SchemaVersion),
        2,
        "frame and IMU sample counted: {:#}",
        rep["errors"]
    );
    assert_eq!(
        error_count(&rep, "mapper", ErrorKind::SchemaVersion),
        1,
        "keyframe counted: {:#}",
        rep["errors"]
    );
    let details = errors_of(&rep, ErrorKind::SchemaVersion);
    assert_eq!(details.len(), 3, "{details:?}");
    let expected = format!(
        "schema version {}, this binary speaks version {SCHEMA_VERSION}",
        SCHEMA_VERSION + 1
    );
    for d in &details {
        assert!(d.contains(&expected), "names both versions: {d}");
    }
    assert!(details.iter().any(|d| d.starts_with("frame of client 0")));
    assert!(details.iter().any(|d| d.starts_with("imu of client 0")));
    assert!(details
        .iter()
        .any(|d| d.starts_with("keyframe of client 0")));
    let c = &rep["clients"][0];
    assert_eq!(c["frames_published"], FRAMES);
    assert_eq!(
        c["frames_received"], FRAMES,
        "every real frame taken: {c:#}"
    );
    assert_eq!(c["frames_dropped"], 0);
    for name in ["tracker:0", "mapper"] {
        assert_eq!(rep["services"][name]["restarts"], 0, "{name} kept running");
    }
}
