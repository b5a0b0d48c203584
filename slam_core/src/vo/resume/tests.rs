//! The map rebuilt from stored keyframes is the map that was stored (observations,
//! covisibility, descriptors, positions); untrusted observations are dropped and counted;
//! stores no VO could have written are refused with the reason.
use nalgebra::{Isometry3, Vector3};

use super::*;
use crate::camera::PinholeRadtan;
use crate::features::{KeyPoint, OrbFeatures};
use crate::vo::KeyframeInertial;

fn camera() -> PinholeRadtan {
    PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0)
}

/// 60 points on a wall 5 m ahead, ids from 1000.
fn wall() -> Vec<StoredPoint> {
    (0..60u64)
        .map(|i| StoredPoint {
            id: 1000 + i,
            p_w: Vector3::new(
                (i % 10) as f64 * 0.3 - 1.4,
                (i / 10) as f64 * 0.3 - 0.8,
                5.0,
            ),
        })
        .collect()
}

/// Keyframe `k` at x = 0.2 k m seeing every point of `wall` (keypoint i on point i, a
/// descriptor per point and keyframe).
fn keyframe(k: u64, wall: &[StoredPoint]) -> Keyframe {
    let t_cw = Isometry3::translation(-0.2 * k as f64, 0.0, 0.0);
    let cam = camera();
    let mut features = OrbFeatures::default();
    for (i, p) in wall.iter().enumerate() {
        let uv = cam.project(&(t_cw * nalgebra::Point3::from(p.p_w)).coords);
        let uv = uv.expect("in view");
        features
            .keypoints
            .push(KeyPoint::at_level0(uv.x as f32, uv.y as f32));
        let mut d = [i as u8; 32];
        d[0] = k as u8;
        features.descriptors.push(d);
    }
    Keyframe {
        id: 7 + k,
        t_ns: 1_000_000_000 + k as i64 * 50_000_000,
        t_cw,
        camera: cam,
        readout_ns: 0,
        features,
        points: wall.iter().map(|p| Some(p.id)).collect(),
        inertial: Some(KeyframeInertial::default()),
        imu: None,
    }
}

fn store(n: u64) -> (Vec<Keyframe>, Vec<StoredPoint>) {
    let w = wall();
    ((0..n).map(|k| keyframe(k, &w)).collect(), w)
}

fn refusal(r: Result<RestoredMap, CoreError>) -> String {
    match r {
        Err(CoreError::Resume(why)) => why,
        Err(e) => panic!("refused with another error: {e}"),
        Ok(_) => panic!("not refused"),
    }
}

/// The rebuilt map equals one built the VO's way (keyframes inserted, points added with
/// their observations): same keyframes, points, observations, covisibility, descriptors.
#[test]
fn the_rebuilt_map_is_the_stored_one() {
    let (kfs, points) = store(4);
    let mut expected = ClientMap::new(1, 1000);
    for kf in &kfs {
        let mut bare = kf.clone();
        bare.points = vec![None; bare.points.len()];
        expected.insert_keyframe(bare);
    }
    for (i, p) in points.iter().enumerate() {
        let obs: Vec<(KfId, u32)> = kfs.iter().map(|k| (k.id, i as u32)).collect();
        assert_eq!(expected.add_point(p.p_w, kfs[0].id, &obs), p.id);
    }
    for kf in &kfs {
        expected.update_covisibility(kf.id);
    }
    assert_eq!(expected.covis_weight(7, 10), 60);
    // Stored in reverse order, an older position of point 1000 given first.
    let mut stored = vec![StoredPoint {
        id: 1000,
        p_w: Vector3::new(9.0, 9.0, 9.0),
    }];
    stored.extend(&points);
    let r = restore_map(1, kfs.into_iter().rev().collect(), &stored, 0).expect("restored");
    let m = &r.map;
    assert_eq!((r.observations_dropped, r.points_unobserved), (0, 0));
    assert_eq!(m.session_id, 1);
    assert_eq!(
        m.keyframes.keys().collect::<Vec<_>>(),
        expected.keyframes.keys().collect::<Vec<_>>()
    );
    assert_eq!(m.points.len(), expected.points.len());
    for (id, p) in &expected.points {
        let q = &m.points[id];
        assert_eq!(q.p_w, p.p_w, "the position given last wins");
        assert_eq!(q.descriptor, p.descriptor);
        assert!((q.normal - p.normal).norm() < 1e-12);
        let (mut a, mut b) = (q.observations.clone(), p.observations.clone());
        a.sort_unstable();
        b.sort_unstable();
        assert_eq!(a, b);
    }
    for &a in expected.keyframes.keys() {
        for &b in expected.keyframes.keys() {
            assert_eq!(m.covis_weight(a, b), expected.covis_weight(a, b));
        }
    }
    assert!(
        m.next_point_id() > 1059,
        "new points never take a stored id"
    );
}

/// Observations of points without a position and repeated ones are dropped and counted;
/// stored points nobody observes stay out; new ids start where asked.
#[test]
fn untrusted_observations_are_dropped_and_counted() {
    let (mut kfs, mut points) = store(3);
    kfs[1].points[3] = Some(5); // no position stored for point 5
    kfs[2].points[4] = Some(1000); // point 1000 twice in one keyframe
    points.push(StoredPoint {
        id: 77,
        p_w: Vector3::new(0.0, 0.0, 3.0),
    });
    let first_new = 1 << 40;
    let r = restore_map(2, kfs, &points, first_new).expect("restored");
    assert_eq!(r.observations_dropped, 2);
    assert_eq!(r.points_unobserved, 1);
    assert!(!r.map.points.contains_key(&77) && !r.map.points.contains_key(&5));
    assert_eq!(r.map.keyframes[&8].points[3], None);
    assert_eq!(r.map.keyframes[&9].points[4], None);
    assert_eq!(r.map.keyframes[&9].points[0], Some(1000));
    for mp in r.map.points.values() {
        for (k, i) in &mp.observations {
            assert_eq!(r.map.keyframes[k].points[*i as usize], Some(mp.id));
        }
    }
    assert_eq!(r.map.next_point_id(), first_new);
}

/// What no VO could have stored is refused, with the reason.
#[test]
fn impossible_stores_are_refused_with_the_reason() {
    let (kfs, points) = store(3);
    assert!(refusal(restore_map(1, vec![], &points, 0)).contains("no stored keyframe"));
    let mut twice = kfs.clone();
    twice.push(kfs[1].clone());
    assert!(refusal(restore_map(1, twice, &points, 0)).contains("stored twice"));
    let mut order = kfs.clone();
    order[2].t_ns = order[0].t_ns;
    assert!(refusal(restore_map(1, order, &points, 0)).contains("not after"));
    let mut nan = kfs.clone();
    nan[1].t_cw.translation.vector.x = f64::NAN;
    assert!(refusal(restore_map(1, nan, &points, 0)).contains("non-finite pose"));
    let mut short = kfs.clone();
    short[0].features.descriptors.pop();
    assert!(refusal(restore_map(1, short, &points, 0)).contains("descriptors"));
    let mut bad = points.clone();
    bad[3].p_w.z = f64::INFINITY;
    assert!(refusal(restore_map(1, kfs.clone(), &bad, 0)).contains("non-finite position"));
    assert!(refusal(restore_map(1, kfs, &points[..20], 0)).contains("fewer than"));
}
