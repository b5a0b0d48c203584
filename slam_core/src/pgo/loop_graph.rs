//! The pose graph of one server map at a loop closure (seed §3.4.2-3.4.3): keyframes as
//! Sim(3) vertices at their current poses (`s = 1`), the map's structure as edges measured
//! from those poses (eq. 3.9: consecutive keyframes of a client, and strong covisibility
//! links — ORB-SLAM's essential graph), and the loop constraints `S~_qm` found so far in
//! this map. The optimised poses are returned as per-keyframe corrections
//! `Δ_k = S_k,new S_k,old⁻¹` (map → map), the form the mapper applies to its current map.
use std::collections::{BTreeMap, HashMap};

use nalgebra::Isometry3;

use super::four_dof::{optimize_four_dof, FourDofEdge};
use super::graph::{Edge, Sim3Graph, Vertex};
use super::{optimize_sim3, PgoMethod, PgoParams, PgoReport};
use crate::ids::KeyframeId;
use crate::lie::{Matrix7, Sim3};
use crate::vo::KfId;
use crate::CoreError;

/// A keyframe of the graph.
#[derive(Debug, Clone)]
pub struct GraphKeyframe {
    /// Keyframe id (server ids: the client is in the bits above 40).
    pub id: KfId,
    /// Current pose `T_wk` (camera → map).
    pub t_wk: Isometry3<f64>,
    /// Covisible keyframes with weights (shared points).
    pub covisible: Vec<(KfId, u32)>,
}

/// A loop constraint: `s_qm` takes points of the matched keyframe's frame into the query
/// keyframe's frame (`x_q = S_qm x_m`), i.e. `S_qm ≈ S_wq⁻¹ S_wm`.
#[derive(Debug, Clone, Copy)]
pub struct LoopConstraint {
    /// Query keyframe.
    pub query: KfId,
    /// Matched keyframe.
    pub matched: KfId,
    /// The measured similarity.
    pub s_qm: Sim3,
}

/// Parameters of [`correct_loop`].
#[derive(Debug, Clone, Copy)]
pub struct LoopGraphParams {
    /// Covisibility links at least this strong become edges (ORB-SLAM: 100).
    pub min_covisibility: u32,
    /// Weight of a loop edge relative to a structure edge.
    pub loop_weight: f64,
    /// Optimisation method.
    pub method: PgoMethod,
    /// LM settings.
    pub pgo: PgoParams,
}

impl Default for LoopGraphParams {
    fn default() -> Self {
        Self {
            min_covisibility: 100,
            loop_weight: 1.0,
            method: PgoMethod::StepwiseDirect,
            pgo: PgoParams::default(),
        }
    }
}

/// Result of [`correct_loop`].
#[derive(Debug, Clone)]
pub struct LoopCorrection {
    /// `Δ_k` per keyframe.
    pub deltas: BTreeMap<KfId, Sim3>,
    /// The optimised poses `S_wk`.
    pub poses: BTreeMap<KfId, Sim3>,
    /// Structure edges (consecutive + covisibility) and loop edges used.
    pub edges: (usize, usize),
    /// The optimiser's report.
    pub report: PgoReport,
}

/// Builds the graph of `keyframes` with the loop constraints `loops` (the newest last) and
/// optimises it with `fixed` held (the matched keyframe of the newest loop: its scale stays
/// 1, seed §3.4.3). Constraints naming unknown keyframes are skipped. Errors when `fixed`
/// is unknown or the optimisation fails.
pub fn correct_loop(
    keyframes: &[GraphKeyframe],
    loops: &[LoopConstraint],
    fixed: KfId,
    params: &LoopGraphParams,
) -> Result<LoopCorrection, CoreError> {
    let (mut g, edges) = loop_graph(keyframes, loops, fixed, params)?;
    let old: Vec<Sim3> = g.poses();
    let report = optimize_sim3(&mut g, params.method, &params.pgo)?;
    let new: Vec<Sim3> = g.poses();
    corrections(&g, &old, &new, edges, report)
}

