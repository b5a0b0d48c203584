//! Fault injection in a visual-inertial two-agent run (issue 19's fault target): every
//! service SIGKILLed once while two visual-inertial clients (`four-agents` agents 0 and 1,
//! one lap each, lock-step, a 10-keyframe client window so that keyframes reach the server
//! all along) build one metric map. Checked: the run completes and every killed service was
//! restarted and recovered; no keyframe is lost (sent == applied, each acknowledged or sent
//! by a tracker killed before it saw the acknowledgement); no IMU segment is lost (in the
//! mapper's journal every keyframe of a client after its session's first carries the IMU
//! samples since the previous one, the segments tile the session's time, and the server
//! keyframes of each client stay linked by them); one metric, gravity-aligned map at the
//! end; the joint server keyframe ATE (SE(3)) within 20% of the fault-free figure.
//!
//! The fault-free figure is not one run's: two lock-step clients are not bit-deterministic
//! (each tracker is locked to its own stream, not to the other's, so their keyframes reach
//! the server in an order scheduling decides), and the joint SE(3) ATE of this data is
//! spread over fault-free runs (release, 15 runs: 0.0198-0.0617 m, median 0.0337 m, in
//! modes: 0.020-0.025 m when the visual global BA after the merge leaves the map's scale at
//! 0.996-0.997, 0.033 m at 0.994, 0.056-0.062 m at 0.988-0.989; BENCHMARKS.md, issue 19,
//! "Faults"). A 20% bound on one run against one other run
//! would test which mode each landed in, so the bound is 20% above the upper end of that
//! spread, or of this build's own fault-free run if higher. The full "each service once"
//! measurement, one kill per run: `benches/vi_faults.py` (session 20, with the global VI
//! BA: fault-free 0.0387-0.0419 m over 5 runs, the six kills 0.0373-0.0438 m).
//!
//! Two runs with kills, several services each (`--kill` repeated), plus the shared
//! fault-free run: 3.1 minutes of the test profile on 2 cores (4.4 when the data is
//! rendered, once per build).
mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use camera_ingest::CameraCounters;
use common::*;
use imu_ingest::ImuCounters;
use loop_closer::LoopCloserCounters;
use mapper::MapperCounters;
use shoal_runtime::journal::{read_journal, Entry};
use slam_core::metrics::Alignment;
use tracker::core::TrackerCounters;

/// Frames per agent (one 32 s lap at 20 Hz).
const FRAMES: u64 = 640;
/// Run options besides the kills: lock-step, both clients visual-inertial, a 10-keyframe
/// VO window (the default 100 would hold every keyframe of the lap until the end of the
/// stream, and the server would see nothing while the services are killed).
const ARGS: [&str; 5] = ["--lockstep", "--mode", "vio", "--set", "tracker.window=10"];
/// Upper end of the fault-free joint server keyframe SE(3) ATE of this data, m (release,
/// 15 runs; module docs).
const FAULT_FREE_SPREAD_MAX_M: f64 = 0.0617;
/// A run with kills may exceed the fault-free figure by this factor (the 20%).
const ATE_FACTOR: f64 = 1.2;

/// The two agents' sequences, rendered once per build (deterministic: seed 3).
fn agents() -> &'static [PathBuf] {
    static SEQ: OnceLock<Vec<PathBuf>> = OnceLock::new();
    SEQ.get_or_init(|| {
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("vi_faults_4a{FRAMES}"));
        if !dir.join("complete").is_file() {
            let tmp = dir.with_extension(format!("tmp{}", std::process::id()));
            let _ = std::fs::remove_dir_all(&tmp);
            synthetic(&tmp, "four-agents", FRAMES as usize, None);
            std::fs::write(tmp.join("complete"), b"").expect("marker");
            let _ = std::fs::remove_dir_all(&dir);
            if std::fs::rename(&tmp, &dir).is_err() {
                // Another test process renamed its copy first: same bytes, use it.
                let _ = std::fs::remove_dir_all(&tmp);
            }
        }
        let agents: Vec<PathBuf> = (0..2).map(|i| dir.join(format!("agent{i}"))).collect();
        for a in &agents {
            assert!(a.is_dir(), "{} missing", a.display());
        }
        agents
    })
}

/// A finished run: its report and output folder.
struct Run {
    rep: serde_json::Value,
    out: tempfile::TempDir,
}

