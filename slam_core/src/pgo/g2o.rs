//! Reading and writing pose graphs in g2o-like text (from `&str`; file IO is the caller's).
//!
//! Lines (whitespace separated, `#` starts a comment, blank lines ignored):
//! - `VERTEX_SE3:QUAT id tx ty tz qx qy qz qw`
//! - `EDGE_SE3:QUAT i j tx ty tz qx qy qz qw` + 21 upper-triangular entries of the 6x6
//!   information in g2o's `(t, R)` order; stored permuted to `(R, t)` (GTSAM's order).
//! - `VERTEX_SIM3:QUAT id tx ty tz qx qy qz qw s`
//! - `EDGE_SIM3:QUAT i j tx ty tz qx qy qz qw s` + 28 upper-triangular entries of the 7x7
//!   information ordered `[translation, rotation, log-scale]`; stored permuted to
//!   `[rotation, translation, log-scale]` (the order of [`crate::lie::Sim3`]);
//!   `Z_ij ≈ S_wi⁻¹ S_wj`.
//! - `FIX id`
//!
//! A file holds one kind of graph. Malformed lines give [`CoreError::Parse`] with the line
//! number; nothing here panics on input.

use std::collections::HashMap;
use std::fmt::Write as _;

use nalgebra::{Isometry3, Quaternion, SMatrix, Translation3, UnitQuaternion, Vector3};

use super::graph::{AnyGraph, Edge, GraphPose, PoseGraph, Se3Graph, Sim3Graph, Vertex};
use crate::lie::{Matrix7, Sim3};
use crate::CoreError;

fn err(line: usize, msg: impl Into<String>) -> CoreError {
    CoreError::Parse {
        line,
        msg: msg.into(),
    }
}

/// Tokens of one line after its tag.
struct Fields<'a> {
    line: usize,
    tag: &'a str,
    tok: Vec<&'a str>,
}

impl Fields<'_> {
    fn expect_len(&self, n: usize) -> Result<(), CoreError> {
        if self.tok.len() != n {
            return Err(err(
                self.line,
                format!("{} needs {n} values, found {}", self.tag, self.tok.len()),
            ));
        }
        Ok(())
    }
    fn id(&self, k: usize) -> Result<u64, CoreError> {
        self.tok[k].parse::<u64>().map_err(|_| {
            err(
                self.line,
                format!("{}: bad vertex id {:?}", self.tag, self.tok[k]),
            )
        })
    }
    fn num(&self, k: usize) -> Result<f64, CoreError> {
        match self.tok[k].parse::<f64>() {
            Ok(v) if v.is_finite() => Ok(v),
            _ => Err(err(
                self.line,
                format!(
                    "{}: bad number {:?} (value {})",
                    self.tag,
                    self.tok[k],
                    k + 1
                ),
            )),
        }
    }
    /// `tx ty tz qx qy qz qw` starting at `k`.
    fn pose(&self, k: usize) -> Result<(Vector3<f64>, UnitQuaternion<f64>), CoreError> {
        let t = Vector3::new(self.num(k)?, self.num(k + 1)?, self.num(k + 2)?);
        let q = Quaternion::new(
            self.num(k + 6)?,
            self.num(k + 3)?,
            self.num(k + 4)?,
            self.num(k + 5)?,
        );
        let n = q.norm();
        if n < 1e-9 {
            return Err(err(self.line, format!("{}: zero quaternion", self.tag)));
        }
        Ok((t, UnitQuaternion::from_quaternion(q)))
    }
    fn scale(&self, k: usize) -> Result<f64, CoreError> {
        let s = self.num(k)?;
        if s <= 0.0 {
            return Err(err(
                self.line,
                format!("{}: scale {s} is not positive", self.tag),
            ));
        }
        Ok(s)
    }
    /// `d(d+1)/2` upper-triangular entries starting at `k`, into a symmetric matrix.
    fn upper<const D: usize>(&self, k: usize) -> Result<nalgebra::SMatrix<f64, D, D>, CoreError> {
        let mut m = nalgebra::SMatrix::<f64, D, D>::zeros();
        let mut idx = k;
        for a in 0..D {
            for b in a..D {
                let v = self.num(idx)?;
                m[(a, b)] = v;
                m[(b, a)] = v;
                idx += 1;
            }
        }
        if (0..D).any(|a| m[(a, a)] < 0.0) {
            return Err(err(
                self.line,
                format!("{}: negative diagonal information", self.tag),
            ));
        }
        Ok(m)
    }
}

