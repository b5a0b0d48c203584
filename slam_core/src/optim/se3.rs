//! The SE(3) exponential used for pose increments and constant-velocity motion.

use nalgebra::{Isometry3, Matrix3, Translation3, UnitQuaternion, Vector3, Vector6};

use crate::geometry::{skew, so3_exp};

/// SE(3) exponential of a twist `ξ = [ρ; φ]` (translation part first): rotation
/// `Exp(φ)` and translation `V(φ) ρ`, `V = I + (1 - cos θ)/θ² [φ]x + (θ - sin θ)/θ³ [φ]x²`.
/// For a constant body twist, `T(t) = T(0) · Exp(t ξ)`.
pub fn se3_exp(xi: &Vector6<f64>) -> Isometry3<f64> {
    let rho = Vector3::new(xi[0], xi[1], xi[2]);
    let phi = Vector3::new(xi[3], xi[4], xi[5]);
    let theta2 = phi.norm_squared();
    let k = skew(&phi);
    let (b, c) = if theta2 < 1e-10 {
        (0.5 - theta2 / 24.0, 1.0 / 6.0 - theta2 / 120.0)
    } else {
        let theta = theta2.sqrt();
        (
            (1.0 - theta.cos()) / theta2,
            (theta - theta.sin()) / (theta2 * theta),
        )
    };
    let v = Matrix3::identity() + k * b + k * k * c;
    Isometry3::from_parts(
        Translation3::from(v * rho),
        UnitQuaternion::from_rotation_matrix(&so3_exp(&phi)),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_matches_composition_of_small_steps() {
        let xi = Vector6::new(0.3, -0.2, 0.5, 0.4, 0.1, -0.3);
        let big = se3_exp(&xi);
        let n = 10_000;
        let step = se3_exp(&(xi / n as f64));
        let mut acc = Isometry3::identity();
        for _ in 0..n {
            acc *= step;
        }
        assert!((acc.translation.vector - big.translation.vector).norm() < 1e-9);
        assert!((acc.rotation.inverse() * big.rotation).angle() < 1e-9);
        let tiny = se3_exp(&(xi * 1e-9));
        assert!((tiny.translation.vector - Vector3::new(0.3, -0.2, 0.5) * 1e-9).norm() < 1e-18);
    }
}
