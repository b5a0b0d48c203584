//! Pose prediction and scale-ratio tracking of the server keyframe handler (seed §3.4.1,
//! eq. 3.1-3.4), as pure functions.
//!
//! Conventions (seed §2.2): `t_ck` maps keyframe-camera coordinates into the client map,
//! `p_c = R_ck p_k + t_ck` (the inverse of [`crate::vo::Keyframe::t_cw`]); `t_sk` maps them
//! into the server map. The scale ratio `λ` is server length / client length.
use nalgebra::{Isometry3, Translation3, Vector3};

/// Relative motion of keyframe `k` with respect to keyframe `j` in the client map
/// (eq. 3.1): `R~_jk = R_cjᵀ R_ck`, `t~_jk = R_cjᵀ (t_ck − t_cj)`, i.e. `T_cj⁻¹ T_ck`.
pub fn relative_client_motion(t_cj: &Isometry3<f64>, t_ck: &Isometry3<f64>) -> Isometry3<f64> {
    t_cj.inverse() * t_ck
}

/// Predicted server pose of keyframe `k` from the server pose of keyframe `j`, both client
/// poses and the scale ratio `λ_j` (eq. 3.1 and 3.4): `R_sk = R_sj R~_jk`,
/// `t_sk = t_sj + λ_j R_sj t~_jk`.
///
/// The same composition gives a client frame's pose in the server map from the feedback
/// (server pose of the last keyframe and `λ`), without transforming the client map.
pub fn predict_server_pose(
    t_cj: &Isometry3<f64>,
    t_sj: &Isometry3<f64>,
    lambda_j: f64,
    t_ck: &Isometry3<f64>,
) -> Isometry3<f64> {
    let rel = relative_client_motion(t_cj, t_ck);
    let t = t_sj.translation.vector + lambda_j * (t_sj.rotation * rel.translation.vector);
    Isometry3::from_parts(Translation3::from(t), t_sj.rotation * rel.rotation)
}

/// Translation of `k` relative to `j` expressed in `j`'s camera frame, `R_jᵀ (t_k − t_j)`,
/// for poses mapping camera coordinates into the same map frame.
pub fn relative_translation(t_mj: &Isometry3<f64>, t_mk: &Isometry3<f64>) -> Vector3<f64> {
    t_mj.rotation.inverse() * (t_mk.translation.vector - t_mj.translation.vector)
}

/// Measured scale ratio (eq. 3.2): `λ~_k = |t^_jk| / |t~_jk|`, the length of the refined
/// server translation from `j` to `k` over the client one. `None` when the client
/// translation is shorter than `min_client_translation` (the ratio is then meaningless) or
/// the result is not finite.
pub fn measured_scale_ratio(
    t_sj: &Isometry3<f64>,
    t_sk: &Isometry3<f64>,
    t_cj: &Isometry3<f64>,
    t_ck: &Isometry3<f64>,
    min_client_translation: f64,
) -> Option<f64> {
    let client = relative_translation(t_cj, t_ck).norm();
    if client.is_nan() || client <= min_client_translation.max(0.0) {
        return None;
    }
    let lambda = relative_translation(t_sj, t_sk).norm() / client;
    lambda.is_finite().then_some(lambda)
}

/// Smoothed scale ratio (eq. 3.3): `λ_k = λ_j + α (λ~_k − λ_j)`; without a measurement
/// `λ_k = λ_j`. The seed uses `α = 0.2`.
pub fn smooth_scale_ratio(lambda_j: f64, measured: Option<f64>, alpha: f64) -> f64 {
    match measured {
        Some(m) if m.is_finite() => lambda_j + alpha * (m - lambda_j),
        _ => lambda_j,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{UnitQuaternion, Vector3};

    fn pose(t: [f64; 3], axis: [f64; 3], angle: f64) -> Isometry3<f64> {
        let r = UnitQuaternion::from_axis_angle(
            &nalgebra::Unit::new_normalize(Vector3::from(axis)),
            angle,
        );
        Isometry3::from_parts(Translation3::new(t[0], t[1], t[2]), r)
    }

    /// Server map = Sim(3) of the client map: `T_sk = S (T_ck)` with scale `s`; the
    /// prediction with `λ = s` is exact, the measured ratio is `s`.
    #[test]
    fn prediction_is_exact_for_a_similarity_between_maps() {
        let s = 2.5;
        let a = pose([0.3, -1.0, 2.0], [0.2, 1.0, 0.1], 0.7);
        let to_server = |t_ck: &Isometry3<f64>| {
            let r = a.rotation * t_ck.rotation;
            let t = a.translation.vector + s * (a.rotation * t_ck.translation.vector);
            Isometry3::from_parts(Translation3::from(t), r)
        };
        let t_cj = pose([1.0, 0.0, 0.5], [0.0, 1.0, 0.0], 0.3);
        let t_ck = pose([1.4, 0.1, 0.2], [0.1, 1.0, 0.0], 0.45);
        let (t_sj, t_sk) = (to_server(&t_cj), to_server(&t_ck));
        let pred = predict_server_pose(&t_cj, &t_sj, s, &t_ck);
        assert!((pred.translation.vector - t_sk.translation.vector).norm() < 1e-12);
        assert!(pred.rotation.angle_to(&t_sk.rotation) < 1e-12);
        let m = measured_scale_ratio(&t_sj, &t_sk, &t_cj, &t_ck, 1e-9).unwrap();
        assert!((m - s).abs() < 1e-12);
        // Eq. 3.1 in the seed's component form.
        let rel = relative_client_motion(&t_cj, &t_ck);
        let r_cj = t_cj.rotation.to_rotation_matrix();
        let t_tilde = r_cj.transpose() * (t_ck.translation.vector - t_cj.translation.vector);
        assert!((rel.translation.vector - t_tilde).norm() < 1e-12);
    }

    #[test]
    fn measured_ratio_needs_client_motion() {
        let t = pose([1.0, 2.0, 3.0], [0.0, 0.0, 1.0], 0.2);
        let t2 = pose([1.0, 2.0, 3.0], [0.0, 0.0, 1.0], 0.4);
        assert_eq!(measured_scale_ratio(&t, &t2, &t, &t2, 1e-6), None);
    }

    /// Eq. 3.3 with α = 0.2: a constant measured ratio is approached geometrically,
    /// `λ_n − λ~ = (1 − α)ⁿ (λ_0 − λ~)`; no measurement leaves λ unchanged.
    #[test]
    fn smoothing_follows_eq_3_3() {
        let alpha = 0.2;
        assert!((smooth_scale_ratio(1.0, Some(2.0), alpha) - 1.2).abs() < 1e-15);
        assert_eq!(smooth_scale_ratio(1.3, None, alpha), 1.3);
        assert_eq!(smooth_scale_ratio(1.3, Some(f64::NAN), alpha), 1.3);
        let mut l = 1.0;
        for _ in 0..10 {
            l = smooth_scale_ratio(l, Some(0.5), alpha);
        }
        assert!((l - (0.5 + 0.8f64.powi(10) * 0.5)).abs() < 1e-12);
    }
}
