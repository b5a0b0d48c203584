//! The mapper end to end (issue 4), real processes on synthetic sequences: the server map
//! of a client is more accurate than its VO keyframes, the client reports its pose in the
//! server map from the mapper's feedback, two clients get a server map each, and (ignored,
//! a benchmark) on the full two-lap `loop` the server map grows little on the second lap.
mod common;

use std::path::Path;

use common::*;
use mapper::MapperCounters;

/// RMSE (m) of the ATE entry `key` of a client report.
fn ate(c: &serde_json::Value, key: &str) -> f64 {
    c[key]["rmse_m"]
        .as_f64()
        .unwrap_or_else(|| panic!("{key} missing in {c:#}"))
}

fn u(v: &serde_json::Value) -> u64 {
    v.as_u64().unwrap_or_else(|| panic!("not a count: {v}"))
}

/// Times (ns) of a TUM file written by shoal (`seconds.nanoseconds ...`).
fn tum_times(path: &Path) -> Vec<i64> {
    let text = std::fs::read_to_string(path).expect("TUM file");
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let t = l.split_whitespace().next().expect("time");
            let (s, ns) = t.split_once('.').expect("seconds.nanoseconds");
            s.parse::<i64>().expect("s") * 1_000_000_000 + ns.parse::<i64>().expect("ns")
        })
        .collect()
}

/// Checks the mapper figures of client `c` and returns (client kf ATE, server kf ATE,
/// per-frame server ATE).
fn check_client(r: &serde_json::Value, out: &Path, c: usize) -> (f64, f64, f64) {
    let cl = &r["clients"][c];
    let sent = u(&cl["keyframes_sent"]);
    assert!(sent >= 10, "client {c} sent {sent} keyframes");
    assert_eq!(u(&cl["keyframes_applied"]), sent, "every keyframe applied");
    assert_eq!(
        u(&cl["keyframes_acked"]),
        sent,
        "every keyframe acknowledged"
    );
    assert!(u(&cl["keyframes_received"]) >= sent);
    let kept = u(&cl["keyframes_kept"]);
    let in_map = u(&cl["server_keyframes"]);
    assert!(
        kept >= 5 && in_map >= 5 && in_map <= kept,
        "kept {kept}, in map {in_map}"
    );
    assert!(cl["keyframe_bytes_per_s"].as_f64().unwrap_or(0.0) > 0.0);
    let counters: MapperCounters = service_counters(r, "mapper");
    assert_eq!(
        counters.client(c as u32).maps,
        1,
        "one server map per client"
    );
    let server_kfs = tum_times(&out.join(format!("keyframes_server_c{c}.txt")));
    assert_eq!(server_kfs.len() as u64, in_map);
    // Per-frame poses in the server map, from the feedback.
    let frames = u(&cl["frames_tracked"]);
    let with_server = u(&cl["frames_server_pose"]);
    assert!(
        with_server * 2 > frames,
        "client {c}: {with_server} of {frames} frames have a server pose"
    );
    assert!(out.join(format!("trajectory_server_c{c}.txt")).is_file());
    (
        ate(cl, "ate_client_keyframes"),
        ate(cl, "ate_server_keyframes"),
        ate(cl, "ate_server_frames"),
    )
}

