//! Loop corrections applied to server maps (seed §3.4.2-3.4.3): the mapper owns the maps and
//! applies what the loop closer computed.
//!
//! - **Merge** ([`merge_maps`]): a loop between keyframes of two different maps gives the
//!   similarity `S_into_from` (`x_into = s R x_from + t`); the `from` map is transformed by
//!   it and moved into the `into` map, and the matched points are fused.
//! - **Pose-graph correction** ([`apply_pose_corrections`]): a loop within one map gives per
//!   keyframe similarity corrections `Δ_k = S_k,new S_k,old⁻¹` (map → map). They are
//!   applied to the keyframes' *current* poses (which local BA may have moved since the loop
//!   closer saw them) and to every point through its reference keyframe (eq. 3.13).
//! - **Scale ratio** after a loop (eq. 3.6, [`scale_ratio_after_loop`]).
use std::collections::BTreeMap;

use nalgebra::Isometry3;

use super::server_map::ServerMap;
use super::types::MapId;
use crate::lie::Sim3;
use crate::vo::{ClientMap, Keyframe, KfId, PointId};
use crate::CoreError;

/// `S ∘ T` for a camera pose `T` (camera → map) with the scale dropped: the camera keeps its
/// rotation relative to the map and its centre moves with the map (`c' = S c`).
pub fn transform_pose(s: &Sim3, t: &Isometry3<f64>) -> Isometry3<f64> {
    s.compose(&Sim3::from_isometry(t, 1.0)).to_isometry()
}

/// Transforms a whole map (keyframe poses and points) by the similarity `s`.
pub fn transform_map(map: &mut ClientMap, s: &Sim3) {
    for kf in map.keyframes.values_mut() {
        kf.t_cw = transform_pose(s, &kf.t_cw.inverse()).inverse();
        transform_velocity(kf, s);
    }
    let ids: Vec<PointId> = map.points.keys().copied().collect();
    for mp in map.points.values_mut() {
        mp.p_w = s.transform_point(&mp.p_w);
    }
    for p in ids {
        map.update_point(p);
    }
}

/// A keyframe's velocity (a visual-inertial map's) in the map moved by `s`: `v' = s R v`.
fn transform_velocity(kf: &mut Keyframe, s: &Sim3) {
    if let Some(i) = kf.inertial.as_mut() {
        i.v_wb = s.r * i.v_wb * s.s;
    }
}

/// Eq. 3.6: after a loop whose correction rescales the client's part of the map by `s`
/// (lengths there are multiplied by `s`), the pseudo-measurement of the scale ratio is
/// `λ~ = s λ` (the seed's `λ_k / s~_cm`, with its `S~_cm` in the opposite direction), and
/// `λ ← λ + β (λ~ - λ)` (seed: `β = 0.9`).
pub fn scale_ratio_after_loop(lambda: f64, s: f64, beta: f64) -> f64 {
    if !(s.is_finite() && s > 0.0) {
        return lambda;
    }
    lambda + beta * (s * lambda - lambda)
}

/// What [`merge_maps`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct MergeReport {
    /// Keyframes moved from the `from` map.
    pub keyframes_moved: usize,
    /// Matched point pairs fused.
    pub points_fused: usize,
}

/// Merges map `from` into map `into` (seed §3.4.2, "if m and c are in different maps"):
/// `from` is transformed by `s_into_from` and absorbed by `into`; each pair `(a, b)` of
/// `point_pairs` (a point of `from`, the same 3-D point in `into`) is fused into `b`.
/// Errors (and leaves the maps unchanged) when a map is missing or both ids are the same.
pub fn merge_maps(
    maps: &mut BTreeMap<MapId, ServerMap>,
    from: MapId,
    into: MapId,
    s_into_from: &Sim3,
    point_pairs: &[(PointId, PointId)],
) -> Result<MergeReport, CoreError> {
    check_merge(maps, from, into, s_into_from)?;
    let Some(mut other) = maps.remove(&from) else {
        return Err(CoreError::InvalidArgument(format!(
            "merge of unknown map {from}"
        )));
    };
    transform_map(&mut other.map, s_into_from);
    let Some(target) = maps.get_mut(&into) else {
        // Checked above; put the map back rather than lose it.
        maps.insert(from, other);
        return Err(CoreError::InvalidArgument(format!(
            "merge into unknown map {into}"
        )));
    };
    let keyframes_moved = target.absorb(other);
    let points_fused = fuse_points(target, point_pairs);
    Ok(MergeReport {
        keyframes_moved,
        points_fused,
    })
}

