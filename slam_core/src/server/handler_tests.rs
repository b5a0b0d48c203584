//! Handler tests on a constructed scene (no rendering): exact projections of a textured
//! plane, the client's point ids, and client poses whose scale drifts.
use nalgebra::{Isometry3, Point3, Vector3};

use super::*;
use crate::camera::PinholeRadtan;
use crate::features::{KeyPoint, OrbFeatures};

const CLIENT: u32 = 3;

fn camera() -> PinholeRadtan {
    PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0)
}

/// World points on the plane z = 5 (a 40 x 30 grid), each with its own descriptor.
fn scene() -> Vec<(Vector3<f64>, [u8; 32])> {
    let mut out = Vec::new();
    let mut h = 0x9e37_79b9_7f4a_7c15u64;
    for i in 0..40 {
        for j in 0..30 {
            let mut d = [0u8; 32];
            for b in d.iter_mut() {
                h ^= h << 13;
                h ^= h >> 7;
                h ^= h << 17;
                *b = h as u8;
            }
            let p = Vector3::new(-6.0 + 0.3 * i as f64, -3.0 + 0.2 * j as f64, 5.0);
            out.push((p, d));
        }
    }
    out
}

/// Keyframe `id` seen from the true pose `t_wk` (camera → world); its client pose is
/// `t_ck`; every visible point carries its index as client point id.
fn keyframe(id: u64, session: u32, t_wk: &Isometry3<f64>, t_ck: &Isometry3<f64>) -> ServerKeyframe {
    let cam = camera();
    let mut features = OrbFeatures::default();
    let mut client_points = Vec::new();
    for (i, (p, d)) in scene().iter().enumerate() {
        let p_k = t_wk.inverse() * Point3::from(*p);
        let Some(uv) = cam.project(&p_k.coords) else {
            continue;
        };
        if !cam.contains(&uv) {
            continue;
        }
        features
            .keypoints
            .push(KeyPoint::at_level0(uv.x as f32, uv.y as f32));
        features.descriptors.push(*d);
        client_points.push(Some(i as u64));
    }
    ServerKeyframe {
        client_id: CLIENT,
        session_id: session,
        id,
        t_ns: id as i64 * 50_000_000,
        t_ck: *t_ck,
        camera: cam,
        readout_ns: 0,
        features,
        client_points,
        inertial: None,
        imu: None,
    }
}

fn true_pose(k: usize) -> Isometry3<f64> {
    Isometry3::translation(0.25 * k as f64, 0.02 * k as f64, 0.0)
}

/// From keyframe 3 on, the client's translations shrink to 80% (scale drift): the handler
/// measures λ~ = 1 / 0.8 (eq. 3.2), smooths λ by eq. 3.3 with α = 0.2, and its refined
/// poses stay on the true trajectory (the server map keeps the scale of its creation).
#[test]
fn scale_ratio_is_measured_and_smoothed_and_poses_follow_the_truth() {
    let mut h = KeyframeHandler::new(CLIENT, HandlerParams::default());
    let mut maps = ServerMaps::new();
    let drift = 0.8;
    let mut lambda = 1.0;
    for k in 0..10 {
        let t_wk = true_pose(k);
        let t_ck = if k < 3 {
            t_wk
        } else {
            let base = true_pose(2).translation.vector;
            Isometry3::from_parts(
                (base + drift * (t_wk.translation.vector - base)).into(),
                t_wk.rotation,
            )
        };
        let r = h
            .handle(&mut maps, keyframe(k as u64, 1, &t_wk, &t_ck))
            .unwrap();
        match k {
            0 => assert_eq!(r.status, KeyframeStatus::First),
            1 => {
                assert_eq!(r.status, KeyframeStatus::MapCreated);
                assert!(r.new_points > 200, "{} points", r.new_points);
                assert_eq!(r.kept.len(), 2);
            }
            2 => {
                // No drift yet: the measured ratio is 1.
                let m = r.lambda_measured.unwrap();
                assert!((m - 1.0).abs() < 1e-3, "{m}");
                lambda += 0.2 * (m - lambda);
                assert!((r.lambda - lambda).abs() < 1e-12);
            }
            _ => {
                let m = r.lambda_measured.unwrap();
                // Every client step from keyframe 2 on is 80% of the true one.
                let expected = 1.0 / drift;
                assert!((m - expected).abs() < 5e-3, "keyframe {k}: λ~ {m}");
                lambda += 0.2 * (m - lambda);
                assert!((r.lambda - lambda).abs() < 1e-12, "eq. 3.3");
                let t = r.t_sk.unwrap();
                assert!(
                    (t.translation.vector - t_wk.translation.vector).norm() < 2e-3,
                    "keyframe {k}: refined pose off the truth"
                );
                assert!(r.inliers > 100);
            }
        }
        h.idle_step(&mut maps);
    }
    assert!(lambda > 1.0 && lambda < 1.0 / drift);
    let fb = h.feedback(&maps).unwrap();
    assert_eq!(fb.acked_keyframe_id, 9);
    assert!((fb.pose.unwrap().2 - lambda).abs() < 1e-12);
}