/// [`correct_loop`] for a metric, gravity-aligned map (`VI_NOTES.md` §4 "Loops and
/// merges"): the same graph, optimised over x, y, z and yaw only ([`optimize_four_dof`]),
/// roll and pitch held (the IMU observes them), no scale (the IMU observes it); a loop
/// constraint's scale is ignored. The corrections are rigid (`s = 1`).
pub fn correct_loop_four_dof(
    keyframes: &[GraphKeyframe],
    loops: &[LoopConstraint],
    fixed: KfId,
    params: &LoopGraphParams,
) -> Result<LoopCorrection, CoreError> {
    let (g, edges) = loop_graph(keyframes, loops, fixed, params)?;
    let old: Vec<Sim3> = g.poses();
    let mut poses: Vec<Isometry3<f64>> = old.iter().map(|s| s.to_isometry()).collect();
    let four: Vec<FourDofEdge> = g
        .edges
        .iter()
        .map(|e| FourDofEdge {
            i: e.i,
            j: e.j,
            measurement: Isometry3::from_parts(e.measurement.t.into(), e.measurement.r),
            weight: e.info[(0, 0)],
        })
        .collect();
    let mut fixed_mask = vec![false; poses.len()];
    for f in &g.fixed {
        fixed_mask[*f] = true;
    }
    let report = optimize_four_dof(&mut poses, &four, &fixed_mask, &params.pgo)?;
    let new: Vec<Sim3> = poses.iter().map(|t| Sim3::from_isometry(t, 1.0)).collect();
    corrections(&g, &old, &new, edges, report)
}

/// The per-keyframe corrections `Δ_k = S_k,new S_k,old⁻¹` and the new poses; errors when
/// the optimisation diverged.
fn corrections(
    g: &Sim3Graph,
    old: &[Sim3],
    new: &[Sim3],
    edges: (usize, usize),
    report: PgoReport,
) -> Result<LoopCorrection, CoreError> {
    let mut deltas = BTreeMap::new();
    let mut poses = BTreeMap::new();
    for ((v, o), n) in g.vertices.iter().zip(old).zip(new) {
        if !(n.s.is_finite() && n.s > 0.0 && n.t.iter().all(|x| x.is_finite())) {
            return Err(CoreError::InvalidArgument(
                "loop graph: optimisation diverged".into(),
            ));
        }
        deltas.insert(v.id, n.compose(&o.inverse()));
        poses.insert(v.id, *n);
    }
    Ok(LoopCorrection {
        deltas,
        poses,
        edges,
        report,
    })
}

