//! `cloi prune`: the paper's Table III experiment on a pose graph. Optimize the full graph,
//! prune it to about one node per grid cell (marginalization + Chow-Liu trees), optimize the
//! pruned graph with the same solver, and report sizes, density and ARPS.

use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use cloi_core::backend::cells::{CellCandidate, CellKey, CellMoments, CellParams};
use cloi_core::backend::prune::{self, PruneParams, PruneReport, PruneScratch, Weighting};
use cloi_core::geom::Se2;
use cloi_core::graph::{PoseEdge, PoseGraph, PoseNode};
use cloi_core::solver::{Method, SolverOptions};
use cloi_eval::arps::arps;
use serde::Serialize;

use crate::graph_io::{self, FileEdge, GraphFile, GraphFormat};
use crate::io::atomic;
use crate::optimize::HostWorkspace;

/// The information term of the node weight.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum WeightArg {
    /// Eq. (3): trace of the node's marginal information.
    Eq3,
    /// Eq. (4): sum of the information of the node's edges.
    Eq4,
}

/// Options of `cloi prune`.
#[derive(Debug, Clone, clap::Args)]
pub struct PruneArgs {
    /// Input pose graph (g2o or TORO).
    pub input: PathBuf,
    /// Input format (default: from the file's first record).
    #[arg(long, value_enum)]
    pub format: Option<GraphFormat>,
    /// Grid cell size, metres.
    #[arg(long)]
    pub cell: f64,
    /// Information term of the node weight.
    #[arg(long, value_enum, default_value_t = WeightArg::Eq4)]
    pub weight: WeightArg,
    /// Share of the information term in the weight (the paper's s).
    #[arg(long, default_value_t = 0.5)]
    pub s: f64,
    /// Initial guess from the file's vertices (default) or chained odometry.
    #[arg(long)]
    pub odometry_init: bool,
    /// Run prune + optimize this many times on the same optimized graph (fresh solver memory
    /// each time) and report the median times.
    #[arg(long, default_value_t = 1)]
    pub repeat: usize,
    /// Stream the graph node by node through a fixed pool instead (the mapper's online mode);
    /// reports the pool's peak use and the ARPS against the batch optimum.
    #[arg(long)]
    pub online: bool,
    /// Online mode: node capacity of the pool.
    #[arg(long, default_value_t = 1500)]
    pub pool: usize,
    /// Online mode: nodes per optimized window.
    #[arg(long, default_value_t = 50)]
    pub window: usize,
    /// Most nodes to eliminate (a work budget; default: all the cell rule selects).
    #[arg(long)]
    pub max_eliminations: Option<usize>,
    /// Write the pruned, optimized graph here (g2o).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Write the JSON report here.
    #[arg(long)]
    pub report: Option<PathBuf>,
}

/// The JSON report of `cloi prune`.
#[derive(Debug, Clone, Serialize)]
pub struct PruneJson {
    /// Input file.
    pub file: String,
    /// Cell size, metres.
    pub cell_m: f64,
    /// Weight used.
    pub weight: WeightArg,
    /// Share of the information term.
    pub s: f64,
    /// Nodes of the full graph.
    pub nodes_before: usize,
    /// Edges of the full graph.
    pub edges_before: usize,
    /// Nodes after pruning.
    pub nodes_after: usize,
    /// Edges after pruning.
    pub edges_after: usize,
    /// Mean kept nodes per occupied cell, over the positions the cells were drawn on (the full
    /// graph's optimum).
    pub nodes_per_cell_mean: f64,
    /// Most kept nodes in one cell.
    pub nodes_per_cell_max: usize,
    /// Edges per node, `edges_after / nodes_after` (the paper's ratio).
    pub edges_per_node_mean: f64,
    /// Most edges touching one node (its degree).
    pub edges_per_node_max: usize,
    /// Average relative position shift of the kept nodes, percent (see `arps`).
    pub arps_percent: f64,
    /// Largest position shift of a kept node between the full and the pruned solution, metres.
    pub max_shift_m: f64,
    /// Kept nodes left out of ARPS because they sit at the origin of the full solution.
    pub arps_nodes_at_origin: usize,
    /// Time to prune (weights, cells, eliminations, compaction; for eq. 3 also the node
    /// marginals), milliseconds, median over `--repeat` runs.
    pub prune_ms: f64,
    /// Time to optimize the pruned graph (ordering included), milliseconds, median.
    pub optimize_ms: f64,
    /// Time to optimize the full graph first (not part of the paper's figure), milliseconds.
    pub full_optimize_ms: f64,
    /// Details of the pruning pass.
    pub eliminated: usize,
    /// Nodes the cell rule dropped but that could not be eliminated.
    pub kept_not_eliminable: usize,
    /// Tree edges added / merged into existing edges.
    pub tree_edges_added: usize,
    /// Tree edges merged into existing edges.
    pub tree_edges_merged: usize,
    /// Outlier loop closures dropped during elimination.
    pub outliers_dropped: usize,
}