#[test]
fn invalid_foreign_and_duplicate_keyframes() {
    let mut h = KeyframeHandler::new(CLIENT, HandlerParams::default());
    let mut maps = ServerMaps::new();
    let kf0 = keyframe(0, 1, &true_pose(0), &true_pose(0));
    let mut bad = kf0.clone();
    bad.client_points.pop();
    assert!(h.handle(&mut maps, bad).is_err());
    let mut foreign = kf0.clone();
    foreign.client_id = CLIENT + 1;
    assert!(h.handle(&mut maps, foreign).is_err());
    let mut nan = kf0.clone();
    nan.t_ck.translation.vector.x = f64::NAN;
    assert!(h.handle(&mut maps, nan).is_err());
    assert_eq!(h.stats().received, 0);
    assert!(h.feedback(&maps).is_none());
    assert_eq!(
        h.handle(&mut maps, kf0.clone()).unwrap().status,
        KeyframeStatus::First
    );
    assert_eq!(
        h.handle(&mut maps, kf0).unwrap().status,
        KeyframeStatus::Duplicate
    );
    let kf1 = keyframe(1, 1, &true_pose(1), &true_pose(1));
    assert_eq!(
        h.handle(&mut maps, kf1).unwrap().status,
        KeyframeStatus::MapCreated
    );
    let fb = h.feedback(&maps).unwrap();
    assert_eq!((fb.acked_keyframe_id, fb.acked_session_id), (1, 1));
    assert_eq!(
        fb.pose.unwrap().0,
        MapId::new(crate::ids::ClientId::new(CLIENT), 0)
    );
}

/// A client VO that revisits the same places makes new point ids for them (its window
/// forgets the old ones): keyframes going back and forth over six poses whose client point
/// ids are renumbered every three keyframes. Forgetting client points unseen for 6 keyframe
/// ids keeps the association table at what the last few keyframes reference; without it the
/// table holds every id ever sent. The poses stay on the truth either way.
#[test]
fn unseen_client_points_are_forgotten() {
    let run = |horizon: u64| {
        let params = HandlerParams {
            assoc_horizon_kfs: horizon,
            ..HandlerParams::default()
        };
        let mut h = KeyframeHandler::new(CLIENT, params);
        let mut maps = ServerMaps::new();
        let mut worst: f64 = 0.0;
        for k in 0..48u64 {
            let step = [0, 1, 2, 3, 4, 5, 4, 3, 2, 1][k as usize % 10];
            let t_wk = true_pose(step);
            let mut kf = keyframe(k, 1, &t_wk, &t_wk);
            for c in kf.client_points.iter_mut().flatten() {
                *c += 10_000 * (k / 3);
            }
            let r = h.handle(&mut maps, kf).unwrap();
            if let Some(t) = r.t_sk {
                worst = worst.max((t.translation.vector - t_wk.translation.vector).norm());
            }
            h.idle_step(&mut maps);
        }
        let map = h.current_map(&maps).unwrap();
        (map.association_count().0, worst)
    };
    let (kept_all, err_all) = run(0);
    let (kept_recent, err_recent) = run(6);
    assert!(
        err_all < 2e-3 && err_recent < 2e-3,
        "{err_all} {err_recent}"
    );
    // 16 renumberings of ~500 visible points: thousands without forgetting; the last
    // 6 ids (at most 3 renumberings) with it.
    assert!(kept_all > 4000, "{kept_all}");
    assert!(kept_recent < 1800, "{kept_recent}");
}