/// The checks of a merge of `from` into `into` (both exist and differ, a usable similarity).
fn check_merge(
    maps: &BTreeMap<MapId, ServerMap>,
    from: MapId,
    into: MapId,
    s_into_from: &Sim3,
) -> Result<(), CoreError> {
    if from == into {
        return Err(CoreError::InvalidArgument(format!(
            "merge of map {from} into itself"
        )));
    }
    if !(s_into_from.s.is_finite()
        && s_into_from.s > 0.0
        && s_into_from.t.iter().all(|v| v.is_finite()))
    {
        return Err(CoreError::InvalidArgument(format!(
            "merge of map {from} into {into}: invalid similarity (scale {})",
            s_into_from.s
        )));
    }
    if !maps.contains_key(&into) {
        return Err(CoreError::InvalidArgument(format!(
            "merge into unknown map {into}"
        )));
    }
    if !maps.contains_key(&from) {
        return Err(CoreError::InvalidArgument(format!(
            "merge of unknown map {from}"
        )));
    }
    Ok(())
}

/// What [`relocalise_in_frozen`] did.
#[derive(Debug, Clone)]
pub struct Relocalisation {
    /// The map that matched the frozen one, out of the store, moved into its frame.
    pub dropped: ServerMap,
    /// The frozen map's keyframe observing most of the matched points (`None`: no pair
    /// names one of its points).
    pub reference: Option<KfId>,
}

/// Map `from` matched the frozen map `into` (`--localize-only`; seed §3.4.2 with the merge
/// replaced by a relocalisation): `into` is left as it is; `from` leaves the store, moved
/// into `into`'s frame by `s_into_from` so that its clients' poses (and the files written
/// of them) follow. Its clients then localise in `into`
/// ([`super::KeyframeHandler::apply_relocalisation`]). Errors (maps unchanged) as
/// [`merge_maps`] does, and when `into` is not frozen or `from` is.
pub fn relocalise_in_frozen(
    maps: &mut BTreeMap<MapId, ServerMap>,
    from: MapId,
    into: MapId,
    s_into_from: &Sim3,
    point_pairs: &[(PointId, PointId)],
) -> Result<Relocalisation, CoreError> {
    check_merge(maps, from, into, s_into_from)?;
    let frozen = |m: MapId| maps.get(&m).is_some_and(ServerMap::is_frozen);
    if !frozen(into) || frozen(from) {
        return Err(CoreError::InvalidArgument(format!(
            "relocalisation of map {from} in {into}: only a live map relocalises in a frozen one"
        )));
    }
    let Some(target) = maps.get(&into).map(|m| &m.map) else {
        return Err(CoreError::InvalidArgument(format!(
            "merge into unknown map {into}"
        )));
    };
    let reference = target.keyframe_sharing_most(point_pairs.iter().map(|(_, b)| b));
    let Some(mut dropped) = maps.remove(&from) else {
        return Err(CoreError::InvalidArgument(format!(
            "merge of unknown map {from}"
        )));
    };
    transform_map(&mut dropped.map, s_into_from);
    Ok(Relocalisation { dropped, reference })
}

/// Fuses each pair `(a, b)` of `pairs` into `b` (both must be points of `map`); returns how
/// many were fused.
pub fn fuse_points(map: &mut ServerMap, pairs: &[(PointId, PointId)]) -> usize {
    let mut n = 0;
    for &(a, b) in pairs {
        if map.map.fuse_point(a, b).is_some() {
            map.redirect_point(a, b);
            n += 1;
        }
    }
    n
}

