//! `cloi optimize`: reads a pose graph, optimizes it with the core's sparse solver, and writes
//! the result and a JSON report.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use cloi_core::geom::Se2;
use cloi_core::graph::{EdgeKind, PoseEdge, PoseGraph, PoseNode, RobustKernel};
use cloi_core::solver::{
    self, Block, Method, SolveError, SolveFailure, SolveReport, SolverBuffers, SolverOptions, Vec3,
};
use serde::Serialize;

use crate::graph_io::{self, aligned_rmse, GraphFile, GraphFormat};
use crate::io::atomic;

/// Initial guess.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum InitMode {
    /// The poses of the file's vertex lines (odometry when the file has none).
    File,
    /// Chained odometry edges from the origin.
    Odometry,
}

/// Iteration scheme.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum SolverKind {
    /// Gauss-Newton, then Levenberg-Marquardt from the initial guess when Gauss-Newton's
    /// result fails a chi2 test (see `cloi_core::solver::Method::Auto`).
    Auto,
    /// Gauss-Newton.
    Gn,
    /// Levenberg-Marquardt.
    Lm,
}

/// Robust model applied to every loop-closure edge (odometry stays Gaussian).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum RobustMode {
    /// Plain least squares.
    None,
    /// Huber kernel, threshold `--kernel-width`.
    Huber,
    /// Cauchy kernel, scale `--kernel-width`.
    Cauchy,
    /// Max-mixture with a null hypothesis (`--null-weight`, `--null-scale`).
    Maxmix,
}

/// Options of `cloi optimize`.
#[derive(Debug, Clone, clap::Args)]
pub struct OptimizeArgs {
    /// Input pose graph (g2o or TORO).
    pub input: PathBuf,
    /// Input format (default: from the file's first record).
    #[arg(long, value_enum)]
    pub format: Option<GraphFormat>,
    /// Initial guess.
    #[arg(long, value_enum, default_value_t = InitMode::File)]
    pub init: InitMode,
    /// Iteration scheme.
    #[arg(long, value_enum, default_value_t = SolverKind::Auto)]
    pub solver: SolverKind,
    /// Robust model for loop closures.
    #[arg(long, value_enum, default_value_t = RobustMode::None)]
    pub robust: RobustMode,
    /// Huber threshold / Cauchy scale, on the Mahalanobis length of a residual.
    #[arg(long, default_value_t = 1.0)]
    pub kernel_width: f64,
    /// Weight of the max-mixture null hypothesis.
    #[arg(long, default_value_t = 1e-3)]
    pub null_weight: f32,
    /// Information scale of the max-mixture null hypothesis.
    #[arg(long, default_value_t = 1e-6)]
    pub null_scale: f32,
    /// Most iterations (linear solves).
    #[arg(long, default_value_t = 100)]
    pub max_iters: u32,
    /// Convergence threshold on the relative cost decrease of one iteration.
    #[arg(long, default_value_t = 1e-8)]
    pub rel_tol: f64,
    /// Gauss-Newton stages over the node order (loops among the first s/S of the nodes act in
    /// stage s).
    #[arg(long, default_value_t = 1)]
    pub stages: u32,
    /// Max-mixture warm start: chi2 gate (3 degrees of freedom) of each loop against the
    /// odometry chain's prediction and covariance; 0 disables it.
    #[arg(long, default_value_t = 16.27)]
    pub gate_chi2: f64,
    /// Most iterations per stage (all stages but the last).
    #[arg(long, default_value_t = 10)]
    pub stage_iters: u32,
    /// Levenberg-Marquardt's initial damping relative to the largest diagonal entry of H.
    #[arg(long, default_value_t = 1e-5)]
    pub lm_tau: f64,
    /// Skip the linear (LAGO-style) re-initialisation of headings and positions.
    #[arg(long)]
    pub no_linear_init: bool,
    /// Write the optimized graph here (g2o).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Write a JSON report here.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Ground truth (g2o vertices or `x y theta` rows) for the position RMSE.
    #[arg(long)]
    pub ground_truth: Option<PathBuf>,
}

