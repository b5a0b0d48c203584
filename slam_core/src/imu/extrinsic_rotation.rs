//! The camera-IMU rotation `R_bc` (and the gyro bias) from gyro vs visual rotations, for a
//! device whose extrinsics are not given (issue 17; seed ch. 4 holds `R_cb` fixed once
//! known; `VI_NOTES.md` §1 conventions: `T_BS` maps camera to body, `R_bc = R_BS`).
//!
//! Between two camera poses `i, j` of a monocular map the camera turns by
//! `R_c,ij = R_wc,iᵀ R_wc,j`; the gyro, preintegrated over the same interval, gives the
//! body's turn `ΔR_ij(b_g)`. Both describe one rigid motion:
//! ```text
//! ΔR_ij(b_g) = R_bc R_c,ij R_bcᵀ                       (hand-eye rotation constraint)
//! ```
//! Two steps, pure functions of the pairs:
//! 1. **Linear**: in quaternions `q_b ⊗ q_bc = q_bc ⊗ q_c`, i.e. `(L(q_b) − R(q_c)) q_bc = 0`
//!    for every pair; `q_bc` is the right singular vector of the smallest singular value of
//!    the stacked 4×4 blocks (with `b_g = 0`). Robust: pairs whose residual angle is large
//!    after a first solve are down-weighted (Huber) and the SVD repeated.
//! 2. **Gauss-Newton** on `[δθ_bc; δb_g]` (6 unknowns) minimising
//!    `Σ ‖Log(ΔR_ij(b_g)ᵀ R_bc R_c,ij R_bcᵀ)‖²_Σ` with the rotation block of the
//!    preintegration covariance plus the visual rotation noise as `Σ`, Huber-weighted.
//!    With `E = ΔRᵀ R_bc R_c R_bcᵀ`, `R_bc ← R_bc Exp(δθ)` and the first-order bias update
//!    `ΔR(b_g + δb) = ΔR Exp(J^R_g δb)`:
//!    `∂r/∂δθ = J_r⁻¹(r) R_bc (R_cᵀ − I)`, `∂r/∂δb = −J_r⁻¹(r) Eᵀ J^R_g`.
//!
//! `R_bc` is determined only when the camera turns about at least two independent axes: the
//! result carries the 1σ of `R_bc` (largest over the axes, from the inverse of the final
//! normal matrix scaled by the residuals' spread) and the estimate is refused as not
//! observable when it exceeds [`ExtrinsicRotationParams::max_sigma_rad`].
use nalgebra::{DMatrix, Matrix3, Matrix4, Matrix6, Rotation3, UnitQuaternion, Vector3, Vector6};

use super::preint::Preintegrated;
use super::ImuBiases;
use crate::lie::{so3_exp, so3_jr_inv, so3_log};

/// Settings of [`estimate_extrinsic_rotation`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExtrinsicRotationParams {
    /// 1σ of a visual relative rotation, rad (pose noise of the monocular map, both ends).
    pub visual_sigma_rad: f64,
    /// Huber threshold on the whitened residual norm.
    pub huber: f64,
    /// Gauss-Newton iterations of step 2.
    pub iterations: usize,
    /// Largest accepted 1σ of `R_bc` about any axis, rad.
    pub max_sigma_rad: f64,
    /// Fewest pairs to try.
    pub min_pairs: usize,
}

impl Default for ExtrinsicRotationParams {
    fn default() -> Self {
        Self {
            visual_sigma_rad: 0.002,
            huber: 3.0,
            iterations: 10,
            max_sigma_rad: 1.0f64.to_radians(),
            min_pairs: 5,
        }
    }
}

/// The estimated camera-IMU rotation.
#[derive(Debug, Clone, PartialEq)]
pub struct ExtrinsicRotation {
    /// Camera to body rotation `R_bc` (`R_BS` of a `T_BS`).
    pub r_bc: Rotation3<f64>,
    /// Gyro bias (effective), rad/s.
    pub gyro_bias: Vector3<f64>,
    /// 1σ of `R_bc`, rad: the largest over the three axes.
    pub sigma_rad: f64,
    /// RMS of the residual angles at the solution, rad.
    pub rms_rad: f64,
    /// Pairs whose residual was beyond the Huber threshold at the solution.
    pub outliers: usize,
}

