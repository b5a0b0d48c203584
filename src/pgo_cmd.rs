//! `shoal pgo`: optimise a pose graph file (g2o-like text, see `slam_core::pgo`) and write
//! the optimised keyframe poses as a TUM trajectory (vertex id as the timestamp).
//!
//! Sim(3) graphs (`VERTEX_SIM3:QUAT` / `EDGE_SIM3:QUAT`) use `--method`; SE(3) graphs
//! (`VERTEX_SE3:QUAT` / `EDGE_SE3:QUAT`) are always optimised by Levenberg-Marquardt on
//! SE(3) minimising GTSAM's cost (with GTSAM's prior on the first vertex when the file has
//! no `FIX`), optionally after a chordal initialisation (`--init chordal`).

use std::path::PathBuf;

use anyhow::Context;
use datasets::trajectory::{push_tum_line, TumDigits, TumRow};
use nalgebra::Isometry3;
use serde::Serialize;
use slam_core::pgo::{
    optimize_se3, optimize_sim3, parse_g2o, AnyGraph, PgoInit, PgoMethod, PgoParams, PgoReport,
};

/// Sim(3) optimisation method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// Scales by linear least squares, then scales + translations (seed eq. 3.10-3.12).
    Stepwise,
    /// Levenberg-Marquardt on all 7 Sim(3) parameters per keyframe.
    Direct,
    /// Stepwise, then direct refinement from its result.
    #[value(name = "stepwise+direct")]
    #[serde(rename = "stepwise+direct")]
    StepwiseDirect,
}

impl From<Method> for PgoMethod {
    fn from(m: Method) -> Self {
        match m {
            Method::Stepwise => PgoMethod::Stepwise,
            Method::Direct => PgoMethod::Direct,
            Method::StepwiseDirect => PgoMethod::StepwiseDirect,
        }
    }
}

/// Initial values of an SE(3) graph.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Init {
    /// The file's vertex values.
    Odometry,
    /// Chordal relaxation of the rotations, then linear translations.
    Chordal,
}

/// Arguments of `shoal pgo`.
#[derive(Debug, Clone, clap::Args)]
#[command(
    long_about = "Optimise a pose graph. Sim(3) files (VERTEX_SIM3:QUAT/EDGE_SIM3:QUAT) use \
    --method. SE(3) files (VERTEX_SE3:QUAT/EDGE_SE3:QUAT) are always optimised by \
    Levenberg-Marquardt on SE(3) minimising GTSAM's cost E = 1/2 sum r^T Omega r (with \
    GTSAM's prior on the first vertex when the file has no FIX line); --method is ignored \
    for them. Writes the optimised poses in TUM format (vertex id as the timestamp)."
)]
pub struct PgoArgs {
    /// Pose graph file (g2o-like text).
    #[arg(long)]
    pub graph: PathBuf,
    /// Sim(3) method (SE(3) graphs: always LM on SE(3)).
    #[arg(long, value_enum, default_value_t = Method::StepwiseDirect)]
    pub method: Method,
    /// Initial values (chordal: SE(3) graphs only).
    #[arg(long, value_enum, default_value_t = Init::Odometry)]
    pub init: Init,
    /// Output TUM trajectory (`id tx ty tz qx qy qz qw`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Largest number of LM iterations per stage.
    #[arg(long, default_value_t = 100)]
    pub max_iterations: usize,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

/// One stage in the JSON output.
#[derive(Debug, Serialize)]
struct StageJson {
    name: &'static str,
    iterations: usize,
    initial_cost: f64,
    final_cost: f64,
    time_s: f64,
    converged: bool,
}

/// The JSON output of `shoal pgo --json`.
#[derive(Debug, Serialize)]
struct PgoJson {
    graph: String,
    kind: &'static str,
    method: String,
    init: Init,
    vertices: usize,
    edges: usize,
    iterations: usize,
    initial_cost: f64,
    final_cost: f64,
    solve_time_s: f64,
    /// Edges whose non-positive-definite information was replaced by GTSAM's effective one.
    repaired_information: usize,
    stages: Vec<StageJson>,
}

/// The optimised graph: kind, method, report, vertex and edge counts, TUM text.
struct Optimised {
    kind: &'static str,
    method: String,
    report: PgoReport,
    vertices: usize,
    edges: usize,
    tum: String,
}

/// TUM trajectory lines `id tx ty tz qx qy qz qw` (the vertex id as the timestamp, 17
/// significant digits) of the rigid part of each pose.
fn write_tum<'a>(poses: impl IntoIterator<Item = (u64, &'a Isometry3<f64>)>) -> String {
    let mut out = String::new();
    for (id, p) in poses {
        let r = TumRow::from_pose(0, p);
        push_tum_line(&mut out, id, &r.t, &r.q, TumDigits::Sci17);
    }
    out
}

/// Optimises the graph of `args` (SE(3) by LM, Sim(3) by `--method`).
fn optimise(args: &PgoArgs, graph: AnyGraph, params: &PgoParams) -> anyhow::Result<Optimised> {
    Ok(match graph {
        AnyGraph::Se3(mut g) => {
            let report = optimize_se3(&mut g, params).context("SE(3) optimisation")?;
            Optimised {
                kind: "se3",
                method: "lm-se3".into(),
                report,
                vertices: g.vertices.len(),
                edges: g.edges.len(),
                tum: write_tum(g.vertices.iter().map(|v| (v.id, &v.pose))),
            }
        }
        AnyGraph::Sim3(mut g) => {
            anyhow::ensure!(
                args.init == Init::Odometry,
                "--init chordal is only implemented for SE(3) graphs"
            );
            let report =
                optimize_sim3(&mut g, args.method.into(), params).context("Sim(3) optimisation")?;
            let poses: Vec<_> = g
                .vertices
                .iter()
                .map(|v| (v.id, v.pose.to_isometry()))
                .collect();
            let method = serde_json::to_value(args.method)?;
            Optimised {
                kind: "sim3",
                method: method.as_str().unwrap_or("?").to_string(),
                report,
                vertices: g.vertices.len(),
                edges: g.edges.len(),
                tum: write_tum(poses.iter().map(|(id, p)| (*id, p))),
            }
        }
    })
}

