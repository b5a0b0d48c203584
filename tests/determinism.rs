//! Lock-step replay is reproducible (issue 15, part 1): three lock-step runs of one
//! synthetic sequence, with the local-mapping thread (the default), give byte-identical
//! per-frame trajectories and server keyframes and the same report counters (times,
//! latencies, CPU, process ids and heap figures aside).
//!
//! The sequence is the `loop` scenario (seed 3, 320 frames) with a client window of 10
//! keyframes (set in a `--config` file), so that keyframes reach the server (and its pose
//! feedback the tracker) all along the run. Without the lock-step synchronisation, three runs of it differ (client
//! keyframes 39-40, server keyframes kept 24-25, per-frame ATE 8.8-9.2 mm on one machine).
mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use common::*;

const FRAMES: usize = 320;
const RUNS: usize = 3;

/// The synthetic sequence (deterministic: same seed, same bytes).
fn sequence(dir: &Path) -> PathBuf {
    let agents = synthetic(&dir.join("agent"), "loop", FRAMES, None);
    agents[0].clone()
}

/// Report entries that measure time or the machine, not the result: left out of the
/// comparison. `frames_resent` / `frames_duplicate`: the camera ingest re-sends a frame
/// whose acknowledgement has not come within 1 s (the recovery timer for a restarted
/// tracker), which a slow machine may hit; the re-send is acknowledged and not re-tracked.
/// `outcome`: whether a service ended by itself (`done`) or was stopped by the launcher at
/// the end of the run a moment before (`stopped`), a race at shutdown.
fn is_timing(key: &str) -> bool {
    let leaf = key.rsplit('.').next().unwrap_or(key);
    let leaf = leaf.split('[').next().unwrap_or(leaf);
    key.split('.').any(|seg| seg.starts_with("latency_ms"))
        || key.contains("cpu_s")
        || leaf.ends_with("_s")
        || leaf.ends_with("_us")
        || leaf.ends_with("_ms")
        || leaf.ends_with("_per_s")
        || leaf.contains("heap")
        || leaf == "pid"
        || leaf == "plot"
        || leaf == "trajectory"
        || leaf == "recovery_s"
        || leaf == "frames_resent"
        || leaf == "frames_duplicate"
        || leaf == "outcome"
}

/// The report flattened to `path = value`, each `(run-specific text, placeholder)` of `subst`
/// replaced in the values (the output folder, the iceoryx2 prefix: they differ by design).
fn flatten(
    v: &serde_json::Value,
    path: &str,
    subst: &[(String, &str)],
    acc: &mut BTreeMap<String, String>,
) {
    match v {
        serde_json::Value::Object(m) => {
            for (k, x) in m {
                let p = if path.is_empty() {
                    k.clone()
                } else {
                    format!("{path}.{k}")
                };
                flatten(x, &p, subst, acc);
            }
        }
        serde_json::Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                flatten(x, &format!("{path}[{i}]"), subst, acc);
            }
        }
        _ => {
            if !is_timing(path) {
                let text = subst
                    .iter()
                    .fold(v.to_string(), |t, (from, to)| t.replace(from.as_str(), to));
                acc.insert(path.to_string(), text);
            }
        }
    }
}

fn read(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn lockstep_runs_with_mapping_thread_are_identical() {
    let tmp = tempdir();
    let seq = sequence(tmp.path());
    // The client window comes from a user's configuration file (`shoal run --config`),
    // which the launcher hands to the tracker whole (`OUT/config/tracker_c0.toml`).
    let config = tmp.path().join("shoal.toml");
    std::fs::write(&config, "mode = \"lockstep\"\n\n[tracker]\nwindow = 10\n").expect("config");
    let config = config.to_str().expect("utf-8 path").to_string();
    let mut runs = Vec::new();
    for r in 0..RUNS {
        let out = tmp.path().join(format!("run{r}"));
        let res = run_pipeline(&[&seq], &out, &format!("det{r}"), &["--config", &config]);
        assert!(res.status.success(), "run {r} failed");
        let tracker_cfg = std::fs::read_to_string(out.join("config/tracker_c0.toml"))
            .expect("the tracker's configuration file");
        assert!(tracker_cfg.contains("window = 10"), "{tracker_cfg}");
        let rep = report(&out);
        assert_eq!(rep["provenance"]["config"]["tracker"]["window"], 10);
        let c = &rep["clients"][0];
        assert_eq!(c["frames_received"], FRAMES as u64, "run {r}");
        // The server took part: keyframes were sent, kept and forwarded to loop closing,
        // and pose feedback reached the tracker during the run.
        assert!(
            c["keyframes_kept"].as_u64().unwrap_or(0) >= 10,
            "run {r}: {c}"
        );
        assert!(
            c["loop_keyframes_received"].as_u64().unwrap_or(0) >= 10,
            "run {r}"
        );
        assert!(
            c["frames_server_pose"].as_u64().unwrap_or(0) >= 50,
            "run {r}"
        );
        let ate = c["ate"]["rmse_m"].as_f64().expect("ATE");
        assert!(ate < 0.05, "run {r}: ATE {ate} m");
        let mut counters = BTreeMap::new();
        let prefix = rep["provenance"]["config"]["ipc_prefix"]
            .as_str()
            .expect("provenance.config.ipc_prefix")
            .to_string();
        let subst = [(out.display().to_string(), "OUT"), (prefix, "PREFIX")];
        flatten(&rep, "", &subst, &mut counters);
        runs.push((out, counters));
    }
    let (first, first_counters) = &runs[0];
    for (out, counters) in &runs[1..] {
        let files: Vec<&str> = [
            "trajectory_c0.txt",
            "keyframes_server_c0.txt",
            "trajectory_server_c0.txt",
        ]
        .into_iter()
        .filter(|f| read(&first.join(f)) != read(&out.join(f)))
        .collect();
        assert!(
            files.is_empty(),
            "{files:?} differ between {} and {}",
            first.display(),
            out.display()
        );
        let diff: Vec<String> = first_counters
            .iter()
            .filter(|(k, v)| counters.get(*k) != Some(*v))
            .map(|(k, v)| format!("{k}: {v} vs {:?}", counters.get(k)))
            .chain(
                counters
                    .keys()
                    .filter(|k| !first_counters.contains_key(*k))
                    .map(|k| format!("{k}: only in {}", out.display())),
            )
            .collect();
        assert!(diff.is_empty(), "report differs:\n{}", diff.join("\n"));
    }
    // What the report says about it: the default mapping thread, synchronised, no wait
    // timed out.
    for (out, _) in &runs {
        let c = &report(out)["clients"][0];
        assert_eq!(c["local_mapping"], "thread", "{c}");
        assert_eq!(c["lockstep_sync"], true, "{c}");
        assert_eq!(c["lockstep_sync_timeouts"], 0, "a wait timed out: {c}");
    }
}

#[test]
fn lockstep_sync_off_is_reported() {
    let tmp = tempdir();
    let seq = sequence(tmp.path());
    let out = tmp.path().join("run");
    let res = run_pipeline(
        &[&seq],
        &out,
        "detoff",
        &[
            "--lockstep",
            "--max-frames",
            "60",
            "--tracker-arg=--no-lockstep-sync",
            "--tracker-arg=--inline-mapping",
        ],
    );
    assert!(res.status.success());
    let c = &report(&out)["clients"][0];
    assert_eq!(c["local_mapping"], "inline", "{c}");
    assert_eq!(c["lockstep_sync"], false, "{c}");
    assert_eq!(c["frames_received"], 60);
}
