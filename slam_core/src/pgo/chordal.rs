//! Chordal initialisation of an SE(3) pose graph (Martinez-Cantin & Castellanos 2005;
//! Carlone et al., ICRA 2015, "Initialization techniques for 3D SLAM"): relax
//! `R_i R_ij = R_j` to a linear least-squares problem in the 9 entries of every rotation
//! (unit weights), project each solution to SO(3), then solve `t_j - t_i = R_i t_ij` for the
//! translations (unit weights). Anchored vertices keep their pose. Lifts odometry-initialised
//! LM out of the local minima it meets on torus3D and sphere_bignoise.

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};

use super::graph::Se3Graph;
use crate::optim::block_sparse::{BlockSparseSystem, Factorization};
use crate::CoreError;

/// The closest rotation (Frobenius norm) to `m`, via SVD with the determinant fixed.
pub fn project_to_so3(m: &Matrix3<f64>) -> Result<Matrix3<f64>, CoreError> {
    let svd = m.svd(true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
        return Err(CoreError::Degenerate("chordal: SVD failed".into()));
    };
    let mut d = Matrix3::identity();
    if (u * vt).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    Ok(u * d * vt)
}

/// Replaces the poses of `graph` (except `anchored` vertices) by the chordal estimate.
/// Errors when the graph is not connected to an anchor (singular system).
pub fn chordal_init(graph: &mut Se3Graph, anchored: &[bool]) -> Result<(), CoreError> {
    let n = graph.vertices.len();
    if anchored.len() != n || !anchored.iter().any(|&a| a) {
        return Err(CoreError::InvalidArgument(
            "chordal: need an anchor mask with at least one anchored vertex".into(),
        ));
    }
    let mut var = vec![None; n];
    let mut nv = 0;
    for (v, slot) in var.iter_mut().enumerate() {
        if !anchored[v] {
            *slot = Some(nv);
            nv += 1;
        }
    }
    if nv == 0 {
        return Ok(());
    }
    let mut pairs: Vec<(u32, u32)> = graph
        .edges
        .iter()
        .filter_map(|e| match (var[e.i], var[e.j]) {
            (Some(a), Some(b)) if a != b => Some((a as u32, b as u32)),
            _ => None,
        })
        .collect();
    let mut sys = BlockSparseSystem::new("pgo");

    // Rotations: unknown X_i = R_iᵀ (3 columns = 3 right-hand sides), residual
    // R_ijᵀ X_i - X_j; normal blocks H_ii += I, H_jj += I, H_ij += -R_ij.
    sys.setup_uniform(nv, 3, 3, &mut pairs, Factorization::SparseBlockAmd)?;
    let eye = Matrix3::<f64>::identity();
    for e in &graph.edges {
        let rij = e.measurement.rotation.to_rotation_matrix().into_inner();
        let ri = graph.vertices[e.i]
            .pose
            .rotation
            .to_rotation_matrix()
            .into_inner();
        let rj = graph.vertices[e.j]
            .pose
            .rotation
            .to_rotation_matrix()
            .into_inner();
        match (var[e.i], var[e.j]) {
            (Some(a), Some(b)) => {
                sys.add_block(sys.block_index(a, a).unwrap_or(0), eye.as_slice(), false);
                sys.add_block(sys.block_index(b, b).unwrap_or(0), eye.as_slice(), false);
                if a != b {
                    let k = sys.block_index(a, b).unwrap_or(0);
                    sys.add_block(k, (-rij).as_slice(), a > b);
                }
            }
            (Some(a), None) => {
                // known X_j = R_jᵀ: rhs_i += R_ij X_j
                sys.add_block(sys.block_index(a, a).unwrap_or(0), eye.as_slice(), false);
                let r = rij * rj.transpose();
                for c in 0..3 {
                    sys.add_rhs(a, c, r.column(c).as_slice());
                }
            }
            (None, Some(b)) => {
                // known X_i = R_iᵀ: rhs_j += R_ijᵀ X_i
                sys.add_block(sys.block_index(b, b).unwrap_or(0), eye.as_slice(), false);
                let r = rij.transpose() * ri.transpose();
                for c in 0..3 {
                    sys.add_rhs(b, c, r.column(c).as_slice());
                }
            }
            (None, None) => {}
        }
    }
    sys.solve()
        .map_err(|e| CoreError::Degenerate(format!("chordal rotations: {e}")))?;
    let dim = 3 * nv;
    let mut rot = vec![Matrix3::<f64>::identity(); n];
    for v in 0..n {
        rot[v] = graph.vertices[v]
            .pose
            .rotation
            .to_rotation_matrix()
            .into_inner();
        if let Some(x) = var[v] {
            let xm = Matrix3::from_fn(|r, c| sys.x()[c * dim + 3 * x + r]);
            rot[v] = project_to_so3(&xm.transpose())?;
        }
    }

    // Translations: t_j - t_i = R_i t_ij, scalar Laplacian with x, y, z as 3 right-hand sides.
    sys.setup_uniform(nv, 1, 3, &mut pairs, Factorization::SparseBlockAmd)?;
    for e in &graph.edges {
        let c = rot[e.i] * e.measurement.translation.vector;
        let ti = graph.vertices[e.i].pose.translation.vector;
        let tj = graph.vertices[e.j].pose.translation.vector;
        match (var[e.i], var[e.j]) {
            (Some(a), Some(b)) => {
                sys.add_block(sys.block_index(a, a).unwrap_or(0), &[1.0], false);
                sys.add_block(sys.block_index(b, b).unwrap_or(0), &[1.0], false);
                if a != b {
                    sys.add_block(sys.block_index(a, b).unwrap_or(0), &[-1.0], false);
                }
                for k in 0..3 {
                    sys.add_rhs(a, k, &[-c[k]]);
                    sys.add_rhs(b, k, &[c[k]]);
                }
            }
            (Some(a), None) => {
                sys.add_block(sys.block_index(a, a).unwrap_or(0), &[1.0], false);
                for k in 0..3 {
                    sys.add_rhs(a, k, &[tj[k] - c[k]]);
                }
            }
            (None, Some(b)) => {
                sys.add_block(sys.block_index(b, b).unwrap_or(0), &[1.0], false);
                for k in 0..3 {
                    sys.add_rhs(b, k, &[ti[k] + c[k]]);
                }
            }
            (None, None) => {}
        }
    }
    sys.solve()
        .map_err(|e| CoreError::Degenerate(format!("chordal translations: {e}")))?;
    for v in 0..n {
        if let Some(x) = var[v] {
            let t = nalgebra::Vector3::new(sys.x()[x], sys.x()[nv + x], sys.x()[2 * nv + x]);
            let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(rot[v]));
            graph.vertices[v].pose = Isometry3::from_parts(Translation3::from(t), q);
        }
    }
    Ok(())
}