/// The batch optimum of a whole graph file from the initial guess `init`.
///
/// # Errors
/// The graph cannot be built or the solve fails.
pub fn batch_optimum(file: &GraphFile, init: &[Se2]) -> Result<Vec<Se2>> {
    let nodes = file.pose_nodes(init);
    let edges = file.pose_edges();
    let (n, m) = (nodes.len(), edges.len());
    let mut node_store = vec![PoseNode::EMPTY; n];
    let mut edge_store = vec![PoseEdge::EMPTY; m];
    let mut g = PoseGraph::new(&mut node_store, &mut edge_store);
    for node in nodes {
        g.add_node_full(node)?;
    }
    for e in edges {
        g.add_edge(e)?;
    }
    let mut ws = HostWorkspace::new(n, m, (16 * n).max(2 * m) + 1024);
    ws.solve(&mut g, &SolverOptions::default())
        .map_err(|f| anyhow::anyhow!("batch optimum: {f}"))?;
    Ok(g.nodes().iter().map(|p| p.pose).collect())
}

/// Median of a non-empty list of times.
fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

/// The result of [`prune_file`].
#[derive(Debug, Clone)]
pub struct Pruned {
    /// The report.
    pub report: PruneJson,
    /// Optimized poses of the kept nodes.
    pub poses: Vec<Se2>,
    /// Edges of the pruned graph (node indices into `poses`).
    pub edges: Vec<PoseEdge>,
    /// Original vertex id of each kept node.
    pub ids: Vec<i64>,
}

