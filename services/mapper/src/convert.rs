//! Wire ↔ algorithm conversions: a keyframe message (header + keypoint records) into a
//! [`ServerKeyframe`], a kept keyframe into a loop keyframe message, a correction message
//! into a [`Correction`] (poses, intrinsics and keypoints through [`shoal_runtime::wire`]).
use std::collections::BTreeMap;

use shm_schema::{
    CorrectionHeader, CorrectionRecord, Intrinsics, KeyframeHeader, KeypointRecord,
    LoopKeyframeHeader, LoopKeypointRecord, MsgMeta, CORRECTION_MERGE, CORRECTION_POSE_GRAPH,
    FLAG_INERTIAL_MAP, MAX_LOOP_COVISIBLE, NO_MAP_POINT, RECORD_KEYFRAME_DELTA, RECORD_POINT_PAIR,
};
use slam_core::camera::PinholeRadtan;
use slam_core::features::OrbFeatures;
use slam_core::ids::MapId;
use slam_core::lie::Sim3;
use slam_core::server::{KeptKeyframe, ServerKeyframe};
use slam_core::vo::{KfId, PointId};

use shoal_runtime::wire::{
    camera_from_intrinsics, iso_from_wire, sim3_from_wire, valid_intrinsics, wire_from_iso,
    wire_keypoint,
};

/// The camera of a keyframe message.
pub fn camera_of(h: &KeyframeHeader) -> PinholeRadtan {
    camera_from_intrinsics(&h.intrinsics, h.width, h.height)
}

/// Converts a keyframe message of client `client` into what the handler takes. Errors
/// (with a reason) on an unusable message: keypoint count not matching the header, a
/// non-finite pose, bad intrinsics. The rolling-shutter readout time is not on the wire
/// (the server map does not use it) and is set to 0.
pub fn server_keyframe(
    client: u32,
    h: &KeyframeHeader,
    records: &[KeypointRecord],
) -> Result<ServerKeyframe, String> {
    if h.n_keypoints as usize != records.len() {
        return Err(format!(
            "keyframe {}: header says {} keypoints, payload holds {}",
            h.keyframe_id,
            h.n_keypoints,
            records.len()
        ));
    }
    let t_ck = iso_from_wire(&h.pose_ck)
        .ok_or_else(|| format!("keyframe {}: invalid pose", h.keyframe_id))?;
    let camera = camera_of(h);
    if !valid_intrinsics(&h.intrinsics, h.width) {
        return Err(format!("keyframe {}: invalid intrinsics", h.keyframe_id));
    }
    // The message carries octaves, not the pyramid's factor: the features get the default
    // scale (`slam_core::features::ORB_SCALE_FACTOR`, the clients' extractor default).
    let mut features = OrbFeatures::with_capacity(records.len());
    let mut client_points = Vec::with_capacity(records.len());
    for r in records {
        features
            .keypoints
            .push(wire_keypoint(r.u, r.v, r.angle, r.response, r.octave));
        features.descriptors.push(r.descriptor);
        client_points.push((r.map_point_id != NO_MAP_POINT).then_some(r.map_point_id));
    }
    let kf = ServerKeyframe {
        client_id: client,
        session_id: h.meta.session_id,
        id: h.keyframe_id,
        t_ns: h.t_ns,
        t_ck,
        camera,
        readout_ns: 0,
        features,
        client_points,
        inertial: None,
        imu: None,
    };
    kf.validate().map_err(|e| e.to_string())?;
    Ok(kf)
}

/// A loop correction as the mapper applies it.
#[derive(Debug, Clone)]
pub enum Correction {
    /// Merge map `from` into map `into` by `S_into_from`, fusing `pairs`.
    Merge {
        /// Correction id.
        id: u64,
        /// The map that is moved.
        from: MapId,
        /// The map it joins.
        into: MapId,
        /// `x_into = s R x_from + t`.
        s_into_from: Sim3,
        /// Point pairs (point of `from`, same point of `into`).
        pairs: Vec<(PointId, PointId)>,
    },
    /// Pose-graph corrections of map `map`.
    PoseGraph {
        /// Correction id.
        id: u64,
        /// The corrected map.
        map: MapId,
        /// Per keyframe `Δ_k`.
        deltas: BTreeMap<KfId, Sim3>,
        /// `Δ` for keyframes without an entry.
        fallback: Sim3,
        /// Point pairs to fuse (loop side, matched side).
        pairs: Vec<(PointId, PointId)>,
    },
}

impl Correction {
    /// Correction id.
    pub fn id(&self) -> u64 {
        match self {
            Correction::Merge { id, .. } | Correction::PoseGraph { id, .. } => *id,
        }
    }
}