/// The JSON report.
#[derive(Debug, Clone, Serialize)]
pub struct OptimizeReport {
    /// Input file.
    pub file: String,
    /// Nodes.
    pub nodes: usize,
    /// Edges.
    pub edges: usize,
    /// Edges that repeat an already measured node pair (kept).
    pub duplicate_pairs: usize,
    /// Initial guess used.
    pub init: InitMode,
    /// Iteration scheme.
    pub solver: SolverKind,
    /// Robust model on loop closures.
    pub robust: RobustMode,
    /// Linear solves.
    pub iterations: u32,
    /// Sum of `e^T Omega e` at the initial guess.
    pub initial_chi2: f64,
    /// The same at the end (robust models ignored, the g2o convention).
    pub final_chi2: f64,
    /// Robust cost at the end (equal to `final_chi2` without a robust model).
    pub final_cost: f64,
    /// Wall time of the solve alone (ordering, factorizations, iterations), milliseconds.
    pub time_ms: f64,
    /// Whether a stopping rule (not the iteration limit) ended the solve.
    pub converged: bool,
    /// The solver's error, if any.
    pub error: Option<String>,
    /// Off-diagonal 3x3 blocks of the Cholesky factor.
    pub factor_blocks: usize,
    /// Loop closures whose max-mixture picked the null hypothesis at the end.
    pub rejected_loops: Option<usize>,
    /// Max-mixture loop closures that passed the odometry-chain gate of the warm start.
    pub gated_loops: usize,
    /// Position RMSE against the ground truth after aligning the first pose, metres.
    pub rmse_m: Option<f64>,
}

/// Solver memory on the heap, grown when a factor does not fit.
#[derive(Debug, Default)]
pub struct HostWorkspace {
    key: solver::AnalysisKey,
    node_u32: [Vec<u32>; 9],
    diag: Vec<Block>,
    work: Vec<Block>,
    rhs: Vec<Vec3>,
    step: Vec<Vec3>,
    saved: Vec<Se2>,
    edge_slot: Vec<u32>,
    edge_trig: Vec<[f64; 2]>,
    edge_flags: Vec<u8>,
    rows: Vec<u32>,
    values: Vec<Block>,
    adj_node: Vec<u32>,
    adj_next: Vec<u32>,
}

impl HostWorkspace {
    /// Room for `nodes`, `edges` and `factor` off-diagonal blocks.
    pub fn new(nodes: usize, edges: usize, factor: usize) -> Self {
        let mut w = HostWorkspace::default();
        w.resize(nodes, edges, factor);
        w
    }

    fn resize(&mut self, nodes: usize, edges: usize, factor: usize) {
        for v in &mut self.node_u32 {
            v.resize(nodes, 0);
        }
        self.diag.resize(nodes, [0.0; 9]);
        self.work.resize(nodes, [0.0; 9]);
        self.rhs.resize(nodes, [0.0; 3]);
        self.step.resize(nodes, [0.0; 3]);
        self.saved.resize(nodes, Se2::IDENTITY);
        self.edge_slot.resize(edges, 0);
        self.edge_trig.resize(edges, [0.0; 2]);
        self.edge_flags.resize(edges, 0);
        self.rows.resize(factor, 0);
        self.values.resize(factor, [0.0; 9]);
        self.adj_node.resize(2 * factor, 0);
        self.adj_next.resize(2 * factor, 0);
    }

    /// Bytes held by the workspace's vectors.
    pub fn bytes(&self) -> usize {
        use std::mem::size_of_val;
        self.node_u32
            .iter()
            .map(|v| size_of_val(&v[..]))
            .sum::<usize>()
            + size_of_val(&self.key)
            + size_of_val(&self.diag[..])
            + size_of_val(&self.work[..])
            + size_of_val(&self.rhs[..])
            + size_of_val(&self.step[..])
            + size_of_val(&self.saved[..])
            + size_of_val(&self.edge_slot[..])
            + size_of_val(&self.edge_trig[..])
            + size_of_val(&self.edge_flags[..])
            + size_of_val(&self.rows[..])
            + size_of_val(&self.values[..])
            + size_of_val(&self.adj_node[..])
            + size_of_val(&self.adj_next[..])
    }

