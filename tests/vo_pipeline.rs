//! The client VO through the whole pipeline (ingests → shared memory → tracker → report),
//! against ground truth. Issue targets (tracker issue):
//! - synthetic `fast-rs` (t_r = 30 ms): with rolling-shutter compensation the ATE is at
//!   least 30% lower than without, and ≤ 1% of the distance;
//! - ../shared/data/kitti07: initialises within the first 15 frames, ≥ 95% of the frames
//!   tracked, ATE after Sim(3) alignment ≤ 1% of the distance (≤ 0.55 m);
//! - the phone clip runs through without error, every frame unposed before initialisation
//!   (it cannot initialise monocularly);
//! - a KITTI 07 stretch starting elsewhere (frame 40, `--frames 40..`): every frame posed
//!   (backward tracking);
//! - ../shared/data/vamr_checkerboard (issue 20: an image folder without timestamps, strong
//!   radial distortion, a planar board with many revisits): every frame posed, within 2% of
//!   the path after Sim(3) alignment, the revisits caught by the mapper.
mod common;

use common::{report, run_pipeline, shared_dataset, synthetic, tempdir};

fn client(rep: &serde_json::Value) -> &serde_json::Value {
    &rep["clients"][0]
}

fn ate_percent(c: &serde_json::Value) -> f64 {
    c["ate"]["rmse_percent"]
        .as_f64()
        .expect("ATE in the report (ground truth present)")
}

#[test]
fn fast_rs_compensation_beats_none() {
    let tmp = tempdir();
    let ds = synthetic(&tmp.path().join("seq"), "fast-rs", 400, None);
    let mut ate = Vec::new();
    for (name, extra) in [("rs", &[][..]), ("nors", &["--tracker-arg=--no-rs"][..])] {
        let out = tmp.path().join(name);
        let o = run_pipeline(&[&ds[0]], &out, &format!("frs_{name}"), extra);
        assert!(o.status.success(), "run {name} failed");
        let rep = report(&out);
        let c = client(&rep);
        let frames = c["frames_total"].as_u64().unwrap();
        let posed =
            c["frames_tracked"].as_u64().unwrap() + c["frames_backfilled"].as_u64().unwrap();
        let pct = ate_percent(c);
        eprintln!("fast-rs {name}: {posed}/{frames} frames with a pose, ATE {pct:.3}%");
        ate.push((pct, posed, frames));
    }
    let (with, posed, frames) = ate[0];
    let without = ate[1].0;
    assert!(posed * 100 >= frames * 95, "{posed}/{frames} frames posed");
    assert!(
        with <= 1.0,
        "ATE with compensation {with:.3}% (target ≤ 1%)"
    );
    assert!(
        with <= 0.7 * without,
        "compensation must lower the ATE by ≥ 30%: {with:.3}% vs {without:.3}%"
    );
}

#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/kitti07 (set SHOAL_DATA)"
)]
#[test]
fn kitti07_initialises_tracks_and_is_accurate() {
    let ds = shared_dataset("kitti07");
    let tmp = tempdir();
    let out = tmp.path().join("out");
    let o = run_pipeline(&[&ds], &out, "kitti07_vo", &[]);
    assert!(o.status.success());
    let rep = report(&out);
    let c = client(&rep);
    let frames = c["frames_total"].as_u64().unwrap();
    let tracked = c["frames_tracked"].as_u64().unwrap();
    let backfilled = c["frames_backfilled"].as_u64().unwrap();
    let rmse = c["ate"]["rmse_m"].as_f64().unwrap();
    let pct = ate_percent(c);
    eprintln!(
        "kitti07: {tracked} tracked + {backfilled} backfilled of {frames}, ATE {rmse:.3} m = {pct:.3}%"
    );
    assert_eq!(frames, 100);
    // The frames before the map exists are the backfilled ones: the map was made within
    // the first 15 frames.
    assert!(
        tracked >= 85,
        "initialised within 15 frames ({tracked} tracked live)"
    );
    assert!(tracked + backfilled >= 95, "≥ 95% of frames with a pose");
    assert!(rmse <= 0.55 && pct <= 1.0, "ATE {rmse:.3} m ({pct:.3}%)");
}