/// Runs both agents with `kills` (`SERVICE@fN` each).
fn run(test: &str, kills: &[&str]) -> Run {
    let out = tempdir();
    let mut args: Vec<&str> = ARGS.to_vec();
    for k in kills {
        args.extend(["--kill", k]);
    }
    let ds = agents();
    let o = run_pipeline(&[&ds[0], &ds[1]], out.path(), test, &args);
    assert!(o.status.success(), "{test}: shoal run failed");
    Run {
        rep: report(out.path()),
        out,
    }
}

/// The fault-free run, once for all the tests of this file, with its joint server ATE.
fn baseline() -> &'static (Run, f64) {
    static BASE: OnceLock<(Run, f64)> = OnceLock::new();
    BASE.get_or_init(|| {
        let r = run("vif_base", &[]);
        assert!(r.rep["faults"].as_array().is_some_and(|f| f.is_empty()));
        check_run(&r, &[]);
        let ate = joint_se3(&r);
        eprintln!("fault-free: joint server keyframe SE(3) ATE {ate:.4} m");
        (r, ate)
    })
}

fn u(v: &serde_json::Value) -> u64 {
    v.as_u64().unwrap_or_else(|| panic!("not a count: {v}"))
}

/// The joint SE(3) ATE of both clients' server keyframes against their ground truths, m.
fn joint_se3(r: &Run) -> f64 {
    joint_server_eval(r.out.path(), agents(), Alignment::Se3)
        .ape
        .rmse
}

/// Everything a run with `killed` services (report names) must show, killed or not.
fn check_run(r: &Run, killed: &[&str]) {
    let rep = &r.rep;
    assert_eq!(rep["timed_out"], false);
    assert_eq!(rep["interrupted"], false);
    check_faults(rep, killed);
    for c in 0..2 {
        let tracker_killed = killed.contains(&format!("tracker:{c}").as_str());
        check_no_keyframe_lost(rep, c, tracker_killed);
        check_segments(r, c);
    }
    check_one_metric_map(rep, &[0, 1]);
}

/// Each service in `killed` was killed once, restarted and recovered; no other kill, no
/// unfired one, no service failed or gave up.
fn check_faults(rep: &serde_json::Value, killed: &[&str]) {
    let faults = rep["faults"].as_array().expect("faults");
    let mut names: Vec<&str> = faults
        .iter()
        .filter_map(|f| f["service"].as_str())
        .collect();
    names.sort();
    let mut want = killed.to_vec();
    want.sort();
    assert_eq!(names, want, "{faults:#?}");
    for f in faults {
        assert!(
            f["recovery_s"].as_f64().is_some_and(|r| r > 0.0),
            "recovered: {f}"
        );
        let s = f["service"].as_str().expect("name");
        assert!(u(&rep["services"][s]["restarts"]) >= 1, "{s} restarted");
    }
    let summary = &rep["faults_summary"];
    assert_eq!(u(&summary["kills"]), killed.len() as u64, "{summary}");
    assert_eq!(u(&summary["recovered"]), killed.len() as u64, "{summary}");
    assert_eq!(u(&summary["unfired"]), 0, "{}", rep["faults_unfired"]);
    for (name, s) in rep["services"].as_object().expect("services") {
        assert_ne!(s["outcome"], "failed", "{name} failed: {s:#}");
    }
    let gave_up = format!("/{}", ErrorKind::GaveUp);
    for k in rep["error_counts"].as_object().expect("errors").keys() {
        assert!(!k.ends_with(&gave_up), "{k}: {:#}", rep["errors"]);
    }
}

/// Client `c`: every frame handled, every keyframe sent applied and acknowledged (or sent
/// by a tracker killed before it saw the acknowledgement, when `tracker_killed`).
fn check_no_keyframe_lost(rep: &serde_json::Value, c: usize, tracker_killed: bool) {
    let cl = &rep["clients"][c];
    assert_eq!(u(&cl["frames_received"]), FRAMES, "client {c}: {cl:#}");
    assert_eq!(u(&cl["frames_dropped"]), 0, "client {c}");
    let sent = u(&cl["keyframes_sent"]);
    assert!(sent >= 40, "client {c}: {sent} keyframes sent");
    assert_eq!(u(&cl["keyframes_applied"]), sent, "client {c}: {cl:#}");
    let at_crash = u(&cl["keyframes_unacked_at_crash"]);
    assert_eq!(u(&cl["keyframes_acked"]) + at_crash, sent, "client {c}");
    if !tracker_killed {
        assert_eq!(at_crash, 0, "client {c}");
    }
}

