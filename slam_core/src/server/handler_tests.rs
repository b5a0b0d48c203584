//! Handler tests on a constructed scene (no rendering): exact projections of a textured
//! plane, the client's point ids, and client poses whose scale drifts.
use nalgebra::{Isometry3, Vector3};

use super::*;
use crate::server::test_scene::{keyframe, true_pose, CLIENT};

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
    assert!((fb.pose.unwrap().lambda - lambda).abs() < 1e-12);
    assert!(!fb.pose.unwrap().metric, "a monocular map: no anchor");
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
        fb.pose.unwrap().map_id,
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
    let mut map = ServerMap::new(MapId::from_raw(1), CLIENT, 1, 0, MapFrame::VISUAL);
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

/// `kf` made a visual-inertial keyframe: a velocity and biases, and an IMU segment from the
/// previous keyframe's time (no samples: the handler only links segments, it does not
/// integrate them here).
fn inertial(mut kf: ServerKeyframe, t_prev_ns: Option<i64>) -> ServerKeyframe {
    use crate::imu::{ImuIntrinsics, ImuNoise, PreintegrationParams};
    use crate::vo::keyframe_imu::{ImuCalibration, KeyframeImu};
    let preint = PreintegrationParams::new(&ImuNoise::zero(), &ImuIntrinsics::default()).unwrap();
    kf.inertial = Some(crate::vo::KeyframeInertial::default());
    kf.imu = Some(KeyframeImu {
        t_prev_ns,
        t_ns: kf.t_ns,
        samples: Vec::new(),
        calib: ImuCalibration {
            preint,
            t_bc: Isometry3::identity(),
            t_d_ns: 0,
        },
    });
    kf
}

/// A visual-inertial client's keyframes build a metric, gravity-aligned map; when its world
/// becomes metric after visual keyframes (its inertial initialisation), the session goes on
/// in a new map; the segment of a discarded keyframe is joined into the next inserted one,
/// so that consecutive server keyframes stay linked by the IMU.
#[test]
fn visual_inertial_keyframes_get_a_metric_map_and_linked_segments() {
    let mut h = KeyframeHandler::new(CLIENT, HandlerParams::default());
    let mut maps = ServerMaps::new();
    let kf = |k: usize| keyframe(k as u64, 1, &true_pose(k), &true_pose(k));
    let t = |k: usize| k as i64 * 50_000_000;
    h.handle(&mut maps, kf(0)).unwrap();
    h.handle(&mut maps, kf(1)).unwrap();
    let visual = h.current_map_id().unwrap();
    assert_eq!(maps[&visual].frame, MapFrame::VISUAL);
    // The client initialised: its keyframes are inertial from 2 on.
    let r = h.handle(&mut maps, inertial(kf(2), Some(t(1)))).unwrap();
    assert_eq!(
        r.status,
        KeyframeStatus::First,
        "a new map for the metric world"
    );
    let r = h.handle(&mut maps, inertial(kf(3), Some(t(2)))).unwrap();
    assert_eq!(r.status, KeyframeStatus::MapCreated);
    let metric = h.current_map_id().unwrap();
    assert_ne!(metric, visual);
    assert_eq!(maps[&metric].frame, MapFrame::INERTIAL);
    assert_eq!(
        maps.len(),
        2,
        "the visual map stays, for the loop closer to merge"
    );
    // Keyframes 4.. alternate a 1 cm step (discarded: nothing new in view) and a 1 m one
    // (kept); each inserted one's segment starts at the previous inserted keyframe.
    let mut inserted = 0;
    for k in 4..12 {
        let x = 0.75 + ((k - 3) / 2) as f64 + 0.01 * ((k - 3) % 2) as f64;
        let near = Isometry3::translation(x, 0.06, 0.0);
        let r = h
            .handle(
                &mut maps,
                inertial(keyframe(k as u64, 1, &near, &near), Some(t(k - 1))),
            )
            .unwrap();
        inserted += usize::from(r.status == KeyframeStatus::Kept);
    }
    h.idle_step(&mut maps);
    let m = &maps[&metric].map;
    let segs: Vec<_> = m
        .keyframes
        .values()
        .map(|k| k.imu.clone().unwrap())
        .collect();
    assert_eq!(segs.len(), 2 + inserted);
    assert!(
        h.stats().discarded > 0 && inserted > 0,
        "{inserted} {:?}",
        h.stats()
    );
    for w in segs.windows(2) {
        assert_eq!(
            w[1].t_prev_ns,
            Some(w[0].t_ns),
            "consecutive server keyframes linked"
        );
    }
    assert!(m.keyframes.values().all(|k| k.inertial.is_some()));
    // The feedback of a metric map gives the scale ratio 1 exactly; the smoothed λ of the
    // measured ratios (≈ 1 up to noise) is only a monitor.
    let fb = h.feedback(&maps).unwrap().pose.unwrap();
    assert_eq!(fb.lambda, 1.0);
    assert!(fb.metric);
    assert_ne!(h.lambda(), 1.0, "λ was measured and smoothed");
}

