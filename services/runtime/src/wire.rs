//! Every conversion between the shared-memory wire types ([`shm_schema`]) and the
//! algorithm's types ([`slam_core`], nalgebra), shared by the services and the launcher:
//! poses and similarities (the wire quaternion is `[x, y, z, w]`, nalgebra's constructor
//! takes `w` first: the swap is done here and nowhere else), camera intrinsics, keypoints and
//! the tracking state. Ids convert through [`slam_core::ids`].
use nalgebra::{Isometry3, Matrix3, Quaternion, Translation3, UnitQuaternion, Vector3};
use shm_schema::{ImuCalib, ImuRecord, Intrinsics, KeyframeHeader, Pose, TrackState};
use slam_core::camera::PinholeRadtan;
use slam_core::imu::{ImuIntrinsics, ImuMeasurement, ImuNoise, PreintegrationParams};
use slam_core::lie::Sim3;
use slam_core::vo::keyframe_imu::{ImuCalibration, KeyframeImu};
use slam_core::vo::VoState;

/// A wire quaternion norm below this is no rotation.
const MIN_QUATERNION_NORM: f64 = 1e-6;

/// The wire rotation `[x, y, z, w]` as a (not normalised) nalgebra quaternion.
fn quaternion_from_wire(q: &[f64; 4]) -> Quaternion<f64> {
    Quaternion::new(q[3], q[0], q[1], q[2])
}

/// The rotation of a wire pose; `None` when not finite or the quaternion is ~0 (the
/// translation is not looked at).
pub fn rotation_from_wire(p: &Pose) -> Option<UnitQuaternion<f64>> {
    if !p.q.iter().all(|v| v.is_finite()) {
        return None;
    }
    let q = quaternion_from_wire(&p.q);
    if q.norm() < MIN_QUATERNION_NORM {
        return None;
    }
    Some(UnitQuaternion::from_quaternion(q))
}

/// A wire pose `T_ab` as an isometry; `None` when not finite or the quaternion is ~0.
pub fn iso_from_wire(p: &Pose) -> Option<Isometry3<f64>> {
    if !p.t.iter().all(|v| v.is_finite()) {
        return None;
    }
    let r = rotation_from_wire(p)?;
    Some(Isometry3::from_parts(
        Translation3::new(p.t[0], p.t[1], p.t[2]),
        r,
    ))
}

/// A wire pose `T_ab` as an isometry without the validity checks of [`iso_from_wire`] (for
/// poses this program recorded itself): a non-finite or zero pose gives a non-finite
/// isometry.
pub fn iso_from_wire_unchecked(p: &Pose) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(p.t[0], p.t[1], p.t[2]),
        UnitQuaternion::from_quaternion(quaternion_from_wire(&p.q)),
    )
}

/// An isometry `T_ab` as a wire pose.
pub fn wire_from_iso(t: &Isometry3<f64>) -> Pose {
    let q = t.rotation.quaternion();
    let v = t.translation.vector;
    Pose {
        t: [v.x, v.y, v.z],
        q: [q.i, q.j, q.k, q.w],
    }
}

/// A wire similarity (pose + scale) as a [`Sim3`]; `None` when not finite or not positive.
pub fn sim3_from_wire(p: &Pose, scale: f64) -> Option<Sim3> {
    if !(scale.is_finite() && scale > 0.0) {
        return None;
    }
    iso_from_wire(p).map(|t| Sim3::from_isometry(&t, scale))
}

/// A [`Sim3`] as a wire pose and scale.
pub fn wire_from_sim3(s: &Sim3) -> (Pose, f64) {
    (wire_from_iso(&s.to_isometry()), s.s)
}

/// The wire intrinsics `(intrinsics, width, height)` of a camera model (the inverse of
/// [`camera_from_intrinsics`]).
pub fn intrinsics_from_camera(c: &PinholeRadtan) -> (Intrinsics, u32, u32) {
    (
        Intrinsics {
            pinhole: [c.fx, c.fy, c.cx, c.cy],
            distortion: [c.k1, c.k2, c.p1, c.p2, c.k3],
        },
        c.width,
        c.height,
    )
}

/// The camera model of a message's intrinsics (frames and keyframes carry the same
/// [`Intrinsics`]): pinhole `[fx, fy, cx, cy]` and radial-tangential `[k1, k2, p1, p2, k3]`.
/// Not checked: see [`valid_intrinsics`].
pub fn camera_from_intrinsics(intrinsics: &Intrinsics, width: u32, height: u32) -> PinholeRadtan {
    PinholeRadtan::from_coefficients(width, height, intrinsics.pinhole, intrinsics.distortion)
}

/// Whether message intrinsics can make a camera: positive focal lengths, a finite principal
/// point and a width.
pub fn valid_intrinsics(i: &Intrinsics, width: u32) -> bool {
    let [fx, fy, cx, cy] = i.pinhole;
    fx > 0.0 && fy > 0.0 && cx.is_finite() && cy.is_finite() && width > 0
}

