//! Helpers shared by the end-to-end tests: the shoal binary, the shared data folder,
//! per-test iceoryx2 prefixes, running a pipeline and reading its outputs.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use serde::de::DeserializeOwned;
pub use shoal_runtime::{ErrorKind, Status};

/// The `shoal` binary under test.
pub fn shoal() -> Command {
    Command::new(env!("CARGO_BIN_EXE_shoal"))
}

/// The real-data folder: `$SHOAL_DATA` when set (no fallback: a path that does not exist
/// means "no data"), else `../shared/data` beside the checkout; the rule of
/// `build_support/shoal_data.rs`, whose `cfg(shoal_data)` ignores the real-data tests when
/// the folder is absent.
pub fn shared_data() -> PathBuf {
    match std::env::var_os("SHOAL_DATA") {
        Some(p) if !p.is_empty() => PathBuf::from(p),
        _ => Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data"),
    }
}

/// The shared data sub-folder `name`. Panics, failing the test, when it is missing: a test
/// that runs (the data folder exists) never passes without its data.
pub fn shared_dataset(name: &str) -> PathBuf {
    let d = shared_data().join(name);
    assert!(
        d.is_dir(),
        "real data {} not found (set SHOAL_DATA to the data folder)",
        d.display()
    );
    d
}

/// A unique iceoryx2 prefix for one test, so parallel tests never see each other.
pub fn prefix(test: &str) -> String {
    format!("st{}_{}_", std::process::id(), test)
}

/// Removes the node-id counter segment iceoryx2 leaves in `/dev/shm` for `prefix` (as the
/// launcher does at the end of a run), for tests that open nodes or run services without
/// the launcher; call it once the test's nodes are dropped and its children have exited.
pub fn remove_counter_segment(prefix: &str) {
    let config = shm_schema::topics::config_with_prefix(prefix).expect("iceoryx2 config");
    // SAFETY: no node of this test's own prefix is left (dropped, children exited).
    let removed = unsafe {
        iceoryx2::testing::remove_global_mgmt_segment::<iceoryx2::prelude::ipc::Service>(&config)
    };
    removed.expect("removing the node counter segment");
}

/// A fresh temporary folder.
pub fn tempdir() -> tempfile::TempDir {
    tempfile::tempdir().expect("temp dir")
}

/// `--mode mono` unless `extra` names the mode: the pipeline tests check the chapter-3
/// (monocular) behaviour, which a synthetic dataset's IMU and extrinsics would otherwise
/// turn visual-inertial.
pub fn pin_mono(extra: &[&str]) -> &'static [&'static str] {
    if extra
        .iter()
        .any(|a| *a == "--mode" || a.starts_with("--mode="))
    {
        &[]
    } else {
        &["--mode", "mono"]
    }
}

