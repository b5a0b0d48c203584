//! The end-of-run summary on the terminal (shared by `shoal run` and `shoal demo`): per
//! client what got a pose, the keyframes, the accuracy against ground truth when the dataset
//! has it, the latency and the files written; then the server, the faults and where the
//! report is. Warnings (a `--kill` that never fired) go to stderr.
use std::fmt::Write as _;
use std::path::Path;

use super::report::{AteReport, ClientReport, RunReport};

/// Prints the summary of `rep` (output folder `out`) to stdout and its warnings to stderr.
pub fn print(rep: &RunReport, out: &Path) {
    print!("{}", text(rep, out));
    for w in warnings(rep) {
        eprintln!("warning: {w}");
    }
}

/// The warnings of a run: every fault injection that killed nothing.
pub fn warnings(rep: &RunReport) -> Vec<String> {
    rep.faults_unfired
        .iter()
        .map(|u| format!("{} never fired: {}", u.spec, u.reason))
        .collect()
}

/// The summary text (every line ends with a newline).
pub fn text(rep: &RunReport, out: &Path) -> String {
    let p = &rep.provenance;
    let mut s = String::new();
    let commit: String = p.git_commit.chars().take(12).collect();
    let dirty = if p.git_dirty == Some(true) {
        "+dirty"
    } else {
        ""
    };
    let _ = writeln!(
        s,
        "shoal {} ({commit}{dirty}, schema v{}), {} replay, {} client(s), wall time {:.1} s{}",
        rep.shoal_version,
        rep.schema_version,
        rep.mode,
        rep.clients.len(),
        rep.wall_time_s,
        end_note(rep)
    );
    for (c, cl) in rep.clients.iter().enumerate() {
        client_lines(&mut s, c, cl);
    }
    let m = &rep.mapper;
    match remote_server_line(rep) {
        Some(line) => s.push_str(&line),
        None => {
            let _ = writeln!(
                s,
                "server: {} map(s), {} keyframes, {} points; {} loop(s), {} merge(s), {} \
                 correction(s) applied",
                m.maps, m.keyframes, m.points, rep.loops, rep.merges, rep.corrections_applied
            );
        }
    }
    faults_line(&mut s, rep);
    let restarts: u32 = rep.services.values().map(|s| s.restarts).sum();
    let _ = writeln!(
        s,
        "{} services, {restarts} restarts, {} errors",
        rep.services.len(),
        rep.error_total()
    );
    let _ = writeln!(s, "report: {}", out.join("report.json").display());
    s
}

fn end_note(rep: &RunReport) -> &'static str {
    match (rep.interrupted, rep.timed_out) {
        (true, _) => " (interrupted)",
        (_, true) => " (stopped by --max-seconds)",
        _ => "",
    }
}

/// Replayed frames: those that got a pose, were dropped, or were corrupt.
fn replayed(cl: &ClientReport) -> u64 {
    cl.frames_received + cl.frames_dropped + cl.frames_corrupt
}

/// `shoal client`: the remote server's acknowledgements and the round trips, in place of
/// the (absent) local server's line.
fn remote_server_line(rep: &RunReport) -> Option<String> {
    let bridges: Vec<_> = (rep.bridges.iter())
        .filter(|(name, _)| name.starts_with("bridge:"))
        .collect();
    if bridges.is_empty() {
        return None;
    }
    let mut s = String::new();
    for ((name, b), cl) in bridges.iter().zip(&rep.clients) {
        let ms = |us: Option<u64>| us.map_or("-".into(), |u| format!("{:.1}", u as f64 * 1e-3));
        let _ = writeln!(
            s,
            "server (remote, {name} slot {}): {} of {} keyframes acknowledged by its mapper; \
             round trip p50 {} ms, p99 {} ms; {} keyframe messages sent ({:.1} kB each), {} \
             dropped while no server answered",
            b.slot.map_or("-".into(), |v| v.to_string()),
            cl.keyframes_acked,
            cl.keyframes_sent,
            ms(b.roundtrip_us_p50),
            ms(b.roundtrip_us_p99),
            b.keyframes_forwarded,
            b.keyframe_bytes as f64 / b.keyframes_forwarded.max(1) as f64 * 1e-3,
            b.keyframes_unsent
        );
    }
    Some(s)
}

