//! A server map (seed §3.4.1): the VO map structure ([`ClientMap`]: keyframes, points,
//! observations, covisibility) in the server frame `s`, plus the association of the client's
//! map-point ids with server points, which gives correspondences between keyframes without
//! descriptor matching.
use std::collections::BTreeMap;

use nalgebra::{Isometry3, Vector2};

use super::types::{KeptKeyframe, KeptPoint, MapFrame, MapId, ServerKeyframe};
use crate::ids::{ClientId, KeyframeId};
use crate::twoview::triangulate::{
    check_point, projection_matrix, triangulate_dlt, CheckView, TriangulationCheck,
};
use crate::vo::{ClientMap, Keyframe, KeyframeInertial, KfId, PointId};

/// Observations of one client point waiting for a second kept keyframe with parallax.
const MAX_PENDING_PER_POINT: usize = 4;

/// One server map: keyframes posed in the server frame (`Keyframe::t_cw` = `T_sk⁻¹`).
#[derive(Debug, Clone)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct ServerMap {
    /// Map id.
    pub id: MapId,
    /// Client whose keyframes built it.
    pub client_id: u32,
    /// VO session it was started for.
    pub session_id: u32,
    /// Keyframes, points, observations and covisibility.
    pub map: ClientMap,
    /// Metric and gravity-aligned, or not.
    pub frame: MapFrame,
    /// Per owner (client, VO session): client map-point id → server point id, and client
    /// map-point id → kept-keyframe observations not yet triangulated. A merged map holds
    /// the associations of every session that was merged into it. Not saved: they only
    /// mean something to live clients (a loaded map starts without any).
    #[cfg_attr(feature = "serde", serde(skip))]
    assoc: BTreeMap<Owner, Associations>,
    /// Frozen (`--localize-only`): clients localise in it, nothing is added to it and
    /// nothing moves it. A property of the run, not of the saved map.
    #[cfg_attr(feature = "serde", serde(skip))]
    frozen: bool,
}

/// A VO session of a client: `(client_id, session_id)`. Client map-point ids are only
/// unique within one.
pub type Owner = (u32, u32);

/// The client-point tables of one owner. Every entry remembers the newest client keyframe
/// id that referenced its client point (`seen`), so that client points the VO can no longer
/// send (erased from its window) are forgotten: a VO revisiting a place makes new point ids
/// for it, and without forgetting the table grows with every id ever sent (about 64 per
/// keyframe on a long loop, BENCHMARKS.md "Long run"), not with the map.
#[derive(Debug, Clone, Default)]
struct Associations {
    /// Client point → (server point, newest client keyframe id that referenced it).
    client_to_server: BTreeMap<PointId, (PointId, KfId)>,
    /// Client point → kept-keyframe observations not yet triangulated, newest client
    /// keyframe id that referenced it.
    pending: BTreeMap<PointId, Pending>,
    /// Newest client keyframe id of this owner seen by [`ServerMap::touch`].
    newest: KfId,
}

#[derive(Debug, Clone, Default)]
struct Pending {
    obs: Vec<(KfId, u32)>,
    seen: KfId,
}

impl ServerMap {
    /// An empty map of frame `frame`; point ids start at `first_point_id`.
    pub fn new(
        id: MapId,
        client_id: u32,
        session_id: u32,
        first_point_id: PointId,
        frame: MapFrame,
    ) -> Self {
        Self {
            id,
            client_id,
            session_id,
            map: ClientMap::new(session_id, first_point_id),
            frame,
            assoc: BTreeMap::new(),
            frozen: false,
        }
    }

    /// Freezes the map (`--localize-only`): handlers localise keyframes in it without
    /// inserting them, run no BA on it, and corrections do not move it
    /// ([`super::correction::relocalise_in_frozen`]).
    pub fn freeze(&mut self) {
        self.frozen = true;
    }

    /// Whether the map is frozen ([`Self::freeze`]).
    pub fn is_frozen(&self) -> bool {
        self.frozen
    }

    /// The server point associated with client point `c` of `owner`, if it still exists.
    pub fn server_point(&self, owner: Owner, c: PointId) -> Option<PointId> {
        self.assoc
            .get(&owner)?
            .client_to_server
            .get(&c)
            .map(|e| e.0)
            .filter(|s| self.map.points.contains_key(s))
    }

    /// Associates client point `c` of `owner` with server point `s` unless `c` already has
    /// a live one.
    pub fn associate(&mut self, owner: Owner, c: PointId, s: PointId) {
        if self.server_point(owner, c).is_none() {
            let a = self.assoc.entry(owner).or_default();
            a.client_to_server.insert(c, (s, a.newest));
            a.pending.remove(&c);
        }
    }

    /// Client keyframe `kf_id` of `owner` references `client_points`: marks them seen
    /// (call before looking them up for that keyframe).
    pub fn touch(&mut self, owner: Owner, kf_id: KfId, client_points: &[Option<PointId>]) {
        let a = self.assoc.entry(owner).or_default();
        a.newest = a.newest.max(kf_id);
        for c in client_points.iter().flatten() {
            if let Some(e) = a.client_to_server.get_mut(c) {
                e.1 = e.1.max(kf_id);
            }
            if let Some(p) = a.pending.get_mut(c) {
                p.seen = p.seen.max(kf_id);
            }
        }
    }