/// Permutes a 6x6 (SE(3)) or 7x7 (Sim(3)) matrix between g2o's translation-first block
/// order `(t, R[, σ])` and the rotation-first order `(R, t[, σ])` of [`crate::lie`] by
/// swapping its first two 3-blocks (an involution; the log-scale row/column stays last).
pub fn swap_rt_blocks<const D: usize>(m: &SMatrix<f64, D, D>) -> SMatrix<f64, D, D> {
    let p = |a: usize| if a < 6 { (a + 3) % 6 } else { a };
    SMatrix::from_fn(|a, b| m[(p(a), p(b))])
}

/// Graph under construction, with the id → index map.
struct Builder<P: GraphPose> {
    graph: PoseGraph<P>,
    index: HashMap<u64, usize>,
    fix_lines: Vec<(usize, u64)>,
}

impl<P: GraphPose> Builder<P> {
    fn new() -> Self {
        Self {
            graph: PoseGraph::default(),
            index: HashMap::new(),
            fix_lines: Vec::new(),
        }
    }
    fn vertex(&mut self, line: usize, id: u64, pose: P) -> Result<(), CoreError> {
        if self.index.insert(id, self.graph.vertices.len()).is_some() {
            return Err(err(line, format!("duplicate vertex id {id}")));
        }
        self.graph.vertices.push(Vertex { id, pose });
        Ok(())
    }
    /// Edges are resolved after all vertices are known (g2o files may list them in any order).
    fn finish(
        mut self,
        edges: Vec<(usize, u64, u64, P, P::Info)>,
    ) -> Result<PoseGraph<P>, CoreError> {
        for (line, a, b, z, info) in edges {
            let i = *self
                .index
                .get(&a)
                .ok_or_else(|| err(line, format!("edge refers to unknown vertex {a}")))?;
            let j = *self
                .index
                .get(&b)
                .ok_or_else(|| err(line, format!("edge refers to unknown vertex {b}")))?;
            if i == j {
                return Err(err(line, format!("edge from vertex {a} to itself")));
            }
            self.graph.edges.push(Edge {
                i,
                j,
                measurement: z,
                info,
            });
        }
        for &(line, id) in &self.fix_lines {
            let k = *self
                .index
                .get(&id)
                .ok_or_else(|| err(line, format!("FIX of unknown vertex {id}")))?;
            self.graph.fixed.push(k);
        }
        self.graph.fixed.sort_unstable();
        self.graph.fixed.dedup();
        Ok(self.graph)
    }
}

/// Parses a g2o-like pose graph (see the module docs). Errors name the offending line.
pub fn parse_g2o(text: &str) -> Result<AnyGraph, CoreError> {
    let mut se3 = Builder::<Isometry3<f64>>::new();
    let mut sim3 = Builder::<Sim3>::new();
    let mut se3_edges = Vec::new();
    let mut sim3_edges = Vec::new();
    let mut fixes = Vec::new();
    // 0 = unknown yet, 1 = SE(3), 2 = Sim(3)
    let mut kind = 0u8;
    for (k, raw) in text.lines().enumerate() {
        let line = k + 1;
        let content = raw.split('#').next().unwrap_or("");
        let mut it = content.split_whitespace();
        let Some(tag) = it.next() else { continue };
        let f = Fields {
            line,
            tag,
            tok: it.collect(),
        };
        let want = match tag {
            "VERTEX_SE3:QUAT" | "EDGE_SE3:QUAT" => 1,
            "VERTEX_SIM3:QUAT" | "EDGE_SIM3:QUAT" => 2,
            "FIX" => 0,
            _ => return Err(err(line, format!("unknown tag {tag:?}"))),
        };
        if want != 0 {
            if kind != 0 && kind != want {
                return Err(err(line, "SE(3) and Sim(3) entries mixed in one file"));
            }
            kind = want;
        }
        match tag {
            "VERTEX_SE3:QUAT" => {
                f.expect_len(8)?;
                let (t, q) = f.pose(1)?;
                se3.vertex(
                    line,
                    f.id(0)?,
                    Isometry3::from_parts(Translation3::from(t), q),
                )?;
            }
            "EDGE_SE3:QUAT" => {
                f.expect_len(2 + 7 + 21)?;
                let (t, q) = f.pose(2)?;
                let info = swap_rt_blocks(&f.upper::<6>(9)?);
                se3_edges.push((
                    line,
                    f.id(0)?,
                    f.id(1)?,
                    Isometry3::from_parts(Translation3::from(t), q),
                    info,
                ));
            }
            "VERTEX_SIM3:QUAT" => {
                f.expect_len(9)?;
                let (t, q) = f.pose(1)?;
                sim3.vertex(line, f.id(0)?, Sim3::new(q, t, f.scale(8)?))?;
            }
            "EDGE_SIM3:QUAT" => {
                f.expect_len(2 + 8 + 28)?;
                let (t, q) = f.pose(2)?;
                let s = f.scale(9)?;
                let info: Matrix7 = swap_rt_blocks(&f.upper::<7>(10)?);
                sim3_edges.push((line, f.id(0)?, f.id(1)?, Sim3::new(q, t, s), info));
            }
            _ => {
                f.expect_len(1)?;
                fixes.push((line, f.id(0)?));
            }
        }
    }
    if kind == 2 {
        sim3.fix_lines = fixes;
        Ok(AnyGraph::Sim3(sim3.finish(sim3_edges)?))
    } else {
        se3.fix_lines = fixes;
        Ok(AnyGraph::Se3(se3.finish(se3_edges)?))
    }
}