    /// The workspace as the core's slices.
    pub fn buffers(&mut self) -> SolverBuffers<'_> {
        let [a, b, c, d, e, f, g, h, i] = &mut self.node_u32;
        SolverBuffers {
            key: &mut self.key,
            node_var: a,
            var_node: b,
            col_end: c,
            diag: &mut self.diag,
            work: &mut self.work,
            rhs: &mut self.rhs,
            step: &mut self.step,
            saved: &mut self.saved,
            scratch: [d, e, f, g, h, i],
            edge_slot: &mut self.edge_slot,
            edge_trig: &mut self.edge_trig,
            edge_flags: &mut self.edge_flags,
            rows: &mut self.rows,
            values: &mut self.values,
            adj_node: &mut self.adj_node,
            adj_next: &mut self.adj_next,
        }
    }

    /// Solves, doubling the factor capacity (outside the timed solve) until the factor fits.
    ///
    /// # Errors
    /// The solver's failure.
    pub fn solve(
        &mut self,
        graph: &mut PoseGraph<'_>,
        options: &SolverOptions,
    ) -> Result<SolveReport, SolveFailure> {
        loop {
            let start: Vec<PoseNode> = graph.nodes().to_vec();
            match solver::solve(graph, &mut self.buffers(), options) {
                Err(SolveFailure {
                    error:
                        SolveError::Capacity {
                            what: "factor blocks",
                            capacity,
                        },
                    ..
                }) if capacity < (1 << 30) => {
                    graph.nodes_mut().copy_from_slice(&start);
                    let (n, m) = (self.diag.len(), self.edge_slot.len());
                    self.resize(n, m, 2 * capacity.max(1024));
                }
                other => return other,
            }
        }
    }
}

/// Robust kernel for a loop-closure edge under `mode`.
pub fn loop_kernel(
    mode: RobustMode,
    width: f64,
    null_weight: f32,
    null_scale: f32,
) -> RobustKernel {
    match mode {
        RobustMode::None => RobustKernel::None,
        RobustMode::Huber => RobustKernel::Huber { delta: width },
        RobustMode::Cauchy => RobustKernel::Cauchy { c: width },
        RobustMode::Maxmix => RobustKernel::max_mixture_with_null(null_weight, null_scale),
    }
}

/// Result of [`optimize_file`]: the report and the optimized poses.
#[derive(Debug, Clone)]
pub struct Optimized {
    /// The report.
    pub report: OptimizeReport,
    /// Optimized poses in node order.
    pub poses: Vec<Se2>,
    /// The graph as read.
    pub graph: GraphFile,
}