    /// Forgets client points of each owner not referenced by any of its last `horizon`
    /// client keyframe ids (the VO erased them: a client point lives only while a keyframe
    /// of the VO's window observes it, so `horizon` must exceed the id span of the client's
    /// window). Returns the entries dropped.
    pub fn forget_unseen(&mut self, horizon: KfId) -> usize {
        let mut dropped = 0;
        for a in self.assoc.values_mut() {
            let Some(limit) = a.newest.checked_sub(horizon) else {
                continue;
            };
            let before = a.client_to_server.len() + a.pending.len();
            a.client_to_server.retain(|_, e| e.1 >= limit);
            a.pending.retain(|_, p| p.seen >= limit);
            dropped += before - a.client_to_server.len() - a.pending.len();
        }
        dropped
    }

    /// Sessions whose client points are associated with this map's points.
    pub fn owners(&self) -> impl Iterator<Item = Owner> + '_ {
        self.assoc.keys().copied()
    }

    /// Moves everything of `other` into this map (keyframes, points, covisibility and the
    /// client-point associations of its owners); `other`'s geometry must already be in this
    /// map's frame and its ids must not collide with this map's (server ids are unique per
    /// client, see [`KeyframeId`]). Returns the number of keyframes moved.
    pub(crate) fn absorb(&mut self, other: ServerMap) -> usize {
        let n = other.map.keyframes.len();
        self.map.absorb(other.map);
        for (owner, a) in other.assoc {
            let mine = self.assoc.entry(owner).or_default();
            mine.newest = mine.newest.max(a.newest);
            mine.client_to_server.extend(a.client_to_server);
            for (c, p) in a.pending {
                let e = mine.pending.entry(c).or_default();
                e.obs.extend(p.obs);
                e.seen = e.seen.max(p.seen);
            }
        }
        n
    }

    /// Drops associations that can no longer be used: client points whose server point was
    /// erased, and waiting observations of keyframes no longer in the map. Without this the
    /// tables grow with every client point ever seen, not with the map (a long run revisiting
    /// the same place keeps creating client points). Returns the entries dropped.
    pub fn prune_associations(&mut self) -> usize {
        let mut dropped = 0;
        let (points, keyframes) = (&self.map.points, &self.map.keyframes);
        for a in self.assoc.values_mut() {
            let before = a.client_to_server.len();
            a.client_to_server.retain(|_, e| points.contains_key(&e.0));
            dropped += before - a.client_to_server.len();
            a.pending.retain(|_, p| {
                let n = p.obs.len();
                p.obs.retain(|(k, _)| keyframes.contains_key(k));
                dropped += n - p.obs.len();
                !p.obs.is_empty()
            });
        }
        dropped
    }

    /// Client-point associations and waiting observations held (for memory figures).
    pub fn association_count(&self) -> (usize, usize) {
        self.assoc.values().fold((0, 0), |a, x| {
            (a.0 + x.client_to_server.len(), a.1 + x.pending.len())
        })
    }

    /// Replaces point `from` by point `to` in the associations (after a fusion).
    pub(crate) fn redirect_point(&mut self, from: PointId, to: PointId) {
        for a in self.assoc.values_mut() {
            for e in a.client_to_server.values_mut() {
                if e.0 == from {
                    e.0 = to;
                }
            }
        }
    }

    /// Server pose `T_sk` (camera → server map) of server keyframe `k`.
    pub fn pose(&self, k: KfId) -> Option<Isometry3<f64>> {
        self.map.keyframes.get(&k).map(|kf| kf.t_cw.inverse())
    }

    /// Server keyframe poses `(t_ns, T_sk)`, oldest first.
    pub fn trajectory(&self) -> Vec<(i64, Isometry3<f64>)> {
        self.map
            .keyframes
            .values()
            .map(|kf| (kf.t_ns, kf.t_cw.inverse()))
            .collect()
    }

    /// Inserts `kf` at server pose `t_sk` with the given server points per keypoint;
    /// returns its server id.
    pub(crate) fn insert(
        &mut self,
        kf: &ServerKeyframe,
        t_sk: &Isometry3<f64>,
        points: &[Option<PointId>],
    ) -> KfId {
        let id = KeyframeId::new(ClientId::new(kf.client_id), kf.id).raw();
        self.map.insert_keyframe(Keyframe {
            id,
            t_ns: kf.t_ns,
            t_cw: t_sk.inverse(),
            camera: kf.camera,
            readout_ns: kf.readout_ns,
            features: kf.features.clone(),
            points: points.to_vec(),
            // A metric, gravity-aligned map keeps the client's velocity, biases and IMU
            // segment (its local BA is visual-inertial); a monocular map has no use for them.
            // Its velocity turns with the server pose (a map merged with another rotates the
            // client's world about the vertical).
            inertial: kf.inertial.filter(|_| self.frame.is_inertial()).map(|i| {
                let r_sc = t_sk.rotation * kf.t_ck.rotation.inverse();
                KeyframeInertial {
                    v_wb: r_sc * i.v_wb,
                    ..i
                }
            }),
            imu: kf.imu.clone().filter(|_| self.frame.is_inertial()),
        });
        for p in points.iter().flatten() {
            self.map.update_point(*p);
        }
        id
    }

    /// Creates points from the client's own correspondences: a keypoint of server keyframe
    /// `k` without a server point whose client point was seen by an earlier kept keyframe is
    /// triangulated with that observation (checked: positive depth, reprojection χ² 5.991,
    /// parallax); otherwise it waits for a later keyframe. Returns the points created.
    pub(crate) fn triangulate_client_tracks(
        &mut self,
        owner: Owner,
        k: KfId,
        client_points: &[Option<PointId>],
    ) -> usize {
        let check = TriangulationCheck::default();
        let mut created = 0;
        for (i, c) in client_points.iter().enumerate() {
            let Some(c) = *c else { continue };
            let free = self
                .map
                .keyframes
                .get(&k)
                .and_then(|kf| kf.points.get(i))
                .is_some_and(|p| p.is_none());
            if !free {
                continue;
            }
            if self.server_point(owner, c).is_some() {
                // Associated, but the refinement rejected or missed the match: leave it.
                continue;
            }
            let candidates = self
                .assoc
                .get(&owner)
                .and_then(|a| a.pending.get(&c))
                .map(|p| p.obs.clone())
                .unwrap_or_default();
            let mut made = None;
            for (k0, i0) in candidates {
                if let Some(p) = self.triangulate_pair(k, i as u32, k0, i0, &check) {
                    made = Some(p);
                    break;
                }
            }
            let a = self.assoc.entry(owner).or_default();
            if let Some(p) = made {
                a.client_to_server.insert(c, (p, a.newest));
                a.pending.remove(&c);
                created += 1;
            } else {
                let newest = a.newest;
                let p = a.pending.entry(c).or_default();
                p.seen = p.seen.max(newest);
                if p.obs.len() >= MAX_PENDING_PER_POINT {
                    p.obs.remove(0);
                }
                p.obs.push((k, i as u32));
            }
        }
        created
    }

    /// Triangulates keypoint `i` of `k` with keypoint `i0` of `k0` (both free) and adds the
    /// point if it passes the checks.
    fn triangulate_pair(
        &mut self,
        k: KfId,
        i: u32,
        k0: KfId,
        i0: u32,
        check: &TriangulationCheck,
    ) -> Option<PointId> {
        let kf = self.map.keyframes.get(&k)?;
        let kf0 = self.map.keyframes.get(&k0)?;
        if k0 == k || kf0.points.get(i0 as usize)?.is_some() {
            return None;
        }
        let kp = *kf.features.keypoints.get(i as usize)?;
        let kp0 = *kf0.features.keypoints.get(i0 as usize)?;
        let px = Vector2::new(kp.x as f64, kp.y as f64);
        let px0 = Vector2::new(kp0.x as f64, kp0.y as f64);
        let b = kf.camera.unproject(&px);
        let b0 = kf0.camera.unproject(&px0);
        let p_w = triangulate_dlt(
            &projection_matrix(&kf.t_cw),
            &b,
            &projection_matrix(&kf0.t_cw),
            &b0,
        )?;
        let views = [
            CheckView {
                t_cw: kf.t_cw,
                pixel: px,
                inv_sigma2: kf.features.scale.inv_sigma2(kp.octave),
            },
            CheckView {
                t_cw: kf0.t_cw,
                pixel: px0,
                inv_sigma2: kf0.features.scale.inv_sigma2(kp0.octave),
            },
        ];
        check_point(&p_w, &views, &kf.camera, check).ok()?;
        Some(self.map.add_point(p_w, k, &[(k0, i0), (k, i)]))
    }

    /// The loop closer's summary of server keyframe `k` ([`KeptKeyframe`]).
    pub fn kept_summary(&self, k: KfId, client_kf_id: KfId) -> Option<KeptKeyframe> {
        let kf = self.map.keyframes.get(&k)?;
        let points = kf
            .points
            .iter()
            .enumerate()
            .filter_map(|(i, p)| {
                let mp = self.map.points.get(&(*p)?)?;
                Some(KeptPoint {
                    keypoint: i as u32,
                    point: mp.id,
                    p_k: (kf.t_cw * nalgebra::Point3::from(mp.p_w)).coords,
                })
            })
            .collect();
        let covisible = self
            .map
            .covisible(k, usize::MAX, 1)
            .into_iter()
            .map(|n| (n, self.map.covis_weight(k, n)))
            .collect();
        Some(KeptKeyframe {
            map_id: self.id,
            kf_id: k,
            client_kf_id,
            t_ns: kf.t_ns,
            t_sk: kf.t_cw.inverse(),
            camera: kf.camera,
            features: kf.features.clone(),
            points,
            covisible,
            frame: self.frame,
        })
    }
}
