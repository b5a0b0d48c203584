//! A session that starts inside a loaded map (issue 20): a client whose VO started in a
//! saved map (`crate::vo::prior`) sends keyframes whose client points are, for what it
//! took from that map, the loaded map's own point ids (the saved clients' range,
//! [`SAVED_CLIENT_BASE`], which no client's VO counter reaches), and whose poses are in
//! that map's frame and scale. Its first keyframe then joins that map at once: the session
//! continues in it as after a relocalisation (`λ = 1`, the named points associated), and
//! the keyframe is refined, kept or discarded there, or only localised in a frozen map
//! (`--localize-only`), instead of starting a server map of its own that the loop closer
//! would have to find and merge later.
//!
//! The names are checked, not trusted: a point counts only when the keyframe's pose
//! projects it onto its keypoint (a loose gate, [`JOIN_GATE_CHI2`]: the client's pose
//! is its own estimate), and [`MIN_JOIN_POINTS`] must pass. A client that loaded another
//! file than this server, whose ids name other points, starts a map of its own.
use nalgebra::Isometry3;

use super::{HandleReport, KeyframeHandler, Last, ServerMaps};
use crate::ids::{MapPointId, SAVED_CLIENT_BASE};
use crate::server::server_map::ServerMap;
use crate::server::types::ServerKeyframe;
use crate::vo::map::PointId;
use crate::CoreError;

/// Fewest named points of one loaded map, checked by reprojection, for a first keyframe to
/// join it.
pub const MIN_JOIN_POINTS: usize = 30;

/// Gate of the named points' reprojection check, in `σ²` of the keypoint's octave (χ²(2)
/// at 95 % is 5.99; four times that, since the pose is the client's).
pub const JOIN_GATE_CHI2: f64 = 4.0 * 5.991;

impl KeyframeHandler {
    /// The session's first keyframe, waiting in `first`, joins the loaded map it names
    /// (module docs): `None` when it names none (it stays the first of a new map).
    pub(super) fn join_named_map(
        &mut self,
        maps: &mut ServerMaps,
    ) -> Option<Result<HandleReport, CoreError>> {
        let first = self.first.as_ref()?;
        let (map_id, named) = maps
            .values()
            .map(|m| (m.id, named_points(m, first)))
            .filter(|(_, n)| n.len() >= MIN_JOIN_POINTS)
            .max_by_key(|(id, n)| (n.len(), std::cmp::Reverse(*id)))?;
        let map = maps.get_mut(&map_id)?;
        let kf = self.first.take()?;
        let owner = (kf.client_id, kf.session_id);
        map.touch(owner, kf.id, &kf.client_points);
        for &p in &named {
            map.associate(owner, p, p);
        }
        self.current = Some(map_id);
        self.reference = map.map.keyframe_sharing_most(&named);
        self.last = Some(joined_last(&kf));
        self.converged = true;
        self.stats.relocalisations += 1;
        self.stats.joined += 1;
        Some(self.track(maps, kf))
    }
}

/// Whether `kf` names points of a loaded map (the saved clients' range): its session may
/// join that map (module docs), so its handler belongs with the loaded maps.
pub fn names_loaded_points(kf: &ServerKeyframe) -> bool {
    kf.client_points.iter().flatten().any(|&c| is_saved(c))
}

/// Whether point id `c` is in the saved clients' range.
fn is_saved(c: PointId) -> bool {
    MapPointId::from_raw(c).client().raw() >= SAVED_CLIENT_BASE
}

/// The last keyframe a joined session's first keyframe is predicted from: itself, the
/// client's frame being the map's (`λ = 1`).
fn joined_last(kf: &ServerKeyframe) -> Last {
    Last {
        client_kf_id: kf.id,
        t_ck: kf.t_ck,
        t_sk: kf.t_ck,
        lambda: 1.0,
        server_kf: None,
        metric: false,
    }
}

/// The points of loaded map `map` that `kf` names and its pose projects onto their
/// keypoints (module docs).
fn named_points(map: &ServerMap, kf: &ServerKeyframe) -> Vec<PointId> {
    let t_cw = kf.t_ck.inverse();
    kf.client_points
        .iter()
        .enumerate()
        .filter_map(|(i, c)| Some((i, (*c).filter(|&c| is_saved(c))?)))
        .filter(|&(i, c)| {
            map.map
                .points
                .get(&c)
                .is_some_and(|p| projects_onto(kf, &t_cw, &p.p_w, i))
        })
        .map(|(_, c)| c)
        .collect()
}

/// Whether world point `p_w` projects within the gate of keypoint `i` of `kf` at `t_cw`.
fn projects_onto(
    kf: &ServerKeyframe,
    t_cw: &Isometry3<f64>,
    p_w: &nalgebra::Vector3<f64>,
    i: usize,
) -> bool {
    let Some(kp) = kf.features.keypoints.get(i) else {
        return false;
    };
    let Some(uv) = kf
        .camera
        .project(&(t_cw * nalgebra::Point3::from(*p_w)).coords)
    else {
        return false;
    };
    let e2 = (uv.x - kp.x as f64).powi(2) + (uv.y - kp.y as f64).powi(2);
    e2 * kf.features.scale.inv_sigma2(kp.octave) < JOIN_GATE_CHI2
}

