//! The MSCKF update (`VI_NOTES.md` §3 "Update"; Mourikis & Roumeliotis, ICRA 2007):
//! per feature, project `r = H_x dx + H_f df + n` on the left null space of `H_f` (QR), gate
//! with χ² at 95 %, stack, compress by QR when there are more rows than states, then the
//! EKF update in Joseph form (symmetric, stays positive).

use nalgebra::{DMatrix, DVector};

/// Residual and Jacobian of one feature after the null-space projection (`2M - 3` rows,
/// noise still `σ² I` because the projection is orthonormal).
#[derive(Debug, Clone, PartialEq)]
pub struct Projected {
    /// Jacobian wrt the error state.
    pub h: DMatrix<f64>,
    /// Residual `z - ẑ`.
    pub r: DVector<f64>,
}

/// Multiplies `(H_x, r)` by `Aᵀ`, `A` the left null space of `H_f` (m x 3): the QR of `H_f`
/// gives `Qᵀ`, whose last `m - 3` rows are `Aᵀ`. When only the depth column (the last)
/// vanishes, as for views from one centre (pure rotation), it is left out and `m - 2` rows
/// are kept. `None` when the bearing columns are rank-deficient or `m <= 3`.
pub fn project_null_space(
    h_x: DMatrix<f64>,
    h_f: DMatrix<f64>,
    r: DVector<f64>,
) -> Option<Projected> {
    let m = h_f.nrows();
    if m <= 3 || h_f.ncols() != 3 {
        return None;
    }
    let qr = h_f.qr();
    let diag = qr.r().diagonal();
    let scale = diag.amax();
    if scale <= 0.0 || diag.rows(0, 2).iter().any(|d| d.abs() < 1e-9 * scale) {
        return None;
    }
    let k = if diag[2].abs() < 1e-9 * scale { 2 } else { 3 };
    let (mut h, mut r) = (h_x, r);
    qr.q_tr_mul(&mut h);
    qr.q_tr_mul(&mut r);
    Some(Projected {
        h: h.rows(k, m - k).into_owned(),
        r: r.rows(k, m - k).into_owned(),
    })
}

/// The 95 % quantile of χ² with `dof` degrees of freedom (Wilson-Hilferty; within ~1 % of
/// the exact value for `dof ≥ 3`, exact table below).
pub fn chi2_95(dof: usize) -> f64 {
    const TABLE: [f64; 10] = [
        3.841, 5.991, 7.815, 9.488, 11.070, 12.592, 14.067, 15.507, 16.919, 18.307,
    ];
    if dof == 0 {
        return 0.0;
    }
    if dof <= TABLE.len() {
        return TABLE[dof - 1];
    }
    let k = dof as f64;
    let a = 2.0 / (9.0 * k);
    k * (1.0 - a + 1.644_853_6 * a.sqrt()).powi(3)
}

/// Mahalanobis distance `rᵀ (H P Hᵀ + σ² I)⁻¹ r`; `None` if the innovation covariance is
/// not positive definite.
pub fn mahalanobis(
    h: &DMatrix<f64>,
    r: &DVector<f64>,
    p: &DMatrix<f64>,
    sigma2: f64,
) -> Option<f64> {
    let mut s = h * p * h.transpose();
    for k in 0..s.nrows() {
        s[(k, k)] += sigma2;
    }
    let c = s.cholesky()?;
    Some(r.dot(&c.solve(r)))
}

/// Stacks projected features into one `(H, r)`.
pub fn stack(parts: &[Projected], dim: usize) -> Projected {
    let rows: usize = parts.iter().map(|p| p.r.len()).sum();
    let mut h = DMatrix::zeros(rows, dim);
    let mut r = DVector::zeros(rows);
    let mut at = 0;
    for p in parts {
        let n = p.r.len();
        h.view_mut((at, 0), (n, dim)).copy_from(&p.h);
        r.rows_mut(at, n).copy_from(&p.r);
        at += n;
    }
    Projected { h, r }
}

/// When `H` has more rows than columns, replaces `(H, r)` by `(T_H, Q_1ᵀ r)` from the QR
/// `H = Q_1 T_H` (same information, noise still `σ² I`).
pub fn compress(m: Projected) -> Projected {
    let (rows, cols) = m.h.shape();
    if rows <= cols {
        return m;
    }
    let qr = m.h.qr();
    let mut r = m.r;
    qr.q_tr_mul(&mut r);
    Projected {
        h: qr.r(),
        r: r.rows(0, cols).into_owned(),
    }
}