/// A global BA solved elsewhere ([`GlobalBa`]): the problem is copied out of the map, a
/// keyframe and a point enter the map while it solves, and the write-back moves them with
/// their client's newest problem keyframe (their pose relative to it is kept), while the
/// problem keyframes are pulled back from a disturbance.
#[test]
fn a_global_ba_solved_elsewhere_carries_its_correction_to_what_came_meanwhile() {
    use crate::imu::window::ViParams;
    use crate::vo::vi_window::ViMappingParams;
    let mut h = KeyframeHandler::new(CLIENT, HandlerParams::default());
    let mut maps = ServerMaps::new();
    for k in 0..8 {
        h.handle(
            &mut maps,
            keyframe(k as u64, 1, &true_pose(k), &true_pose(k)),
        )
        .unwrap();
        h.idle_step(&mut maps);
    }
    let id = h.current_map_id().unwrap();
    let m = maps.get_mut(&id).unwrap();
    assert!(m.map.keyframes.len() >= 3, "{}", m.map.keyframes.len());
    // Disturb every keyframe but the oldest (the gauge): the BA pulls them back.
    for (i, kf) in m.map.keyframes.values_mut().enumerate().skip(1) {
        kf.t_cw = Isometry3::translation(0.02 * i as f64, -0.01, 0.005) * kf.t_cw;
    }
    let mut gba = GlobalBa::prepare(m, &ViMappingParams::default()).unwrap();
    assert!(!gba.is_inertial(), "a visual map");
    // Meanwhile a keyframe (a copy of the newest, 10 cm on) and a point it made.
    let (&newest, last) = m.map.keyframes.iter().next_back().unwrap();
    let mut new_kf = last.clone();
    let new_id = newest + 1;
    new_kf.id = new_id;
    new_kf.t_cw = Isometry3::translation(-0.1, 0.0, 0.0) * last.t_cw;
    let (&some_point, p) = m.map.points.iter().next().unwrap();
    let mut new_point = p.clone();
    let new_pid = m.map.points.keys().max().unwrap() + 1;
    new_point.id = new_pid;
    new_point.observations = vec![(new_id, 0)];
    m.map.keyframes.insert(new_id, new_kf);
    m.map.points.insert(new_pid, new_point);
    assert!(m.map.points.contains_key(&some_point));
    let before = |m: &ServerMap| {
        let (r, n) = (&m.map.keyframes[&newest], &m.map.keyframes[&new_id]);
        let rel = r.t_cw * n.t_cw.inverse();
        let p_r = r.t_cw * nalgebra::Point3::from(m.map.points[&new_pid].p_w);
        (rel, p_r, r.t_cw)
    };
    let (rel0, p0, t_ref0) = before(m);
    assert!(gba.solve(&ViParams::default()));
    let applied = gba.apply(m).unwrap();
    assert_eq!(
        (applied.keyframes_propagated, applied.points_propagated),
        (1, 1),
        "{applied:?}"
    );
    let (rel1, p1, t_ref1) = before(m);
    let moved = (t_ref1.inverse() * t_ref0).translation.vector.norm();
    assert!(moved > 0.01, "the newest problem keyframe moved {moved} m");
    assert!(
        (rel1.to_homogeneous() - rel0.to_homogeneous()).amax() < 1e-9,
        "the new keyframe kept its pose relative to it"
    );
    assert!((p1 - p0).norm() < 1e-9, "and so did the new point");
    assert!(applied.client_deltas.contains_key(&CLIENT));
}