/// Runs the experiment; returns the report and the pruned graph.
///
/// # Errors
/// Unreadable input, a failed full solve, or bad parameters.
pub fn prune_file(args: &PruneArgs) -> Result<Pruned> {
    if !(args.cell > 0.0 && args.cell.is_finite()) {
        bail!(
            "--cell must be a positive number of metres, got {}",
            args.cell
        );
    }
    if !(0.0..=1.0).contains(&args.s) {
        bail!("--s must be within 0..=1, got {}", args.s);
    }
    let file = graph_io::read_graph(&args.input, args.format)?;
    let init = if args.odometry_init {
        file.odometry_guess()
    } else {
        file.poses.clone()
    };
    let nodes = file.pose_nodes(&init);
    let edges = file.pose_edges();
    let (n, m) = (nodes.len(), edges.len());
    // Room for the tree edges that pruning adds before it compacts.
    let edge_capacity = m + n + 64;
    let mut node_store = vec![PoseNode::EMPTY; n];
    let mut edge_store = vec![PoseEdge::EMPTY; edge_capacity];
    let mut g = PoseGraph::new(&mut node_store, &mut edge_store);
    for node in nodes {
        g.add_node_full(node)?;
    }
    for (k, e) in edges.into_iter().enumerate() {
        g.add_edge(e)
            .with_context(|| format!("{}: edge {k}", args.input.display()))?;
    }
    let options = SolverOptions {
        method: Method::GaussNewton,
        ..SolverOptions::default()
    };
    // The pruned graph starts next to its optimum: no linear re-initialisation.
    let warm = SolverOptions {
        linear_init: false,
        ..options
    };

    // 1. The full optimum: the reference for ARPS.
    let mut ws = HostWorkspace::new(n, edge_capacity, (16 * n).max(2 * edge_capacity) + 1024);
    let t0 = Instant::now();
    ws.solve(&mut g, &options)
        .map_err(|f| anyhow::anyhow!("optimizing the full graph: {f}"))?;
    let full_optimize_ms = t0.elapsed().as_secs_f64() * 1e3;
    let original: Vec<Se2> = g.nodes().iter().map(|p| p.pose).collect();

    // 2. Prune.
    let params = PruneParams {
        cells: CellParams {
            cell_size: args.cell,
            s: args.s,
        },
        weighting: match args.weight {
            WeightArg::Eq3 => Weighting::NodeInformation,
            WeightArg::Eq4 => Weighting::EdgeInformation,
        },
        max_eliminations: args.max_eliminations.unwrap_or(usize::MAX),
        ..PruneParams::default()
    };
    let mut scratch = OwnedPruneScratch::new(n, edge_capacity);
    let full_nodes: Vec<PoseNode> = g.nodes().to_vec();
    let full_edges: Vec<PoseEdge> = g.edges().to_vec();
    let mut prune_times = Vec::new();
    let mut optimize_times = Vec::new();
    let mut report = PruneReport::default();
    for round in 0..args.repeat.max(1) {
        if round > 0 {
            // Start again from the full optimum, with fresh solver memory.
            g.clear();
            for node in &full_nodes {
                g.add_node_full(*node)?;
            }
            for e in &full_edges {
                g.add_edge(*e)?;
            }
            ws = HostWorkspace::new(n, edge_capacity, (16 * n).max(2 * edge_capacity) + 1024);
        }
        let t1 = Instant::now();
        if args.weight == WeightArg::Eq3 {
            cloi_core::solver::marginal_information_traces(
                &mut g,
                &mut ws.buffers(),
                &mut scratch.node_information,
            )
            .map_err(|e| anyhow::anyhow!("node marginals for eq. (3): {e}"))?;
        }
        report = prune::prune(&mut g, &params, &mut scratch.scratch())?;
        prune_times.push(t1.elapsed().as_secs_f64() * 1e3);

        // 3. Optimize the pruned graph.
        let t2 = Instant::now();
        if let Err(f) = ws.solve(&mut g, &warm) {
            bail!("optimizing the pruned graph: {f} (pruning: {report:?})");
        }
        optimize_times.push(t2.elapsed().as_secs_f64() * 1e3);
    }
    let prune_ms = median(&mut prune_times);
    let optimize_ms = median(&mut optimize_times);
    // `order` now maps old node indices to new ones.
    let kept_original: Vec<Se2> = (0..n)
        .filter(|&i| scratch.order()[i] != u32::MAX)
        .map(|i| original[i])
        .collect();
    let pruned: Vec<Se2> = g.nodes().iter().map(|p| p.pose).collect();
    let pruned_edges: Vec<PoseEdge> = g.edges().to_vec();

    // 4. Density of the result.
    let mut per_cell = std::collections::BTreeMap::<CellKey, usize>::new();
    for p in &kept_original {
        *per_cell
            .entry(CellKey::of(p.x, p.y, args.cell))
            .or_default() += 1;
    }
    let mut degree = vec![0usize; pruned.len()];
    for e in &pruned_edges {
        degree[e.from.0 as usize] += 1;
        if e.to != e.from {
            degree[e.to.0 as usize] += 1;
        }
    }
    let (arps_percent, arps_nodes_at_origin) = arps(&kept_original, &pruned).unwrap_or((0.0, 0));
    let json = PruneJson {
        file: args.input.display().to_string(),
        cell_m: args.cell,
        weight: args.weight,
        s: args.s,
        nodes_before: report.nodes_before,
        edges_before: report.edges_before,
        nodes_after: report.nodes_after,
        edges_after: report.edges_after,
        nodes_per_cell_mean: pruned.len() as f64 / per_cell.len().max(1) as f64,
        nodes_per_cell_max: per_cell.values().copied().max().unwrap_or(0),
        edges_per_node_mean: report.edges_after as f64 / report.nodes_after.max(1) as f64,
        edges_per_node_max: degree.iter().copied().max().unwrap_or(0),
        arps_percent,
        arps_nodes_at_origin,
        max_shift_m: kept_original
            .iter()
            .zip(&pruned)
            .map(|(a, b)| (a.x - b.x).hypot(a.y - b.y))
            .fold(0.0, f64::max),
        prune_ms,
        optimize_ms,
        full_optimize_ms,
        eliminated: report.eliminated,
        kept_not_eliminable: report.kept_not_eliminable,
        tree_edges_added: report.tree_edges_added,
        tree_edges_merged: report.tree_edges_merged,
        outliers_dropped: report.outliers_dropped,
    };
    let ids = (0..n)
        .filter(|&i| scratch.order()[i] != u32::MAX)
        .map(|i| file.ids[i])
        .collect();
    Ok(Pruned {
        report: json,
        poses: pruned,
        edges: pruned_edges,
        ids,
    })
}

