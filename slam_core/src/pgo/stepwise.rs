//! Stepwise Sim(3) pose graph optimisation (seed §3.4.3, eq. 3.10-3.12): scales first by
//! linear least squares, then scales and translations with the rotations held.

use faer::linalg::solvers::SolveLstsqCore;
use faer::sparse::{SparseColMat, Triplet};
use faer::{Conj, Mat};

use super::graph::Sim3Graph;
use crate::CoreError;

/// Step 1 (eq. 3.10-3.11): with rotations and translations fixed, the scales of the free
/// vertices solve `s̃_ij s_i - s_j = n₁` for every edge (`S_wj = S_wi Z_ij` gives
/// `s_j = s_i s̃_ij` in our `x_w = s R x_k + t` convention), unit weights, fixed vertices
/// keep their scale (the matched keyframe of a loop is fixed to its current scale). The tall
/// sparse system is solved by faer's sparse QR. Only the scales of `graph` change.
pub fn solve_scales(graph: &mut Sim3Graph, fixed: &[bool]) -> Result<(), CoreError> {
    let n = graph.vertices.len();
    if fixed.len() != n {
        return Err(CoreError::InvalidArgument(
            "stepwise: bad fixed mask".into(),
        ));
    }
    let mut var = vec![None; n];
    let mut nv = 0usize;
    for (v, slot) in var.iter_mut().enumerate() {
        if !fixed[v] {
            *slot = Some(nv);
            nv += 1;
        }
    }
    if nv == 0 {
        return Ok(());
    }
    let mut trips = Vec::with_capacity(2 * graph.edges.len());
    let mut rhs = Vec::with_capacity(graph.edges.len());
    for e in &graph.edges {
        let sz = e.measurement.s;
        let (si, sj) = (graph.vertices[e.i].pose.s, graph.vertices[e.j].pose.s);
        let row = rhs.len();
        match (var[e.i], var[e.j]) {
            (Some(a), Some(b)) => {
                trips.push(Triplet::new(row, a, sz));
                trips.push(Triplet::new(row, b, -1.0));
                rhs.push(0.0);
            }
            (Some(a), None) => {
                trips.push(Triplet::new(row, a, sz));
                rhs.push(sj);
            }
            (None, Some(b)) => {
                trips.push(Triplet::new(row, b, -1.0));
                rhs.push(-sz * si);
            }
            (None, None) => {}
        }
    }
    let m = rhs.len();
    if m < nv {
        return Err(CoreError::NotEnoughData(format!(
            "stepwise scales: {m} constraints for {nv} free scales"
        )));
    }
    let a = SparseColMat::<usize, f64>::try_new_from_triplets(m, nv, &trips)
        .map_err(|e| CoreError::Degenerate(format!("stepwise scales: {e:?}")))?;
    let qr = a
        .sp_qr()
        .map_err(|e| CoreError::Degenerate(format!("stepwise scales: QR failed: {e:?}")))?;
    let mut b = Mat::<f64>::from_fn(m, 1, |r, _| rhs[r]);
    qr.solve_lstsq_in_place_with_conj(Conj::No, b.as_mut());
    for (vertex, x) in graph.vertices.iter_mut().zip(&var) {
        if let Some(x) = *x {
            let s = b[(x, 0)];
            if !(s.is_finite() && s > 0.0) {
                return Err(CoreError::Degenerate(format!(
                    "stepwise scales: vertex {} got scale {s}",
                    vertex.id
                )));
            }
            vertex.pose.s = s;
        }
    }
    Ok(())
}

/// Tangent coordinates optimised in step 2 (eq. 3.12): translation `ρ` and log-scale `σ`
/// (indices 3-6 of `[ω; ρ; σ]`); the rotation `ω` is held.
pub const STEP2_ACTIVE: [usize; 4] = [3, 4, 5, 6];
