//! The client map of the monocular VO (seed §3.3): keyframes, map points, observations and
//! the covisibility graph. Plain data with consistent updates; no threads, no IPC.
//!
//! Poses are `t_cw` (world → camera, `p_c = R_cw p_w + t_cw`), as in the pose optimiser.
use std::collections::{BTreeMap, HashMap};

use nalgebra::{Isometry3, Translation3, Vector3};

use crate::camera::PinholeRadtan;
use crate::features::{hamming, OrbFeatures};
use crate::lie::Sim3;

/// Keyframe id, unique per client across sessions.
pub type KfId = u64;
/// Map-point id, unique per client across sessions.
pub type PointId = u64;

/// A keyframe: a frame kept in the map with its features and pose.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct Keyframe {
    /// Id.
    pub id: KfId,
    /// Frame time (mid-row), ns.
    pub t_ns: i64,
    /// World → camera pose at the mid-row time.
    pub t_cw: Isometry3<f64>,
    /// Camera model.
    pub camera: PinholeRadtan,
    /// Rolling-shutter readout time of the frame, ns (0 = global shutter).
    pub readout_ns: i64,
    /// Keypoints and descriptors.
    pub features: OrbFeatures,
    /// Map point seen by each keypoint.
    pub points: Vec<Option<PointId>>,
    /// Velocity and biases when a visual-inertial client made it ([`crate::vio`]), in the
    /// metric, gravity-aligned world of the map; `None` for a monocular keyframe.
    pub inertial: Option<KeyframeInertial>,
    /// The IMU samples since the previous keyframe when a visual-inertial client made it
    /// ([`super::keyframe_imu`]); `None` for a monocular keyframe.
    pub imu: Option<super::keyframe_imu::KeyframeImu>,
}

/// The inertial state of a keyframe ([`Keyframe::inertial`]).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct KeyframeInertial {
    /// Velocity of the body (IMU) in the world, m/s.
    pub v_wb: Vector3<f64>,
    /// Effective IMU biases (`crate::imu::preint` module docs).
    pub biases: crate::imu::ImuBiases,
    /// Visual-inertial windows of local mapping that refined this state
    /// ([`super::vi_window`]; 0: the IMU's prediction or the initialisation's).
    pub refined: u32,
}

impl Keyframe {
    /// Camera centre in the world frame.
    pub fn center(&self) -> Vector3<f64> {
        self.t_cw.inverse().translation.vector
    }

    /// Number of keypoints with a map point.
    pub fn n_points(&self) -> usize {
        self.points.iter().filter(|p| p.is_some()).count()
    }
}

/// A 3D point of the map with its observations.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct MapPoint {
    /// Id.
    pub id: PointId,
    /// Position in the world frame.
    pub p_w: Vector3<f64>,
    /// Most distinctive descriptor of its observations (median Hamming distance).
    pub descriptor: [u8; 32],
    /// Observations: (keyframe, keypoint index).
    pub observations: Vec<(KfId, u32)>,
    /// Mean viewing direction (unit), world frame.
    pub normal: Vector3<f64>,
    /// Keyframe that created it.
    pub first_kf: KfId,
    /// Frames in whose view it was predicted.
    pub visible: u32,
    /// Frames where it was matched.
    pub found: u32,
}

impl MapPoint {
    /// Found / visible ratio (ORB-SLAM's culling criterion).
    pub fn found_ratio(&self) -> f64 {
        if self.visible == 0 {
            1.0
        } else {
            self.found as f64 / self.visible as f64
        }
    }
}