/// Why no rotation was estimated.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ExtrinsicRotationError {
    /// Fewer pairs than [`ExtrinsicRotationParams::min_pairs`], or lengths that differ.
    #[error("{pairs} rotation pairs ({preints} preintegrations): too few or mismatched")]
    TooFewPairs {
        /// Visual relative rotations given.
        pairs: usize,
        /// Preintegrations given.
        preints: usize,
    },
    /// The camera did not turn about two independent axes: `R_bc` is not determined.
    #[error("camera-IMU rotation not observable: 1σ {sigma_deg:.2}° (rotate about more axes)")]
    NotObservable {
        /// 1σ reached, degrees.
        sigma_deg: f64,
    },
}

/// `R_bc` and the gyro bias from the visual relative rotations `r_c[k] = R_wc,kᵀ R_wc,k+1`
/// of consecutive poses and the gyro preintegrated over the same intervals, `preints[k]`
/// (module docs). Pure; allocates per call, not per pair.
pub fn estimate_extrinsic_rotation(
    r_c: &[Rotation3<f64>],
    preints: &[Preintegrated],
    params: &ExtrinsicRotationParams,
) -> Result<ExtrinsicRotation, ExtrinsicRotationError> {
    if r_c.len() != preints.len() || r_c.len() < params.min_pairs.max(2) {
        return Err(ExtrinsicRotationError::TooFewPairs {
            pairs: r_c.len(),
            preints: preints.len(),
        });
    }
    let mut r_bc = linear_rotation(r_c, preints, None);
    let weights: Vec<f64> = r_c
        .iter()
        .zip(preints)
        .map(|(rc, pre)| {
            let e = so3_log(&(pre.delta_r().inverse() * r_bc * rc * r_bc.inverse())).norm();
            let s = information_sigma(pre, params);
            huber_weight(e / s, params.huber)
        })
        .collect();
    r_bc = linear_rotation(r_c, preints, Some(&weights));
    refine(r_c, preints, r_bc, params)
}

