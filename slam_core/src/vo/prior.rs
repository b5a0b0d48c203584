//! A saved server map as a client's starting map (issue 20: a session on a loaded map
//! relocalises at its first revisit, not only once its own monocular VO has initialised).
//!
//! A server map is a [`ClientMap`] in the server's world with the server's ids. Before its
//! VO initialises, the client tracks each frame against it too (ORB-SLAM's localisation
//! against a map, seed §3.3's relocalisation): the first frame that relocalises starts the
//! session *in that map*, its world, scale and points, with
//! [`super::VoTracker::start_in_prior_map`]. From there the VO maps as usual; its new
//! keyframes and points are its own and go to the server, whose loop closer then finds the
//! match with the loaded map at once (an almost identical similarity) and merges, or, with
//! `--localize-only`, relocalises the session in the frozen map.
//!
//! The map's keyframes are *prior keyframes*: renumbered `1..=N` in time order, below every
//! id a tracker start gives ([`ClientKeyframeId::first_of_start`] of start 1), so
//! [`is_prior_keyframe`] tells them apart and the tracker never sends, spools or reports
//! them; being the oldest ids, they are the first to leave the VO's window. Their points
//! keep the saved ids (server point ids of the loaded clients' range, far above any client
//! point counter), and the VO's new points continue past them.
use super::map::{ClientMap, Keyframe, KfId};
use super::resume::{restore_map, RestoredMap, StoredPoint};
use crate::ids::ClientKeyframeId;
use crate::CoreError;

/// Whether `id` is a prior keyframe's (module docs): below tracker start 1's range.
pub fn is_prior_keyframe(id: KfId) -> bool {
    ClientKeyframeId::from_raw(id).start() == 0
}

/// The client map of saved map `saved` (module docs): its keyframes without their inertial
/// state and IMU segments (a prior for the monocular VO), renumbered `1..=N` by time (equal
/// times nudged 1 ns apart), their points with positions and observations, covisibility and
/// descriptors recomputed ([`restore_map`]). Refused as `restore_map` refuses (fewer than
/// [`super::resume::MIN_RESTORED_POINTS`] points, cameras of different sizes, ...), and for
/// more keyframes than the prior range holds.
pub fn prior_client_map(saved: &ClientMap) -> Result<RestoredMap, CoreError> {
    let first_own = ClientKeyframeId::first_of_start(1).raw();
    if saved.keyframes.len() as u64 >= first_own {
        return Err(CoreError::Resume(format!(
            "{} keyframes, more than a prior map holds",
            saved.keyframes.len()
        )));
    }
    let mut keyframes: Vec<Keyframe> = saved.keyframes.values().cloned().collect();
    keyframes.sort_by_key(|k| (k.t_ns, k.id));
    let mut last_t = i64::MIN;
    for (i, kf) in keyframes.iter_mut().enumerate() {
        kf.id = i as KfId + 1;
        kf.t_ns = kf.t_ns.max(last_t.saturating_add(1));
        last_t = kf.t_ns;
        kf.inertial = None;
        kf.imu = None;
    }
    let points: Vec<StoredPoint> = saved
        .points
        .values()
        .map(|p| StoredPoint {
            id: p.id,
            p_w: p.p_w,
        })
        .collect();
    restore_map(1, keyframes, &points, 0)
}

#[cfg(test)]
mod tests {
    use nalgebra::{Isometry3, Vector3};

    use super::*;
    use crate::camera::PinholeRadtan;
    use crate::features::{KeyPoint, OrbFeatures};

    /// A keyframe at `x` seeing points `ids` (one keypoint each).
    fn keyframe(id: KfId, t_ns: i64, x: f64, ids: &[u64]) -> Keyframe {
        let mut features = OrbFeatures::default();
        for (i, _) in ids.iter().enumerate() {
            features
                .keypoints
                .push(KeyPoint::at_level0(10.0 + i as f32, 20.0));
            features.descriptors.push([i as u8; 32]);
        }
        Keyframe {
            id,
            t_ns,
            t_cw: Isometry3::translation(-x, 0.0, 0.0),
            camera: PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0),
            readout_ns: 0,
            features,
            points: ids.iter().map(|&p| Some(p)).collect(),
            inertial: Some(Default::default()),
            imu: None,
        }
    }

    /// A saved map of two clients' keyframes (server ids, one time shared) becomes prior
    /// keyframes 1..=3 in time order, points and observations kept, no inertial state; a
    /// map with too few points is refused.
    #[test]
    fn a_saved_map_becomes_prior_keyframes_in_time_order() {
        let base = 1u64 << 63;
        let ids: Vec<u64> = (0..40).map(|i| base + i).collect();
        let mut saved = ClientMap::new(7, 0);
        for &p in &ids {
            saved.insert_point(p, Vector3::new(p as f64 * 1e-20, 0.0, 3.0), 0);
        }
        // Server keyframe ids: client 2's before client 1's in id order, later in time.
        saved.insert_keyframe(keyframe((2 << 40) | 5, 3_000, 0.2, &ids));
        saved.insert_keyframe(keyframe((1 << 40) | 9, 1_000, 0.0, &ids));
        saved.insert_keyframe(keyframe((1 << 40) | 8, 1_000, 0.1, &ids[..35]));
        let prior = prior_client_map(&saved).expect("prior").map;
        let ks: Vec<(KfId, i64)> = prior.keyframes.values().map(|k| (k.id, k.t_ns)).collect();
        assert_eq!(ks, vec![(1, 1_000), (2, 1_001), (3, 3_000)]);
        assert!(prior.keyframes.keys().all(|&k| is_prior_keyframe(k)));
        assert!(!is_prior_keyframe(
            ClientKeyframeId::first_of_start(1).raw()
        ));
        // Keyframe 1 is the saved (1<<40)|8 at x = 0.1, seeing 35 points.
        assert_eq!(prior.keyframes[&1].t_cw.translation.vector.x, -0.1);
        assert_eq!(prior.keyframes[&1].points.iter().flatten().count(), 35);
        assert_eq!(prior.points.len(), 40);
        assert_eq!(prior.points[&(base + 39)].observations.len(), 2);
        assert!(prior.keyframes.values().all(|k| k.inertial.is_none()));
        assert!(
            prior.next_point_id() > base + 39,
            "new points after the saved ones"
        );
        let mut small = ClientMap::new(7, 0);
        for &p in &ids[..10] {
            small.insert_point(p, Vector3::new(0.0, 0.0, 3.0), 0);
        }
        small.insert_keyframe(keyframe(1 << 40, 0, 0.0, &ids[..10]));
        assert!(matches!(
            prior_client_map(&small),
            Err(CoreError::Resume(_))
        ));
    }
}