/// The client map of one VO session.
#[derive(Debug, Clone, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct ClientMap {
    /// VO session this map belongs to.
    pub session_id: u32,
    /// Keyframes by id (ordered: oldest first).
    pub keyframes: BTreeMap<KfId, Keyframe>,
    /// Map points by id.
    #[cfg_attr(feature = "serde", serde(serialize_with = "crate::serde_sorted::map"))]
    pub points: HashMap<PointId, MapPoint>,
    /// Covisibility weights: shared points between two keyframes.
    #[cfg_attr(
        feature = "serde",
        serde(serialize_with = "crate::serde_sorted::nested")
    )]
    covis: HashMap<KfId, HashMap<KfId, u32>>,
    next_point_id: PointId,
    /// A similarity of the world the visual-inertial window found (its gravity and scale
    /// correction, [`super::vi_window`]) that the client has still to apply to the whole
    /// session (map, tracking state, earlier poses) as a world move.
    pub world_correction: Option<Sim3>,
    /// The visual-inertial window of the first keyframe at or after this camera time
    /// (ns) is a whole-session one ([`super::vi_window`] module docs, "Session windows"):
    /// asked by the visual-inertial client at its refinement times, cleared when solved.
    pub session_window_from_ns: Option<i64>,
}

impl ClientMap {
    /// Moves the map into another world frame by the similarity `x' = s R x + t` (the
    /// metric, gravity-aligned world of an inertial initialisation, `imu::init`, or the
    /// server map's frame the client anchors to, `vio::anchor`): points `p' = s R p + t`,
    /// viewing directions `R n`, keyframe poses by [`transform_pose_cw`] (the camera frame
    /// keeps its orientation, its coordinates scale by `s`). Keyframe velocities become
    /// `s R v` (their units scale with the world's).
    pub fn transform_world(&mut self, m: &Sim3) {
        for kf in self.keyframes.values_mut() {
            kf.t_cw = transform_pose_cw(&kf.t_cw, m);
            if let Some(i) = kf.inertial.as_mut() {
                i.v_wb = m.r * (i.v_wb * m.s);
            }
        }
        for p in self.points.values_mut() {
            p.p_w = m.transform_point(&p.p_w);
            p.normal = m.r * p.normal;
        }
        // A pending correction of the old world, in the new one (`M C M⁻¹`).
        if let Some(c) = self.world_correction.as_mut() {
            *c = m.compose(c).compose(&m.inverse());
        }
    }

    /// An empty map for session `session_id`; point ids start at `first_point_id`.
    pub fn new(session_id: u32, first_point_id: PointId) -> Self {
        Self {
            session_id,
            next_point_id: first_point_id,
            ..Self::default()
        }
    }

    /// Next point id that will be given.
    pub fn next_point_id(&self) -> PointId {
        self.next_point_id
    }

    /// Inserts a keyframe (its `points` must name existing points or `None`); observations
    /// of its points are registered and the covisibility updated.
    pub fn insert_keyframe(&mut self, kf: Keyframe) {
        let id = kf.id;
        let obs: Vec<(u32, PointId)> = kf
            .points
            .iter()
            .enumerate()
            .filter_map(|(i, p)| p.map(|p| (i as u32, p)))
            .collect();
        self.keyframes.insert(id, kf);
        for (i, p) in obs {
            if let Some(mp) = self.points.get_mut(&p) {
                if !mp.observations.iter().any(|o| o.0 == id) {
                    mp.observations.push((id, i));
                }
            } else if let Some(k) = self.keyframes.get_mut(&id) {
                k.points[i as usize] = None;
            }
        }
        self.update_covisibility(id);
    }

    /// Creates a point at `p_w` observed by the given (keyframe, keypoint) pairs; returns its
    /// id. Observations of unknown keyframes are ignored.
    pub fn add_point(&mut self, p_w: Vector3<f64>, first_kf: KfId, obs: &[(KfId, u32)]) -> PointId {
        let id = self.next_point_id;
        self.next_point_id += 1;
        let mut mp = MapPoint {
            id,
            p_w,
            descriptor: [0; 32],
            observations: Vec::with_capacity(obs.len()),
            normal: Vector3::zeros(),
            first_kf,
            visible: 1,
            found: 1,
        };
        for &(k, i) in obs {
            if let Some(kf) = self.keyframes.get_mut(&k) {
                if let Some(slot) = kf.points.get_mut(i as usize) {
                    *slot = Some(id);
                    mp.observations.push((k, i));
                }
            }
        }
        self.points.insert(id, mp);
        self.update_point(id);
        id
    }