fn client_lines(s: &mut String, c: usize, cl: &ClientReport) {
    let _ = writeln!(
        s,
        "client {c}: {}/{} frames posed ({} tracked, {} backfilled); unposed: {} before \
         initialisation, {} lost, {} dropped, {} corrupt; keyframes {} sent, {} applied \
         ({:.2}/s, {:.1} kB each, {} with an IMU segment)",
        cl.frames_posed,
        replayed(cl),
        cl.frames_tracked,
        cl.frames_backfilled,
        cl.frames_unposed.before_init,
        cl.frames_unposed.lost,
        cl.frames_unposed.dropped,
        cl.frames_unposed.corrupt,
        cl.keyframes_sent,
        cl.keyframes_applied,
        cl.keyframes_per_s,
        cl.keyframe_bytes_mean * 1e-3,
        cl.keyframes_with_imu
    );
    mode_line(s, cl);
    // The Sim(3) figures, with the SE(3) ATE (no scale correction) when there is one.
    let acc = |name: &str, a: &Option<AteReport>, se3: &Option<AteReport>| {
        a.as_ref().map(|a| {
            let rpe = a
                .rpe_rmse_m
                .map_or(String::new(), |r| format!(", RPE {r:.4} m"));
            let se3 = se3
                .as_ref()
                .map_or(String::new(), |e| format!("; se3 ATE {:.4} m", e.rmse_m));
            format!(
                "{name} ATE {:.4} m ({:.2}% of {:.1} m, {} poses, scale {:.3}{se3}){rpe}",
                a.rmse_m, a.rmse_percent, a.path_length_m, a.n, a.scale
            )
        })
    };
    let accuracy: Vec<String> = [
        acc("frames", &cl.ate, &cl.ate_se3),
        acc(
            "server keyframes",
            &cl.ate_server_keyframes,
            &cl.ate_server_keyframes_se3,
        ),
    ]
    .into_iter()
    .flatten()
    .collect();
    if accuracy.is_empty() {
        let _ = writeln!(s, "  accuracy: no ground truth or too few poses");
    } else {
        let _ = writeln!(s, "  {}", accuracy.join("; "));
    }
    let l = &cl.latency_ms_publish_to_pose;
    let _ = writeln!(
        s,
        "  frame publish -> pose: p50 {:.2} ms, p90 {:.2} ms, p99 {:.2} ms, max {:.2} ms ({} frames)",
        l.p50, l.p90, l.p99, l.max, l.n
    );
    let files = if cl.files.is_empty() {
        "none".to_string()
    } else {
        cl.files.join(" ")
    };
    let _ = writeln!(s, "  data {} -> files {files}", cl.dataset);
}

/// What the client ran and why; for a visual-inertial client, its initialisation.
fn mode_line(s: &mut String, cl: &ClientReport) {
    if cl.client_mode.is_empty() {
        return;
    }
    let mut line = format!("  mode {} ({})", cl.client_mode, cl.client_mode_reason);
    if let Some(v) = &cl.vio {
        let _ = write!(line, "; inertial initialisation {}", v.status);
        if let (Some(after), Some(scale)) = (v.initialised_after_s, v.scale) {
            let _ = write!(
                line,
                " {after:.2} s after the first frame (scale {scale:.3}, {} refinement(s))",
                v.refinements
            );
        }
        if let Some(r) = &v.reason {
            let _ = write!(line, ": {r}");
        }
        resume_part(&mut line, v);
        if let Some(a) = &cl.ate_4dof {
            let tilt = a.tilt_rmse_deg.unwrap_or(f64::NAN);
            let _ = write!(
                line,
                "; 4-DoF ATE {:.4} m ({:.2}%), roll/pitch error {tilt:.2}°",
                a.rmse_m, a.rmse_percent
            );
        }
    }
    if !cl.frames_by_source.is_empty() || cl.frames_orientation_only > 0 {
        let by: Vec<String> = cl
            .frames_by_source
            .iter()
            .map(|(k, n)| format!("{n} {k}"))
            .collect();
        let _ = write!(
            line,
            "; poses: {}; {} orientation only",
            by.join(", "),
            cl.frames_orientation_only
        );
    }
    let _ = writeln!(s, "{line}");
}

/// A killed tracker's session resumed from the spool (issue 17), or why not.
fn resume_part(line: &mut String, v: &tracker::VioReport) {
    if let Some(kf) = v.resumed_from_keyframe {
        let _ = write!(
            line,
            "; resumed after a kill from keyframe {} ({} keyframes), tracking again at its frame {}",
            slam_core::ids::ClientKeyframeId::from_raw(kf),
            v.resumed_keyframes.unwrap_or(0),
            v.resumed_after_frames.map_or("-".into(), |n| n.to_string())
        );
    } else if let Some(why) = &v.resume_refused {
        let _ = write!(line, "; not resumed after a kill: {why}");
    }
}

fn faults_line(s: &mut String, rep: &RunReport) {
    let f = &rep.faults_summary;
    if f.kills == 0 && rep.faults_unfired.is_empty() {
        return;
    }
    let ms = |v: Option<f64>| v.map_or("-".to_string(), |s| format!("{:.0} ms", s * 1e3));
    let _ = writeln!(
        s,
        "faults: {} kills, {} recovered, recovery p50 {}, max {}; {} never fired",
        f.kills,
        f.recovered,
        ms(f.recovery_p50_s),
        ms(f.recovery_max_s),
        rep.faults_unfired.len()
    );
}