/// The graph of [`correct_loop`] at the keyframes' current poses, with its fixed vertex;
/// `(structure edges, loop edges)`.
fn loop_graph(
    keyframes: &[GraphKeyframe],
    loops: &[LoopConstraint],
    fixed: KfId,
    params: &LoopGraphParams,
) -> Result<(Sim3Graph, (usize, usize)), CoreError> {
    let mut g = Sim3Graph::default();
    let mut index: HashMap<KfId, usize> = HashMap::with_capacity(keyframes.len());
    let mut order: Vec<&GraphKeyframe> = keyframes.iter().collect();
    order.sort_by_key(|k| k.id);
    for k in &order {
        index.insert(k.id, g.vertices.len());
        g.vertices.push(Vertex {
            id: k.id,
            pose: Sim3::from_isometry(&k.t_wk, 1.0),
        });
    }
    let Some(&f) = index.get(&fixed) else {
        return Err(CoreError::InvalidArgument(format!(
            "loop graph: fixed keyframe {fixed} unknown"
        )));
    };
    g.fixed.push(f);
    let info = Matrix7::identity();
    let measured = |g: &Sim3Graph, i: usize, j: usize| {
        g.vertices[i].pose.inverse().compose(&g.vertices[j].pose)
    };
    let mut seen: std::collections::HashSet<(usize, usize)> = std::collections::HashSet::new();
    // Consecutive keyframes of each client (ids are ordered per client).
    for w in order.windows(2) {
        if KeyframeId::from_raw(w[0].id).client() != KeyframeId::from_raw(w[1].id).client() {
            continue;
        }
        let (i, j) = (index[&w[0].id], index[&w[1].id]);
        seen.insert((i, j));
        let z = measured(&g, i, j);
        g.edges.push(Edge {
            i,
            j,
            measurement: z,
            info,
        });
    }
    for k in &order {
        for (n, w) in &k.covisible {
            if *w < params.min_covisibility {
                continue;
            }
            let (Some(&a), Some(&b)) = (index.get(&k.id), index.get(n)) else {
                continue;
            };
            let (i, j) = (a.min(b), a.max(b));
            if i == j || !seen.insert((i, j)) {
                continue;
            }
            let z = measured(&g, i, j);
            g.edges.push(Edge {
                i,
                j,
                measurement: z,
                info,
            });
        }
    }
    let structure = g.edges.len();
    for l in loops {
        let (Some(&i), Some(&j)) = (index.get(&l.query), index.get(&l.matched)) else {
            continue;
        };
        if i == j || !(l.s_qm.s.is_finite() && l.s_qm.s > 0.0) {
            continue;
        }
        g.edges.push(Edge {
            i,
            j,
            measurement: l.s_qm,
            info: info * params.loop_weight,
        });
    }
    let n_loops = g.edges.len() - structure;
    Ok((g, (structure, n_loops)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    /// A circle of keyframes whose odometry drifts in scale (each step 2% shorter than the
    /// last): the loop constraint between the last and the first keyframe pulls the end
    /// back, every method reduces the end-point error, and the fixed keyframe stays put.
    #[test]
    fn loop_constraint_removes_scale_drift_on_a_circle() {
        let n = 40usize;
        let r = 10.0;
        let truth: Vec<Isometry3<f64>> = (0..n)
            .map(|k| {
                let a = 2.0 * std::f64::consts::PI * k as f64 / n as f64;
                Isometry3::from_parts(
                    Translation3::new(r * a.cos(), r * a.sin(), 0.0),
                    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), a),
                )
            })
            .collect();
        // Drifted estimate: chain the true relative motions with shrinking scale.
        let mut est = vec![truth[0]];
        for k in 1..n {
            let rel = truth[k - 1].inverse() * truth[k];
            let s = 0.98f64.powi(k as i32);
            let rel = Isometry3::from_parts((rel.translation.vector * s).into(), rel.rotation);
            est.push(est[k - 1] * rel);
        }
        let kfs: Vec<GraphKeyframe> = (0..n)
            .map(|k| GraphKeyframe {
                id: k as u64,
                t_wk: est[k],
                covisible: Vec::new(),
            })
            .collect();
        // The loop: the last keyframe sees the first. In the drifted map, lengths near the
        // end are s_end times the true ones, so the last keyframe's ideal vertex has scale
        // 1/s_end and S_qm = S_wq⁻¹ S_w0 = [R_rel, s_end t_rel, s_end].
        let rel_true = truth[n - 1].inverse() * truth[0];
        let s_end = 0.98f64.powi(n as i32 - 1);
        let loops = [LoopConstraint {
            query: (n - 1) as u64,
            matched: 0,
            s_qm: Sim3::new(
                rel_true.rotation,
                rel_true.translation.vector * s_end,
                s_end,
            ),
        }];
        let end_err_before =
            (est[n - 1].translation.vector - truth[n - 1].translation.vector).norm();
        for method in [
            PgoMethod::Stepwise,
            PgoMethod::Direct,
            PgoMethod::StepwiseDirect,
        ] {
            let p = LoopGraphParams {
                method,
                ..LoopGraphParams::default()
            };
            let c = correct_loop(&kfs, &loops, 0, &p).unwrap();
            assert_eq!(c.edges, (n - 1, 1));
            let first = c.poses[&0];
            assert!(first.t.norm() < 1e-9 + truth[0].translation.vector.norm());
            let end = c.poses[&((n - 1) as u64)];
            let err = (end.t - truth[n - 1].translation.vector).norm();
            assert!(
                err < 0.25 * end_err_before,
                "{method:?}: end error {err} vs {end_err_before} before"
            );
            // Δ applied to the old pose gives the new one.
            let d = c.deltas[&((n - 1) as u64)];
            let moved = d.compose(&Sim3::from_isometry(&est[n - 1], 1.0));
            assert!((moved.t - end.t).norm() < 1e-9);
        }
        assert!(correct_loop(&kfs, &loops, 999, &LoopGraphParams::default()).is_err());
    }
}
