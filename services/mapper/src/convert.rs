//! Wire ↔ algorithm conversions: a keyframe message (header + keypoint records + IMU
//! records) into a [`ServerKeyframe`], a kept keyframe into a loop keyframe message, a
//! correction message into a [`Correction`] (poses, intrinsics, keypoints and the IMU
//! calibration through [`shoal_runtime::wire`]).
use std::collections::BTreeMap;

use nalgebra::Vector3;
use shm_schema::{
    CorrectionHeader, CorrectionRecord, ImuRecord, Intrinsics, KeyframeHeader, KeypointRecord,
    LoopKeyframeHeader, LoopKeypointRecord, MsgMeta, CORRECTION_MERGE, CORRECTION_POSE_GRAPH,
    FLAG_INERTIAL_MAP, MAX_LOOP_COVISIBLE, NO_MAP_POINT, RECORD_KEYFRAME_DELTA, RECORD_POINT_PAIR,
};
use slam_core::camera::PinholeRadtan;
use slam_core::features::OrbFeatures;
use slam_core::ids::MapId;
use slam_core::imu::ImuBiases;
use slam_core::lie::Sim3;
use slam_core::server::{KeptKeyframe, ServerKeyframe};
use slam_core::vo::keyframe_imu::KeyframeImu;
use slam_core::vo::{KeyframeInertial, KfId, PointId};

use shoal_runtime::wire::{
    camera_from_intrinsics, iso_from_wire, keyframe_imu_from_wire, sim3_from_wire,
    valid_intrinsics, wire_from_iso, wire_keypoint,
};

/// The camera of a keyframe message.
pub fn camera_of(h: &KeyframeHeader) -> PinholeRadtan {
    camera_from_intrinsics(&h.intrinsics, h.width, h.height)
}

/// A keyframe message converted: the keyframe, and why its IMU part was refused if it was
/// (the keyframe is then visual-only: no segment, no velocity and biases).
#[derive(Debug)]
pub struct Converted {
    /// The keyframe for the handler.
    pub kf: ServerKeyframe,
    /// Why the IMU segment or the inertial state was refused (`ErrorKind::BadImuSegment`).
    pub imu_refused: Option<String>,
}

/// Converts a keyframe message of client `client` into what the handler takes. Errors
/// (with a reason) on an unusable message: keypoint count not matching the header, a
/// non-finite pose, bad intrinsics. The IMU part (`imu`: the payload's IMU records, or why
/// the payload does not hold them) is checked by [`inertial_parts`]; refused, the keyframe
/// goes on visual-only and [`Converted::imu_refused`] says why. The rolling-shutter readout
/// time is not on the wire (the server map does not use it) and is set to 0.
pub fn server_keyframe(
    client: u32,
    h: &KeyframeHeader,
    records: &[KeypointRecord],
    imu: Result<&[ImuRecord], String>,
) -> Result<Converted, String> {
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
    let (inertial, seg, imu_refused) = match imu.and_then(|r| inertial_parts(h, r)) {
        Ok((inertial, seg)) => (inertial, seg, None),
        Err(e) => (None, None, Some(format!("keyframe {}: {e}", h.keyframe_id))),
    };
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
        inertial,
        imu: seg,
    };
    kf.validate().map_err(|e| e.to_string())?;
    Ok(Converted { kf, imu_refused })
}

