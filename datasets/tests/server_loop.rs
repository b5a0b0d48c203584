//! The server keyframe handler (seed §3.4.1) on the client VO's keyframes of the rendered
//! synthetic `loop` (two laps of the same closed path): the server map is more accurate than
//! the client's keyframes, grows little on the second lap, is deterministic on replay, and a
//! new VO session starts a new server map.
//!
//! The VO runs once per test binary (about a minute in the dev profile); set
//! `SHOAL_SERVER_KF_CACHE=/some/file` to keep its keyframes between runs while developing.
use std::io::{Read, Write};
use std::sync::OnceLock;
use std::time::Instant;

use datasets::sim::{Scenario, SimParams, SimWorld};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use slam_core::features::{KeyPoint, OrbFeatures};
use slam_core::metrics::{evaluate, Alignment, EvalParams};
use slam_core::server::{
    frame_pose_in_server_map, HandlerParams, KeyframeHandler, KeyframeStatus, ServerKeyframe,
    ServerMaps,
};
use slam_core::vo::{VoParams, VoTracker};

const CLIENT: u32 = 7;
/// Lap period of the `loop` scenario (s) at 20 Hz.
const LAP_FRAMES: usize = 640;

struct Run {
    world: SimWorld,
    keyframes: Vec<ServerKeyframe>,
}

fn world() -> SimWorld {
    let mut p = SimParams::new(Scenario::Loop);
    p.seed = 3;
    SimWorld::new(p).expect("sim world")
}

fn run() -> &'static Run {
    static RUN: OnceLock<Run> = OnceLock::new();
    RUN.get_or_init(|| {
        let world = world();
        let cache = std::env::var_os("SHOAL_SERVER_KF_CACHE");
        if let Some(kfs) = cache.as_ref().and_then(|c| load(c.as_ref(), &world)) {
            return Run {
                world,
                keyframes: kfs,
            };
        }
        let keyframes = run_vo(&world);
        if let Some(c) = cache {
            save(c.as_ref(), &keyframes);
        }
        Run { world, keyframes }
    })
}

/// The client VO with a window of 10 keyframes: the evicted ones (and all at the end) are
/// what the client sends.
fn run_vo(world: &SimWorld) -> Vec<ServerKeyframe> {
    let cam = world.calib().model;
    let params = VoParams {
        window: 10,
        ..VoParams::default()
    };
    let mut vo = VoTracker::new(params, cam).expect("vo");
    let mut img = vec![0u8; (cam.width * cam.height) as usize];
    let mut out = Vec::new();
    for k in 0..world.n_frames() {
        let frame = world.vo_frame(k, &mut img).expect("render");
        let session = vo.session_id();
        let o = vo.process(&frame).expect("vo step");
        // Keyframes evicted by a session change belong to the old session.
        let s = if o.new_session {
            session
        } else {
            vo.session_id()
        };
        out.extend(
            o.evicted
                .iter()
                .map(|kf| ServerKeyframe::from_vo(CLIENT, s, kf)),
        );
    }
    let s = vo.session_id();
    out.extend(
        vo.drain_keyframes()
            .iter()
            .map(|kf| ServerKeyframe::from_vo(CLIENT, s, kf)),
    );
    out
}

fn gt(world: &SimWorld, t_ns: i64) -> Isometry3<f64> {
    world.pose_cam_at(t_ns + world.time_offset_ns())
}

fn ate(world: &SimWorld, traj: &[(i64, Isometry3<f64>)]) -> f64 {
    let t: Vec<i64> = traj.iter().map(|p| p.0).collect();
    let est: Vec<Isometry3<f64>> = traj.iter().map(|p| p.1).collect();
    let reference: Vec<Isometry3<f64>> = t.iter().map(|t| gt(world, *t)).collect();
    let p = EvalParams {
        alignment: Alignment::Sim3,
        ..Default::default()
    };
    evaluate(&t, &reference, &t, &est, &p)
        .expect("evaluate")
        .ape
        .rmse
}