/// Decodes a correction message; errors (with a reason) on an unusable one.
pub fn correction(
    h: &CorrectionHeader,
    records: &[CorrectionRecord],
) -> Result<Correction, String> {
    if h.n_records as usize != records.len() {
        return Err(format!(
            "correction {}: header says {} records, payload holds {}",
            h.correction_id,
            h.n_records,
            records.len()
        ));
    }
    let s = sim3_from_wire(&h.sim3, h.scale).ok_or_else(|| {
        format!(
            "correction {}: invalid similarity (scale {})",
            h.correction_id, h.scale
        )
    })?;
    let mut pairs = Vec::new();
    let mut deltas = BTreeMap::new();
    for (i, r) in records.iter().enumerate() {
        match r.kind {
            RECORD_POINT_PAIR => pairs.push((r.a, r.b)),
            RECORD_KEYFRAME_DELTA => {
                let d = sim3_from_wire(&r.delta, r.scale).ok_or_else(|| {
                    format!(
                        "correction {}: record {i}: invalid keyframe delta",
                        h.correction_id
                    )
                })?;
                deltas.insert(r.a, d);
            }
            k => {
                return Err(format!(
                    "correction {}: record {i}: unknown kind {k}",
                    h.correction_id
                ))
            }
        }
    }
    match h.kind {
        CORRECTION_MERGE => Ok(Correction::Merge {
            id: h.correction_id,
            from: MapId::from_raw(h.from_map),
            into: MapId::from_raw(h.into_map),
            s_into_from: s,
            pairs,
        }),
        CORRECTION_POSE_GRAPH => Ok(Correction::PoseGraph {
            id: h.correction_id,
            map: MapId::from_raw(h.into_map),
            deltas,
            fallback: s,
            pairs,
        }),
        k => Err(format!("correction {}: unknown kind {k}", h.correction_id)),
    }
}

/// The loop closer's message for a kept keyframe (seed §3.4.2: descriptors, points in the
/// keyframe's frame, covisible neighbours); `intrinsics`/`width`/`height` are those of the
/// client's keyframe message.
pub fn loop_keyframe(
    kept: &KeptKeyframe,
    meta: MsgMeta,
    intrinsics: &Intrinsics,
    width: u32,
    height: u32,
) -> (LoopKeyframeHeader, Vec<LoopKeypointRecord>) {
    let f = &kept.features;
    let mut records: Vec<LoopKeypointRecord> = f
        .keypoints
        .iter()
        .zip(&f.descriptors)
        .map(|(k, d)| LoopKeypointRecord {
            u: k.x,
            v: k.y,
            angle: k.angle,
            response: k.response,
            octave: k.octave as u32,
            descriptor: *d,
            ..LoopKeypointRecord::default()
        })
        .collect();
    for p in &kept.points {
        if let Some(r) = records.get_mut(p.keypoint as usize) {
            r.has_point = 1;
            r.point_id = p.point;
            r.p_k = [p.p_k.x, p.p_k.y, p.p_k.z];
        }
    }
    let mut h = LoopKeyframeHeader {
        meta,
        map_id: kept.map_id.raw(),
        kf_id: kept.kf_id,
        client_kf_id: kept.client_kf_id,
        t_ns: kept.t_ns,
        pose_sk: wire_from_iso(&kept.t_sk),
        intrinsics: *intrinsics,
        width,
        height,
        n_keypoints: records.len() as u32,
        ..LoopKeyframeHeader::default()
    };
    if kept.frame.is_inertial() {
        h.meta.flags |= FLAG_INERTIAL_MAP;
    }
    for (i, (k, w)) in kept.covisible.iter().take(MAX_LOOP_COVISIBLE).enumerate() {
        h.covisible_ids[i] = *k;
        h.covisible_weights[i] = *w;
        h.n_covisible = i as u32 + 1;
    }
    (h, records)
}

#[cfg(test)]
mod tests {
    use super::*;
    use shm_schema::Pose;

    #[test]
    fn message_to_server_keyframe() {
        let mut h = KeyframeHeader {
            keyframe_id: 7,
            n_keypoints: 2,
            width: 640,
            height: 480,
            pose_ck: Pose::IDENTITY,
            ..KeyframeHeader::default()
        };
        h.intrinsics.pinhole = [400.0, 400.0, 320.0, 240.0];
        let recs = [
            KeypointRecord {
                u: 10.0,
                v: 20.0,
                octave: 2,
                map_point_id: 42,
                ..KeypointRecord::default()
            },
            KeypointRecord::default(),
        ];
        let kf = server_keyframe(3, &h, &recs).expect("valid");
        assert_eq!(kf.client_id, 3);
        assert_eq!(kf.client_points, vec![Some(42), None]);
        assert_eq!(kf.features.keypoints[0].octave, 2);
        assert!(server_keyframe(3, &h, &recs[..1]).is_err());
        h.intrinsics.pinhole[0] = 0.0;
        assert!(server_keyframe(3, &h, &recs).is_err());
    }
}
