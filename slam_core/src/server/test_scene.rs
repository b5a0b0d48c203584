//! A constructed scene for server tests (no rendering): exact projections of a textured
//! plane seen by a pinhole camera, every visible point carrying its index as the client's
//! point id. The handler's own tests use it, and so do other crates' (`map_store`'s saved
//! maps), through the `testing` feature.
use nalgebra::{Isometry3, Point3, Vector3};

use super::ServerKeyframe;
use crate::camera::PinholeRadtan;
use crate::features::{KeyPoint, OrbFeatures};

/// The client the keyframes come from.
pub const CLIENT: u32 = 3;

/// The camera: 640 x 480, focal 500 px, centred.
pub fn camera() -> PinholeRadtan {
    PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0)
}

/// World points on the plane z = 5 (a 40 x 30 grid), each with its own descriptor.
pub fn scene() -> Vec<(Vector3<f64>, [u8; 32])> {
    let mut out = Vec::new();
    let mut h = 0x9e37_79b9_7f4a_7c15u64;
    for i in 0..40 {
        for j in 0..30 {
            let mut d = [0u8; 32];
            for b in d.iter_mut() {
                h ^= h << 13;
                h ^= h >> 7;
                h ^= h << 17;
                *b = h as u8;
            }
            let p = Vector3::new(-6.0 + 0.3 * i as f64, -3.0 + 0.2 * j as f64, 5.0);
            out.push((p, d));
        }
    }
    out
}

/// Keyframe `id` seen from the true pose `t_wk` (camera → world); its client pose is
/// `t_ck`; every visible point carries its index as client point id.
pub fn keyframe(
    id: u64,
    session: u32,
    t_wk: &Isometry3<f64>,
    t_ck: &Isometry3<f64>,
) -> ServerKeyframe {
    let cam = camera();
    let mut features = OrbFeatures::default();
    let mut client_points = Vec::new();
    for (i, (p, d)) in scene().iter().enumerate() {
        let p_k = t_wk.inverse() * Point3::from(*p);
        let Some(uv) = cam.project(&p_k.coords) else {
            continue;
        };
        if !cam.contains(&uv) {
            continue;
        }
        features
            .keypoints
            .push(KeyPoint::at_level0(uv.x as f32, uv.y as f32));
        features.descriptors.push(*d);
        client_points.push(Some(i as u64));
    }
    ServerKeyframe {
        client_id: CLIENT,
        session_id: session,
        id,
        t_ns: id as i64 * 50_000_000,
        t_ck: *t_ck,
        camera: cam,
        readout_ns: 0,
        features,
        client_points,
        inertial: None,
        imu: None,
    }
}

/// True pose `k` of a sideways trajectory (0.25 per step along x), facing the plane.
pub fn true_pose(k: usize) -> Isometry3<f64> {
    Isometry3::translation(0.25 * k as f64, 0.02 * k as f64, 0.0)
}