/// EKF update with noise `σ² I`: `K = P Hᵀ S⁻¹`, returns `dx = K r` and sets
/// `P ← (I - K H) P (I - K H)ᵀ + σ² K Kᵀ` (Joseph form), symmetrised. `None` (P untouched)
/// if `S` is not positive definite.
pub fn ekf_update(p: &mut DMatrix<f64>, m: &Projected, sigma2: f64) -> Option<DVector<f64>> {
    let k = kalman_gain(p, &m.h, sigma2)?;
    let dx = &k * &m.r;
    joseph_in_place(p, &k, &m.h, sigma2);
    Some(dx)
}

/// `K = P Hᵀ (H P Hᵀ + σ² I)⁻¹`; `None` if the innovation covariance is not positive.
pub fn kalman_gain(p: &DMatrix<f64>, h: &DMatrix<f64>, sigma2: f64) -> Option<DMatrix<f64>> {
    let pht = p * h.transpose();
    let mut s = h * &pht;
    for k in 0..s.nrows() {
        s[(k, k)] += sigma2;
    }
    let chol = s.cholesky()?;
    Some(chol.solve(&pht.transpose()).transpose())
}

/// `P ← (I - K H) P (I - K H)ᵀ + σ² K Kᵀ`, symmetrised (Joseph form: stays positive).
pub fn joseph_in_place(p: &mut DMatrix<f64>, k: &DMatrix<f64>, h: &DMatrix<f64>, sigma2: f64) {
    let mut ikh = -k * h;
    for d in 0..ikh.nrows() {
        ikh[(d, d)] += 1.0;
    }
    let mut next = &ikh * &*p * ikh.transpose() + k * k.transpose() * sigma2;
    symmetrise(&mut next);
    *p = next;
}