#[test]
fn server_map_is_better_than_client_keyframes_and_grows_little_on_the_second_lap() {
    let run = run();
    let world = &run.world;
    let lap2_start = world.frame_time_ns(LAP_FRAMES);
    let kfs = &run.keyframes;
    let sessions: std::collections::BTreeSet<u32> = kfs.iter().map(|k| k.session_id).collect();
    assert_eq!(sessions.len(), 1, "the VO should not lose track on `loop`");
    let client_lap1 = kfs.iter().filter(|k| k.t_ns < lap2_start).count();
    let client_lap2 = kfs.len() - client_lap1;
    let mut h = KeyframeHandler::new(CLIENT, HandlerParams::default());
    let mut maps = ServerMaps::new();
    let mut server_at_lap1_end = None;
    let mut handled = Vec::new();
    let mut statuses = [0usize; 5];
    let mut lambdas = Vec::new();
    let start = Instant::now();
    for kf in kfs {
        if kf.t_ns >= lap2_start && server_at_lap1_end.is_none() {
            server_at_lap1_end = h.current_map(&maps).map(|m| m.map.keyframes.len());
        }
        let t_ns = kf.t_ns;
        let r = h.handle(&mut maps, kf.clone()).expect("handle");
        if std::env::var_os("SHOAL_SERVER_DEBUG").is_some() {
            let e = r
                .t_sk
                .map(|t| (t.translation.vector - kf.t_ck.translation.vector).norm());
            eprintln!(
                "kf {} {:?} inliers {} new {} lm {:?} l {:.3} |t_sk - t_ck| {:?}",
                kf.id, r.status, r.inliers, r.new_points, r.lambda_measured, r.lambda, e
            );
        }
        statuses[r.status as usize] += 1;
        if let Some(t) = r.t_sk {
            handled.push((t_ns, t));
        }
        lambdas.push(r.lambda);
        h.idle_step(&mut maps);
    }
    let per_kf_ms = start.elapsed().as_secs_f64() * 1e3 / kfs.len() as f64;
    let map = h.current_map(&maps).expect("a server map");
    let server_final = map.map.keyframes.len();
    let server_lap1 = server_at_lap1_end.expect("keyframes on both laps");
    let client_traj: Vec<(i64, Isometry3<f64>)> = kfs.iter().map(|k| (k.t_ns, k.t_ck)).collect();
    let ate_client = ate(world, &client_traj);
    let ate_server_map = ate(world, &map.trajectory());
    let ate_server_handled = ate(world, &handled);
    let (h1, h2): (Vec<_>, Vec<_>) = handled.iter().partition(|p| p.0 < lap2_start);
    let (c1, c2): (Vec<_>, Vec<_>) = client_traj.iter().partition(|p| p.0 < lap2_start);
    let (ate_h2, ate_c2) = (ate(world, &h2), ate(world, &c2));
    println!(
        "per lap ATE (Sim3 per lap): handled server poses {:.4} / {ate_h2:.4} m, client {:.4} / \
         {ate_c2:.4} m",
        ate(world, &h1),
        ate(world, &c1),
    );
    let growth = server_final as f64 / server_lap1 as f64 - 1.0;
    let (lmin, lmax) = lambdas
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), l| (a.min(*l), b.max(*l)));
    println!(
        "client keyframes: lap 1 {client_lap1}, lap 2 {client_lap2}; server map keyframes: \
         end of lap 1 {server_lap1}, end {server_final} (growth {:.1}%), points {}; \
         statuses [first, created, kept, discarded, dup] {statuses:?}; culled {}; \
         ATE (Sim3) client kfs {ate_client:.4} m, server map kfs {ate_server_map:.4} m, \
         server poses of all handled kfs {ate_server_handled:.4} m; lambda in \
         [{lmin:.3}, {lmax:.3}], final {:.3}; {per_kf_ms:.1} ms per keyframe (handle + idle)",
        100.0 * growth,
        map.map.points.len(),
        h.stats().culled,
        h.lambda(),
    );
    assert!(
        (client_lap2 as f64) > 0.8 * client_lap1 as f64,
        "the client sends about as many keyframes on both laps"
    );
    assert!(
        growth < 0.2,
        "server map grew {:.1}% on lap 2",
        100.0 * growth
    );
    // What the design promises: the server map beats the client's keyframes, and on the
    // revisits (lap 2, matched into the lap-1 map) the server's live poses beat the client's.
    // Measured (seed 3, deterministic) with the client's local mapping at every keyframe (as
    // a lock-step pipeline maps; `slam_core` runs it inline since issue 16 moved the thread
    // into the tracker service): client keyframes 0.0324 m, server map 0.0136 m (0.42x);
    // lap 2 alone 0.0134 m vs the client's 0.0232 m (0.58x). The server's live poses of
    // lap 1 (first visits, 0.0492 m) are worse than such a client's (0.0241 m): only a
    // client whose mapping thread skipped BAs (0.0540 m, the figures before) was beaten on
    // all handled keyframes (0.0288 m), so that is no longer asserted. The bounds leave
    // margin for changes of the VO, and fail for a server merely on par.
    assert!(
        ate_server_map < 0.5 * ate_client,
        "server map {ate_server_map} vs client {ate_client}: not 2x better"
    );
    assert!(
        ate_h2 < 0.7 * ate_c2,
        "revisits: server poses {ate_h2} vs client {ate_c2} on lap 2"
    );
    assert!(
        h.stats().revisit_global_ba >= 1,
        "lap 2 revisits lap 1: a global BA was due"
    );
    // Ablation: the same keyframes without the revisit global BA.
    let mut h0 = KeyframeHandler::new(
        CLIENT,
        HandlerParams {
            revisit_min_points: 0,
            ..HandlerParams::default()
        },
    );
    let mut maps0 = ServerMaps::new();
    for kf in kfs {
        h0.handle(&mut maps0, kf.clone()).expect("handle");
        h0.idle_step(&mut maps0);
    }
    let ate_no_revisit = ate(world, &h0.current_map(&maps0).expect("map").trajectory());
    println!(
        "server map kfs with the revisit global BA {ate_server_map:.4} m ({} BAs), without \
         {ate_no_revisit:.4} m; client kfs {ate_client:.4} m",
        h.stats().revisit_global_ba
    );
    assert!(
        ate_server_map < ate_no_revisit,
        "the revisit BA did not help: {ate_server_map} vs {ate_no_revisit}"
    );
    // Ablation: no revisit search either (lap 2 is not matched into the lap-1 map).
    let mut h_blind = KeyframeHandler::new(
        CLIENT,
        HandlerParams {
            revisit_min_points: 0,
            spatial_keyframes: 0,
            ..HandlerParams::default()
        },
    );
    let mut maps_blind = ServerMaps::new();
    let mut handled_blind = Vec::new();
    for kf in kfs {
        let r = h_blind.handle(&mut maps_blind, kf.clone()).expect("handle");
        if let Some(t) = r.t_sk {
            handled_blind.push((kf.t_ns, t));
        }
        h_blind.idle_step(&mut maps_blind);
    }
    let blind_lap2: Vec<_> = handled_blind
        .iter()
        .copied()
        .filter(|p| p.0 >= lap2_start)
        .collect();
    let ate_blind_h2 = ate(world, &blind_lap2);
    println!(
        "without revisit search nor revisit BA: server poses {:.4} m, lap 2 {ate_blind_h2:.4} m \
         (with: {ate_server_handled:.4} / {ate_h2:.4} m; client {ate_client:.4} / {ate_c2:.4} m)",
        ate(world, &handled_blind)
    );
    // Measured 0.0427 m: lap 2 drifts on like the client's own poses when it is not matched
    // into the lap-1 map.
    assert!(
        ate_h2 < 0.6 * ate_blind_h2,
        "the revisit search did not help lap 2: {ate_h2} vs {ate_blind_h2}"
    );
}

