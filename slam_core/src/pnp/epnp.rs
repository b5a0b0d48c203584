//! EPnP (Lepetit, Moreno-Noguer & Fua 2009, "EPnP: An Accurate O(n) Solution to the PnP
//! Problem"), written from the paper.
//!
//! Every world point is a barycentric combination `p_i = Σ_j α_ij c_j` of four control
//! points (centroid + principal directions). The projections give a 2n x 12 linear system
//! `M x = 0` in the camera-frame control points `x`; its solution is a combination
//! `x = Σ_k β_k v_k` of the `N` right singular vectors of the smallest singular values. The
//! `β` follow from preserving the six control-point distances: closed-form
//! linearisations for `N = 1, 2, 3` (paper, section 3.3), each polished by Gauss-Newton on
//! the four `β` (section 3.4); the candidate with the lowest reprojection error wins. The
//! pose then is the rigid alignment ([`crate::geometry::umeyama`]) of the world points with
//! their camera-frame reconstructions.

use nalgebra::{
    Isometry3, Matrix3, Matrix4, Point3, SMatrix, SVector, SymmetricEigen, Translation3,
    UnitQuaternion, Vector2, Vector3, Vector4, Vector6,
};

use crate::geometry::umeyama;

type M12 = SMatrix<f64, 12, 12>;
type V12 = SVector<f64, 12>;
type L6x10 = SMatrix<f64, 6, 10>;

/// Reusable buffers of [`epnp`].
#[derive(Debug, Clone, Default)]
pub(crate) struct EpnpScratch {
    alphas: Vec<Vector4<f64>>,
    world: Vec<Vector3<f64>>,
    obs: Vec<Vector2<f64>>,
    camera: Vec<Vector3<f64>>,
}

/// The control-point pairs whose distances constrain the `β`.
const PAIRS: [(usize, usize); 6] = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)];