#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/phone_honorv10 (set SHOAL_DATA)"
)]
#[test]
fn phone_clip_gives_no_pose_but_orientations_and_says_why() {
    // The clip is 0.8 s of hand-held motion, nearly pure rotation: with SHOAL_DEBUG_INIT=1
    // the two-view initialiser rejects every frame against the first one (parallax 0.1-0.2
    // deg < 1 deg, or homography and essential matrix ambiguous), so the monocular VO cannot
    // initialise; the visual-inertial initialisation (chapter 5) is what can. Every frame
    // is accounted for as unposed before initialisation, none as lost or dropped.
    let ds = shared_dataset("phone_honorv10");
    let tmp = tempdir();
    let out = tmp.path().join("out");
    let o = run_pipeline(&[&ds], &out, "phone_vo", &["--mode", "auto"]);
    assert!(o.status.success());
    let rep = report(&out);
    let c = client(&rep);
    assert_eq!(c["frames_received"].as_u64(), Some(25));
    let errors = rep["errors"].as_array().map_or(0, |a| a.len());
    assert_eq!(errors, 0, "no errors: {}", rep["errors"]);
    assert_eq!(c["frames_posed"], 0, "{c:#}");
    let unposed = &c["frames_unposed"];
    assert_eq!(unposed["before_init"], 25, "{unposed:#}");
    assert_eq!(unposed["total"], 25, "{unposed:#}");
    assert_eq!(c["keyframes_sent"], 0);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("0/25 frames posed") && stdout.contains("25 before initialisation"),
        "{stdout}"
    );
    // Issue 17: an IMU without extrinsics runs the visual-inertial client without inertial
    // initialisation: no scale is invented, every frame gets a gyro orientation, and the
    // report says why.
    assert_eq!(c["client_mode"], "vio", "{}", c["client_mode_reason"]);
    assert_eq!(c["vio"]["status"], "disabled", "{}", c["vio"]);
    assert!(c["vio"]["reason"]
        .as_str()
        .unwrap_or("")
        .contains("extrinsics"));
    assert!(c["vio"]["scale"].is_null() && c["world_moves"].as_u64().unwrap_or(0) == 0);
    assert_eq!(c["frames_orientation_only"], 25, "{c:#}");
    let last = phone_last_orientation(&out.join("orientation_c0.txt"));
    let gyro = phone_gyro_turn(&ds.join("gyro_accel.csv"), last.0);
    let r_bc = nalgebra::UnitQuaternion::from_axis_angle(
        &nalgebra::Vector3::x_axis(),
        std::f64::consts::PI,
    );
    let expected = r_bc.inverse() * gyro * r_bc;
    let err = (last.1.inverse() * expected).angle().to_degrees();
    eprintln!(
        "phone: last orientation {:.3}° from the first, {err:.4}° from the gyro's",
        last.1.angle().to_degrees()
    );
    assert!(err < 0.02, "orientation {err}° from the integrated gyro");
}

/// The last row of an `orientation_c{i}.txt`: time (ns) and `R_wc`.
fn phone_last_orientation(path: &std::path::Path) -> (i64, nalgebra::UnitQuaternion<f64>) {
    let text = std::fs::read_to_string(path).expect("orientation file");
    let rows: Vec<Vec<f64>> = text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| {
            l.split_whitespace()
                .take(5)
                .map(|v| v.parse().expect("number"))
                .collect()
        })
        .collect();
    assert_eq!(rows.len(), 25, "one orientation per frame");
    let r = rows.last().expect("rows");
    let q = nalgebra::Quaternion::new(r[4], r[1], r[2], r[3]);
    (
        (r[0] * 1e9).round() as i64,
        nalgebra::UnitQuaternion::from_quaternion(q),
    )
}

/// The body's turn integrated from the phone's gyro (its first sample to `t_ns`, the mean
/// rate of each sample pair), independently of the pipeline.
fn phone_gyro_turn(csv: &std::path::Path, t_ns: i64) -> nalgebra::UnitQuaternion<f64> {
    let text = std::fs::read_to_string(csv).expect("gyro csv");
    let s: Vec<(i64, nalgebra::Vector3<f64>)> = text
        .lines()
        .skip(1)
        .map(|l| {
            let v: Vec<&str> = l.split(',').collect();
            let w = |i: usize| v[i].parse::<f64>().expect("rate");
            (
                v[0].parse().expect("t"),
                nalgebra::Vector3::new(w(1), w(2), w(3)),
            )
        })
        .collect();
    let mut r = nalgebra::UnitQuaternion::identity();
    for k in 0..s.len() - 1 {
        let (a, b) = (s[k].0, s[k + 1].0.min(t_ns));
        if b > a {
            let w = (s[k].1 + s[k + 1].1) * 0.5;
            r *= nalgebra::UnitQuaternion::from_scaled_axis(w * ((b - a) as f64 * 1e-9));
        }
    }
    r
}