#[test]
fn replay_is_deterministic() {
    let run = run();
    let n = run.keyframes.len().min(60);
    let replay = || {
        let mut h = KeyframeHandler::new(CLIENT, HandlerParams::default());
        let mut maps = ServerMaps::new();
        for kf in &run.keyframes[..n] {
            h.handle(&mut maps, kf.clone()).expect("handle");
            h.idle_step(&mut maps);
        }
        (h, maps)
    };
    let ((a, am), (b, bm)) = (replay(), replay());
    let (ma, mb) = (
        a.current_map(&am).expect("map"),
        b.current_map(&bm).expect("map"),
    );
    assert_eq!(ma.trajectory(), mb.trajectory());
    assert_eq!(ma.map.points.len(), mb.map.points.len());
    for (id, p) in &ma.map.points {
        let q = &mb.map.points[id];
        assert_eq!(p.p_w, q.p_w);
        assert_eq!(p.observations, q.observations);
    }
    assert_eq!(a.stats(), b.stats());
    assert_eq!(a.feedback(&am), b.feedback(&bm));
}

#[test]
fn session_change_starts_a_new_server_map_and_feedback_composes_eq_3_4() {
    let run = run();
    let kfs = &run.keyframes[..run.keyframes.len().min(60)];
    let mut h = KeyframeHandler::new(CLIENT, HandlerParams::default());
    let mut maps = ServerMaps::new();
    let mut last_fb = None;
    // The client restarts its VO (a new session) after the first keyframe from 25 on that
    // the handler discarded: that one is the old session's last.
    let mut switch: Option<usize> = None;
    let mut last_discarded = None;
    for (i, kf) in kfs.iter().enumerate() {
        let mut kf = kf.clone();
        if switch.is_some_and(|s| i >= s) {
            // The client lost track and restarted its VO: the same images, a new session.
            kf.session_id += 1;
        }
        let t_ck = kf.t_ck;
        let r = h.handle(&mut maps, kf).expect("handle");
        // The client's composition of the previous feedback is the handler's prediction.
        if let (Some((t_cj, fb)), Some(pred)) = (last_fb, r.t_sk_predicted) {
            let fb: slam_core::server::FeedbackPose = fb;
            let p: Isometry3<f64> = frame_pose_in_server_map(&t_cj, &fb.t_sk, fb.lambda, &t_ck);
            assert!((p.translation.vector - pred.translation.vector).norm() < 1e-12);
        }
        if switch == Some(i) {
            // The old session's discarded last keyframe joins its map at the session's end
            // and goes to loop closing with the new session's first.
            let ended: Vec<u64> = r.kept.iter().map(|k| k.client_kf_id).collect();
            assert_eq!(ended, last_discarded.into_iter().collect::<Vec<_>>());
            let k = last_discarded.expect("set with the switch");
            let first_map = maps.values().next().expect("the first map");
            assert!(first_map.map.keyframes.contains_key(&h.server_kf_id(k)));
            assert_eq!(h.stats().kept_at_session_end, 1);
        }
        if i == 0 || switch == Some(i) {
            assert_eq!(r.status, KeyframeStatus::First);
        } else if i == 1 || switch.map(|s| s + 1) == Some(i) {
            assert_eq!(r.status, KeyframeStatus::MapCreated);
        } else {
            assert!(matches!(
                r.status,
                KeyframeStatus::Kept | KeyframeStatus::Discarded
            ));
        }
        if switch.is_none() && i >= 24 && r.status == KeyframeStatus::Discarded {
            switch = Some(i + 1);
            last_discarded = Some(r.client_kf_id);
        }
        // Feedback after the idle step (local BA may move the last keyframe).
        h.idle_step(&mut maps);
        let fb = h.feedback(&maps).expect("feedback");
        assert_eq!(fb.acked_keyframe_id, r.client_kf_id);
        last_fb = fb.pose.map(|p| (t_ck, p));
    }
    let switch = switch.expect("a discarded keyframe to end the first session at");
    assert!(switch + 2 < kfs.len(), "the new session has keyframes");
    assert_eq!(maps.len(), 2);
    let ids: Vec<_> = maps.keys().copied().collect();
    let second = &maps[&ids[1]];
    assert_eq!(second.session_id, kfs[switch].session_id + 1);
    assert!(second.map.keyframes.len() >= 2);
    // A keyframe of the old session now is stale.
    let r = h.handle(&mut maps, kfs[10].clone()).expect("handle");
    assert_eq!(r.status, KeyframeStatus::Duplicate);
}