fn write_pose(out: &mut String, t: &Vector3<f64>, q: &UnitQuaternion<f64>) {
    let _ = write!(
        out,
        " {:.17e} {:.17e} {:.17e} {:.17e} {:.17e} {:.17e} {:.17e}",
        t.x, t.y, t.z, q.i, q.j, q.k, q.w
    );
}

fn write_upper<const D: usize>(out: &mut String, m: &nalgebra::SMatrix<f64, D, D>) {
    for a in 0..D {
        for b in a..D {
            let _ = write!(out, " {:.17e}", m[(a, b)]);
        }
    }
}

fn write_fixes<P: GraphPose>(out: &mut String, g: &PoseGraph<P>) {
    for &k in &g.fixed {
        if let Some(v) = g.vertices.get(k) {
            let _ = writeln!(out, "FIX {}", v.id);
        }
    }
}

/// Writes an SE(3) graph (info permuted back to g2o's `(t, R)` order); round-trips with
/// [`parse_g2o`].
pub fn write_g2o_se3(g: &Se3Graph) -> String {
    let mut out = String::new();
    for v in &g.vertices {
        let _ = write!(out, "VERTEX_SE3:QUAT {}", v.id);
        write_pose(&mut out, &v.pose.translation.vector, &v.pose.rotation);
        out.push('\n');
    }
    for e in &g.edges {
        let (a, b) = (g.vertices[e.i].id, g.vertices[e.j].id);
        let _ = write!(out, "EDGE_SE3:QUAT {a} {b}");
        write_pose(
            &mut out,
            &e.measurement.translation.vector,
            &e.measurement.rotation,
        );
        write_upper(&mut out, &swap_rt_blocks(&e.info));
        out.push('\n');
    }
    write_fixes(&mut out, g);
    out
}