    /// Inserts point `id` at `p_w` with no observation yet, for a map rebuilt from stored
    /// keyframes ([`crate::vo::resume`]): the keyframes inserted after it register theirs.
    /// The id counter moves past `id`, so that new points never take a stored id.
    pub fn insert_point(&mut self, id: PointId, p_w: Vector3<f64>, first_kf: KfId) {
        let mp = MapPoint {
            id,
            p_w,
            descriptor: [0; 32],
            observations: Vec::new(),
            normal: Vector3::zeros(),
            first_kf,
            visible: 1,
            found: 1,
        };
        self.points.insert(id, mp);
        self.next_point_id = self.next_point_id.max(id.saturating_add(1));
    }

    /// Adds an observation of point `p` by keypoint `i` of keyframe `k`.
    pub fn add_observation(&mut self, p: PointId, k: KfId, i: u32) {
        let Some(kf) = self.keyframes.get_mut(&k) else {
            return;
        };
        let Some(slot) = kf.points.get_mut(i as usize) else {
            return;
        };
        if let Some(old) = slot.replace(p) {
            if old != p {
                if let Some(mp) = self.points.get_mut(&old) {
                    mp.observations.retain(|o| *o != (k, i));
                }
            }
        }
        if let Some(mp) = self.points.get_mut(&p) {
            if !mp.observations.contains(&(k, i)) {
                mp.observations.push((k, i));
            }
        }
    }

    /// Removes point `p` and all its observations.
    pub fn erase_point(&mut self, p: PointId) {
        if let Some(mp) = self.points.remove(&p) {
            for (k, i) in mp.observations {
                if let Some(kf) = self.keyframes.get_mut(&k) {
                    if let Some(slot) = kf.points.get_mut(i as usize) {
                        if *slot == Some(p) {
                            *slot = None;
                        }
                    }
                }
            }
        }
    }

    /// Moves all keyframes, points and covisibility edges of `other` into this map (a map
    /// merge; `other` must already be expressed in this map's frame and its ids must not
    /// collide with this map's). The point-id counter continues after both maps' counters.
    pub fn absorb(&mut self, other: ClientMap) {
        self.keyframes.extend(other.keyframes);
        self.points.extend(other.points);
        for (k, nb) in other.covis {
            self.covis.entry(k).or_default().extend(nb);
        }
        self.next_point_id = self.next_point_id.max(other.next_point_id);
    }

    /// Renames every keyframe id by `kf` and every point id by `pt` (keys, keyframe → point
    /// links, observations, first keyframes, covisibility, the point-id counter): a map read
    /// from a file whose ids would collide with the live run's (`map_store::remap`). Both
    /// functions must be injective.
    pub fn rename_ids(&mut self, kf: impl Fn(KfId) -> KfId, pt: impl Fn(PointId) -> PointId) {
        let kfs = std::mem::take(&mut self.keyframes);
        for (_, mut k) in kfs {
            k.id = kf(k.id);
            for p in k.points.iter_mut().flatten() {
                *p = pt(*p);
            }
            self.keyframes.insert(k.id, k);
        }
        let points = std::mem::take(&mut self.points);
        for (_, mut p) in points {
            p.id = pt(p.id);
            p.first_kf = kf(p.first_kf);
            for o in &mut p.observations {
                o.0 = kf(o.0);
            }
            self.points.insert(p.id, p);
        }
        let covis = std::mem::take(&mut self.covis);
        for (k, nb) in covis {
            let nb = nb.into_iter().map(|(n, w)| (kf(n), w)).collect();
            self.covis.insert(kf(k), nb);
        }
        self.next_point_id = pt(self.next_point_id);
    }