// --- keyframe cache (development only) ---

fn save(path: &std::path::Path, kfs: &[ServerKeyframe]) {
    let mut b = Vec::new();
    b.extend((kfs.len() as u64).to_le_bytes());
    for k in kfs {
        b.extend(k.session_id.to_le_bytes());
        b.extend(k.id.to_le_bytes());
        b.extend(k.t_ns.to_le_bytes());
        b.extend(k.readout_ns.to_le_bytes());
        let q = k.t_ck.rotation.coords;
        let t = k.t_ck.translation.vector;
        for v in [q.x, q.y, q.z, q.w, t.x, t.y, t.z] {
            b.extend(v.to_le_bytes());
        }
        b.extend((k.features.len() as u64).to_le_bytes());
        for (i, kp) in k.features.keypoints.iter().enumerate() {
            for v in [kp.x, kp.y, kp.angle, kp.response, kp.size] {
                b.extend(v.to_le_bytes());
            }
            b.push(kp.octave);
            b.extend(k.features.descriptors[i]);
            b.extend(k.client_points[i].unwrap_or(u64::MAX).to_le_bytes());
        }
    }
    if let Ok(mut f) = std::fs::File::create(path) {
        let _ = f.write_all(&b);
    }
}

fn load(path: &std::path::Path, world: &SimWorld) -> Option<Vec<ServerKeyframe>> {
    let mut b = Vec::new();
    std::fs::File::open(path).ok()?.read_to_end(&mut b).ok()?;
    let mut at = 0usize;
    let mut take = |n: usize| -> Option<&[u8]> {
        let s = b.get(at..at + n)?;
        at += n;
        Some(s)
    };
    macro_rules! rd {
        ($t:ty) => {
            <$t>::from_le_bytes(take(std::mem::size_of::<$t>())?.try_into().ok()?)
        };
    }
    let n = rd!(u64) as usize;
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let session_id = rd!(u32);
        let id = rd!(u64);
        let t_ns = rd!(i64);
        let readout_ns = rd!(i64);
        let mut v = [0f64; 7];
        for x in &mut v {
            *x = rd!(f64);
        }
        let t_ck = Isometry3::from_parts(
            Translation3::new(v[4], v[5], v[6]),
            UnitQuaternion::from_quaternion(Quaternion::new(v[3], v[0], v[1], v[2])),
        );
        let m = rd!(u64) as usize;
        let mut features = OrbFeatures::with_capacity(m);
        let mut client_points = Vec::with_capacity(m);
        for _ in 0..m {
            let (x, y, angle, response, size) = (rd!(f32), rd!(f32), rd!(f32), rd!(f32), rd!(f32));
            let octave = rd!(u8);
            let d: [u8; 32] = take(32)?.try_into().ok()?;
            let p = rd!(u64);
            features.keypoints.push(KeyPoint {
                x,
                y,
                angle,
                response,
                size,
                octave,
            });
            features.descriptors.push(d);
            client_points.push((p != u64::MAX).then_some(p));
        }
        out.push(ServerKeyframe {
            client_id: CLIENT,
            session_id,
            id,
            t_ns,
            t_ck,
            camera: world.calib().model,
            readout_ns,
            features,
            client_points,
            inertial: None,
            imu: None,
        });
    }
    Some(out)
}