#[test]
fn forget_unseen_keeps_recently_referenced_points() {
    let mut map = ServerMap::new(MapId::from_raw(1), CLIENT, 1, 0);
    let (a, b) = ((CLIENT, 1), (CLIENT, 2));
    map.touch(a, 1, &[]);
    map.associate(a, 10, 100);
    map.touch(a, 5, &[Some(11)]);
    map.associate(a, 11, 101);
    map.touch(a, 8, &[Some(10)]);
    map.touch(b, 3, &[]);
    map.associate(b, 10, 102);
    map.touch(a, 12, &[]);
    // Owner a: point 10 seen at 8, point 11 at 5; limit 12 - 5 = 7. Owner b: newest 3.
    assert_eq!(map.forget_unseen(5), 1);
    assert_eq!(map.association_count().0, 2);
    assert_eq!(map.forget_unseen(100), 0);
}

/// A visual-inertial client's keyframe `id` (every 50 ms, IMU every 1 ms): its segment
/// from the previous keyframe as the wire carries it (none for the session's first).
fn with_imu(mut kf: ServerKeyframe) -> ServerKeyframe {
    use crate::imu::{ImuMeasurement, PreintegrationParams};
    use crate::vo::keyframe_imu::{ImuCalibration, KeyframeImu};
    let t = kf.t_ns;
    let t_prev = (kf.id > 0).then(|| t - 50_000_000);
    let samples = t_prev.map_or_else(Vec::new, |t0| {
        (t0..=t)
            .step_by(1_000_000)
            .map(|t_ns| ImuMeasurement {
                t_ns,
                gyro: Vector3::new(0.01, 0.0, 0.0),
                accel: Vector3::new(0.0, 0.0, 9.81),
            })
            .collect()
    });
    let preint = PreintegrationParams::new(&Default::default(), &Default::default());
    kf.imu = Some(KeyframeImu {
        t_prev_ns: t_prev,
        t_ns: t,
        samples,
        calib: ImuCalibration {
            preint: preint.expect("params"),
            t_bc: Isometry3::identity(),
            t_d_ns: 0,
        },
    });
    kf.inertial = Some(crate::vo::KeyframeInertial {
        v_wb: Vector3::new(1.0, 0.0, 0.0),
        ..Default::default()
    });
    kf
}

/// Camera steps along x between keyframes, m: small ones (discarded: the map already
/// has the view) and large ones (kept).
const STEPS: [f64; 14] = [
    0.0, 0.3, 0.02, 0.02, 0.02, 1.2, 0.02, 0.02, 1.2, 0.02, 0.02, 0.02, 1.2, 0.02,
];

/// Issue 19: a visual-inertial client's keyframes reach the server map with their IMU
/// segments and velocities; the segments of keyframes the handler discards join the next
/// kept keyframe's, so that consecutive keyframes of the map are linked and their
/// segments tile the time axis (one sample every ms, each once).
#[test]
fn discarded_keyframes_segments_join_the_next_kept() {
    let mut h = KeyframeHandler::new(CLIENT, HandlerParams::default());
    let mut maps = ServerMaps::new();
    let mut statuses = Vec::new();
    for k in 0..STEPS.len() {
        let t_wk = Isometry3::translation(STEPS[..=k].iter().sum(), 0.0, 0.0);
        let r = h
            .handle(&mut maps, with_imu(keyframe(k as u64, 1, &t_wk, &t_wk)))
            .expect("handled");
        statuses.push(r.status);
        h.idle_step(&mut maps);
    }
    let discarded = statuses
        .iter()
        .filter(|s| **s == KeyframeStatus::Discarded)
        .count();
    assert!(discarded >= 2, "{statuses:?}");
    let map = h.current_map(&maps).expect("map");
    let kfs: Vec<&crate::vo::Keyframe> = map.map.keyframes.values().collect();
    assert!(kfs.len() >= 4, "{statuses:?}");
    for w in kfs.windows(2) {
        let (a, b) = (w[0].imu.as_ref(), w[1].imu.as_ref());
        let (a, b) = (a.expect("segment"), b.expect("segment"));
        assert!(b.links(a), "{} -> {}", a.t_ns, b.t_ns);
        let n = (b.t_ns - a.t_ns) / 1_000_000 + 1;
        assert_eq!(b.samples.len() as i64, n, "every sample once");
    }
    let span = kfs[kfs.len() - 1].t_ns - kfs[0].t_ns;
    let covered: i64 = kfs[1..]
        .iter()
        .filter_map(|k| k.imu.as_ref())
        .map(|s| s.t_ns - s.t_prev_ns.expect("linked"))
        .sum();
    assert_eq!(covered, span);
    let v = kfs[2].inertial.expect("inertial").v_wb;
    assert!((v - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-9, "{v}");
}