/// What [`apply_pose_corrections`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CorrectionReport {
    /// Keyframes moved by their own correction.
    pub keyframes_corrected: usize,
    /// Keyframes the loop closer did not know (newer, in flight) moved by the fallback.
    pub keyframes_fallback: usize,
    /// Points moved.
    pub points_moved: usize,
}

/// Applies per-keyframe corrections `deltas[k] = Δ_k` (map → map similarities) to `map`:
/// each keyframe pose becomes `Δ_k ∘ T_k` (see [`transform_pose`]); keyframes without an
/// entry take `fallback` (the correction of the newest keyframe the loop closer knew). Each
/// point moves with the correction of its reference keyframe, the first that observed it
/// (eq. 3.13: it keeps its coordinates in that keyframe's frame); if that keyframe is gone,
/// with the first of its observers that has one.
pub fn apply_pose_corrections(
    map: &mut ClientMap,
    deltas: &BTreeMap<KfId, Sim3>,
    fallback: &Sim3,
) -> CorrectionReport {
    let mut report = CorrectionReport::default();
    let delta_of = |k: &KfId| deltas.get(k);
    for (k, kf) in map.keyframes.iter_mut() {
        let d = match delta_of(k) {
            Some(d) => {
                report.keyframes_corrected += 1;
                d
            }
            None => {
                report.keyframes_fallback += 1;
                fallback
            }
        };
        kf.t_cw = transform_pose(d, &kf.t_cw.inverse()).inverse();
        transform_velocity(kf, d);
    }
    let ids: Vec<PointId> = map.points.keys().copied().collect();
    for mp in map.points.values_mut() {
        let d = delta_of(&mp.first_kf)
            .or_else(|| mp.observations.iter().find_map(|(k, _)| delta_of(k)))
            .unwrap_or(fallback);
        mp.p_w = d.transform_point(&mp.p_w);
        report.points_moved += 1;
    }
    for p in ids {
        map.update_point(p);
    }
    report
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::PinholeRadtan;
    use crate::features::{KeyPoint, OrbFeatures};
    use crate::ids::{ClientId, KeyframeId, MapPointId};
    use crate::server::MapFrame;
    use crate::vo::Keyframe;
    use nalgebra::{UnitQuaternion, Vector3};

    fn kf(id: KfId, t_wk: Isometry3<f64>, n: usize) -> Keyframe {
        let mut features = OrbFeatures::default();
        for i in 0..n {
            features.keypoints.push(KeyPoint::at_level0(i as f32, 0.0));
            features.descriptors.push([i as u8; 32]);
        }
        Keyframe {
            id,
            t_ns: id as i64,
            t_cw: t_wk.inverse(),
            camera: PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0),
            readout_ns: 0,
            features,
            points: vec![None; n],
            inertial: None,
            imu: None,
        }
    }

    /// Two keyframes observing three points, in a map of `client`'s id range.
    fn small_map(id: MapId, client: u32, kf_base: KfId) -> ServerMap {
        let first_point = MapPointId::first_of_client(ClientId::new(client)).raw();
        let mut m = ServerMap::new(id, client, 1, first_point, MapFrame::VISUAL);
        let a = kf_base;
        let b = kf_base + 1;
        m.map.insert_keyframe(kf(a, Isometry3::identity(), 3));
        m.map
            .insert_keyframe(kf(b, Isometry3::translation(1.0, 0.0, 0.0), 3));
        for i in 0..3u32 {
            m.map
                .add_point(Vector3::new(i as f64, 0.5, 4.0), a, &[(a, i), (b, i)]);
        }
        m
    }

    #[test]
    fn merge_transforms_absorbs_and_fuses() {
        let (m1, m2, m7) = (MapId::from_raw(1), MapId::from_raw(2), MapId::from_raw(7));
        let c1_kf = |k: KfId| KeyframeId::new(ClientId::new(1), k).raw();
        let mut maps = BTreeMap::new();
        maps.insert(m1, small_map(m1, 0, 10));
        maps.insert(m2, small_map(m2, 1, c1_kf(0)));
        let s = Sim3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.3, 0.0),
            Vector3::new(1.0, 2.0, 3.0),
            2.0,
        );
        let from_points: Vec<PointId> = {
            let mut v: Vec<_> = maps[&m2].map.points.keys().copied().collect();
            v.sort();
            v
        };
        let into_points: Vec<PointId> = {
            let mut v: Vec<_> = maps[&m1].map.points.keys().copied().collect();
            v.sort();
            v
        };
        let p_before = maps[&m2].map.points[&from_points[1]].p_w;
        let c_before = maps[&m2].map.keyframes[&c1_kf(1)].center();
        let pairs = [(from_points[0], into_points[0])];
        let r = merge_maps(&mut maps, m2, m1, &s, &pairs).unwrap();
        assert_eq!(r.keyframes_moved, 2);
        assert_eq!(r.points_fused, 1);
        assert!(!maps.contains_key(&m2));
        let m = &maps[&m1];
        assert_eq!(m.map.keyframes.len(), 4);
        assert_eq!(m.map.points.len(), 5);
        let p_after = m.map.points[&from_points[1]].p_w;
        assert!((p_after - s.transform_point(&p_before)).norm() < 1e-12);
        let c_after = m.map.keyframes[&c1_kf(1)].center();
        assert!((c_after - s.transform_point(&c_before)).norm() < 1e-12);
        // The fused point is seen by all four keyframes now.
        assert_eq!(m.map.points[&into_points[0]].observations.len(), 4);
        assert!(m.map.covis_weight(10, c1_kf(0)) >= 1);
        // Errors leave the maps alone.
        assert!(merge_maps(&mut maps, m1, m1, &s, &[]).is_err());
        assert!(merge_maps(&mut maps, m7, m1, &s, &[]).is_err());
        let bad = Sim3::new(UnitQuaternion::identity(), Vector3::zeros(), 0.0);
        assert!(merge_maps(&mut maps, m1, m7, &bad, &[]).is_err());
        assert_eq!(maps.len(), 1);
    }

    #[test]
    fn pose_corrections_move_keyframes_and_points_with_their_reference() {
        let mut m = small_map(MapId::from_raw(1), 0, 10);
        let d10 = Sim3::new(UnitQuaternion::identity(), Vector3::new(0.0, 1.0, 0.0), 1.0);
        let fallback = Sim3::new(UnitQuaternion::identity(), Vector3::zeros(), 0.5);
        let deltas: BTreeMap<KfId, Sim3> = [(10, d10)].into_iter().collect();
        let p_before: Vec<_> = m.map.points.values().map(|p| (p.id, p.p_w)).collect();
        let c11 = m.map.keyframes[&11].center();
        let r = apply_pose_corrections(&mut m.map, &deltas, &fallback);
        assert_eq!((r.keyframes_corrected, r.keyframes_fallback), (1, 1));
        assert_eq!(r.points_moved, 3);
        for (id, p) in p_before {
            // Every point's reference keyframe is 10.
            assert!((m.map.points[&id].p_w - (p + Vector3::new(0.0, 1.0, 0.0))).norm() < 1e-12);
        }
        assert!((m.map.keyframes[&11].center() - 0.5 * c11).norm() < 1e-12);
        assert!((m.map.keyframes[&10].center() - Vector3::new(0.0, 1.0, 0.0)).norm() < 1e-12);
    }

    #[test]
    fn scale_ratio_update_follows_eq_3_6() {
        assert!((scale_ratio_after_loop(2.0, 1.5, 0.9) - (2.0 + 0.9 * (3.0 - 2.0))).abs() < 1e-12);
        assert_eq!(scale_ratio_after_loop(2.0, f64::NAN, 0.9), 2.0);
        assert_eq!(scale_ratio_after_loop(2.0, 1.0, 0.9), 2.0);
    }
}