#[test]
fn server_map_pose_feedback_and_journal_replay_on_loop() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "loop", 400, None);
    let out = dir.path().join("out");
    let o = run_pipeline(
        &[&ds[0]],
        &out,
        "mapper_loop",
        &["--tracker-arg=--window=10"],
    );
    assert!(o.status.success(), "shoal run failed");
    let r = report(&out);
    assert_eq!(
        r["error_counts"].as_object().map_or(0, |m| m.len()),
        0,
        "{r:#}"
    );
    assert_eq!(u(&r["mapper"]["maps"]), 1);
    assert!(u(&r["mapper"]["points"]) > 200);
    let (client_kf, server_kf, server_frames) = check_client(&r, &out, 0);
    let client_frames = ate(&r["clients"][0], "ate");
    eprintln!(
        "ATE (Sim3) client kfs {client_kf:.4} m, server kfs {server_kf:.4} m, per-frame \
         server poses {server_frames:.4} m (client frames {client_frames:.4} m)"
    );
    // Over 400 frames (no revisit yet) the server keyframes are about as accurate as the
    // client's (measured 0.007-0.014 m either way round, the VO's timing varies between
    // runs); "better" is checked on the full two laps (ignored test below).
    assert!(
        server_kf < 2.0 * client_kf.max(0.005),
        "server keyframes {server_kf} vs client keyframes {client_kf}"
    );
    // The per-frame server pose composes the VO motion since the fed-back keyframe (up to a
    // window of keyframes back, scaled by lambda) with its server pose: worse than the
    // client's own trajectory (measured 0.04 m = 0.3% of the path vs 0.01 m) but within 1%
    // of the distance travelled; a wrong composition is off by metres.
    let pct = r["clients"][0]["ate_server_frames"]["rmse_percent"]
        .as_f64()
        .expect("percent");
    assert!(
        pct < 1.0,
        "per-frame server poses {server_frames} m = {pct:.2}% of the path"
    );
    // The journal holds every applied keyframe; a mapper started on it rebuilds the same map.
    let journal = std::fs::metadata(out.join("mapper_journal.bin")).expect("journal");
    assert!(journal.len() > 10 * 64 * 100);
    let rebuilt = dir.path().join("rebuilt");
    std::fs::create_dir_all(&rebuilt).expect("dir");
    std::fs::copy(out.join("mapper_journal.bin"), rebuilt.join("j.bin")).expect("copy");
    let status = rebuilt.join("status.json");
    let mut child = shoal()
        .args(["service", "mapper", "--clients", "1", "--journal"])
        .arg(rebuilt.join("j.bin"))
        .arg("--out")
        .arg(&rebuilt)
        .arg("--status")
        .arg(&status)
        .env("SHOAL_IPC_PREFIX", prefix("mapper_replay"))
        .stdout(std::process::Stdio::null())
        .spawn()
        .expect("start mapper");
    let applied = u(&r["clients"][0]["keyframes_applied"]);
    let start = std::time::Instant::now();
    loop {
        let replayed = std::fs::read_to_string(&status)
            .ok()
            .and_then(|t| serde_json::from_str::<Status>(&t).ok())
            .map(|s| {
                s.counters_as::<MapperCounters>()
                    .client(0)
                    .keyframes_replayed
            });
        if replayed == Some(applied) || start.elapsed().as_secs() > 120 {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    // SAFETY: plain kill(2) on our own child's pid.
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    assert!(child.wait().expect("mapper exit").success());
    remove_counter_segment(&prefix("mapper_replay"));
    let a = std::fs::read_to_string(out.join("keyframes_server_c0.txt")).expect("run");
    let b = std::fs::read_to_string(rebuilt.join("keyframes_server_c0.txt")).expect("rebuilt");
    assert_eq!(a, b, "the replayed journal gives the same server keyframes");
}

#[test]
fn two_clients_get_their_own_server_maps() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "two-agents", 240, None);
    assert_eq!(ds.len(), 2);
    let out = dir.path().join("out");
    let o = run_pipeline(
        &[&ds[0], &ds[1]],
        &out,
        "mapper_two",
        &["--tracker-arg=--window=10"],
    );
    assert!(o.status.success(), "shoal run failed");
    let r = report(&out);
    assert_eq!(u(&r["mapper"]["maps"]), 2, "{:#}", r["mapper"]);
    let mut sum = 0;
    for c in 0..2 {
        let (ck, sk, sf) = check_client(&r, &out, c);
        eprintln!("client {c}: ATE client kfs {ck:.4} m, server kfs {sk:.4} m, frames {sf:.4} m");
        sum += u(&r["clients"][c]["server_keyframes"]);
    }
    assert_eq!(u(&r["mapper"]["keyframes"]), sum);
}

/// The full two laps of `loop` (1280 frames; a few minutes): run with
/// `cargo test --release --test mapper -- --ignored --nocapture`.
#[test]
#[ignore]
fn second_lap_grows_the_server_map_little() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "loop", 1280, None);
    let out = dir.path().join("out");
    let o = run_pipeline(
        &[&ds[0]],
        &out,
        "mapper_laps",
        &["--tracker-arg=--window=10"],
    );
    assert!(o.status.success(), "shoal run failed");
    let r = report(&out);
    let (ck, sk, sf) = check_client(&r, &out, 0);
    let data = datasets::open(&ds[0]).expect("dataset");
    let lap2 = data.frames[640].t_ns;
    let client = tum_times(&out.join("keyframes_client_c0.txt"));
    let client_lap1 = client.iter().filter(|t| **t < lap2).count();
    let client_lap2 = client.len() - client_lap1;
    let growth_log = std::fs::read_to_string(out.join("map_growth_c0.txt")).expect("growth");
    let rows: Vec<(i64, usize)> = growth_log
        .lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            Some((f.first()?.parse().ok()?, f.get(1)?.parse().ok()?))
        })
        .collect();
    let at_lap1 = rows.iter().rfind(|r| r.0 < lap2).expect("lap 1").1;
    let at_end = rows.last().expect("rows").1;
    let growth = at_end as f64 / at_lap1 as f64 - 1.0;
    eprintln!(
        "client keyframes lap 1 {client_lap1}, lap 2 {client_lap2}; server map {at_lap1} at \
         the end of lap 1, {at_end} at the end ({:.1}%); ATE client kfs {ck:.4} m, server \
         kfs {sk:.4} m, per-frame server poses {sf:.4} m",
        100.0 * growth
    );
    assert!(client_lap2 as f64 > 0.8 * client_lap1 as f64);
    assert!(
        growth < 0.2,
        "server map grew {:.1}% on lap 2",
        100.0 * growth
    );
    assert!(sk < ck);
}