    /// Fuses point `from` into point `into` (the same 3-D point found twice, e.g. on both
    /// sides of a loop): every observation of `from` moves to `into` unless its keyframe
    /// already observes `into`; `from` is erased. Returns the keyframes whose observations
    /// changed (their covisibility is updated), or `None` when either point is missing.
    pub fn fuse_point(&mut self, from: PointId, into: PointId) -> Option<Vec<KfId>> {
        if from == into || !self.points.contains_key(&into) {
            return None;
        }
        let gone = self.points.remove(&from)?;
        let mut touched = Vec::with_capacity(gone.observations.len());
        for (k, i) in gone.observations {
            let Some(kf) = self.keyframes.get_mut(&k) else {
                continue;
            };
            let sees_into = kf.points.contains(&Some(into));
            if let Some(slot) = kf.points.get_mut(i as usize) {
                if *slot == Some(from) {
                    *slot = if sees_into { None } else { Some(into) };
                }
            }
            if !sees_into {
                if let Some(mp) = self.points.get_mut(&into) {
                    if !mp.observations.iter().any(|o| o.0 == k) {
                        mp.observations.push((k, i));
                    }
                }
            }
            touched.push(k);
        }
        for k in &touched {
            self.update_covisibility(*k);
        }
        self.update_point(into);
        Some(touched)
    }

    /// Removes keyframe `k` from the map (window or culling): its observations go, points
    /// left with fewer than `min_obs` observations are erased. Returns the keyframe.
    pub fn remove_keyframe(&mut self, k: KfId, min_obs: usize) -> Option<Keyframe> {
        let kf = self.keyframes.remove(&k)?;
        for (i, p) in kf.points.iter().enumerate() {
            let Some(p) = p else { continue };
            let erase = match self.points.get_mut(p) {
                Some(mp) => {
                    mp.observations.retain(|o| *o != (k, i as u32));
                    mp.observations.len() < min_obs
                }
                None => false,
            };
            if erase {
                self.erase_point(*p);
            } else {
                self.update_point(*p);
            }
        }
        if let Some(nb) = self.covis.remove(&k) {
            for n in nb.keys() {
                if let Some(m) = self.covis.get_mut(n) {
                    m.remove(&k);
                }
            }
        }
        Some(kf)
    }

    /// Recomputes the covisibility edges of keyframe `k` (weights = shared points).
    pub fn update_covisibility(&mut self, k: KfId) {
        let Some(kf) = self.keyframes.get(&k) else {
            return;
        };
        let mut counts: HashMap<KfId, u32> = HashMap::new();
        for p in kf.points.iter().flatten() {
            if let Some(mp) = self.points.get(p) {
                for (o, _) in &mp.observations {
                    if *o != k {
                        *counts.entry(*o).or_insert(0) += 1;
                    }
                }
            }
        }
        if let Some(old) = self.covis.insert(k, HashMap::new()) {
            for n in old.keys() {
                if let Some(m) = self.covis.get_mut(n) {
                    m.remove(&k);
                }
            }
        }
        for (n, w) in counts {
            self.covis.entry(k).or_default().insert(n, w);
            self.covis.entry(n).or_default().insert(k, w);
        }
    }

    /// Covisibility weight between two keyframes.
    pub fn covis_weight(&self, a: KfId, b: KfId) -> u32 {
        self.covis
            .get(&a)
            .and_then(|m| m.get(&b))
            .copied()
            .unwrap_or(0)
    }

    /// The `n` keyframes sharing most points with `k` (weight ≥ `min_weight`), best first.
    pub fn covisible(&self, k: KfId, n: usize, min_weight: u32) -> Vec<KfId> {
        let mut v: Vec<(KfId, u32)> = self
            .covis
            .get(&k)
            .map(|m| {
                m.iter()
                    .filter(|(_, w)| **w >= min_weight)
                    .map(|(a, w)| (*a, *w))
                    .collect()
            })
            .unwrap_or_default();
        v.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        v.truncate(n);
        v.into_iter().map(|(a, _)| a).collect()
    }

    /// Recomputes a point's descriptor (the observation descriptor with the least median
    /// Hamming distance to the others) and mean viewing direction.
    pub fn update_point(&mut self, p: PointId) {
        let Some(mp) = self.points.get(&p) else {
            return;
        };
        let mut descs: Vec<[u8; 32]> = Vec::with_capacity(mp.observations.len());
        let mut normal = Vector3::zeros();
        for (k, i) in &mp.observations {
            if let Some(kf) = self.keyframes.get(k) {
                if let Some(d) = kf.features.descriptors.get(*i as usize) {
                    descs.push(*d);
                }
                let dir = mp.p_w - kf.center();
                let n = dir.norm();
                if n > 0.0 {
                    normal += dir / n;
                }
            }
        }
        let best = best_descriptor(&descs);
        if let Some(mp) = self.points.get_mut(&p) {
            if let Some(d) = best {
                mp.descriptor = d;
            }
            let n = normal.norm();
            if n > 0.0 {
                mp.normal = normal / n;
            }
        }
    }