/// Writes a Sim(3) graph; round-trips with [`parse_g2o`].
pub fn write_g2o_sim3(g: &Sim3Graph) -> String {
    let mut out = String::new();
    for v in &g.vertices {
        let _ = write!(out, "VERTEX_SIM3:QUAT {}", v.id);
        write_pose(&mut out, &v.pose.t, &v.pose.r);
        let _ = writeln!(out, " {:.17e}", v.pose.s);
    }
    for e in &g.edges {
        let (a, b) = (g.vertices[e.i].id, g.vertices[e.j].id);
        let _ = write!(out, "EDGE_SIM3:QUAT {a} {b}");
        write_pose(&mut out, &e.measurement.t, &e.measurement.r);
        let _ = write!(out, " {:.17e}", e.measurement.s);
        write_upper(&mut out, &swap_rt_blocks(&e.info));
        out.push('\n');
    }
    write_fixes(&mut out, g);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Matrix6;

    const SIM: &str = "# a comment\n\
        VERTEX_SIM3:QUAT 0 0 0 0 0 0 0 1 1\n\
        VERTEX_SIM3:QUAT 1 1 0 0 0 0 0.7071067811865476 0.7071067811865476 2  # trailing\n\
        \n\
        EDGE_SIM3:QUAT 0 1 1 0 0 0 0 0.7071067811865476 0.7071067811865476 2 \
        1 0 0 0 0 0 0 1 0 0 0 0 0 1 0 0 0 0 2 0 0 0 2 0 0 2 0 5\n\
        FIX 0\n";

    #[test]
    fn parses_sim3_and_round_trips() {
        let AnyGraph::Sim3(g) = parse_g2o(SIM).unwrap() else {
            panic!("not sim3")
        };
        assert_eq!(g.vertices.len(), 2);
        assert_eq!(g.edges.len(), 1);
        assert_eq!(g.fixed, vec![0]);
        assert_eq!(g.vertices[1].pose.s, 2.0);
        let e = g.edges[0];
        assert_eq!((e.i, e.j), (0, 1));
        // File diag (t: 1 1 1, R: 2 2 2, σ: 5), stored (R, t, σ).
        assert_eq!(e.info[(6, 6)], 5.0);
        assert_eq!(e.info[(3, 3)], 1.0);
        assert_eq!(e.info[(0, 0)], 2.0);
        let again = parse_g2o(&write_g2o_sim3(&g)).unwrap();
        assert_eq!(again, AnyGraph::Sim3(g));
    }

    #[test]
    fn parses_se3_and_permutes_information() {
        // info diag (t: 1 2 3, R: 4 5 6) plus a t-R cross term (tx, rz) = 0.5
        let mut upper = Vec::new();
        let mut m = Matrix6::<f64>::from_diagonal(&nalgebra::Vector6::new(1., 2., 3., 4., 5., 6.));
        m[(0, 5)] = 0.5;
        m[(5, 0)] = 0.5;
        for a in 0..6 {
            for b in a..6 {
                upper.push(format!("{}", m[(a, b)]));
            }
        }
        let text = format!(
            "VERTEX_SE3:QUAT 5 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 7 1 2 3 0 0 0 1\n\
             EDGE_SE3:QUAT 5 7 1 2 3 0 0 0 1 {}\n",
            upper.join(" ")
        );
        let AnyGraph::Se3(g) = parse_g2o(&text).unwrap() else {
            panic!("not se3")
        };
        let info = g.edges[0].info;
        assert_eq!(info[(0, 0)], 4.0); // R first
        assert_eq!(info[(3, 3)], 1.0);
        assert_eq!(info[(2, 3)], 0.5); // (rz, tx)
        assert_eq!(g.first_vertex(), Some(0));
        assert_eq!(parse_g2o(&write_g2o_se3(&g)).unwrap(), AnyGraph::Se3(g));
    }

    fn line_of(text: &str) -> usize {
        match parse_g2o(text) {
            Err(CoreError::Parse { line, .. }) => line,
            other => panic!("expected a parse error, got {other:?}"),
        }
    }

    #[test]
    fn malformed_lines_name_their_line() {
        let v = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n";
        assert_eq!(line_of(&format!("{v}VERTEX_SE3:QUAT 1 0 0 0 0 0 0\n")), 2);
        assert_eq!(
            line_of(&format!("{v}\nVERTEX_SE3:QUAT x 0 0 0 0 0 0 1\n")),
            3
        );
        assert_eq!(
            line_of(&format!("{v}VERTEX_SE3:QUAT 1 0 nan 0 0 0 0 1\n")),
            2
        );
        assert_eq!(line_of(&format!("{v}VERTEX_SE3:QUAT 1 0 0 0 0 0 0 0\n")), 2);
        assert_eq!(line_of(&format!("{v}VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n")), 2);
        assert_eq!(line_of(&format!("{v}BOGUS 1 2\n")), 2);
        assert_eq!(line_of(&format!("{v}FIX 3\n")), 2);
        assert_eq!(
            line_of(&format!("{v}VERTEX_SIM3:QUAT 1 0 0 0 0 0 0 1 1\n")),
            2
        );
        assert_eq!(line_of("VERTEX_SIM3:QUAT 1 0 0 0 0 0 0 1 -1\n"), 1);
        let short_edge =
            format!("{v}VERTEX_SE3:QUAT 1 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1 1 0\n");
        assert_eq!(line_of(&short_edge), 3);
        let upper21 = vec!["1"; 21].join(" ");
        let dangling = format!("{v}EDGE_SE3:QUAT 0 9 0 0 0 0 0 0 1 {upper21}\n");
        assert_eq!(line_of(&dangling), 2);
        let self_loop = format!("{v}EDGE_SE3:QUAT 0 0 0 0 0 0 0 0 1 {upper21}\n");
        assert_eq!(line_of(&self_loop), 2);
    }

    #[test]
    fn swap_is_an_involution() {
        let m = Matrix6::from_fn(|a, b| (a * 6 + b) as f64);
        assert_eq!(swap_rt_blocks(&swap_rt_blocks(&m)), m);
        assert_eq!(swap_rt_blocks(&m)[(0, 0)], m[(3, 3)]);
        let m7 = Matrix7::from_fn(|a, b| (a * 7 + b) as f64);
        assert_eq!(swap_rt_blocks(&swap_rt_blocks(&m7)), m7);
        assert_eq!(swap_rt_blocks(&m7)[(0, 0)], m7[(3, 3)]);
        assert_eq!(swap_rt_blocks(&m7)[(6, 1)], m7[(6, 4)]);
    }
}