/// `P ← (P + Pᵀ)/2`.
pub fn symmetrise(p: &mut DMatrix<f64>) {
    let n = p.nrows();
    for i in 0..n {
        for j in (i + 1)..n {
            let v = 0.5 * (p[(i, j)] + p[(j, i)]);
            p[(i, j)] = v;
            p[(j, i)] = v;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prior_metric_is_the_mahalanobis_norm_also_on_a_singular_prior() {
        let mut rng = crate::calib::sim::Rng::new(5);
        let a = DMatrix::from_fn(6, 6, |_, _| rng.normal());
        let scale = DVector::from_vec(vec![1e-4, 1.0, 25.0, 1e-6, 0.01, 4.0]);
        let p =
            DMatrix::from_diagonal(&scale) * (&a * a.transpose()) * DMatrix::from_diagonal(&scale);
        let e = DVector::from_fn(6, |_, _| rng.normal()).component_mul(&scale);
        let exact = e.dot(&p.clone().cholesky().unwrap().solve(&e));
        let got = PriorMetric::new(&p).unwrap().cost(&e);
        assert!((got - exact).abs() < 1e-6 * exact, "{got} vs {exact}");
        // A duplicated state (the newest clone): P singular, e in its range (equal rows).
        let mut big = DMatrix::zeros(7, 7);
        big.view_mut((0, 0), (6, 6)).copy_from(&p);
        big.view_mut((6, 0), (1, 6)).copy_from(&p.row(0));
        big.view_mut((0, 6), (6, 1)).copy_from(&p.column(0));
        big[(6, 6)] = p[(0, 0)];
        let y = &big * DVector::from_fn(7, |_, _| rng.normal());
        let z = y.rows(0, 6).into_owned();
        let exact = z.dot(&p.clone().cholesky().unwrap().solve(&z));
        let got = PriorMetric::new(&big).unwrap().cost(&y);
        assert!((got - exact).abs() < 1e-6 * exact, "{got} vs {exact}");
        // A correction off the range is penalised hard, never taken as free.
        let mut off = y.clone();
        off[6] += 1e-3 * p[(0, 0)].sqrt();
        let jump = PriorMetric::new(&big).unwrap().cost(&off) - got;
        assert!(jump > 1e3, "off the range costs only {jump} more");
    }

    #[test]
    fn null_space_removes_the_feature_and_keeps_the_noise_white() {
        let mut rng = crate::calib::sim::Rng::new(3);
        let h_f = DMatrix::from_fn(8, 3, |_, _| rng.normal());
        let h_x = DMatrix::from_fn(8, 5, |_, _| rng.normal());
        let df = DVector::from_vec(vec![0.3, -0.2, 0.5]);
        // A residual made only of the feature term projects to zero.
        let p = project_null_space(h_x.clone(), h_f.clone(), &h_f * &df).unwrap();
        assert_eq!(p.h.nrows(), 5);
        assert!(p.r.norm() < 1e-12);
        // The projection is orthonormal: its rows A^T satisfy A^T A = I. Recover A^T by
        // projecting the identity.
        let a_t = project_null_space(DMatrix::identity(8, 8), h_f.clone(), DVector::zeros(8))
            .unwrap()
            .h;
        assert!((&a_t * a_t.transpose() - DMatrix::identity(5, 5)).norm() < 1e-12);
        assert!((&a_t * &h_f).norm() < 1e-12);
        assert!(project_null_space(h_x, DMatrix::zeros(8, 3), DVector::zeros(8)).is_none());
    }

    /// A depth column of zeros (views from one centre) is left out: `m - 2` rows; a
    /// vanishing bearing column is refused.
    #[test]
    fn a_vanishing_depth_column_keeps_m_minus_two_rows() {
        let m = 8;
        let mut h_f = DMatrix::from_fn(m, 3, |i, j| ((i * 3 + j) as f64 * 0.7).sin());
        h_f.column_mut(2).fill(0.0);
        let h_x = DMatrix::from_fn(m, 5, |i, j| ((i + 2 * j) as f64 * 0.3).cos());
        let r = DVector::from_fn(m, |i, _| i as f64 * 0.1);
        let p = project_null_space(h_x, h_f.clone(), r).expect("bearing columns full rank");
        assert_eq!(p.r.len(), m - 2);
        h_f.column_mut(1).fill(0.0);
        let none = project_null_space(DMatrix::zeros(m, 5), h_f, DVector::zeros(m));
        assert!(none.is_none(), "a vanishing bearing column is refused");
    }

    #[test]
    fn chi2_quantiles_are_close_to_tables() {
        assert!((chi2_95(1) - 3.841).abs() < 1e-3);
        assert!((chi2_95(20) - 31.410).abs() < 0.1);
        assert!((chi2_95(100) - 124.342).abs() < 0.2);
    }

    #[test]
    fn compressed_update_equals_the_full_one() {
        let n = 4;
        let mut rng = crate::calib::sim::Rng::new(4);
        let h = DMatrix::from_fn(9, n, |_, _| rng.normal());
        let r = DVector::from_fn(9, |_, _| rng.normal());
        let p0 = DMatrix::from_fn(n, n, |i, j| if i == j { 2.0 } else { 0.1 });
        let full = Projected {
            h: h.clone(),
            r: r.clone(),
        };
        let (mut pa, mut pb) = (p0.clone(), p0.clone());
        let dxa = ekf_update(&mut pa, &full, 0.5).unwrap();
        let small = compress(full);
        assert_eq!(small.h.nrows(), n);
        let dxb = ekf_update(&mut pb, &small, 0.5).unwrap();
        assert!((dxa - dxb).norm() < 1e-10);
        assert!((pa - &pb).norm() < 1e-10);
        assert!(pb.clone().cholesky().is_some());
    }
}

/// The prior term `eᵀ P₀⁻¹ e` of the iterated update's cost, for the line search of
/// [`super::CalibFilter`]. `P₀` is singular right after a clone (the newest clone duplicates
/// the IMU state), so it is factored as `D^{-1/2} P₀ D^{-1/2} + εI` (`D` its diagonal, ε
/// 1e-10): every correction `K r` lies in the range of `P₀`, where the regularisation does not
/// change the value to working precision.
#[derive(Debug, Clone)]
pub struct PriorMetric {
    inv_sqrt_diag: DVector<f64>,
    chol: nalgebra::Cholesky<f64, nalgebra::Dyn>,
}

impl PriorMetric {
    /// Factors `P₀`; `None` when a diagonal entry is not positive.
    pub fn new(p0: &DMatrix<f64>) -> Option<Self> {
        let d = p0.diagonal();
        if d.iter().any(|v| v.is_nan() || *v <= 0.0) {
            return None;
        }
        let inv_sqrt_diag = d.map(|v| 1.0 / v.sqrt());
        let mut scaled = p0.clone();
        for (i, mut col) in scaled.column_iter_mut().enumerate() {
            col.component_mul_assign(&inv_sqrt_diag);
            col *= inv_sqrt_diag[i];
        }
        for i in 0..scaled.nrows() {
            scaled[(i, i)] += 1e-10;
        }
        Some(Self {
            inv_sqrt_diag,
            chol: scaled.cholesky()?,
        })
    }

    /// `eᵀ P₀⁻¹ e`.
    pub fn cost(&self, e: &DVector<f64>) -> f64 {
        let scaled = e.component_mul(&self.inv_sqrt_diag);
        scaled.dot(&self.chol.solve(&scaled))
    }
}

/// `Σ ‖r‖² / σ²` over projected features (the null-space projection is orthonormal, so this
/// is the reprojection cost at the features' best positions).
pub fn residual_cost(parts: &[Projected], sigma2: f64) -> f64 {
    parts.iter().map(|p| p.r.norm_squared()).sum::<f64>() / sigma2
}
