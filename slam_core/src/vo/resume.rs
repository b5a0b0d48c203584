//! A VO session's client map rebuilt from stored keyframes (issue 17: the successor of a
//! SIGKILLed visual-inertial tracker resumes its session from the keyframe spool instead of
//! initialising again). Pure: keyframes and point positions in, a consistent [`ClientMap`]
//! out, or a [`CoreError::Resume`] saying why not; the VO takes it with
//! [`super::VoTracker::resume_session`].
//!
//! What a store keeps of a keyframe is what the server gets of it (seed §3.3: pose,
//! keypoints, descriptors, the client map-point id of each keypoint, the inertial state),
//! plus the world positions of the points it observes as they were when it was stored. A
//! point stored with several keyframes takes the position given last (the caller passes
//! the newest keyframe's last: the most refined). The map rebuilt holds every stored
//! keyframe and every stored point some keyframe observes, with observations, covisibility,
//! descriptors and viewing directions recomputed. What cannot be trusted is dropped and
//! counted ([`RestoredMap`]): an observation of a point without a stored position (the
//! store was written before the point existed), a second keypoint of one keyframe on the
//! same point. Refused: no keyframe, two keyframes of one id, keyframes out of time order,
//! a non-finite pose, position or inertial state, keypoint tables of different lengths,
//! cameras of different sizes, and fewer than [`MIN_RESTORED_POINTS`] points (too few to
//! relocalise against).
use std::collections::{HashMap, HashSet};

use nalgebra::Vector3;

use super::map::{ClientMap, Keyframe, KfId, PointId};
use crate::CoreError;

/// Fewest map points a rebuilt map must have: relocalisation needs 15 inlier matches with
/// map points (`tracker/reloc.rs`), and a frame sees only part of the map.
pub const MIN_RESTORED_POINTS: usize = 30;

/// A map point as stored: its id and world position (in the world of the stored keyframes).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StoredPoint {
    /// Client map-point id.
    pub id: PointId,
    /// Position in the world frame.
    pub p_w: Vector3<f64>,
}

/// What [`restore_map`] rebuilt, and what it left out.
#[derive(Debug, Clone)]
pub struct RestoredMap {
    /// The session's map.
    pub map: ClientMap,
    /// Keypoint observations dropped: no stored position for their point, or a second
    /// keypoint of the same keyframe on it.
    pub observations_dropped: usize,
    /// Stored points no keyframe observes (not in the map).
    pub points_unobserved: usize,
}

/// Rebuilds the map of VO session `session_id` from stored `keyframes` (any order) and
/// `points` (a later entry of an id wins); new points of the session will be numbered
/// from `first_new_point_id` on (past every stored id in any case). Module docs for what
/// is dropped and what is refused.
pub fn restore_map(
    session_id: u32,
    mut keyframes: Vec<Keyframe>,
    points: &[StoredPoint],
    first_new_point_id: PointId,
) -> Result<RestoredMap, CoreError> {
    check_keyframes(&mut keyframes)?;
    let positions = stored_positions(points)?;
    let mut dropped = 0;
    let mut first_kf: HashMap<PointId, KfId> = HashMap::new();
    for kf in &mut keyframes {
        dropped += drop_untrusted_observations(kf, &positions);
        for p in kf.points.iter().flatten() {
            first_kf.entry(*p).or_insert(kf.id);
        }
    }
    let mut map = ClientMap::new(session_id, first_new_point_id);
    for (&id, &kf) in &first_kf {
        if let Some(p_w) = positions.get(&id) {
            map.insert_point(id, *p_w, kf);
        }
    }
    for kf in keyframes {
        map.insert_keyframe(kf);
    }
    let ids: Vec<PointId> = map.points.keys().copied().collect();
    for p in ids {
        map.update_point(p);
    }
    if map.points.len() < MIN_RESTORED_POINTS {
        return Err(CoreError::Resume(format!(
            "{} map points observed by the stored keyframes, fewer than the {MIN_RESTORED_POINTS} to relocalise against",
            map.points.len()
        )));
    }
    Ok(RestoredMap {
        points_unobserved: positions.len() - map.points.len(),
        observations_dropped: dropped,
        map,
    })
}

/// Sorts the keyframes by id and refuses what no VO could have made (module docs).
fn check_keyframes(keyframes: &mut [Keyframe]) -> Result<(), CoreError> {
    let refuse = |why: String| Err(CoreError::Resume(why));
    keyframes.sort_by_key(|k| k.id);
    let Some(first) = keyframes.first() else {
        return refuse("no stored keyframe".into());
    };
    let size = (first.camera.width, first.camera.height);
    for pair in keyframes.windows(2) {
        let (a, b) = (&pair[0], &pair[1]);
        if a.id == b.id {
            return refuse(format!("keyframe {} stored twice", a.id));
        }
        if b.t_ns <= a.t_ns {
            return refuse(format!(
                "keyframe {} at {} ns is not after keyframe {} at {} ns",
                b.id, b.t_ns, a.id, a.t_ns
            ));
        }
    }
    for kf in keyframes.iter() {
        let n = kf.features.keypoints.len();
        if kf.features.descriptors.len() != n || kf.points.len() != n {
            return refuse(format!(
                "keyframe {}: {n} keypoints, {} descriptors, {} point slots",
                kf.id,
                kf.features.descriptors.len(),
                kf.points.len()
            ));
        }
        if (kf.camera.width, kf.camera.height) != size {
            return refuse(format!("keyframe {}: camera of another size", kf.id));
        }
        if !keyframe_finite(kf) {
            return refuse(format!(
                "keyframe {}: non-finite pose or inertial state",
                kf.id
            ));
        }
    }
    Ok(())
}

/// The keyframe's pose and inertial state are finite.
fn keyframe_finite(kf: &Keyframe) -> bool {
    let pose = kf.t_cw.translation.vector.iter().all(|v| v.is_finite())
        && kf.t_cw.rotation.coords.iter().all(|v| v.is_finite());
    let inertial = kf.inertial.is_none_or(|i| {
        i.v_wb
            .iter()
            .chain(i.biases.gyro.iter())
            .chain(i.biases.accel.iter())
            .all(|v| v.is_finite())
    });
    pose && inertial
}

/// The stored positions by id (a later entry wins); a non-finite one refuses the store.
fn stored_positions(points: &[StoredPoint]) -> Result<HashMap<PointId, Vector3<f64>>, CoreError> {
    let mut out = HashMap::with_capacity(points.len());
    for p in points {
        if !p.p_w.iter().all(|v| v.is_finite()) {
            return Err(CoreError::Resume(format!(
                "map point {}: non-finite position",
                p.id
            )));
        }
        out.insert(p.id, p.p_w);
    }
    Ok(out)
}

/// Clears the keyframe's observations of points without a position and its second
/// observations of a point; returns how many.
fn drop_untrusted_observations(
    kf: &mut Keyframe,
    positions: &HashMap<PointId, Vector3<f64>>,
) -> usize {
    let mut seen: HashSet<PointId> = HashSet::with_capacity(kf.points.len());
    let mut dropped = 0;
    for slot in kf.points.iter_mut() {
        if let Some(p) = *slot {
            if !positions.contains_key(&p) || !seen.insert(p) {
                *slot = None;
                dropped += 1;
            }
        }
    }
    dropped
}

#[cfg(test)]
mod tests;