/// The pruned graph as a [`GraphFile`] for the g2o writer, with the original vertex ids.
fn pruned_file(p: &Pruned) -> GraphFile {
    GraphFile {
        ids: p.ids.clone(),
        poses: p.poses.clone(),
        fixed: vec![false; p.poses.len()],
        has_vertices: true,
        edges: p
            .edges
            .iter()
            .map(|e| FileEdge {
                from: e.from.0 as usize,
                to: e.to.0 as usize,
                measurement: e.measurement,
                information: e.information,
            })
            .collect(),
        duplicate_pairs: 0,
    }
}

/// `cloi prune`.
///
/// # Errors
/// See [`prune_file`]; output files that cannot be written.
pub fn run(args: &PruneArgs, out: &mut dyn Write) -> Result<()> {
    if args.online {
        let file = graph_io::read_graph(&args.input, args.format)?;
        let init = if args.odometry_init {
            file.odometry_guess()
        } else {
            file.poses.clone()
        };
        let batch = batch_optimum(&file, &init)?;
        let report = crate::prune_online::run_online(
            &file,
            &batch,
            &crate::prune_online::OnlineSettings {
                pool_nodes: args.pool,
                pool_edges: 4 * args.pool,
                window: args.window,
                cell: args.cell,
                s: args.s,
            },
        )?;
        let text = serde_json::to_string_pretty(&report)?;
        if let Some(path) = &args.report {
            atomic::write_file(path, text.as_bytes())?;
        }
        writeln!(out, "{text}")?;
        return Ok(());
    }
    let pruned = prune_file(args)?;
    let text = serde_json::to_string_pretty(&pruned.report)?;
    if let Some(path) = &args.out {
        let g2o = graph_io::write_g2o(&pruned_file(&pruned), &pruned.poses);
        atomic::write_file(path, g2o.as_bytes())?;
    }
    if let Some(path) = &args.report {
        atomic::write_file(path, text.as_bytes())?;
    }
    writeln!(out, "{text}")?;
    Ok(())
}

/// Prune scratch on the heap for `nodes` nodes and `edges` edges, allocated once (as the
/// pools are) and lent to the core as a [`PruneScratch`].
#[derive(Debug)]
pub struct OwnedPruneScratch {
    node_information: Vec<f64>,
    candidates: Vec<CellCandidate>,
    order: Vec<u32>,
    keys: Vec<CellKey>,
    geometric: Vec<f64>,
    cells: Vec<CellMoments>,
    keep: Vec<bool>,
    head: Vec<u32>,
    edge_alive: Vec<bool>,
    next: Vec<u32>,
}

impl OwnedPruneScratch {
    /// Scratch for a pool of `nodes` nodes and `edges` edges.
    pub fn new(nodes: usize, edges: usize) -> Self {
        OwnedPruneScratch {
            node_information: vec![0.0; nodes],
            candidates: vec![
                CellCandidate {
                    x: 0.0,
                    y: 0.0,
                    information: 0.0,
                    protected: false
                };
                nodes
            ],
            order: vec![0; nodes],
            keys: vec![CellKey::default(); nodes],
            geometric: vec![0.0; nodes],
            cells: vec![CellMoments::EMPTY; nodes],
            keep: vec![false; nodes],
            head: vec![0; nodes],
            edge_alive: vec![false; edges],
            next: vec![0; 2 * edges],
        }
    }

    /// The renumbering of the last pruning (old node index -> new, see [`PruneScratch`]).
    pub fn order(&self) -> &[u32] {
        &self.order
    }

    /// Bytes held by the scratch.
    pub fn bytes(&self) -> usize {
        use std::mem::size_of_val;
        size_of_val(&self.node_information[..])
            + size_of_val(&self.candidates[..])
            + size_of_val(&self.order[..])
            + size_of_val(&self.keys[..])
            + size_of_val(&self.geometric[..])
            + size_of_val(&self.cells[..])
            + size_of_val(&self.keep[..])
            + size_of_val(&self.head[..])
            + size_of_val(&self.edge_alive[..])
            + size_of_val(&self.next[..])
    }

    /// The scratch as the core's slices.
    pub fn scratch(&mut self) -> PruneScratch<'_> {
        PruneScratch {
            node_information: &mut self.node_information,
            candidates: &mut self.candidates,
            order: &mut self.order,
            keys: &mut self.keys,
            geometric: &mut self.geometric,
            cells: &mut self.cells,
            keep: &mut self.keep,
            head: &mut self.head,
            edge_alive: &mut self.edge_alive,
            next: &mut self.next,
        }
    }
}