/// A journaled keyframe: session, IMU time, and its segment's border times and records.
#[derive(Debug, Clone, Copy)]
struct Journaled {
    session: u32,
    imu_t_ns: i64,
    seg: Option<(i64, i64, u32)>,
}

/// Client `c`'s keyframes in the mapper's journal, each once, in (session, time) order.
fn journaled(out: &Path, c: u32) -> Vec<Journaled> {
    let j = read_journal(&out.join("mapper_journal.bin")).expect("journal");
    let mut by_key: BTreeMap<(u32, i64), Journaled> = BTreeMap::new();
    for e in j.entries {
        let Entry::Keyframe { client, header, .. } = e else {
            continue;
        };
        if client != c {
            continue;
        }
        let h = *header;
        assert_eq!(
            h.has_imu, 1,
            "client {c}: keyframe {} without IMU",
            h.keyframe_id
        );
        let k = Journaled {
            session: h.meta.session_id,
            imu_t_ns: h.imu_t1_ns,
            seg: (h.n_imu > 0).then_some((h.imu_t0_ns, h.imu_t1_ns, h.n_imu)),
        };
        by_key.entry((k.session, k.imu_t_ns)).or_insert(k);
    }
    by_key.into_values().collect()
}

/// No IMU segment of client `c` lost: in the journal every keyframe after its session's
/// first starts its segment where the previous one ended and holds every sample of the
/// stream in between (plus the two interpolated borders), the report counts them, and the
/// client's server keyframes are all linked by their segments (`imu_segments_server_c{c}`).
fn check_segments(r: &Run, c: usize) {
    let kfs = journaled(r.out.path(), c as u32);
    let stamps = imu_stamps(&agents()[c]);
    let mut sessions = 0;
    for (i, k) in kfs.iter().enumerate() {
        let prev = i
            .checked_sub(1)
            .map(|p| kfs[p])
            .filter(|p| p.session == k.session);
        let Some(p) = prev else {
            sessions += 1;
            continue;
        };
        let (t0, t1, n) = k
            .seg
            .unwrap_or_else(|| panic!("client {c}: keyframe at {} has no segment", k.imu_t_ns));
        assert_eq!(
            (t0, t1),
            (p.imu_t_ns, k.imu_t_ns),
            "client {c}: segment tiles"
        );
        let inside = stamps.iter().filter(|t| **t > t0 && **t < t1).count();
        assert_eq!(
            n as usize,
            inside + 2,
            "client {c}: every sample of [{t0}, {t1}]"
        );
    }
    let cl = &r.rep["clients"][c];
    assert_eq!(sessions, 1, "client {c}: one session");
    assert_eq!(
        u(&cl["keyframes_with_imu"]),
        kfs.len() as u64 - 1,
        "client {c}"
    );
    let samples: u64 = kfs
        .iter()
        .filter_map(|k| k.seg)
        .map(|s| u64::from(s.2))
        .sum();
    assert_eq!(u(&cl["keyframe_imu_samples"]), samples, "client {c}");
    assert_eq!(u(&cl["imu_segments_refused"]), 0, "client {c}");
    let linked = server_links(r.out.path(), c);
    assert!(linked >= 15, "client {c}: {linked} linked server keyframes");
    let m: MapperCounters = service_counters(&r.rep, "mapper");
    let windows = m.client(c as u32).vi_windows;
    assert!(
        windows >= 3,
        "client {c}: {windows} visual-inertial local BAs"
    );
}

/// `imu_segments_server_c{c}.txt`: every server keyframe of the client after its first is
/// linked to the one before it by its segment; returns how many.
fn server_links(out: &Path, c: usize) -> usize {
    let path = out.join(format!("imu_segments_server_c{c}.txt"));
    let text = std::fs::read_to_string(path).expect("server segments");
    let rows: Vec<Vec<i64>> = text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split(' ').map(|v| v.parse().expect("number")).collect())
        .collect();
    for w in rows.windows(2) {
        let (a, b) = (&w[0], &w[1]);
        assert_eq!(
            b[6], 1,
            "client {c}: server keyframe at {} not linked",
            b[0]
        );
        assert_eq!(b[1], a[2], "client {c}: starts where the previous one ends");
    }
    rows.len().saturating_sub(1)
}