/// Runs `shoal run` on `datasets` into `out` (`--mode mono` unless `extra` says otherwise,
/// [`pin_mono`]); returns the process output.
pub fn run_pipeline(datasets: &[&Path], out: &Path, test: &str, extra: &[&str]) -> Output {
    let mut cmd = shoal();
    cmd.arg("run");
    for d in datasets {
        cmd.arg("--dataset").arg(d);
    }
    cmd.arg("--out")
        .arg(out)
        .arg("--quiet")
        .arg("--ipc-prefix")
        .arg(prefix(test));
    cmd.arg("--max-seconds").arg(MAX_RUN_S.to_string());
    cmd.args(pin_mono(extra));
    cmd.args(extra);
    let res = cmd.output().expect("run shoal");
    if !res.status.success() {
        eprintln!("stdout:\n{}", String::from_utf8_lossy(&res.stdout));
        eprintln!("stderr:\n{}", String::from_utf8_lossy(&res.stderr));
    }
    let timed_out = std::fs::read_to_string(out.join("report.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .is_some_and(|r| r["timed_out"] == true);
    assert!(
        !timed_out,
        "the run was cut at --max-seconds {MAX_RUN_S} (a hang, or a machine far too loaded): \
         its figures would describe part of the data"
    );
    res
}

/// The hang guard of [`run_pipeline`], s: far above a lock-step run's time on 2 cores
/// (a 900-frame `loop` run took over 240 s under a load average of 7, sessions 11 and 13,
/// and its loop test then failed as if no loop had been found).
pub const MAX_RUN_S: u32 = 900;

/// Starts `shoal run --quiet` on `dataset` into `out` in the background (stdout discarded,
/// iceoryx2 prefix of `test`, at most 120 s) with `extra` arguments; the caller waits for it.
pub fn spawn_pipeline(
    dataset: &Path,
    out: &Path,
    test: &str,
    extra: &[&str],
) -> std::process::Child {
    shoal()
        .args(["run", "--quiet", "--max-seconds", "120"])
        .arg("--dataset")
        .arg(dataset)
        .arg("--out")
        .arg(out)
        .arg("--ipc-prefix")
        .arg(prefix(test))
        .args(pin_mono(extra))
        .args(extra)
        .stdout(std::process::Stdio::null())
        .spawn()
        .expect("spawn shoal run")
}

/// Waits until `OUT/status/NAME.json` exists with counters, read as the service's counter
/// type `C`, for which `done` holds (`what` names the condition in the failure); returns the
/// status.
pub fn wait_counters<C: DeserializeOwned + Default>(
    out: &Path,
    file: &str,
    what: &str,
    done: impl Fn(&C) -> bool,
) -> Status {
    let v = wait_status_until(out, file, what, |v| {
        serde_json::from_value::<Status>(v.clone()).is_ok_and(|s| done(&s.counters_as()))
    });
    serde_json::from_value(v).expect("status")
}

/// Waits until `OUT/status/NAME.json` exists (the service wrote its status); returns it.
pub fn wait_status_written(out: &Path, file: &str) -> Status {
    let v = wait_status_until(out, file, "a status", |v| {
        serde_json::from_value::<Status>(v.clone()).is_ok()
    });
    serde_json::from_value(v).expect("status")
}

/// The counters of service `name` in report.json, as the service's counter type `C`.
pub fn service_counters<C: DeserializeOwned>(rep: &serde_json::Value, name: &str) -> C {
    let v = rep["services"][name]["counters"].clone();
    serde_json::from_value(v).unwrap_or_else(|e| panic!("counters of {name}: {e}"))
}

/// The counters a restarted service resumed from (a report.json fault's
/// `counters_at_restart`), as the service's counter type `C`.
pub fn counters_at_restart<C: DeserializeOwned>(fault: &serde_json::Value) -> C {
    let v = fault["counters_at_restart"].clone();
    serde_json::from_value(v).unwrap_or_else(|e| panic!("counters at restart: {e}: {fault}"))
}

/// The count of errors of `kind` met by service `name` in report.json (`error_counts`,
/// keyed `service/kind`).
pub fn error_count(rep: &serde_json::Value, name: &str, kind: ErrorKind) -> u64 {
    rep["error_counts"][format!("{name}/{kind}")]
        .as_u64()
        .unwrap_or(0)
}

/// Waits (at most 120 s) until `OUT/status/NAME.json` parses and `done` holds for it
/// (`what` names the condition in the failure); returns the status.
pub fn wait_status_until(
    out: &Path,
    file: &str,
    what: &str,
    done: impl Fn(&serde_json::Value) -> bool,
) -> serde_json::Value {
    let path = out.join("status").join(format!("{file}.json"));
    let start = std::time::Instant::now();
    loop {
        if let Ok(text) = std::fs::read_to_string(&path) {
            if let Ok(v) = serde_json::from_str::<serde_json::Value>(&text) {
                if done(&v) {
                    return v;
                }
            }
        }
        assert!(
            start.elapsed() < std::time::Duration::from_secs(120),
            "{file} never reached {what}"
        );
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
}

/// SIGKILL of a process of our own run (pid from its status file).
pub fn sigkill(pid: u64) {
    // SAFETY: kill(2) on a pid read from our own run's status file.
    let r = unsafe { libc::kill(pid as i32, libc::SIGKILL) };
    assert_eq!(r, 0, "SIGKILL {pid}");
}

/// Reads `OUT/report.json`.
pub fn report(out: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(out.join("report.json")).expect("report.json");
    serde_json::from_str(&text).expect("report.json is JSON")
}

/// Generates a small synthetic sequence (EuRoC layout) of `frames` frames; returns the
/// agent folders.
pub fn synthetic(
    dir: &Path,
    scenario: &str,
    frames: usize,
    readout_ms: Option<f64>,
) -> Vec<PathBuf> {
    let mut p = datasets::sim::SimParams::new(scenario.parse().expect("scenario"));
    p.frames = Some(frames);
    p.readout_ms = readout_ms;
    p.seed = 3;
    let s = datasets::sim::generate(&p, dir).expect("generate synthetic sequence");
    s.agents.into_iter().map(|a| a.dir).collect()
}

/// FNV-1a 64, the checksum of the tracker's frame log.
pub use tracker::fnv1a;

/// One frame line of a tracker frame log.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameLine {
    pub seq: u64,
    pub index: usize,
    pub t_ns: i64,
    pub readout_ns: i64,
    pub width: u32,
    pub height: u32,
    pub bytes: usize,
    pub checksum: u64,
}

/// Parses a tracker frame log: (frames, imu (seq, t_ns)).
pub fn frame_log(path: &Path) -> (Vec<FrameLine>, Vec<(u64, i64)>) {
    let text = std::fs::read_to_string(path).expect("frame log");
    let mut frames = Vec::new();
    let mut imu = Vec::new();
    for line in text.lines() {
        let f: Vec<&str> = line.split_whitespace().collect();
        match f.first() {
            Some(&"frame") => frames.push(FrameLine {
                seq: f[1].parse().unwrap(),
                index: f[2].parse().unwrap(),
                t_ns: f[3].parse().unwrap(),
                readout_ns: f[4].parse().unwrap(),
                width: f[5].parse().unwrap(),
                height: f[6].parse().unwrap(),
                bytes: f[7].parse().unwrap(),
                checksum: u64::from_str_radix(f[8], 16).unwrap(),
            }),
            Some(&"imu") => imu.push((f[1].parse().unwrap(), f[2].parse().unwrap())),
            _ => {}
        }
    }
    (frames, imu)
}

/// Checks that `frames` are exactly the dataset's frames, in order, with the right
/// timestamps, sizes and pixels.
pub fn assert_frames_match(dataset: &Path, frames: &[FrameLine]) {
    let ds = datasets::open(dataset).expect("open dataset");
    assert_eq!(
        frames.len(),
        ds.frames.len(),
        "every frame arrived exactly once"
    );
    let (w, h) = (ds.camera.model.width, ds.camera.model.height);
    let mut buf = vec![0u8; (w * h) as usize];
    for (k, (f, rec)) in frames.iter().zip(&ds.frames).enumerate() {
        assert_eq!(f.seq, k as u64, "sequence number of frame {k}");
        assert_eq!(f.index, k, "dataset index of frame {k}");
        assert_eq!(f.t_ns, rec.t_ns, "timestamp of frame {k}");
        assert_eq!(f.readout_ns, rec.readout_ns, "readout time of frame {k}");
        assert_eq!(
            (f.width, f.height, f.bytes),
            (w, h, buf.len()),
            "size of frame {k}"
        );
        datasets::decode_gray_into(&rec.path, &mut buf, w, h).expect("decode");
        assert_eq!(f.checksum, fnv1a(&buf), "pixel checksum of frame {k}");
    }
}

/// Names of the entries of `/dev/shm` that start with the iceoryx2 prefix of `test` (what
/// a run on that prefix has in shared memory), sorted.
pub fn shm_entries(test: &str) -> Vec<String> {
    let p = prefix(test);
    let mut names: Vec<String> = std::fs::read_dir("/dev/shm")
        .expect("list /dev/shm")
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(&p))
        .collect();
    names.sort();
    names
}

/// The server keyframes of every client (`OUT/keyframes_server_c{i}.txt`, client `i` on
/// `ds[i]`, all in one map) against their agents' ground truths in one evaluation with
/// `alignment`; each agent's times are shifted by 1000 s so poses never associate across
/// agents.
pub fn joint_server_eval(
    out: &Path,
    ds: &[PathBuf],
    alignment: slam_core::metrics::Alignment,
) -> slam_core::metrics::EvalResult {
    const SHIFT: i64 = 1_000_000_000_000; // 1000 s
    let (mut gt_t, mut gt_p, mut est_t, mut est_p) = (vec![], vec![], vec![], vec![]);
    for (c, d) in ds.iter().enumerate() {
        let dataset = datasets::open(d).expect("dataset");
        let gt = dataset.ground_truth.expect("ground truth");
        let est = datasets::trajectory::read_tum(&out.join(format!("keyframes_server_c{c}.txt")))
            .expect("server keyframes");
        let shift = c as i64 * SHIFT;
        gt_t.extend(gt.iter().map(|g| g.t_ns + shift));
        gt_p.extend(gt.iter().map(|g| g.pose));
        est_t.extend(est.poses.iter().map(|p| p.t_ns + shift));
        est_p.extend(est.poses.iter().map(|p| p.pose));
    }
    let params = slam_core::metrics::EvalParams {
        alignment,
        ..Default::default()
    };
    slam_core::metrics::evaluate(&gt_t, &gt_p, &est_t, &est_p, &params).expect("ATE")
}

/// The IMU stamps of a synthetic EuRoC folder (`mav0/imu0/data.csv`), ns.
pub fn imu_stamps(agent: &Path) -> Vec<i64> {
    let text = std::fs::read_to_string(agent.join("mav0/imu0/data.csv")).expect("imu0");
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| l.split(',').next()?.trim().parse().ok())
        .collect()
}

/// The report lists one map at the end, holding `clients`, metric and gravity-aligned.
pub fn check_one_metric_map(rep: &serde_json::Value, clients: &[u32]) {
    let maps = rep["maps"].as_array().expect("maps");
    assert_eq!(maps.len(), 1, "{maps:?}");
    let m = &maps[0];
    assert_eq!(m["clients"], serde_json::json!(clients), "{m}");
    assert_eq!(
        (m["metric"].as_bool(), m["gravity_aligned"].as_bool()),
        (Some(true), Some(true))
    );
}
