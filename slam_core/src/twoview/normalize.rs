//! Shared numerics of the linear two-view solvers: Hartley's isotropic normalisation
//! (Hartley 1997, "In defense of the eight-point algorithm") and the null vector of a 9x9
//! normal matrix.

use nalgebra::{Matrix3, SMatrix, SVector, SymmetricEigen, Vector2};

/// A 9x9 normal matrix `AᵀA` of a DLT system.
pub(crate) type Normal9 = SMatrix<f64, 9, 9>;
/// One row of a DLT system (or a flattened 3x3 matrix, row-major).
pub(crate) type Row9 = SVector<f64, 9>;

/// Similarity `T` moving `points` to zero mean and mean distance `√2` from the origin:
/// `x̂ = T x`. `None` when the points are not finite or all coincide.
pub(crate) fn hartley<'a, I>(points: I) -> Option<Matrix3<f64>>
where
    I: IntoIterator<Item = &'a Vector2<f64>> + Clone,
{
    let mut mean = Vector2::zeros();
    let mut n = 0usize;
    for p in points.clone() {
        mean += p;
        n += 1;
    }
    if n == 0 {
        return None;
    }
    mean /= n as f64;
    let mut dist = 0.0;
    for p in points {
        dist += (p - mean).norm();
    }
    dist /= n as f64;
    if !dist.is_finite() || dist < 1e-12 {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / dist;
    Some(Matrix3::new(
        s,
        0.0,
        -s * mean.x,
        0.0,
        s,
        -s * mean.y,
        0.0,
        0.0,
        1.0,
    ))
}

/// Applies a normalisation (affine, last row `0 0 1`) to a 2D point.
#[inline]
pub(crate) fn apply(t: &Matrix3<f64>, p: &Vector2<f64>) -> Vector2<f64> {
    Vector2::new(t[(0, 0)] * p.x + t[(0, 2)], t[(1, 1)] * p.y + t[(1, 2)])
}

/// The unit eigenvector of the smallest eigenvalue of `ata`, reshaped row-major to a 3x3
/// matrix. `None` on non-finite input.
pub(crate) fn null_matrix(ata: &Normal9) -> Option<Matrix3<f64>> {
    if !ata.iter().all(|v| v.is_finite()) {
        return None;
    }
    let eig = SymmetricEigen::new(*ata);
    let (imin, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    let v = eig.eigenvectors.column(imin);
    let m = Matrix3::new(v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8]);
    m.iter().all(|x| x.is_finite()).then_some(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hartley_normalises() {
        let pts = [
            Vector2::new(1.0, 2.0),
            Vector2::new(3.0, 2.0),
            Vector2::new(2.0, 5.0),
        ];
        let t = hartley(pts.iter()).expect("spread");
        let q: Vec<_> = pts.iter().map(|p| apply(&t, p)).collect();
        let mean = q.iter().fold(Vector2::zeros(), |a, p| a + p) / 3.0;
        assert!(mean.norm() < 1e-12);
        let d = q.iter().map(|p| p.norm()).sum::<f64>() / 3.0;
        assert!((d - std::f64::consts::SQRT_2).abs() < 1e-12);
        let same = [Vector2::new(1.0, 1.0); 3];
        assert!(hartley(same.iter()).is_none());
        assert!(hartley([].iter()).is_none());
    }
}