/// The joint server keyframe ATE is within [`ATE_FACTOR`] of the fault-free figure.
fn check_ate(r: &Run, what: &str) {
    let ate = joint_se3(r);
    let base = baseline().1;
    let reference = base.max(FAULT_FREE_SPREAD_MAX_M);
    let sim3 = joint_server_eval(r.out.path(), agents(), Alignment::Sim3);
    eprintln!(
        "{what}: joint server keyframe SE(3) ATE {ate:.4} m (Sim(3) {:.4} m, scale {:.4}); \
         fault-free {base:.4} m, spread up to {FAULT_FREE_SPREAD_MAX_M} m",
        sim3.ape.rmse, sim3.alignment.scale
    );
    assert!(
        ate <= ATE_FACTOR * reference,
        "{what}: joint server keyframe SE(3) ATE {ate} m > {ATE_FACTOR} × {reference} m"
    );
}

/// The kill of `service` in `rep`.
fn fault<'a>(rep: &'a serde_json::Value, service: &str) -> &'a serde_json::Value {
    rep["faults"]
        .as_array()
        .and_then(|f| f.iter().find(|f| f["service"] == service))
        .unwrap_or_else(|| panic!("no kill of {service}"))
}

/// Client 0's tracker, twice (before and after the mapper), and the mapper. Each of the
/// tracker's successors resumes client 0's session from the spool (the second one from a
/// spool its predecessor, itself a successor, wrote): the spooled keyframes are rebuilt
/// with their IMU segments and sent with them when they leave the window, and the IMU
/// ingest replays the samples since the session's newest keyframe, so the next keyframe's
/// segment starts there (one session, the segments tile it, none lost or overlapping).
/// The restarted mapper rebuilds its maps from the journal and takes the keyframes re-sent
/// to it. Measured (test profile): 0.0307 m, fault-free 0.0390 m.
#[test]
fn kill_tracker_and_mapper() {
    const KILLED: [&str; 3] = ["tracker:0", "mapper", "tracker:0"];
    let r = run(
        "vif_trk_map",
        &["tracker:0@f240", "mapper@f420", "tracker:0@f520"],
    );
    check_run(&r, &KILLED);
    let rep = &r.rep;
    let trk: TrackerCounters = service_counters(rep, "tracker:0");
    assert_eq!(trk.vio_resumes, 2, "{trk:?}");
    assert!(trk.keyframes_resumed >= 10, "{trk:?}");
    assert_eq!(trk.imu_replays_asked, 2, "{trk:?}");
    let imu: ImuCounters = service_counters(rep, "imu_ingest:0");
    assert_eq!(imu.imu_replays, 2, "{imu:?}");
    assert!(imu.imu_samples_replayed > 0, "{imu:?}");
    assert_eq!(error_count(rep, "tracker:0", ErrorKind::VioResume), 0);
    let vio = &rep["clients"][0]["vio"];
    assert_eq!(vio["resumed"], 2, "{vio}");
    let before: MapperCounters = counters_at_restart(fault(rep, "mapper"));
    let applied_before = before.client(0).keyframes_applied;
    assert!(
        applied_before > 0,
        "keyframes applied before the mapper kill"
    );
    let m: MapperCounters = service_counters(rep, "mapper");
    assert!(
        m.client(0).keyframes_replayed >= applied_before,
        "the journal was replayed: {m:?}"
    );
    check_ate(&r, "tracker:0 and mapper killed");
}

/// Client 0's IMU ingest, client 1's camera ingest and the loop closer: the ingests
/// resume where their status said, the loop closer rebuilds its database from the mapper
/// (resync) and still merges the two clients' maps.
#[test]
fn kill_ingests_and_loop_closer() {
    const KILLED: [&str; 3] = ["imu_ingest:0", "camera_ingest:1", "loop_closer"];
    let r = run(
        "vif_ing_lc",
        &[
            "imu_ingest:0@f200",
            "camera_ingest:1@f300",
            "loop_closer@f400",
        ],
    );
    check_run(&r, &KILLED);
    let rep = &r.rep;
    let imu: ImuCounters = counters_at_restart(fault(rep, "imu_ingest:0"));
    assert!(imu.imu_samples_published > 0, "resumed");
    let cam: CameraCounters = counters_at_restart(fault(rep, "camera_ingest:1"));
    assert!(cam.frames_published > 0, "resumed");
    let lc: LoopCloserCounters = service_counters(rep, "loop_closer");
    assert!(lc.resync_keyframes > 0, "resynchronised: {lc:?}");
    check_ate(&r, "imu_ingest:0, camera_ingest:1 and loop_closer killed");
}
