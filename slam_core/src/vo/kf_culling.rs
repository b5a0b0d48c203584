//! Redundant keyframe culling (seed §3.3 local mapping and §3.4.1 server handler; ORB-SLAM's
//! KeyFrameCulling): a keyframe whose map points are more than 90% seen by at least three
//! other keyframes, at the same or a finer scale, adds nothing and is removed. Usable by the
//! client's local mapping and by the server's keyframe handler.
use super::keyframe_imu::join_segments;
use super::map::{ClientMap, Keyframe, KfId};
use crate::ids::KeyframeId;

/// Parameters of [`redundant_fraction`] and [`cull_redundant_keyframes`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KfCullingParams {
    /// A keyframe is redundant when more than this fraction of its points is seen by
    /// `min_observers` other keyframes (seed: 0.9).
    pub redundancy: f64,
    /// Other keyframes that must see a point (seed: 3).
    pub min_observers: usize,
    /// "Same or finer scale": the other observation's octave is at most this many levels
    /// above the keyframe's own (ORB-SLAM: 1).
    pub octave_slack: u8,
    /// Keyframes of the neighbourhood examined around the latest keyframe (best covisible).
    pub neighbours: usize,
    /// Points with fewer observations are erased with a culled keyframe.
    pub min_point_observations: usize,
}

impl Default for KfCullingParams {
    fn default() -> Self {
        Self {
            redundancy: 0.9,
            min_observers: 3,
            octave_slack: 1,
            neighbours: 20,
            min_point_observations: 2,
        }
    }
}

/// Fraction of keyframe `k`'s map points seen by at least `min_observers` other keyframes
/// at the same or a finer scale (0 when `k` is unknown or has no point).
pub fn redundant_fraction(map: &ClientMap, k: KfId, params: &KfCullingParams) -> f64 {
    let Some(kf) = map.keyframes.get(&k) else {
        return 0.0;
    };
    let (mut total, mut redundant) = (0usize, 0usize);
    for (i, p) in kf.points.iter().enumerate() {
        let Some(mp) = p.and_then(|p| map.points.get(&p)) else {
            continue;
        };
        total += 1;
        if mp.observations.len() <= params.min_observers {
            continue;
        }
        let octave = kf.features.keypoints.get(i).map_or(0, |kp| kp.octave);
        let max_octave = octave.saturating_add(params.octave_slack);
        let observers = mp
            .observations
            .iter()
            .filter(|(o, j)| {
                *o != k
                    && map
                        .keyframes
                        .get(o)
                        .and_then(|okf| okf.features.keypoints.get(*j as usize))
                        .is_some_and(|kp| kp.octave <= max_octave)
            })
            .count();
        if observers >= params.min_observers {
            redundant += 1;
        }
    }
    if total == 0 {
        0.0
    } else {
        redundant as f64 / total as f64
    }
}

/// Removes the redundant keyframes among the best covisible neighbours of `latest`
/// (examined in ascending id order, each decision seeing the removals before it, so the
/// result is deterministic). Never removes `latest`, the first keyframe of the map, a
/// keyframe in `protected`, or a keyframe whose IMU segment has no keyframe of its client
/// after it to join (its client's newest in a server map that other clients' handlers
/// cull: the client's next keyframe will start its segment there). Returns the removed
/// ids.
pub fn cull_redundant_keyframes(
    map: &mut ClientMap,
    latest: KfId,
    protected: &[KfId],
    params: &KfCullingParams,
) -> Vec<KfId> {
    let first = map.keyframes.keys().next().copied();
    let mut candidates = map.covisible(latest, params.neighbours, 1);
    candidates.sort_unstable();
    let mut removed = Vec::new();
    for k in candidates {
        if k == latest || Some(k) == first || protected.contains(&k) || imu_has_no_successor(map, k)
        {
            continue;
        }
        if redundant_fraction(map, k, params) > params.redundancy {
            let neighbours = map.covisible(k, usize::MAX, 1);
            if let Some(culled) = map.remove_keyframe(k, params.min_point_observations) {
                join_imu_into_successor(map, &culled);
                for n in neighbours {
                    map.update_covisibility(n);
                }
                removed.push(k);
            }
        }
    }
    removed
}