/// `--localize-only`: client 3 maps the scene (keyframes 0-6, true poses) and its map is
/// frozen; client 4, whose VO frame is the world moved by a similarity (half the scale),
/// makes a map of its own from keyframes 2-3, which then relocalises in the frozen map by
/// the true similarity. Its next keyframes are localised there on the true poses and
/// never inserted; no idle step runs; the frozen map is exactly as it was.
#[test]
fn a_map_relocalised_in_a_frozen_map_localises_in_it_without_changing_it() {
    use crate::server::correction::relocalise_in_frozen;
    let mut maps = ServerMaps::new();
    let mut a = KeyframeHandler::new(CLIENT, HandlerParams::default());
    for k in 0..7 {
        let t = true_pose(k);
        a.handle(&mut maps, keyframe(k as u64, 1, &t, &t)).unwrap();
        a.idle_step(&mut maps);
    }
    let frozen_id = a.current_map_id().unwrap();
    maps.get_mut(&frozen_id).unwrap().freeze();
    let before = maps[&frozen_id].clone();
    let s_cw = Sim3::new(
        nalgebra::UnitQuaternion::from_euler_angles(0.05, -0.1, 0.3),
        Vector3::new(0.4, -0.2, 0.1),
        0.5,
    );
    let client = CLIENT + 1;
    let mut b = KeyframeHandler::new(client, HandlerParams::default());
    let kf_b = |k: usize| {
        let t_wk = true_pose(k);
        let mut kf = keyframe(k as u64, 1, &t_wk, &transform_pose(&s_cw, &t_wk));
        kf.client_id = client;
        kf
    };
    for k in 2..4 {
        b.handle(&mut maps, kf_b(k)).unwrap();
    }
    let from = b.current_map_id().unwrap();
    // Point pairs (point of b's map, the same scene point in the frozen map).
    let pairs: Vec<(PointId, PointId)> = (0..1200u64)
        .filter_map(|i| {
            let p = maps[&from].server_point((client, 1), i)?;
            Some((p, maps[&frozen_id].server_point((CLIENT, 1), i)?))
        })
        .collect();
    assert!(pairs.len() > 100, "{} pairs", pairs.len());
    let s = s_cw.inverse();
    let e = relocalise_in_frozen(&mut maps, frozen_id, from, &s, &pairs).unwrap_err();
    assert!(e.to_string().contains("frozen"), "{e}");
    let r = relocalise_in_frozen(&mut maps, from, frozen_id, &s, &pairs).unwrap();
    assert!(
        !maps.contains_key(&from),
        "the relocalised map leaves the store"
    );
    let reference = r.reference.expect("a frozen keyframe sees the pairs");
    assert!(maps[&frozen_id].map.keyframes.contains_key(&reference));
    for (k, kf) in &r.dropped.map.keyframes {
        let truth = true_pose(KeyframeId::from_raw(*k).client_kf() as usize);
        let err = (kf.t_cw.inverse().translation.vector - truth.translation.vector).norm();
        assert!(
            err < 1e-6,
            "dropped keyframe {k:#x} moved into the frozen frame: {err}"
        );
    }
    assert!(b.apply_relocalisation(from, frozen_id, &s, &r.dropped, r.reference));
    assert!(!a.apply_relocalisation(from, frozen_id, &s, &r.dropped, r.reference));
    for k in 4..10 {
        let rep = b.handle(&mut maps, kf_b(k)).unwrap();
        assert_eq!(rep.status, KeyframeStatus::Discarded, "keyframe {k}");
        assert_eq!(rep.map_id, Some(frozen_id));
        let err = (rep.t_sk.unwrap().translation.vector - true_pose(k).translation.vector).norm();
        assert!(err < 2e-3, "keyframe {k}: localised {err} off the truth");
        assert!(rep.inliers > 100, "keyframe {k}: {} inliers", rep.inliers);
        assert!(b.idle_step(&mut maps).is_none(), "no BA in a frozen map");
    }
    assert_eq!((b.stats().localised, b.stats().relocalisations), (6, 1));
    let after = &maps[&frozen_id];
    assert_eq!(after.map.keyframes.len(), before.map.keyframes.len());
    for (k, kf) in &before.map.keyframes {
        assert_eq!(
            after.map.keyframes[k].t_cw, kf.t_cw,
            "keyframe {k:#x} moved"
        );
    }
    assert_eq!(after.map.points.len(), before.map.points.len());
    for (p, mp) in &before.map.points {
        let now = &after.map.points[p];
        assert_eq!(
            (now.p_w, now.observations.len()),
            (mp.p_w, mp.observations.len())
        );
    }
    // The session's end inserts nothing either.
    b.handle(&mut maps, {
        let mut kf = kf_b(0);
        kf.session_id = 2;
        kf
    })
    .unwrap();
    assert_eq!(
        maps[&frozen_id].map.keyframes.len(),
        before.map.keyframes.len()
    );
}