/// Reads, optimizes and evaluates one graph (no output files).
///
/// # Errors
/// The input or ground truth cannot be read; solver failures other than the iteration limit
/// are reported in `report.error` (the poses are then the last estimate).
pub fn optimize_file(args: &OptimizeArgs) -> Result<Optimized> {
    let graph = graph_io::read_graph(&args.input, args.format)?;
    let init = match args.init {
        InitMode::File => graph.poses.clone(),
        InitMode::Odometry => graph.odometry_guess(),
    };
    let nodes = graph.pose_nodes(&init);
    let kernel = loop_kernel(
        args.robust,
        args.kernel_width,
        args.null_weight,
        args.null_scale,
    );
    let mut edges: Vec<PoseEdge> = graph.pose_edges();
    for e in &mut edges {
        if e.kind == EdgeKind::Loop {
            e.robust = kernel;
        }
    }
    let n = nodes.len();
    let m = edges.len();
    let mut ws = HostWorkspace::new(n, m, (16 * n).max(2 * m) + 1024);
    let mut node_store = vec![PoseNode::EMPTY; n];
    let mut edge_store = vec![PoseEdge::EMPTY; m];
    let mut pg = PoseGraph::new(&mut node_store, &mut edge_store);
    for node in nodes {
        pg.add_node_full(node)?;
    }
    for (k, e) in edges.into_iter().enumerate() {
        pg.add_edge(e)
            .with_context(|| format!("{}: edge {k}", args.input.display()))?;
    }
    let options = SolverOptions {
        method: match args.solver {
            SolverKind::Auto => Method::Auto,
            SolverKind::Gn => Method::GaussNewton,
            SolverKind::Lm => Method::LevenbergMarquardt,
        },
        max_iterations: args.max_iters,
        relative_tolerance: args.rel_tol,
        linear_init: !args.no_linear_init,
        stages: args.stages,
        gate_chi2: args.gate_chi2,
        lm_tau: args.lm_tau,
        stage_iterations: args.stage_iters,
        ..SolverOptions::default()
    };
    let t0 = Instant::now();
    let outcome = ws.solve(&mut pg, &options);
    let time_ms = t0.elapsed().as_secs_f64() * 1e3;
    let (rep, error) = match outcome {
        Ok(r) => (r, None),
        Err(f) => (f.report, Some(f.error)),
    };
    let poses: Vec<Se2> = pg.nodes().iter().map(|n| n.pose).collect();
    let rejected_loops = (args.robust == RobustMode::Maxmix).then_some(rep.rejected_loops);
    let rmse_m = match &args.ground_truth {
        Some(p) => {
            let truth = graph_io::read_ground_truth(p)?;
            if truth.len() != poses.len() {
                bail!(
                    "{}: ground truth has {} poses, the graph {} nodes",
                    p.display(),
                    truth.len(),
                    poses.len()
                );
            }
            aligned_rmse(&poses, &truth)
        }
        None => None,
    };
    let report = OptimizeReport {
        file: args.input.display().to_string(),
        nodes: n,
        edges: m,
        duplicate_pairs: graph.duplicate_pairs,
        init: args.init,
        solver: args.solver,
        robust: args.robust,
        iterations: rep.iterations,
        initial_chi2: rep.initial_chi2,
        final_chi2: rep.final_chi2,
        final_cost: rep.final_cost,
        time_ms,
        converged: rep.converged,
        error: error.map(|e| e.to_string()),
        factor_blocks: rep.factor_blocks,
        rejected_loops,
        gated_loops: rep.gated_loops,
        rmse_m,
    };
    if let Some(e) = error {
        if e != SolveError::MaxIterations {
            log::warn!("{}: {e}", args.input.display());
        }
    }
    Ok(Optimized {
        report,
        poses,
        graph,
    })
}

/// Runs `cloi optimize`.
///
/// # Errors
/// Unreadable input, unwritable output, or a solver failure other than the iteration limit
/// (the outputs are still written).
pub fn run(args: &OptimizeArgs, out: &mut dyn Write) -> Result<()> {
    let res = optimize_file(args)?;
    let r = &res.report;
    if let Some(path) = &args.out {
        atomic::write_file(path, graph_io::write_g2o(&res.graph, &res.poses).as_bytes())?;
    }
    if let Some(path) = &args.report {
        let json = serde_json::to_string_pretty(r)?;
        atomic::write_file(path, json.as_bytes())?;
    }
    writeln!(
        out,
        "{}: {} nodes, {} edges, {} iterations, chi2 {:.6} -> {:.6}, {:.3} ms, converged: {}{}{}",
        display_name(&args.input),
        r.nodes,
        r.edges,
        r.iterations,
        r.initial_chi2,
        r.final_chi2,
        r.time_ms,
        r.converged,
        r.rmse_m
            .map(|v| format!(", rmse {v:.4} m"))
            .unwrap_or_default(),
        r.error
            .as_ref()
            .map(|e| format!(" ({e})"))
            .unwrap_or_default(),
    )?;
    match &r.error {
        Some(e) if e != &SolveError::MaxIterations.to_string() => {
            bail!("{}: {e}", args.input.display())
        }
        _ => Ok(()),
    }
}