/// EPnP pose `T_cw` from the correspondences `(points_w[i], xn[i])` for `i` in `idx`
/// (normalised image coordinates; at least 4). `None` on a degenerate configuration.
pub(crate) fn epnp<I>(
    points_w: &[Vector3<f64>],
    xn: &[Vector2<f64>],
    idx: I,
    s: &mut EpnpScratch,
) -> Option<Isometry3<f64>>
where
    I: Iterator<Item = usize> + Clone,
{
    s.world.clear();
    s.world.extend(idx.clone().map(|i| points_w[i]));
    s.obs.clear();
    s.obs.extend(idx.clone().map(|i| xn[i]));
    let n = s.world.len();
    if n < 4 {
        return None;
    }
    // Control points: centroid and principal axes scaled by their spread.
    let c0 = s.world.iter().fold(Vector3::zeros(), |a, p| a + p) / n as f64;
    let mut cov = Matrix3::zeros();
    for p in &s.world {
        let d = p - c0;
        cov += d * d.transpose();
    }
    let eig = SymmetricEigen::new(cov / n as f64);
    let lmax = eig.eigenvalues.max();
    if !(lmax.is_finite() && lmax > 0.0) {
        return None;
    }
    let mut ctrl = [c0; 4];
    let mut axes = Matrix3::zeros();
    for k in 0..3 {
        // A (near-)planar set keeps a small third axis so the barycentric system stays
        // invertible; its coordinates along that axis are then ~0.
        let scale = eig.eigenvalues[k].max(lmax * 1e-8).sqrt();
        let a = eig.eigenvectors.column(k) * scale;
        ctrl[k + 1] = c0 + a;
        axes.set_column(k, &a);
    }
    let axes_inv = axes.try_inverse()?;
    s.alphas.clear();
    let mut mtm = M12::zeros();
    for (p, x) in s.world.iter().zip(&s.obs) {
        let a = axes_inv * (p - c0);
        let alpha = Vector4::new(1.0 - a.x - a.y - a.z, a.x, a.y, a.z);
        s.alphas.push(alpha);
        let (u, v) = (x.x, x.y);
        let mut r1 = V12::zeros();
        let mut r2 = V12::zeros();
        for j in 0..4 {
            r1[3 * j] = alpha[j];
            r1[3 * j + 2] = -alpha[j] * u;
            r2[3 * j + 1] = alpha[j];
            r2[3 * j + 2] = -alpha[j] * v;
        }
        mtm.ger(1.0, &r1, &r1, 1.0);
        mtm.ger(1.0, &r2, &r2, 1.0);
    }
    if !mtm.iter().all(|v| v.is_finite()) {
        return None;
    }
    let eig = SymmetricEigen::new(mtm);
    let mut order: [usize; 12] = std::array::from_fn(|i| i);
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let kernel: [V12; 4] = std::array::from_fn(|k| eig.eigenvectors.column(order[k]).into_owned());

    // Distance constraints: L · b = ρ with b the 10 products of the β.
    let mut l = L6x10::zeros();
    let mut rho = Vector6::zeros();
    for (row, &(a, b)) in PAIRS.iter().enumerate() {
        let dv: [Vector3<f64>; 4] = std::array::from_fn(|k| {
            Vector3::new(
                kernel[k][3 * a] - kernel[k][3 * b],
                kernel[k][3 * a + 1] - kernel[k][3 * b + 1],
                kernel[k][3 * a + 2] - kernel[k][3 * b + 2],
            )
        });
        let mut col = 0;
        for k2 in 0..4 {
            for k1 in 0..=k2 {
                let f = if k1 == k2 { 1.0 } else { 2.0 };
                l[(row, col)] = f * dv[k1].dot(&dv[k2]);
                col += 1;
            }
        }
        rho[row] = (ctrl[a] - ctrl[b]).norm_squared();
    }
    // Column order of b: (11, 12, 22, 13, 23, 33, 14, 24, 34, 44).
    let mut candidates: [Option<Vector4<f64>>; 3] = [None; 3];
    // N = 1: β1 from the distances directly.
    {
        let (mut num, mut den) = (0.0, 0.0);
        for (row, &(a, b)) in PAIRS.iter().enumerate() {
            let dv = Vector3::new(
                kernel[0][3 * a] - kernel[0][3 * b],
                kernel[0][3 * a + 1] - kernel[0][3 * b + 1],
                kernel[0][3 * a + 2] - kernel[0][3 * b + 2],
            )
            .norm();
            num += dv * rho[row].sqrt();
            den += dv * dv;
        }
        if den > 0.0 {
            candidates[0] = Some(Vector4::new(num / den, 0.0, 0.0, 0.0));
        }
    }
    // N = 2: linear in (β11, β12, β22).
    {
        let a = l.fixed_columns::<3>(0).into_owned();
        if let Some(x) = (a.transpose() * a)
            .try_inverse()
            .map(|m| m * a.transpose() * rho)
        {
            let b1 = x[0].abs().sqrt();
            let b2 = x[2].abs().sqrt() * x[1].signum();
            candidates[1] = Some(Vector4::new(b1, b2, 0.0, 0.0));
        }
    }
    // N = 3: linear in (β11, β12, β22, β13, β23, β33).
    {
        let a = l.fixed_columns::<6>(0).into_owned();
        if let Some(x) = a.try_inverse().map(|m| m * rho) {
            let b1 = x[0].abs().sqrt();
            let b2 = x[2].abs().sqrt() * x[1].signum();
            let b3 = x[5].abs().sqrt() * x[3].signum();
            candidates[2] = Some(Vector4::new(b1, b2, b3, 0.0));
        }
    }
    let mut best: Option<(f64, Isometry3<f64>)> = None;
    for beta in candidates.into_iter().flatten() {
        let beta = gauss_newton(&l, &rho, beta);
        let Some(pose) = pose_from_betas(&kernel, &beta, s) else {
            continue;
        };
        let err = reprojection_error(&pose, s);
        if err.is_finite() && best.is_none_or(|(e, _)| err < e) {
            best = Some((err, pose));
        }
    }
    best.map(|(_, p)| p)
}