/// Step 1: the SVD solution of the stacked `(L(q_b) − R(q_c))` blocks, `b_g = 0`, weighted.
fn linear_rotation(
    r_c: &[Rotation3<f64>],
    preints: &[Preintegrated],
    weights: Option<&[f64]>,
) -> Rotation3<f64> {
    let mut a = DMatrix::zeros(4 * r_c.len(), 4);
    for (k, (rc, pre)) in r_c.iter().zip(preints).enumerate() {
        let q_b = UnitQuaternion::from_rotation_matrix(&pre.delta_r());
        let q_c = UnitQuaternion::from_rotation_matrix(rc);
        let w = weights.map_or(1.0, |w| w[k]);
        let block = (quat_left(&q_b) - quat_right(&q_c)) * w;
        a.fixed_view_mut::<4, 4>(4 * k, 0).copy_from(&block);
    }
    // The smallest singular vector of A is the eigenvector of AᵀA's smallest eigenvalue.
    let ata = (a.transpose() * &a).fixed_view::<4, 4>(0, 0).into_owned();
    let eig = ata.symmetric_eigen();
    let (imin, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .fold(
            (0, f64::INFINITY),
            |b, (i, &v)| if v < b.1 { (i, v) } else { b },
        );
    let x = eig.eigenvectors.column(imin);
    // x = (w, x, y, z), scalar first.
    let q = nalgebra::Quaternion::new(x[0], x[1], x[2], x[3]);
    UnitQuaternion::from_quaternion(q).to_rotation_matrix()
}

/// `L(q)` with `q ⊗ p = L(q) p`, scalar-first `(w, x, y, z)`.
fn quat_left(q: &UnitQuaternion<f64>) -> Matrix4<f64> {
    let (w, x, y, z) = (q.w, q.i, q.j, q.k);
    Matrix4::new(w, -x, -y, -z, x, w, -z, y, y, z, w, -x, z, -y, x, w)
}

/// `R(q)` with `p ⊗ q = R(q) p`, scalar-first `(w, x, y, z)`.
fn quat_right(q: &UnitQuaternion<f64>) -> Matrix4<f64> {
    let (w, x, y, z) = (q.w, q.i, q.j, q.k);
    Matrix4::new(w, -x, -y, -z, x, w, z, -y, y, -z, w, x, z, y, -x, w)
}

/// The residual angle's 1σ of a pair: the preintegrated rotation's and both visual ends'.
fn information_sigma(pre: &Preintegrated, params: &ExtrinsicRotationParams) -> f64 {
    let c = pre.covariance().fixed_view::<3, 3>(0, 0).trace() / 3.0;
    (c + 2.0 * params.visual_sigma_rad.powi(2)).sqrt()
}

/// Huber weight (on the square root scale) for a whitened residual norm `e`.
fn huber_weight(e: f64, k: f64) -> f64 {
    if e <= k {
        1.0
    } else {
        (k / e).sqrt()
    }
}

/// Step 2: Gauss-Newton on `[δθ_bc; δb_g]` (module docs), then the 1σ and the verdict.
fn refine(
    r_c: &[Rotation3<f64>],
    preints: &[Preintegrated],
    mut r_bc: Rotation3<f64>,
    params: &ExtrinsicRotationParams,
) -> Result<ExtrinsicRotation, ExtrinsicRotationError> {
    let mut bg = Vector3::zeros();
    let mut inlier = vec![true; r_c.len()];
    // Huber-weighted Gauss-Newton; then the pairs far beyond the threshold are dropped and
    // the solve repeated on the rest (Huber bounds an outlier's pull, dropping removes it).
    for pass in 0..2 {
        for _ in 0..params.iterations.max(1) {
            let n = normal_equations(r_c, preints, &r_bc, &bg, &inlier, params);
            let Some(dx) = n.h.cholesky().map(|c| c.solve(&-n.b)) else {
                break;
            };
            r_bc *= so3_exp(&dx.fixed_rows::<3>(0).into_owned());
            bg += dx.fixed_rows::<3>(3);
            if dx.norm() < 1e-10 {
                break;
            }
        }
        if pass == 0 {
            let biases = ImuBiases {
                gyro: bg,
                accel: Vector3::zeros(),
            };
            for (k, (rc, pre)) in r_c.iter().zip(preints).enumerate() {
                let e = residual(rc, pre, &r_bc, &biases).norm() / information_sigma(pre, params);
                inlier[k] = e <= 2.0 * params.huber;
            }
        }
    }
    let n = normal_equations(r_c, preints, &r_bc, &bg, &inlier, params);
    // The inliers' whitened spread scales the stated covariance when the noise model is
    // optimistic (never below it).
    let used = inlier.iter().filter(|&&i| i).count();
    let dof = (3 * (used - n.outliers.min(used))).saturating_sub(6).max(1) as f64;
    let spread = (n.chi2_inliers / dof).max(1.0);
    let sigma = rotation_sigma(&n.h, spread);
    if sigma.is_nan() || sigma > params.max_sigma_rad {
        return Err(ExtrinsicRotationError::NotObservable {
            sigma_deg: sigma.to_degrees(),
        });
    }
    Ok(ExtrinsicRotation {
        r_bc,
        gyro_bias: bg,
        sigma_rad: sigma,
        rms_rad: (n.sq_angle / used.max(1) as f64).sqrt(),
        outliers: r_c.len() - used + n.outliers,
    })
}

/// 1σ of `R_bc` about its worst axis from the normal matrix `h` over `[δθ_bc; δb_g]`: the
/// rotation block's information with the bias marginalised (Schur complement), its smallest
/// eigenvalue; infinite when it is not positive.
fn rotation_sigma(h: &Matrix6<f64>, spread: f64) -> f64 {
    let h_rr = h.fixed_view::<3, 3>(0, 0);
    let h_rb = h.fixed_view::<3, 3>(0, 3);
    let Some(h_bb_inv) = h.fixed_view::<3, 3>(3, 3).into_owned().try_inverse() else {
        return f64::INFINITY;
    };
    let info = h_rr - h_rb * h_bb_inv * h_rb.transpose();
    let lambda_min = info.symmetric_eigen().eigenvalues.min();
    if lambda_min > 0.0 {
        (spread / lambda_min).sqrt()
    } else {
        f64::INFINITY
    }
}

/// The residual `Log(ΔR(b_g)ᵀ R_bc R_c R_bcᵀ)` of one pair.
fn residual(
    rc: &Rotation3<f64>,
    pre: &Preintegrated,
    r_bc: &Rotation3<f64>,
    biases: &ImuBiases,
) -> Vector3<f64> {
    let (dr, _, _) = pre.corrected(biases);
    so3_log(&(dr.inverse() * r_bc * rc * r_bc.inverse()))
}

/// The Gauss-Newton system of step 2 at `(r_bc, bg)`.
struct Normal {
    h: Matrix6<f64>,
    b: Vector6<f64>,
    /// Σ whitened squared residuals of the pairs within the Huber threshold.
    chi2_inliers: f64,
    /// Σ squared residual angles, rad².
    sq_angle: f64,
    outliers: usize,
}

fn normal_equations(
    r_c: &[Rotation3<f64>],
    preints: &[Preintegrated],
    r_bc: &Rotation3<f64>,
    bg: &Vector3<f64>,
    inlier: &[bool],
    params: &ExtrinsicRotationParams,
) -> Normal {
    let mut n = Normal {
        h: Matrix6::zeros(),
        b: Vector6::zeros(),
        chi2_inliers: 0.0,
        sq_angle: 0.0,
        outliers: 0,
    };
    let biases = ImuBiases {
        gyro: *bg,
        accel: Vector3::zeros(),
    };
    for ((rc, pre), _) in r_c.iter().zip(preints).zip(inlier).filter(|(_, &i)| i) {
        let (dr, _, _) = pre.corrected(&biases);
        let e_rot = dr.inverse() * r_bc * rc * r_bc.inverse();
        let r = so3_log(&e_rot);
        let jri = so3_jr_inv(&r);
        let mut j = nalgebra::Matrix3x6::zeros();
        let d_theta: Matrix3<f64> =
            jri * r_bc.matrix() * (rc.matrix().transpose() - Matrix3::identity());
        let d_bias: Matrix3<f64> = -jri * e_rot.matrix().transpose() * pre.d_r_d_bg();
        j.fixed_view_mut::<3, 3>(0, 0).copy_from(&d_theta);
        j.fixed_view_mut::<3, 3>(0, 3).copy_from(&d_bias);
        let s = information_sigma(pre, params);
        let e = r.norm() / s;
        let w = huber_weight(e, params.huber).powi(2) / (s * s);
        if e > params.huber {
            n.outliers += 1;
        } else {
            n.chi2_inliers += e * e;
        }
        n.h += j.transpose() * j * w;
        n.b += j.transpose() * r * w;
        n.sq_angle += r.norm_squared();
    }
    n
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::imu::{ImuNoise, PreintegrationParams};

    /// A body turning with the rate `omega(t)` for `seconds`, the camera mounted with
    /// `r_bc`: the pairs every `step_s`, with `gyro_bias` on the gyro.
    fn pairs(
        omega: impl Fn(f64) -> Vector3<f64>,
        r_bc: &Rotation3<f64>,
        gyro_bias: &Vector3<f64>,
        seconds: f64,
    ) -> (Vec<Rotation3<f64>>, Vec<Preintegrated>) {
        let params =
            PreintegrationParams::new(&ImuNoise::default(), &Default::default()).expect("params");
        let (dt, step) = (0.005, 40);
        let n = (seconds / dt) as usize / step;
        let (mut r_wb, mut out_c, mut out_p) = (Rotation3::identity(), vec![], vec![]);
        for k in 0..n {
            let mut pre = Preintegrated::new(ImuBiases::default(), params);
            let r_wb_i = r_wb;
            for s in 0..step {
                let t = (k * step + s) as f64 * dt;
                let w = omega(t + 0.5 * dt);
                pre.integrate(dt, &(w + gyro_bias), &Vector3::new(0.0, 0.0, 9.81));
                r_wb *= so3_exp(&(w * dt));
            }
            let (r_wc_i, r_wc_j) = (r_wb_i * r_bc, r_wb * r_bc);
            out_c.push(r_wc_i.inverse() * r_wc_j);
            out_p.push(pre);
        }
        (out_c, out_p)
    }

    fn r_bc_true() -> Rotation3<f64> {
        Rotation3::from_scaled_axis(Vector3::new(0.1, -1.4, 0.3))
    }

    #[test]
    fn rotation_about_three_axes_recovers_r_bc_and_the_gyro_bias() {
        let bg = Vector3::new(0.01, -0.02, 0.005);
        let omega = |t: f64| {
            Vector3::new(
                (1.3 * t).sin(),
                0.8 * (0.7 * t).cos(),
                0.5 * (2.1 * t).sin(),
            )
        };
        let (r_c, pre) = pairs(omega, &r_bc_true(), &bg, 6.0);
        let est = estimate_extrinsic_rotation(&r_c, &pre, &Default::default()).expect("estimated");
        let err = (est.r_bc.inverse() * r_bc_true()).angle().to_degrees();
        eprintln!(
            "R_bc error {err:.5}°, b_g error {:.2e}, 1σ {:.4}°, rms {:.2e}",
            (est.gyro_bias - bg).norm(),
            est.sigma_rad.to_degrees(),
            est.rms_rad
        );
        assert!(err < 0.01, "R_bc error {err}°");
        assert!((est.gyro_bias - bg).norm() < 1e-4);
        assert_eq!(est.outliers, 0);
    }

    #[test]
    fn outlier_pairs_do_not_move_the_estimate() {
        let omega = |t: f64| Vector3::new(1.5 * (1.1 * t).sin(), 1.2 * (0.6 * t).cos(), 0.4);
        let (mut r_c, pre) = pairs(omega, &r_bc_true(), &Vector3::zeros(), 6.0);
        for k in [3, 11, 20] {
            r_c[k] *= Rotation3::from_scaled_axis(Vector3::new(0.2, 0.0, -0.1));
        }
        let est = estimate_extrinsic_rotation(&r_c, &pre, &Default::default()).expect("estimated");
        let err = (est.r_bc.inverse() * r_bc_true()).angle().to_degrees();
        assert!(err < 0.1, "R_bc error {err}° with 3 outliers");
        assert_eq!(est.outliers, 3);
    }

    #[test]
    fn rotation_about_one_axis_is_refused() {
        let omega = |t: f64| Vector3::new(0.0, 0.0, (0.9 * t).sin());
        let (r_c, pre) = pairs(omega, &r_bc_true(), &Vector3::zeros(), 6.0);
        let r = estimate_extrinsic_rotation(&r_c, &pre, &Default::default());
        assert!(
            matches!(r, Err(ExtrinsicRotationError::NotObservable { .. })),
            "{r:?}"
        );
    }

    #[test]
    fn too_few_or_mismatched_pairs_are_an_error() {
        let omega = |t: f64| Vector3::new(t.sin(), t.cos(), 0.3);
        let (r_c, pre) = pairs(omega, &r_bc_true(), &Vector3::zeros(), 0.8);
        assert!(matches!(
            estimate_extrinsic_rotation(&r_c, &pre, &Default::default()),
            Err(ExtrinsicRotationError::TooFewPairs { .. })
        ));
        let (r_c, pre) = pairs(omega, &r_bc_true(), &Vector3::zeros(), 3.0);
        assert!(matches!(
            estimate_extrinsic_rotation(&r_c[1..], &pre, &Default::default()),
            Err(ExtrinsicRotationError::TooFewPairs { .. })
        ));
    }
}