/// A keypoint of a keyframe message (its size restored from the octave). Keyframe messages
/// carry neither sizes nor the pyramid's scale factor: the size is `PATCH_SIZE ·
/// factor^octave` with [`slam_core::features::ORB_SCALE_FACTOR`], the clients' extractor
/// default.
pub fn wire_keypoint(
    u: f32,
    v: f32,
    angle: f32,
    response: f32,
    octave: u32,
) -> slam_core::features::KeyPoint {
    let octave = octave.min(u8::MAX as u32) as u8;
    slam_core::features::KeyPoint {
        x: u,
        y: v,
        angle,
        response,
        size: slam_core::features::PATCH_SIZE
            * (slam_core::features::ORB_SCALE_FACTOR as f32).powi(octave as i32),
        octave,
    }
}

/// The wire tracking state of a VO state.
pub fn track_state_from_vo(s: VoState) -> TrackState {
    match s {
        VoState::NotInitialized => TrackState::NotInitialized,
        VoState::Initializing => TrackState::Initializing,
        VoState::Tracking => TrackState::Tracking,
        VoState::Lost => TrackState::Lost,
    }
}

/// A visual-inertial client's IMU calibration as a keyframe message carries it (issue 19;
/// matrices column-major).
pub fn wire_from_imu_calibration(c: &ImuCalibration) -> ImuCalib {
    let (n, k) = (&c.preint.noise, &c.preint.intrinsics);
    let cols = |m: &Matrix3<f64>| -> [f64; 9] { std::array::from_fn(|i| m.as_slice()[i]) };
    ImuCalib {
        pose_bc: wire_from_iso(&c.t_bc),
        t_d_ns: c.t_d_ns,
        gyro_noise_density: n.gyro_noise_density,
        accel_noise_density: n.accel_noise_density,
        gyro_bias_rw: n.gyro_bias_rw,
        accel_bias_rw: n.accel_bias_rw,
        t_a: cols(&k.t_a),
        t_g: cols(&k.t_g),
        t_s: cols(&k.t_s),
    }
}

/// The IMU calibration of a keyframe message (the inverse of
/// [`wire_from_imu_calibration`]); errors with the reason when the pose is not finite or the
/// preintegration settings are refused (a noise density negative or not finite, `T_a` or
/// `T_g` singular).
pub fn imu_calibration_from_wire(c: &ImuCalib) -> Result<ImuCalibration, String> {
    let t_bc = iso_from_wire(&c.pose_bc).ok_or("invalid camera-to-body pose T_bc")?;
    let noise = ImuNoise {
        gyro_noise_density: c.gyro_noise_density,
        accel_noise_density: c.accel_noise_density,
        gyro_bias_rw: c.gyro_bias_rw,
        accel_bias_rw: c.accel_bias_rw,
    };
    let intrinsics = ImuIntrinsics {
        t_a: Matrix3::from_column_slice(&c.t_a),
        t_g: Matrix3::from_column_slice(&c.t_g),
        t_s: Matrix3::from_column_slice(&c.t_s),
    };
    let preint = PreintegrationParams::new(&noise, &intrinsics).map_err(|e| e.to_string())?;
    Ok(ImuCalibration {
        preint,
        t_bc,
        t_d_ns: c.t_d_ns,
    })
}

/// An IMU record of a keyframe message as a measurement.
pub fn imu_measurement(r: &ImuRecord) -> ImuMeasurement {
    ImuMeasurement {
        t_ns: r.t_ns,
        gyro: Vector3::from(r.gyro),
        accel: Vector3::from(r.accel),
    }
}

/// A measurement as an IMU record of a keyframe message.
pub fn imu_record(m: &ImuMeasurement) -> ImuRecord {
    ImuRecord {
        t_ns: m.t_ns,
        gyro: m.gyro.into(),
        accel: m.accel.into(),
        reserved: 0,
    }
}