#[cfg(test)]
mod tests {
    use nalgebra::Isometry3;

    use super::*;
    use crate::ids::{ClientId, KeyframeId};
    use crate::server::test_scene::{keyframe, true_pose, CLIENT};
    use crate::server::types::{KeyframeStatus, MapId};
    use crate::server::HandlerParams;

    /// A map of client `CLIENT` over true poses 0..7, renamed into the saved clients'
    /// range as a load renames it; with, per scene point index, its loaded point id.
    fn loaded_map(maps: &mut ServerMaps) -> (MapId, Vec<Option<PointId>>) {
        let mut a = KeyframeHandler::new(CLIENT, HandlerParams::default());
        for k in 0..7 {
            let t = true_pose(k);
            a.handle(maps, keyframe(k as u64, 1, &t, &t)).unwrap();
            a.idle_step(maps);
        }
        let id = a.current_map_id().unwrap();
        let mut m = maps.remove(&id).unwrap();
        let saved = ClientId::new(SAVED_CLIENT_BASE);
        let base = MapPointId::first_of_client(saved).raw();
        let by_index: Vec<Option<PointId>> = (0..1200u64)
            .map(|i| {
                m.server_point((CLIENT, 1), i)
                    .map(|p| base + MapPointId::from_raw(p).counter())
            })
            .collect();
        let kf =
            |k: crate::vo::KfId| KeyframeId::new(saved, KeyframeId::from_raw(k).client_kf()).raw();
        m.map
            .rename_ids(kf, |p| base + MapPointId::from_raw(p).counter());
        m.id = MapId::new(saved, 0);
        m.client_id = SAVED_CLIENT_BASE;
        let id = m.id;
        maps.insert(id, m);
        (id, by_index)
    }

    /// Client 4's keyframe `k` seen from the truth, its client pose `t_ck`, naming the
    /// loaded points it sees by their ids (its other points by its own).
    fn naming(k: usize, t_ck: &Isometry3<f64>, ids: &[Option<PointId>]) -> ServerKeyframe {
        let mut kf = keyframe(k as u64, 1, &true_pose(k), t_ck);
        kf.client_id = CLIENT + 1;
        for c in kf.client_points.iter_mut().flatten() {
            *c = ids[*c as usize].unwrap_or(*c);
        }
        kf
    }

    /// A session whose first keyframe names a loaded map's points, at a pose that projects
    /// them onto its keypoints, continues in that map at once (no map of its own, λ = 1),
    /// its keyframes refined at the truth; named from a pose 0.5 m off, it starts a map of
    /// its own; in a frozen map it is only localised.
    #[test]
    fn a_session_naming_a_loaded_maps_points_joins_it() {
        let mut maps = ServerMaps::new();
        let (loaded, ids) = loaded_map(&mut maps);
        let first = naming(3, &true_pose(3), &ids);
        assert!(names_loaded_points(&first));
        assert!(!names_loaded_points(&keyframe(
            3,
            1,
            &true_pose(3),
            &true_pose(3)
        )));
        let mut b = KeyframeHandler::new(CLIENT + 1, HandlerParams::default());
        let r = b.handle(&mut maps, first).unwrap();
        assert_ne!(r.status, KeyframeStatus::First);
        assert_eq!(
            (r.map_id, b.stats().maps, b.stats().joined),
            (Some(loaded), 0, 1)
        );
        for k in 4..8 {
            let r = b.handle(&mut maps, naming(k, &true_pose(k), &ids)).unwrap();
            assert_eq!(r.map_id, Some(loaded), "keyframe {k}");
            let err = (r.t_sk.unwrap().translation.vector - true_pose(k).translation.vector).norm();
            assert!(err < 2e-3, "keyframe {k}: {err} off the truth");
            assert!(
                (r.lambda - 1.0).abs() < 1e-2,
                "keyframe {k}: λ {}",
                r.lambda
            );
        }
        assert_eq!(maps.len(), 1, "no map of its own");

        let off = Isometry3::translation(0.5, 0.0, 0.0) * true_pose(3);
        let mut c = KeyframeHandler::new(CLIENT + 1, HandlerParams::default());
        let r = c.handle(&mut maps, naming(3, &off, &ids)).unwrap();
        assert_eq!((r.status, c.stats().joined), (KeyframeStatus::First, 0));

        let mut maps = ServerMaps::new();
        let (loaded, ids) = loaded_map(&mut maps);
        maps.get_mut(&loaded).unwrap().freeze();
        let before = maps[&loaded].map.keyframes.len();
        let mut d = KeyframeHandler::new(CLIENT + 1, HandlerParams::default());
        for k in 3..6 {
            let r = d.handle(&mut maps, naming(k, &true_pose(k), &ids)).unwrap();
            assert_eq!(
                (r.status, r.map_id),
                (KeyframeStatus::Discarded, Some(loaded))
            );
        }
        assert_eq!((d.stats().localised, d.stats().joined), (3, 1));
        assert_eq!(maps[&loaded].map.keyframes.len(), before);
    }
}