/// The velocity and biases (with `inertial`; `refined` 0: no server window has refined
/// them yet) and the IMU segment (with `has_imu`) of a keyframe message, checked (issue 19,
/// `VI_NOTES.md` §4 Fig. 5.4): finite values, a valid calibration, `n_imu` records (none for
/// a session's first keyframe), strictly increasing times from exactly `imu_t0_ns` to
/// exactly `imu_t1_ns` = `t_ns + t_d`. A monocular message gives `(None, None)`.
pub fn inertial_parts(
    h: &KeyframeHeader,
    imu: &[ImuRecord],
) -> Result<(Option<KeyframeInertial>, Option<KeyframeImu>), String> {
    let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
    let inertial = if h.inertial == 0 {
        None
    } else if finite(&h.velocity_w) && finite(&h.gyro_bias) && finite(&h.accel_bias) {
        Some(KeyframeInertial {
            v_wb: Vector3::from(h.velocity_w),
            biases: ImuBiases {
                gyro: Vector3::from(h.gyro_bias),
                accel: Vector3::from(h.accel_bias),
            },
            refined: 0,
        })
    } else {
        return Err("non-finite velocity or biases".into());
    };
    if h.has_imu == 0 {
        if !imu.is_empty() {
            return Err(format!("{} IMU records without an IMU", imu.len()));
        }
        return Ok((inertial, None));
    }
    Ok((inertial, Some(keyframe_imu_from_wire(h, imu)?)))
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
        let conv = server_keyframe(3, &h, &recs, Ok(&[])).expect("valid");
        let kf = conv.kf;
        assert_eq!(kf.client_id, 3);
        assert_eq!(kf.client_points, vec![Some(42), None]);
        assert_eq!(kf.features.keypoints[0].octave, 2);
        assert!(kf.imu.is_none() && kf.inertial.is_none() && conv.imu_refused.is_none());
        assert!(server_keyframe(3, &h, &recs[..1], Ok(&[])).is_err());
        h.intrinsics.pinhole[0] = 0.0;
        assert!(server_keyframe(3, &h, &recs, Ok(&[])).is_err());
    }

    /// A visual-inertial keyframe message at 2 s (t_d = 1 ms) with the segment from 1.95 s:
    /// samples every 20 ms, borders exact.
    fn vi_message() -> (KeyframeHeader, Vec<ImuRecord>) {
        let (t0, t1) = (1_951_000_000, 2_001_000_000);
        let imu: Vec<ImuRecord> = [t0, t0 + 9_000_000, t0 + 29_000_000, t1]
            .iter()
            .map(|&t_ns| ImuRecord {
                t_ns,
                gyro: [0.1, 0.0, -0.1],
                accel: [0.0, 0.0, 9.81],
                reserved: 0,
            })
            .collect();
        let mut h = KeyframeHeader {
            keyframe_id: 8,
            t_ns: 2_000_000_000,
            width: 640,
            height: 480,
            pose_ck: Pose::IDENTITY,
            inertial: 1,
            velocity_w: [1.0, 2.0, 3.0],
            gyro_bias: [1e-3, 0.0, 0.0],
            n_imu: imu.len() as u32,
            has_imu: 1,
            imu_t0_ns: t0,
            imu_t1_ns: t1,
            ..KeyframeHeader::default()
        };
        h.intrinsics.pinhole = [400.0, 400.0, 320.0, 240.0];
        h.imu_calib.t_d_ns = 1_000_000;
        h.imu_calib.gyro_noise_density = 1.7e-4;
        h.imu_calib.pose_bc.t = [0.05, 0.0, 0.0];
        (h, imu)
    }

    /// Issue 19: the segment, calibration, velocity and biases of a visual-inertial message
    /// reach the server keyframe; a session's first keyframe has a segment without
    /// predecessor; a monocular message has none.
    #[test]
    fn visual_inertial_message_to_server_keyframe() {
        let (h, imu) = vi_message();
        let conv = server_keyframe(1, &h, &[], Ok(&imu)).expect("valid");
        assert!(conv.imu_refused.is_none(), "{:?}", conv.imu_refused);
        let seg = conv.kf.imu.expect("segment");
        assert_eq!((seg.t_prev_ns, seg.t_ns), (Some(h.imu_t0_ns), h.imu_t1_ns));
        assert!(seg.is_complete());
        assert_eq!(seg.samples.len(), 4);
        assert_eq!(seg.samples[2].t_ns, imu[2].t_ns);
        assert_eq!(seg.samples[2].accel.z, 9.81);
        assert_eq!(seg.calib.t_d_ns, 1_000_000);
        assert_eq!(seg.calib.preint.noise.gyro_noise_density, 1.7e-4);
        assert_eq!(seg.calib.t_bc.translation.vector.x, 0.05);
        let inertial = conv.kf.inertial.expect("inertial");
        assert_eq!(inertial.v_wb, Vector3::new(1.0, 2.0, 3.0));
        assert_eq!(inertial.biases.gyro.x, 1e-3);
        let mut first = h;
        (first.n_imu, first.imu_t0_ns) = (0, 0);
        let seg = server_keyframe(1, &first, &[], Ok(&[]))
            .expect("valid")
            .kf
            .imu;
        let seg = seg.expect("a segment without predecessor");
        assert_eq!((seg.t_prev_ns, seg.samples.len()), (None, 0));
        let mut mono = first;
        (mono.has_imu, mono.inertial) = (0, 0);
        let conv = server_keyframe(1, &mono, &[], Ok(&[])).expect("valid");
        assert!(conv.kf.imu.is_none() && conv.kf.inertial.is_none());
        assert!(conv.imu_refused.is_none());
    }

    /// A segment that does not hold is refused with its reason and the keyframe goes on
    /// visual-only: times out of order, a NaN, borders off `imu_t0_ns`/`imu_t1_ns`, a
    /// keyframe time that is not `t_ns + t_d`, a payload that does not hold `n_imu`
    /// records, a singular `T_a`, a non-finite velocity.
    #[test]
    fn a_bad_segment_leaves_the_keyframe_visual_only() {
        let (h, imu) = vi_message();
        let mut cases: Vec<(&str, KeyframeHeader, Vec<ImuRecord>)> = Vec::new();
        let mut swapped = imu.clone();
        swapped.swap(1, 2);
        cases.push(("not after the previous", h, swapped));
        let mut nan = imu.clone();
        nan[1].gyro[2] = f64::NAN;
        cases.push(("non-finite", h, nan));
        let mut early = h;
        early.imu_t0_ns -= 1;
        cases.push(("the segment is", early, imu.clone()));
        let mut late = h;
        late.t_ns += 1;
        cases.push(("t_d", late, imu.clone()));
        let mut more = h;
        more.n_imu = 5;
        cases.push(("header says 5", more, imu.clone()));
        let mut singular = h;
        singular.imu_calib.t_a = [0.0; 9];
        cases.push(("T_a", singular, imu.clone()));
        let mut fast = h;
        fast.velocity_w[0] = f64::INFINITY;
        cases.push(("velocity", fast, imu.clone()));
        for (why, h, imu) in cases {
            let conv = server_keyframe(1, &h, &[], Ok(&imu)).expect("still a keyframe");
            let e = conv.imu_refused.expect("refused");
            assert!(e.contains(why) && e.contains("keyframe 8"), "{why}: {e}");
            assert!(conv.kf.imu.is_none() && conv.kf.inertial.is_none(), "{why}");
        }
        let conv = server_keyframe(1, &h, &[], Err("payload short".into())).expect("keyframe");
        assert!(conv
            .imu_refused
            .is_some_and(|e| e.contains("payload short")));
    }
}