/// The IMU segment of a keyframe message with `has_imu` (issue 19, `VI_NOTES.md` §4 Fig.
/// 5.4), checked: a valid calibration, `imu_t1_ns` = `t_ns + t_d`, `n_imu` finite records
/// (none for a session's first keyframe: a segment without predecessor), strictly
/// increasing times from exactly `imu_t0_ns` to exactly `imu_t1_ns`. Shared by the mapper
/// (a received message) and the tracker (a spooled one, rebuilt into its client map).
pub fn keyframe_imu_from_wire(
    h: &KeyframeHeader,
    imu: &[ImuRecord],
) -> Result<KeyframeImu, String> {
    let calib = imu_calibration_from_wire(&h.imu_calib)?;
    if h.imu_t1_ns != h.t_ns.saturating_add(calib.t_d_ns) {
        return Err(format!(
            "IMU time {} ns is not the frame time {} ns + t_d {} ns",
            h.imu_t1_ns, h.t_ns, calib.t_d_ns
        ));
    }
    let mut seg = KeyframeImu {
        t_prev_ns: None,
        t_ns: h.imu_t1_ns,
        samples: Vec::new(),
        calib,
    };
    if h.n_imu as usize != imu.len() {
        return Err(format!(
            "{} IMU records, header says {}",
            imu.len(),
            h.n_imu
        ));
    }
    let (Some(first), Some(last)) = (imu.first(), imu.last()) else {
        return Ok(seg);
    };
    let finite = |r: &ImuRecord| r.gyro.iter().chain(&r.accel).all(|v| v.is_finite());
    if let Some(i) = imu.iter().position(|r| !finite(r)) {
        return Err(format!("IMU record {i}: non-finite value"));
    }
    if let Some(i) = imu.windows(2).position(|w| w[1].t_ns <= w[0].t_ns) {
        return Err(format!(
            "IMU record {}: time not after the previous one",
            i + 1
        ));
    }
    if imu.len() < 2 || first.t_ns != h.imu_t0_ns || last.t_ns != h.imu_t1_ns {
        return Err(format!(
            "IMU records over [{}, {}] ns, the segment is [{}, {}] ns",
            first.t_ns, last.t_ns, h.imu_t0_ns, h.imu_t1_ns
        ));
    }
    seg.t_prev_ns = Some(h.imu_t0_ns);
    seg.samples = imu.iter().map(imu_measurement).collect();
    Ok(seg)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose() -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(1.0, -2.0, 0.5),
            UnitQuaternion::from_euler_angles(0.1, -0.3, 0.7),
        )
    }

    #[test]
    fn pose_round_trip_and_bad_poses() {
        let t = pose();
        let w = wire_from_iso(&t);
        let q = t.rotation.quaternion();
        assert_eq!(w.q, [q.i, q.j, q.k, q.w], "wire order is [x, y, z, w]");
        let back = iso_from_wire(&w).expect("valid");
        assert_eq!(back, iso_from_wire_unchecked(&w));
        assert!((back.translation.vector - t.translation.vector).norm() < 1e-12);
        assert!(back.rotation.angle_to(&t.rotation) < 1e-12);
        assert_eq!(rotation_from_wire(&w), Some(back.rotation));
        let mut bad = w;
        bad.t[0] = f64::NAN;
        assert!(iso_from_wire(&bad).is_none());
        assert!(
            rotation_from_wire(&bad).is_some(),
            "only the rotation is looked at"
        );
        bad = Pose {
            t: [0.0; 3],
            q: [0.0; 4],
        };
        assert!(iso_from_wire(&bad).is_none());
        assert!(rotation_from_wire(&bad).is_none());
        assert!(sim3_from_wire(&w, 0.0).is_none());
        let s = sim3_from_wire(&w, 2.0).expect("valid");
        let (w2, scale) = wire_from_sim3(&s);
        assert_eq!(scale, 2.0);
        assert!(w2.t.iter().zip(&w.t).all(|(a, b)| (a - b).abs() < 1e-12));
    }

    #[test]
    fn intrinsics_round_trip() {
        let mut c = PinholeRadtan::pinhole(752, 480, 458.0, 457.0, 367.0, 248.0);
        c.k1 = -0.28;
        c.p2 = 1e-5;
        let (i, w, h) = intrinsics_from_camera(&c);
        assert!(valid_intrinsics(&i, w));
        assert_eq!(camera_from_intrinsics(&i, w, h), c);
    }

    #[test]
    fn track_states() {
        assert_eq!(track_state_from_vo(VoState::Tracking), TrackState::Tracking);
        assert_eq!(track_state_from_vo(VoState::Lost), TrackState::Lost);
    }

    /// The IMU calibration survives the wire (T_bc, t_d, noise densities, intrinsics); a
    /// singular T_a or a negative density is refused with the reason.
    #[test]
    fn imu_calibration_round_trips() {
        let mut intrinsics = ImuIntrinsics::default();
        intrinsics.t_a[(0, 1)] = 2e-3;
        intrinsics.t_s[(2, 0)] = -1e-4;
        let calib = ImuCalibration {
            preint: PreintegrationParams::new(&ImuNoise::default(), &intrinsics).expect("params"),
            t_bc: pose(),
            t_d_ns: -3_500_000,
        };
        let w = wire_from_imu_calibration(&calib);
        assert_eq!(w.t_a[3], 2e-3, "column-major");
        let back = imu_calibration_from_wire(&w).expect("valid");
        assert_eq!(back.preint, calib.preint);
        assert_eq!(back.t_d_ns, calib.t_d_ns);
        assert!((back.t_bc.translation.vector - calib.t_bc.translation.vector).norm() < 1e-15);
        let mut bad = w;
        bad.t_a = [0.0; 9];
        assert!(imu_calibration_from_wire(&bad).is_err_and(|e| e.contains("T_a")));
        bad = w;
        bad.accel_noise_density = -1.0;
        assert!(imu_calibration_from_wire(&bad).is_err());
    }
}