/// The 10 products `b(β)` in the column order of `L`.
fn products(b: &Vector4<f64>) -> SVector<f64, 10> {
    SVector::<f64, 10>::from([
        b[0] * b[0],
        b[0] * b[1],
        b[1] * b[1],
        b[0] * b[2],
        b[1] * b[2],
        b[2] * b[2],
        b[0] * b[3],
        b[1] * b[3],
        b[2] * b[3],
        b[3] * b[3],
    ])
}

/// Gauss-Newton on `|L b(β) - ρ|²` over the four `β` (5 damped steps).
fn gauss_newton(l: &L6x10, rho: &Vector6<f64>, mut beta: Vector4<f64>) -> Vector4<f64> {
    for _ in 0..5 {
        let r = l * products(&beta) - rho;
        // d b / d β (10 x 4).
        let b = beta;
        let db = SMatrix::<f64, 10, 4>::from_row_slice(&[
            2.0 * b[0],
            0.0,
            0.0,
            0.0, //
            b[1],
            b[0],
            0.0,
            0.0, //
            0.0,
            2.0 * b[1],
            0.0,
            0.0, //
            b[2],
            0.0,
            b[0],
            0.0, //
            0.0,
            b[2],
            b[1],
            0.0, //
            0.0,
            0.0,
            2.0 * b[2],
            0.0, //
            b[3],
            0.0,
            0.0,
            b[0], //
            0.0,
            b[3],
            0.0,
            b[1], //
            0.0,
            0.0,
            b[3],
            b[2], //
            0.0,
            0.0,
            0.0,
            2.0 * b[3],
        ]);
        let j = l * db;
        let mut h: Matrix4<f64> = j.transpose() * j;
        let tr = h.trace().max(1e-300);
        for k in 0..4 {
            h[(k, k)] += 1e-12 * tr;
        }
        let Some(chol) = h.cholesky() else {
            break;
        };
        let step = chol.solve(&(j.transpose() * r));
        if !step.iter().all(|v| v.is_finite()) {
            break;
        }
        beta -= step;
    }
    beta
}

/// Camera-frame control points from the `β`, then the camera-frame points, then the pose.
fn pose_from_betas(
    kernel: &[V12; 4],
    beta: &Vector4<f64>,
    s: &mut EpnpScratch,
) -> Option<Isometry3<f64>> {
    let x: V12 =
        kernel[0] * beta[0] + kernel[1] * beta[1] + kernel[2] * beta[2] + kernel[3] * beta[3];
    let cc: [Vector3<f64>; 4] =
        std::array::from_fn(|j| Vector3::new(x[3 * j], x[3 * j + 1], x[3 * j + 2]));
    s.camera.clear();
    let mut zsum = 0.0;
    for a in &s.alphas {
        let p = cc[0] * a[0] + cc[1] * a[1] + cc[2] * a[2] + cc[3] * a[3];
        zsum += p.z;
        s.camera.push(p);
    }
    if zsum < 0.0 {
        s.camera.iter_mut().for_each(|p| *p = -*p);
    }
    let sim = umeyama(&s.world, &s.camera, false).ok()?;
    Some(Isometry3::from_parts(
        Translation3::from(sim.translation),
        UnitQuaternion::from_rotation_matrix(&sim.rotation),
    ))
}

/// Sum of squared normalised reprojection errors of the scratch correspondences (infinite
/// when a point is behind the camera).
fn reprojection_error(pose: &Isometry3<f64>, s: &EpnpScratch) -> f64 {
    let mut e = 0.0;
    for (p, x) in s.world.iter().zip(&s.obs) {
        let q = pose * Point3::from(*p);
        if q.z <= 0.0 {
            return f64::INFINITY;
        }
        e += (Vector2::new(q.x / q.z, q.y / q.z) - x).norm_squared();
    }
    e
}
