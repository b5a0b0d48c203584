//! Wire ↔ nalgebra conversions of poses and similarities, shared by the services.
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use shm_schema::Pose;
use slam_core::lie::Sim3;

/// A wire pose `T_ab` as an isometry; `None` when not finite or the quaternion is ~0.
pub fn iso_from_wire(p: &Pose) -> Option<Isometry3<f64>> {
    if !p.t.iter().chain(p.q.iter()).all(|v| v.is_finite()) {
        return None;
    }
    let q = Quaternion::new(p.q[3], p.q[0], p.q[1], p.q[2]);
    if q.norm() < 1e-6 {
        return None;
    }
    Some(Isometry3::from_parts(
        Translation3::new(p.t[0], p.t[1], p.t[2]),
        UnitQuaternion::from_quaternion(q),
    ))
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
/// [`crate::camera_from_intrinsics`]).
pub fn intrinsics_from_camera(
    c: &slam_core::camera::PinholeRadtan,
) -> (shm_schema::Intrinsics, u32, u32) {
    (
        shm_schema::Intrinsics {
            pinhole: [c.fx, c.fy, c.cx, c.cy],
            distortion: [c.k1, c.k2, c.p1, c.p2, c.k3],
        },
        c.width,
        c.height,
    )
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

/// Whether message intrinsics can make a camera: positive focal lengths, a finite principal
/// point and a width.
pub fn valid_intrinsics(i: &shm_schema::Intrinsics, width: u32) -> bool {
    let [fx, fy, cx, cy] = i.pinhole;
    fx > 0.0 && fy > 0.0 && cx.is_finite() && cy.is_finite() && width > 0
}