/// A stretch of KITTI 07 the other tests do not start at (frames 40-99, `--frames 40..`:
/// the dataset's own times): the initialiser replaces its reference while the car drives
/// forward, so the first 12 frames came before the reference and had no pose (48/60).
/// Tracked backwards once the map has a few keyframes, every frame has a pose, and the
/// frames posed before keep their accuracy.
#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/kitti07 (set SHOAL_DATA)"
)]
#[test]
fn kitti07_from_frame_40_poses_every_frame() {
    let tmp = tempdir();
    let ds = shared_dataset("kitti07");
    let out = tmp.path().join("out");
    let o = run_pipeline(&[&ds], &out, "k07_40", &["--frames", "40.."]);
    assert!(o.status.success());
    let rep = report(&out);
    let c = client(&rep);
    let posed = c["frames_posed"].as_u64().unwrap();
    eprintln!(
        "KITTI 07 from frame 40: {posed}/60 posed, unposed {}, ATE {}",
        c["frames_unposed"], c["ate"]["rmse_m"]
    );
    assert_eq!(c["frames_total"], 60);
    assert!(posed * 100 >= 60 * 98, "{posed}/60 frames posed: {c:#}");
    assert_eq!(posed + c["frames_unposed"]["total"].as_u64().unwrap(), 60);
    // 0.0325 m over the 60 frames (the 48 frames posed without backward tracking: 0.0223 m,
    // unchanged); 1% of the 44.5 m driven is the KITTI target.
    assert!(
        ate_percent(c) <= 0.15,
        "ATE {}% of the path",
        ate_percent(c)
    );
    let first = first_time_s(&out.join("trajectory_c0.txt"));
    let times = std::fs::read_to_string(ds.join("times.txt")).unwrap();
    let t40: f64 = times.lines().nth(40).unwrap().trim().parse().unwrap();
    assert!(
        (first - t40).abs() < 1e-6,
        "frame 40 keeps its time: {first} vs {t40}"
    );
}

/// The first time (s) of a TUM trajectory file.
fn first_time_s(path: &std::path::Path) -> f64 {
    let text = std::fs::read_to_string(path).unwrap();
    let line = text.lines().find(|l| !l.starts_with('#')).expect("a pose");
    line.split_whitespace().next().unwrap().parse().unwrap()
}

/// The VAMR hand-held checkerboard sequence (issue 20), read as an image folder (`images/`,
/// `K.txt`, `D.txt`, `groundtruth_tum.txt`; frame k at k / 20 s): 736 real frames at desk
/// scale with strong radial distortion, a mostly planar scene and many revisits. Every
/// frame is posed, the client trajectory is within 2% of the 2.38 m path after Sim(3)
/// alignment (measured 1.16%, 0.028 m), and the server keyframes are closer to the truth
/// than the client's frames (measured 0.020 m): the mapper's own revisit search catches
/// the revisits (frames 500-549 see again what 0-49 saw) and runs its global BAs.
#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/vamr_checkerboard (set SHOAL_DATA)"
)]
#[test]
fn vamr_checkerboard_real_hand_held_sequence() {
    let tmp = tempdir();
    let ds = shared_dataset("vamr_checkerboard");
    let out = tmp.path().join("out");
    let o = run_pipeline(&[&ds], &out, "vamr", &["--mode", "mono"]);
    assert!(o.status.success());
    let rep = report(&out);
    let c = client(&rep);
    let (client_m, server_m) = (
        c["ate"]["rmse_m"].as_f64().unwrap(),
        c["ate_server_keyframes"]["rmse_m"].as_f64().unwrap(),
    );
    let m: mapper::MapperCounters = common::service_counters(&rep, "mapper");
    let revisits = m.client(0).revisit_global_ba;
    eprintln!(
        "vamr_checkerboard: {} posed, client ATE {client_m:.4} m ({:.2}%), server keyframes \
         {server_m:.4} m, {revisits} revisit global BAs",
        c["frames_posed"],
        ate_percent(c)
    );
    assert_eq!(
        (c["frames_total"].as_u64(), c["frames_posed"].as_u64()),
        (Some(736), Some(736))
    );
    assert!(ate_percent(c) <= 2.0, "client ATE {}%", ate_percent(c));
    assert!(
        server_m < client_m,
        "server keyframes {server_m} m vs client {client_m} m"
    );
    assert!(revisits >= 1, "no revisit found: {m:?}");
    let last = std::fs::read_to_string(out.join("trajectory_c0.txt")).unwrap();
    let t_last: f64 = last
        .lines()
        .last()
        .unwrap()
        .split_whitespace()
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!(
        (t_last - 735.0 / 20.0).abs() < 1e-6,
        "frame 735 at 735 / 20 s: {t_last}"
    );
}