    /// Median depth of keyframe `k`'s points in its camera frame.
    pub fn median_depth(&self, k: KfId) -> Option<f64> {
        let kf = self.keyframes.get(&k)?;
        let mut z: Vec<f64> = kf
            .points
            .iter()
            .flatten()
            .filter_map(|p| self.points.get(p))
            .map(|mp| (kf.t_cw * nalgebra::Point3::from(mp.p_w)).z)
            .collect();
        if z.is_empty() {
            return None;
        }
        z.sort_by(f64::total_cmp);
        Some(z[z.len() / 2])
    }

    /// The keyframe observing most of `points` (the lowest id among equals): the reference
    /// keyframe of a frame matched to them.
    pub fn keyframe_sharing_most<'a>(
        &self,
        points: impl IntoIterator<Item = &'a PointId>,
    ) -> Option<KfId> {
        let mut counts: BTreeMap<KfId, usize> = BTreeMap::new();
        for p in points {
            for (k, _) in self.points.get(p).map_or(&[][..], |p| &p.observations[..]) {
                *counts.entry(*k).or_insert(0) += 1;
            }
        }
        counts
            .into_iter()
            .max_by(|a, b| a.1.cmp(&b.1).then(b.0.cmp(&a.0)))
            .map(|(k, _)| k)
    }

    /// Number of points of keyframe `k` observed by at least `min_obs` keyframes.
    pub fn tracked_points(&self, k: KfId, min_obs: usize) -> usize {
        self.keyframes.get(&k).map_or(0, |kf| {
            kf.points
                .iter()
                .flatten()
                .filter(|p| {
                    self.points
                        .get(p)
                        .is_some_and(|m| m.observations.len() >= min_obs)
                })
                .count()
        })
    }
}

/// The descriptor with the least median Hamming distance to the others.
pub fn best_descriptor(descs: &[[u8; 32]]) -> Option<[u8; 32]> {
    if descs.len() <= 2 {
        return descs.first().copied();
    }
    let mut best = (u32::MAX, 0);
    let mut row = vec![0u32; descs.len()];
    for (i, a) in descs.iter().enumerate() {
        for (j, b) in descs.iter().enumerate() {
            row[j] = hamming(a, b);
        }
        row.sort_unstable();
        let med = row[(descs.len() - 1) / 2];
        if med < best.0 {
            best = (med, i);
        }
    }
    Some(descs[best.1])
}

