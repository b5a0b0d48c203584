//! Information matrices that are not positive definite, handled as GTSAM 4.3 does.
//!
//! Some public graphs (cubicle: 5021 of 16869 edges) carry indefinite information matrices.
//! GTSAM's `noiseModel::Gaussian::Information` takes `R = llt(Ω).matrixU()` from Eigen's
//! `LLT` without checking its status, so its cost uses `RᵀR` instead of `Ω`. Eigen's
//! unblocked `LLT` stops at the first column `k` whose pivot `x = Ω_kk - |L_k,0:k|²` is not
//! positive, leaving `L_kk = Ω_kk` (not square-rooted) and later columns untouched.
//! [`gtsam_effective_information`] reproduces that, so that the optimised cost matches
//! GTSAM's `graph.error()` on such files.

use nalgebra::SMatrix;

/// `Some(RᵀR)` as GTSAM would use it when `omega` is not positive definite (Eigen's `LLT`
/// failing at some column), `None` when `omega` is positive definite (used as is).
pub fn gtsam_effective_information<const D: usize>(
    omega: &SMatrix<f64, D, D>,
) -> Option<SMatrix<f64, D, D>> {
    // Work on the lower triangle, as Eigen's LLT<Lower> does.
    let mut a = *omega;
    let mut failed = false;
    for k in 0..D {
        let mut x = a[(k, k)];
        for j in 0..k {
            x -= a[(k, j)] * a[(k, j)];
        }
        if x <= 0.0 || !x.is_finite() {
            failed = true;
            break;
        }
        let x = x.sqrt();
        a[(k, k)] = x;
        for i in k + 1..D {
            let mut v = a[(i, k)];
            for j in 0..k {
                v -= a[(i, j)] * a[(k, j)];
            }
            a[(i, k)] = v / x;
        }
    }
    if !failed {
        return None;
    }
    let l = SMatrix::<f64, D, D>::from_fn(|i, j| if i >= j { a[(i, j)] } else { 0.0 });
    Some(l * l.transpose())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Matrix6;

    #[test]
    fn positive_definite_is_kept_and_cubicle_edge_matches_gtsam() {
        let pd = Matrix6::from_diagonal_element(3.0);
        assert!(gtsam_effective_information(&pd).is_none());
        // cubicle.g2o line 5753 in GTSAM's (R, t) order; GTSAM 4.3's noise model has
        // RᵀR(t_z, t_z) = 2468177940 (= (84022.3² + 132748²)/10 + 10²), rest unchanged.
        let mut m = Matrix6::zeros();
        m[(0, 0)] = 10.0;
        m[(1, 1)] = 10.0;
        m[(2, 2)] = 91520.2;
        m[(3, 3)] = 2.46483e6;
        m[(3, 4)] = 5.3553e6;
        m[(4, 3)] = 5.3553e6;
        m[(4, 4)] = 1.52034e7;
        m[(5, 5)] = 10.0;
        m[(0, 5)] = 84022.3;
        m[(5, 0)] = 84022.3;
        m[(1, 5)] = 132748.0;
        m[(5, 1)] = 132748.0;
        let e = gtsam_effective_information(&m).expect("indefinite");
        let expect_zz = (84022.3f64.powi(2) + 132748f64.powi(2)) / 10.0 + 100.0;
        assert!((e[(5, 5)] - expect_zz).abs() < 1e-6 * expect_zz);
        let mut rest = e - m;
        rest[(5, 5)] = 0.0;
        assert!(rest.norm() < 1e-6, "{rest}");
    }
}