/// Prints the result as text.
fn print_text(out: &PgoJson, init: Init) {
    println!(
        "{} ({} graph, {} vertices, {} edges), method {}, init {:?}",
        out.graph, out.kind, out.vertices, out.edges, out.method, init
    );
    if out.repaired_information > 0 {
        println!(
            "  {} edges have an information matrix that is not positive definite: \
             using GTSAM's effective information (R^T R of Eigen's partial LLT)",
            out.repaired_information
        );
    }
    for s in &out.stages {
        println!(
            "  {:<28} {:>4} iterations  E {:.9e} -> {:.9e}  {:.4} s{}",
            s.name,
            s.iterations,
            s.initial_cost,
            s.final_cost,
            s.time_s,
            if s.converged { "" } else { "  (not converged)" }
        );
    }
    println!(
        "iterations {}  initial E {:.9e}  final E {:.9e}  solve time {:.4} s",
        out.iterations, out.initial_cost, out.final_cost, out.solve_time_s
    );
}

/// Runs `shoal pgo`.
pub fn run(args: &PgoArgs) -> anyhow::Result<()> {
    let text = std::fs::read_to_string(&args.graph)
        .with_context(|| format!("reading {}", args.graph.display()))?;
    let graph = parse_g2o(&text).with_context(|| format!("parsing {}", args.graph.display()))?;
    let mut params = PgoParams::default();
    params.lm.max_iterations = args.max_iterations;
    params.init = match args.init {
        Init::Odometry => PgoInit::Odometry,
        Init::Chordal => PgoInit::Chordal,
    };
    let o = optimise(args, graph, &params)?;
    if let Some(out) = &args.out {
        std::fs::write(out, &o.tum).with_context(|| format!("writing {}", out.display()))?;
    }
    let r = &o.report;
    let stage = |s: &slam_core::pgo::StageReport| StageJson {
        name: s.name,
        iterations: s.iterations,
        initial_cost: s.initial_cost,
        final_cost: s.final_cost,
        time_s: s.time_s,
        converged: s.converged,
    };
    let out = PgoJson {
        graph: args.graph.display().to_string(),
        kind: o.kind,
        method: o.method.clone(),
        init: args.init,
        vertices: o.vertices,
        edges: o.edges,
        iterations: r.iterations,
        initial_cost: r.initial_cost,
        final_cost: r.final_cost,
        solve_time_s: r.solve_time_s,
        repaired_information: r.repaired_information,
        stages: r.stages.iter().map(stage).collect(),
    };
    if args.json {
        println!("{}", serde_json::to_string(&out)?);
    } else {
        print_text(&out, args.init);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(graph: PathBuf, out: PathBuf, method: Method, init: Init) -> PgoArgs {
        PgoArgs {
            graph,
            method,
            init,
            out: Some(out),
            max_iterations: 100,
            json: true,
        }
    }

    #[test]
    fn sim3_file_to_tum() {
        let dir = tempfile::tempdir().unwrap();
        let graph = dir.path().join("g.g2o");
        // Three keyframes 1 m apart by odometry; the loop edge says 2->0 is 1.5 m back, so
        // the scales must change. Identity information (28 upper entries).
        let info = "1 0 0 0 0 0 0 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1";
        let text = format!(
            "VERTEX_SIM3:QUAT 10 0 0 0 0 0 0 1 1\nVERTEX_SIM3:QUAT 11 1 0 0 0 0 0 1 1\n\
             VERTEX_SIM3:QUAT 12 2 0 0 0 0 0 1 1\n\
             EDGE_SIM3:QUAT 10 11 1 0 0 0 0 0 1 1 {info}\n\
             EDGE_SIM3:QUAT 11 12 1 0 0 0 0 0 1 1 {info}\n\
             EDGE_SIM3:QUAT 12 10 -1.5 0 0 0 0 0 1 1 {info}\nFIX 10\n"
        );
        std::fs::write(&graph, text).unwrap();
        for method in [Method::Stepwise, Method::Direct, Method::StepwiseDirect] {
            let out = dir.path().join("out.tum");
            run(&args(graph.clone(), out.clone(), method, Init::Odometry)).unwrap();
            let tum = std::fs::read_to_string(&out).unwrap();
            let lines: Vec<&str> = tum.lines().collect();
            assert_eq!(lines.len(), 3);
            assert!(lines[0].starts_with("10 "));
            assert_eq!(lines[2].split_whitespace().count(), 8);
        }
        let out = dir.path().join("x.tum");
        let err = run(&args(graph, out, Method::Direct, Init::Chordal)).unwrap_err();
        assert!(format!("{err:#}").contains("SE(3)"));
    }

    #[test]
    fn malformed_file_names_the_line() {
        let dir = tempfile::tempdir().unwrap();
        let graph = dir.path().join("bad.g2o");
        std::fs::write(
            &graph,
            "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 2\n",
        )
        .unwrap();
        let err = run(&args(
            graph,
            dir.path().join("o"),
            Method::Direct,
            Init::Odometry,
        ))
        .unwrap_err();
        assert!(format!("{err:#}").contains("line 2"), "{err:#}");
    }
}