fn display_name(p: &Path) -> String {
    p.file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| p.display().to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    /// A small square loop with noisy odometry and one loop closure, as g2o text.
    fn square_g2o() -> String {
        let mut s = String::new();
        let mut pose = Se2::IDENTITY;
        let step = |i: usize| {
            let turn = if i % 4 == 3 {
                std::f64::consts::FRAC_PI_2
            } else {
                0.0
            };
            Se2::new(
                1.0 + 0.01 * (i as f64).sin(),
                0.02 * (i as f64).cos(),
                turn + 0.01,
            )
        };
        for i in 0..16 {
            s += &format!("VERTEX_SE2 {i} {} {} {}\n", pose.x, pose.y, pose.theta);
            pose = pose.compose(&step(i));
        }
        for i in 0..15 {
            let z = step(i);
            s += &format!(
                "EDGE_SE2 {i} {} {} {} {} 100 0 0 100 0 1000\n",
                i + 1,
                z.x,
                z.y,
                z.theta
            );
        }
        s += "EDGE_SE2 15 0 1 0 1.5707963267948966 100 0 0 100 0 1000\n";
        s
    }

    fn temp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("cloi-opt-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    #[test]
    fn optimize_writes_graph_and_report() {
        let input = temp("square.g2o");
        std::fs::write(&input, square_g2o()).unwrap();
        let out = temp("square_opt.g2o");
        let report = temp("square.json");
        for solver in ["gn", "lm"] {
            let cli = crate::cli::Cli::try_parse_from([
                "cloi",
                "optimize",
                input.to_str().unwrap(),
                "--solver",
                solver,
                "--init",
                "odometry",
                "--out",
                out.to_str().unwrap(),
                "--report",
                report.to_str().unwrap(),
                "--ground-truth",
                input.to_str().unwrap(),
            ])
            .unwrap();
            let mut text = Vec::new();
            crate::cli::run(cli, &mut text).unwrap();
            let r: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
            assert_eq!(r["nodes"], 16);
            assert_eq!(r["edges"], 16);
            assert_eq!(r["converged"], true);
            let (c0, c1) = (
                r["initial_chi2"].as_f64().unwrap(),
                r["final_chi2"].as_f64().unwrap(),
            );
            assert!(c1 < c0 && c1 > 0.0, "{c0} -> {c1}");
            assert!(r["time_ms"].as_f64().unwrap() >= 0.0);
            assert!(r["iterations"].as_u64().unwrap() >= 1);
            assert!(r["rmse_m"].as_f64().unwrap() >= 0.0);
            // The optimized graph reads back with the same edges and a lower chi2.
            let back = graph_io::read_graph(&out, None).unwrap();
            assert_eq!(back.edges.len(), 16);
        }
    }

    #[test]
    fn missing_input_is_an_error_not_a_panic() {
        let cli = crate::cli::Cli::try_parse_from(["cloi", "optimize", "/nonexistent/graph.g2o"])
            .unwrap();
        let err = crate::cli::run(cli, &mut Vec::new()).unwrap_err();
        assert!(format!("{err:#}").contains("/nonexistent/graph.g2o"));
    }

    #[test]
    fn corrupt_is_seeded_and_maxmix_rejects_its_loops() {
        let input = temp("sq.g2o");
        std::fs::write(&input, square_g2o()).unwrap();
        let a = temp("sq_a.g2o");
        let b = temp("sq_b.g2o");
        for out in [&a, &b] {
            let cli = crate::cli::Cli::try_parse_from([
                "cloi",
                "corrupt",
                input.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
                "--outliers",
                "5",
                "--seed",
                "3",
            ])
            .unwrap();
            crate::cli::run(cli, &mut Vec::new()).unwrap();
        }
        let ta = std::fs::read_to_string(&a).unwrap();
        assert_eq!(ta, std::fs::read_to_string(&b).unwrap());
        assert_eq!(ta.lines().filter(|l| l.starts_with("EDGE_SE2")).count(), 21);
        let args = |robust: &str| {
            let cli = crate::cli::Cli::try_parse_from([
                "cloi",
                "optimize",
                a.to_str().unwrap(),
                "--robust",
                robust,
            ])
            .unwrap();
            match cli.command {
                crate::cli::Command::Optimize(o) => o,
                _ => unreachable!(),
            }
        };
        let clean = optimize_file(&OptimizeArgs {
            input: input.clone(),
            ..args("none")
        })
        .unwrap();
        let mm = optimize_file(&args("maxmix")).unwrap();
        assert_eq!(mm.report.rejected_loops, Some(5));
        for (p, q) in mm.poses.iter().zip(&clean.poses) {
            assert!((p.x - q.x).abs() < 1e-3 && (p.y - q.y).abs() < 1e-3);
        }
    }
}