/// A world → camera pose after the world moved by `x' = s R x + t`
/// ([`ClientMap::transform_world`]): `R_c'w' = R_cw Rᵀ`, `t_c'w' = s t_cw - R_cw Rᵀ t` (the
/// camera frame keeps its orientation, its coordinates scale by `s`; its centre moves to
/// `s R c + t`).
pub fn transform_pose_cw(t_cw: &Isometry3<f64>, m: &Sim3) -> Isometry3<f64> {
    let r_cw = t_cw.rotation * m.r.inverse();
    Isometry3::from_parts(
        Translation3::from(t_cw.translation.vector * m.s - r_cw * m.t),
        r_cw,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::features::KeyPoint;
    use nalgebra::UnitQuaternion;

    fn kf(id: KfId, n: usize, x: f64) -> Keyframe {
        let kp = KeyPoint::at_level0(0.0, 0.0);
        Keyframe {
            id,
            t_ns: id as i64,
            t_cw: Isometry3::translation(-x, 0.0, 0.0),
            camera: PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0),
            readout_ns: 0,
            features: OrbFeatures {
                keypoints: vec![kp; n],
                descriptors: (0..n).map(|i| [i as u8; 32]).collect(),
                ..OrbFeatures::default()
            },
            points: vec![None; n],
            inertial: None,
            imu: None,
        }
    }

    /// Moving the world by a similarity leaves every point where each keyframe sees it:
    /// the camera-frame direction of each point is unchanged (its depth scales by `s`), and
    /// each keyframe's centre moves as a point does.
    #[test]
    fn a_world_move_keeps_what_each_keyframe_sees() {
        let mut m = ClientMap::new(1, 100);
        let mut k2 = kf(2, 10, 1.0);
        k2.t_cw = Isometry3::new(Vector3::new(-1.0, 0.2, 0.3), Vector3::new(0.1, -0.3, 0.2));
        m.insert_keyframe(kf(1, 10, 0.0));
        m.insert_keyframe(k2);
        for i in 0..4u32 {
            m.add_point(Vector3::new(i as f64, 0.5, 5.0), 1, &[(1, i), (2, i)]);
        }
        let seen = |m: &ClientMap| -> Vec<Vector3<f64>> {
            let mut v = Vec::new();
            for kf in m.keyframes.values() {
                let mut ps: Vec<_> = m.points.values().collect();
                ps.sort_by_key(|p| p.id);
                v.extend(
                    ps.iter()
                        .map(|p| kf.t_cw * nalgebra::Point3::from(p.p_w))
                        .map(|c| c.coords),
                );
            }
            v
        };
        let before = seen(&m);
        let s = 2.5;
        let r = UnitQuaternion::from_scaled_axis(Vector3::new(0.4, 0.1, -1.2));
        let centres = |m: &ClientMap| -> Vec<Vector3<f64>> {
            let c = |kf: &Keyframe| kf.t_cw.inverse().translation.vector;
            m.keyframes.values().map(c).collect()
        };
        let centres_before = centres(&m);
        let move_ = Sim3::new(r, Vector3::new(-3.0, 1.5, 0.25), s);
        m.transform_world(&move_);
        for (a, b) in centres_before.iter().zip(centres(&m)) {
            assert!((move_.transform_point(a) - b).norm() < 1e-12, "{a} vs {b}");
        }
        for (a, b) in before.iter().zip(seen(&m)) {
            assert!((a * s - b).norm() < 1e-12, "{a} vs {b}");
        }
    }

    #[test]
    fn observations_covisibility_and_removal_stay_consistent() {
        let mut m = ClientMap::new(1, 100);
        m.insert_keyframe(kf(1, 10, 0.0));
        m.insert_keyframe(kf(2, 10, 1.0));
        m.insert_keyframe(kf(3, 10, 2.0));
        for i in 0..6u32 {
            m.add_point(Vector3::new(i as f64, 0.0, 5.0), 1, &[(1, i), (2, i)]);
        }
        for i in 0..3u32 {
            let p = m.keyframes[&1].points[i as usize].unwrap();
            m.add_observation(p, 3, i);
        }
        for k in [1, 2, 3] {
            m.update_covisibility(k);
        }
        assert_eq!(m.covis_weight(1, 2), 6);
        assert_eq!(m.covis_weight(2, 3), 3);
        assert_eq!(m.covisible(1, 5, 1), vec![2, 3]);
        assert_eq!(m.tracked_points(1, 3), 3);
        assert!((m.median_depth(1).unwrap() - 5.0).abs() < 1e-12);
        // Removing keyframe 1: points seen by 2 and 3 survive, the rest keep 1 obs and go.
        m.remove_keyframe(1, 2);
        assert_eq!(m.points.len(), 3);
        assert_eq!(m.keyframes[&2].n_points(), 3);
        assert_eq!(m.covis_weight(2, 1), 0);
        for mp in m.points.values() {
            for (k, i) in &mp.observations {
                assert_eq!(m.keyframes[k].points[*i as usize], Some(mp.id));
            }
        }
    }

    #[test]
    fn best_descriptor_is_the_median_one() {
        // Median distances to all (self included): 64, 32, 32, 64, 192 bits.
        let d = [[0u8; 32], [1u8; 32], [3u8; 32], [7u8; 32], [255u8; 32]];
        assert_eq!(best_descriptor(&d), Some([1u8; 32]));
    }
}
