//! Pose-graph data: vertices (keyframe poses `T_wk` or `S_wk`), relative-pose edges with
//! their information matrices, and the fixed (gauge) vertices.

use nalgebra::{Isometry3, Matrix6};

use crate::lie::{Matrix7, Sim3};

/// A pose type a graph can hold, with the information matrix of its edges.
pub trait GraphPose: Copy + std::fmt::Debug {
    /// Information matrix of one edge (ordered like the pose's tangent vector).
    type Info: Copy + std::fmt::Debug + PartialEq;
}

impl GraphPose for Isometry3<f64> {
    /// 6x6, ordered `[rotation, translation]` (GTSAM's order; the g2o parser permutes).
    type Info = Matrix6<f64>;
}

impl GraphPose for Sim3 {
    /// 7x7, ordered `[translation, rotation, log-scale]`.
    type Info = Matrix7;
}

/// One vertex: the file's id and the pose `T_wk` / `S_wk` (`x_w = s R x_k + t`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Vertex<P> {
    /// Id as written in the file (used as the timestamp of the TUM output).
    pub id: u64,
    /// Current estimate.
    pub pose: P,
}

/// A relative-pose constraint `Z_ij ≈ X_i⁻¹ X_j` between vertices `i` and `j` (indices into
/// [`PoseGraph::vertices`]); residual `Log(Z_ij⁻¹ X_i⁻¹ X_j)` (seed eq. 3.9).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Edge<P: GraphPose> {
    /// Index of the first vertex.
    pub i: usize,
    /// Index of the second vertex.
    pub j: usize,
    /// Measurement `Z_ij`.
    pub measurement: P,
    /// Information matrix `Ω` of the residual.
    pub info: P::Info,
}

/// A pose graph: vertices, edges and the indices of vertices held fixed.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseGraph<P: GraphPose> {
    /// Vertices in file order.
    pub vertices: Vec<Vertex<P>>,
    /// Edges (vertex indices).
    pub edges: Vec<Edge<P>>,
    /// Indices of fixed vertices (`FIX` lines), ascending, no repeats.
    pub fixed: Vec<usize>,
}

impl<P: GraphPose> Default for PoseGraph<P> {
    fn default() -> Self {
        Self {
            vertices: Vec::new(),
            edges: Vec::new(),
            fixed: Vec::new(),
        }
    }
}

impl<P: GraphPose> PoseGraph<P> {
    /// Index of the vertex with the smallest id (GTSAM puts its prior there), if any.
    pub fn first_vertex(&self) -> Option<usize> {
        (0..self.vertices.len()).min_by_key(|&k| self.vertices[k].id)
    }

    /// The poses in vertex order.
    pub fn poses(&self) -> Vec<P> {
        self.vertices.iter().map(|v| v.pose).collect()
    }

    /// Checks indices and finiteness-independent structure: every edge refers to existing,
    /// distinct vertices and every fixed index exists.
    pub fn validate(&self) -> Result<(), crate::CoreError> {
        let n = self.vertices.len();
        for (k, e) in self.edges.iter().enumerate() {
            if e.i >= n || e.j >= n || e.i == e.j {
                return Err(crate::CoreError::InvalidArgument(format!(
                    "pose graph edge {k} ({}, {}) with {n} vertices",
                    e.i, e.j
                )));
            }
        }
        if self.fixed.iter().any(|&f| f >= n) {
            return Err(crate::CoreError::InvalidArgument(
                "pose graph: fixed vertex index out of range".into(),
            ));
        }
        Ok(())
    }
}

/// A graph of rigid keyframe poses (`VERTEX_SE3:QUAT` / `EDGE_SE3:QUAT`).
pub type Se3Graph = PoseGraph<Isometry3<f64>>;
/// A graph of similarity keyframe poses (`VERTEX_SIM3:QUAT` / `EDGE_SIM3:QUAT`).
pub type Sim3Graph = PoseGraph<Sim3>;

/// Either kind of graph, as read from a file.
#[derive(Debug, Clone, PartialEq)]
pub enum AnyGraph {
    /// SE(3) graph.
    Se3(Se3Graph),
    /// Sim(3) graph.
    Sim3(Sim3Graph),
}