/// Whether keyframe `k` has an IMU segment and no keyframe of its client after it (the
/// segment would have nowhere to go, [`join_imu_into_successor`]).
fn imu_has_no_successor(map: &ClientMap, k: KfId) -> bool {
    map.keyframes.get(&k).is_some_and(|kf| kf.imu.is_some())
        && successor_of_client(map, k).is_none()
}

/// The keyframe after `k` in id order when it is of `k`'s client.
fn successor_of_client(map: &ClientMap, k: KfId) -> Option<KfId> {
    let client = |id: KfId| KeyframeId::from_raw(id).client();
    map.keyframes
        .range(k + 1..)
        .next()
        .map(|(id, _)| *id)
        .filter(|id| client(*id) == client(k))
}

/// A culled keyframe's IMU segment joins the next keyframe's, so the keyframes around it
/// stay linked ([`crate::vo::keyframe_imu`]). The next keyframe is the next id of the same
/// client: in a server map ids carry the client in their high bits
/// ([`crate::ids::KeyframeId`]; a VO's ids are all of client 0), and a merged map holds
/// other clients' keyframes after a client's newest.
fn join_imu_into_successor(map: &mut ClientMap, culled: &Keyframe) {
    let Some(seg) = &culled.imu else {
        return;
    };
    let next = successor_of_client(map, culled.id);
    if let Some(next) = next.and_then(|n| map.keyframes.get_mut(&n)?.imu.as_mut()) {
        join_segments(seg, next);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::PinholeRadtan;
    use crate::features::{KeyPoint, OrbFeatures};
    use nalgebra::{Isometry3, Vector3};

    fn kf(id: KfId, n: usize, octave: u8) -> Keyframe {
        let kp = KeyPoint {
            x: 10.0,
            y: 10.0,
            angle: 0.0,
            response: 1.0,
            size: 31.0,
            octave,
        };
        Keyframe {
            id,
            t_ns: id as i64,
            t_cw: Isometry3::translation(-(id as f64) * 0.1, 0.0, 0.0),
            camera: PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0),
            readout_ns: 0,
            features: OrbFeatures {
                keypoints: vec![kp; n],
                descriptors: vec![[0; 32]; n],
                ..OrbFeatures::default()
            },
            points: vec![None; n],
            inertial: None,
            imu: None,
        }
    }

    /// Keyframes 0-4 made by `kf`, each seeing the same 20 points.
    fn five_keyframes_seeing_20_points(kf: impl Fn(KfId) -> Keyframe) -> ClientMap {
        let mut m = ClientMap::new(1, 0);
        for id in 0..5 {
            m.insert_keyframe(kf(id));
        }
        for i in 0..20u32 {
            let obs: Vec<(KfId, u32)> = (0..5).map(|k| (k, i)).collect();
            m.add_point(Vector3::new(i as f64 * 0.1, 0.0, 5.0), 0, &obs);
        }
        for k in 0..5 {
            m.update_covisibility(k);
        }
        m
    }

    /// Five keyframes see the same 20 points. One removal at a time: keyframes 1 and 2 go,
    /// then the points of keyframe 3 are seen by only two others and it stays; the first and
    /// the latest always stay, protected keyframes too.
    #[test]
    fn culls_redundant_but_never_first_or_latest() {
        let build = || five_keyframes_seeing_20_points(|id| kf(id, 20, 0));
        let p = KfCullingParams::default();
        let mut m = build();
        assert_eq!(redundant_fraction(&m, 2, &p), 1.0);
        assert_eq!(cull_redundant_keyframes(&mut m, 4, &[], &p), vec![1, 2]);
        assert_eq!(
            m.keyframes.keys().copied().collect::<Vec<_>>(),
            vec![0, 3, 4]
        );
        assert_eq!(m.points.len(), 20);
        let mut m = build();
        assert_eq!(cull_redundant_keyframes(&mut m, 4, &[1, 2], &p), vec![3]);
    }

    /// Keyframes carrying IMU segments (every 10 ns, samples each ns): culling 1 and 2
    /// leaves keyframe 3's segment starting at keyframe 0, with every sample once.
    #[test]
    fn culled_keyframes_join_their_imu_segments_into_the_next() {
        let m = culled_with_imu(0);
        let (k0, k3) = (&m.keyframes[&0], &m.keyframes[&3]);
        let seg = k3.imu.as_ref().expect("imu");
        assert!(seg.links(k0.imu.as_ref().expect("imu")));
        let times: Vec<i64> = seg.samples.iter().map(|s| s.t_ns).collect();
        assert_eq!(times, (0..=30).collect::<Vec<_>>());
    }

    /// The server's culling (the same function on a server map, issue 19): with server ids
    /// (client in the high bits) a culled keyframe's segment joins its client's next
    /// keyframe, never another client's keyframe that follows it in id order.
    #[test]
    fn server_culling_joins_segments_within_a_client() {
        use crate::ids::ClientId;
        let base = KeyframeId::new(ClientId::new(1), 0).raw();
        let m = culled_with_imu(base);
        let seg = m.keyframes[&(base + 3)].imu.as_ref().expect("imu");
        assert!(seg.links(m.keyframes[&base].imu.as_ref().expect("imu")));
        assert_eq!(seg.samples.len(), 31);
        // Client 1's newest keyframe culled: client 2's keyframe after it in id order, with
        // a segment of the same times (two clients replaying one dataset), is left alone.
        let mut m = ClientMap::new(1, 0);
        let other = KeyframeId::new(ClientId::new(2), 0).raw();
        let culled = with_segment(kf(base + 1, 1, 0), 10);
        let mut next = with_segment(kf(other, 1, 0), 20);
        next.imu.as_mut().expect("imu").t_prev_ns = Some(10);
        let before = next.imu.clone();
        m.insert_keyframe(next);
        join_imu_into_successor(&mut m, &culled);
        assert_eq!(m.keyframes[&other].imu, before);
    }

    /// A merged server map (issue 19): client 1's keyframes 0-4, then client 2's; every
    /// one sees the same points, so all are redundant. Client 2's handler culls around its
    /// own newest: client 1's newest keyframe stays (its segment has no keyframe of client
    /// 1 to join; client 1's next keyframe will link to it), the others of client 1 go with
    /// their segments joined into the next, so no sample of client 1 is lost.
    #[test]
    fn a_clients_newest_keyframe_with_a_segment_is_not_culled_by_another_client() {
        use crate::ids::ClientId;
        let (c1, c2) = (
            KeyframeId::new(ClientId::new(1), 0).raw(),
            KeyframeId::new(ClientId::new(2), 0).raw(),
        );
        let mut m = ClientMap::new(1, 0);
        let ids: Vec<KfId> = (0..5)
            .map(|i| c1 + i)
            .chain((0..5).map(|i| c2 + i))
            .collect();
        for (i, id) in ids.iter().enumerate() {
            let t = 10 * (i as i64 % 5);
            m.insert_keyframe(with_segment(kf(*id, 20, 0), t));
        }
        for i in 0..20u32 {
            let obs: Vec<(KfId, u32)> = ids.iter().map(|k| (*k, i)).collect();
            m.add_point(Vector3::new(i as f64 * 0.1, 0.0, 5.0), 0, &obs);
        }
        for k in &ids {
            m.update_covisibility(*k);
        }
        let p = KfCullingParams {
            neighbours: 20,
            ..KfCullingParams::default()
        };
        let culled = cull_redundant_keyframes(&mut m, c2 + 4, &[], &p);
        assert!(!culled.contains(&(c1 + 4)), "{culled:?}");
        assert!(culled.contains(&(c1 + 1)), "{culled:?}");
        let newest = m.keyframes[&(c1 + 4)].imu.as_ref().expect("segment");
        // Client 1's chain from its first keyframe to its newest: linked, every sample once.
        let kept: Vec<&Keyframe> = m.keyframes.range(c1..c1 + 5).map(|(_, k)| k).collect();
        assert_eq!(kept.first().map(|k| k.id), Some(c1));
        for w in kept.windows(2) {
            let (a, b) = (w[0].imu.as_ref().unwrap(), w[1].imu.as_ref().unwrap());
            assert!(b.links(a), "{} -> {}", w[0].id, w[1].id);
        }
        let times: Vec<i64> = newest.samples.iter().map(|s| s.t_ns).collect();
        assert_eq!(kept.len(), 2, "client 1's first and newest");
        assert_eq!(
            times,
            (0..=40).collect::<Vec<_>>(),
            "every sample since the first"
        );
    }

    /// Keyframe `k` with the segment from `t - 10` (none before 0) to `t`, samples each ns.
    fn with_segment(mut k: Keyframe, t: i64) -> Keyframe {
        use crate::imu::ImuMeasurement;
        use crate::vo::keyframe_imu::{bracket, ImuCalibration, KeyframeImu};
        let calib = ImuCalibration {
            preint: crate::imu::PreintegrationParams::new(&Default::default(), &Default::default())
                .expect("params"),
            t_bc: Isometry3::identity(),
            t_d_ns: 0,
        };
        let samples: Vec<ImuMeasurement> = (0..=50)
            .map(|t| ImuMeasurement {
                t_ns: t,
                gyro: Vector3::zeros(),
                accel: Vector3::zeros(),
            })
            .collect();
        let t_prev = (t > 0).then(|| t - 10);
        k.imu = Some(KeyframeImu {
            t_prev_ns: t_prev,
            t_ns: t,
            samples: bracket(&samples, t_prev.unwrap_or(t), t).to_vec(),
            calib,
        });
        k
    }

    /// Five keyframes with ids `base..base + 5`, segments every 10 ns, after culling
    /// (keyframes `base + 1` and `base + 2` go).
    fn culled_with_imu(base: KfId) -> ClientMap {
        let mut m = ClientMap::new(1, 0);
        for i in 0..5 {
            m.insert_keyframe(with_segment(kf(base + i, 20, 0), 10 * i as i64));
        }
        for i in 0..20u32 {
            let obs: Vec<(KfId, u32)> = (0..5).map(|k| (base + k, i)).collect();
            m.add_point(Vector3::new(i as f64 * 0.1, 0.0, 5.0), 0, &obs);
        }
        for k in 0..5 {
            m.update_covisibility(base + k);
        }
        let p = KfCullingParams::default();
        let culled = cull_redundant_keyframes(&mut m, base + 4, &[], &p);
        assert_eq!(culled, vec![base + 1, base + 2]);
        m
    }

    #[test]
    fn coarser_observations_do_not_count() {
        let mut m = ClientMap::new(1, 0);
        m.insert_keyframe(kf(0, 10, 0));
        m.insert_keyframe(kf(1, 10, 0));
        for id in 2..5 {
            m.insert_keyframe(kf(id, 10, 3));
        }
        for i in 0..10u32 {
            let obs: Vec<(KfId, u32)> = (0..5).map(|k| (k, i)).collect();
            m.add_point(Vector3::new(i as f64 * 0.1, 0.0, 5.0), 0, &obs);
        }
        for k in 0..5 {
            m.update_covisibility(k);
        }
        let p = KfCullingParams::default();
        // Keyframe 1 (octave 0): others at octave 3 are coarser; only keyframe 0 counts.
        assert_eq!(redundant_fraction(&m, 1, &p), 0.0);
        // Keyframe 3 (octave 3): all four others are at the same or a finer scale.
        assert_eq!(redundant_fraction(&m, 3, &p), 1.0);
    }
}
