//! `cloi prune --online`: the back-end as the mapper runs it. A pose graph file is streamed
//! node by node into a pose graph of fixed capacity (the pool), smaller than the file; every
//! window of new nodes is optimized, and when the pool is nearly full the old part of the
//! graph is pruned to one node per cell (the newest window stays protected). Memory is the
//! pool, whatever the length of the stream.
//!
//! A new node starts at its predecessor's current estimate composed with the odometry between
//! them (the temporal node's mean, the paper's eq. 8). An edge that reaches back to a node that
//! has been eliminated is re-attached to the kept node that took over its cell (or the nearest
//! kept node), with its measurement composed through the relative pose between the two at
//! elimination time; its information is kept as is. This bookkeeping (one small record per
//! streamed node) belongs to the test harness: the mapper itself closes loops against kept
//! nodes and submaps only.

use std::collections::BTreeMap;
use std::time::Instant;

use anyhow::{bail, Result};
use cloi_core::backend::cells::{CellKey, CellParams};
use cloi_core::backend::prune::{self, PruneParams};
use cloi_core::geom::Se2;
use cloi_core::graph::{EdgeKind, PoseEdge, PoseGraph, PoseNode};
use cloi_core::solver::{Method, SolveError, SolverOptions};
use cloi_core::storage::NodeId;
use serde::Serialize;

use crate::graph_io::GraphFile;
use crate::optimize::HostWorkspace;
use crate::prune::OwnedPruneScratch;

/// Settings of an online run.
#[derive(Clone, Copy, Debug)]
pub struct OnlineSettings {
    /// Node capacity of the pool.
    pub pool_nodes: usize,
    /// Edge capacity of the pool.
    pub pool_edges: usize,
    /// Nodes per window (optimized together).
    pub window: usize,
    /// Cell size, metres.
    pub cell: f64,
    /// Share of the information term.
    pub s: f64,
}

/// What an online run did.
#[derive(Clone, Debug, Serialize)]
pub struct OnlineReport {
    /// Nodes streamed.
    pub nodes_streamed: usize,
    /// Edges streamed.
    pub edges_streamed: usize,
    /// Node capacity of the pool.
    pub pool_nodes: usize,
    /// Edge capacity of the pool.
    pub pool_edges: usize,
    /// Most nodes held at once.
    pub peak_nodes: usize,
    /// Most edges held at once.
    pub peak_edges: usize,
    /// Pruning passes.
    pub prunes: usize,
    /// Window optimizations.
    pub optimizations: usize,
    /// Window optimizations that stopped at their iteration limit.
    pub unsettled_windows: usize,
    /// Edges dropped because both ends had merged into one kept node.
    pub edges_collapsed: usize,
    /// Nodes at the end.
    pub nodes_final: usize,
    /// Edges at the end.
    pub edges_final: usize,
    /// ARPS of the kept nodes against the batch optimum of the whole file, percent.
    pub arps_vs_batch_percent: f64,
    /// Largest position difference of a kept node from the batch optimum, metres.
    pub max_shift_vs_batch_m: f64,
    /// Wall time of the whole stream (optimizations and pruning), milliseconds.
    pub total_ms: f64,
}

/// Where a streamed node lives now: graph node `node`, at `rel` from it.
#[derive(Clone, Copy, Debug)]
struct Anchor {
    node: u32,
    rel: Se2,
}

/// Streams `file` through a pool and compares the result with `batch` (the batch optimum of
/// the whole file, one pose per file node).
///
/// # Errors
/// The pool is too small for one window plus what pruning keeps, or a solve fails.
pub fn run_online(file: &GraphFile, batch: &[Se2], cfg: &OnlineSettings) -> Result<OnlineReport> {
    let n = file.poses.len();
    if cfg.window == 0 || cfg.pool_nodes < 2 * cfg.window {
        bail!(
            "the pool ({} nodes) must hold at least two windows of {}",
            cfg.pool_nodes,
            cfg.window
        );
    }
    // Edges become available when their newer node arrives.
    let mut by_node: Vec<Vec<usize>> = vec![Vec::new(); n];
    for (k, e) in file.edges.iter().enumerate() {
        by_node[e.from.max(e.to)].push(k);
    }
    let mut node_store = vec![PoseNode::EMPTY; cfg.pool_nodes];
    let mut edge_store = vec![PoseEdge::EMPTY; cfg.pool_edges];
    let mut g = PoseGraph::new(&mut node_store, &mut edge_store);
    let mut anchors: Vec<Option<Anchor>> = vec![None; n];
    let mut file_of: Vec<usize> = Vec::with_capacity(cfg.pool_nodes);
    let mut ws = HostWorkspace::new(cfg.pool_nodes, cfg.pool_edges, 16 * cfg.pool_nodes + 1024);
    let options = SolverOptions {
        method: Method::GaussNewton,
        max_iterations: 30,
        ..SolverOptions::default()
    };
    let mut report = OnlineReport {
        nodes_streamed: n,
        edges_streamed: file.edges.len(),
        pool_nodes: cfg.pool_nodes,
        pool_edges: cfg.pool_edges,
        peak_nodes: 0,
        peak_edges: 0,
        prunes: 0,
        optimizations: 0,
        unsettled_windows: 0,
        edges_collapsed: 0,
        nodes_final: 0,
        edges_final: 0,
        arps_vs_batch_percent: 0.0,
        max_shift_vs_batch_m: 0.0,
        total_ms: 0.0,
    };
    let mut scratch = OwnedPruneScratch::new(cfg.pool_nodes, cfg.pool_edges);
    let params = PruneParams {
        cells: CellParams {
            cell_size: cfg.cell,
            s: cfg.s,
        },
        ..PruneParams::default()
    };
    let t0 = Instant::now();
    let mut in_window = 0usize;
    for i in 0..n {
        // Make room first: prune everything but the newest window.
        if g.node_count() + 1 > cfg.pool_nodes || g.edge_count() + 8 * cfg.window > cfg.pool_edges {
            let protect_from = g.node_count().saturating_sub(cfg.window);
            prune_pool(
                &mut g,
                &params,
                protect_from,
                &mut scratch,
                &mut anchors,
                &mut file_of,
            )?;
            report.prunes += 1;
            ws = HostWorkspace::new(cfg.pool_nodes, cfg.pool_edges, 16 * cfg.pool_nodes + 1024);
            if g.node_count() + 1 > cfg.pool_nodes
                || g.edge_count() + 8 * cfg.window > cfg.pool_edges
            {
                bail!(
                    "pool exhausted at node {i}: pruning left {} nodes and {} edges (the area mapped needs \
                     more cells than the pool holds: raise --pool or --cell)",
                    g.node_count(),
                    g.edge_count()
                );
            }
        }
        // Initial guess: predecessor's estimate composed with the odometry to this node.
        let guess = initial_guess(file, i, &g, &anchors, &by_node);
        let id = g.add_node(guess)?;
        anchors[i] = Some(Anchor {
            node: id.0,
            rel: Se2::IDENTITY,
        });
        file_of.push(i);
        for &k in &by_node[i] {
            let e = &file.edges[k];
            let (Some(a), Some(b)) = (anchors[e.from], anchors[e.to]) else {
                continue;
            };
            if a.node == b.node {
                report.edges_collapsed += 1;
                continue;
            }
            // x_from = x_a (+) ra, x_to = x_b (+) rb  =>  x_a^-1 x_b = ra (+) z (+) rb^-1.
            let z = a.rel.compose(&e.measurement).compose(&b.rel.inverse());
            let kind = if e.from.abs_diff(e.to) == 1 {
                EdgeKind::Odometry
            } else {
                EdgeKind::Loop
            };
            g.add_edge(PoseEdge::new(
                NodeId(a.node),
                NodeId(b.node),
                z,
                e.information,
                kind,
            ))?;
        }
        report.peak_nodes = report.peak_nodes.max(g.node_count());
        report.peak_edges = report.peak_edges.max(g.edge_count());
        in_window += 1;
        if in_window == cfg.window || i + 1 == n {
            in_window = 0;
            match ws.solve(&mut g, &options) {
                Ok(_) => {}
                // The estimate improved but did not settle within the window's iterations: the
                // next window goes on from it.
                Err(f) if f.error == SolveError::MaxIterations => report.unsettled_windows += 1,
                Err(f) => bail!("window ending at node {i}: {f}"),
            }
            report.optimizations += 1;
        }
    }
    report.total_ms = t0.elapsed().as_secs_f64() * 1e3;
    report.nodes_final = g.node_count();
    report.edges_final = g.edge_count();
    let mut sum = 0.0;
    let mut used = 0usize;
    for (node, &f) in g.nodes().iter().zip(&file_of) {
        let (Some(b), p) = (batch.get(f), node.pose) else {
            continue;
        };
        let d = (b.x - p.x).hypot(b.y - p.y);
        report.max_shift_vs_batch_m = report.max_shift_vs_batch_m.max(d);
        let norm = b.x.hypot(b.y);
        if norm >= 1e-3 {
            sum += d / norm;
            used += 1;
        }
    }
    report.arps_vs_batch_percent = if used > 0 {
        100.0 * sum / used as f64
    } else {
        0.0
    };
    Ok(report)
}

fn initial_guess(
    file: &GraphFile,
    i: usize,
    g: &PoseGraph<'_>,
    anchors: &[Option<Anchor>],
    by_node: &[Vec<usize>],
) -> Se2 {
    let pose_of = |a: Anchor| g.node(NodeId(a.node)).map(|p| p.pose.compose(&a.rel));
    for &k in &by_node[i] {
        let e = &file.edges[k];
        if e.to == i && e.from + 1 == i {
            if let Some(p) = anchors[e.from].and_then(pose_of) {
                return p.compose(&e.measurement);
            }
        }
    }
    i.checked_sub(1)
        .and_then(|p| anchors[p])
        .and_then(pose_of)
        .unwrap_or(file.poses[i])
}

/// Prunes the pool and re-anchors the streamed nodes of every eliminated graph node.
fn prune_pool(
    g: &mut PoseGraph<'_>,
    params: &PruneParams,
    protect_from: usize,
    s: &mut OwnedPruneScratch,
    anchors: &mut [Option<Anchor>],
    file_of: &mut Vec<usize>,
) -> Result<()> {
    let before: Vec<Se2> = g.nodes().iter().map(|p| p.pose).collect();
    let params = PruneParams {
        protect_from,
        ..*params
    };
    prune::prune(g, &params, &mut s.scratch())?;
    let remap = &s.order()[..before.len()];
    // Kept nodes by cell, for re-anchoring.
    let mut by_cell: BTreeMap<CellKey, u32> = BTreeMap::new();
    for (old, &new) in remap.iter().enumerate() {
        if new != u32::MAX {
            by_cell
                .entry(CellKey::of(
                    before[old].x,
                    before[old].y,
                    params.cells.cell_size,
                ))
                .or_insert(new);
        }
    }
    let kept: Vec<(u32, Se2)> = remap
        .iter()
        .enumerate()
        .filter(|(_, &n)| n != u32::MAX)
        .map(|(o, &n)| (n, before[o]))
        .collect();
    // New home of every old graph node: itself, or a kept node nearby.
    let home: Vec<(u32, Se2)> = (0..before.len())
        .map(|old| {
            let p = before[old];
            if remap[old] != u32::MAX {
                return (remap[old], Se2::IDENTITY);
            }
            let key = CellKey::of(p.x, p.y, params.cells.cell_size);
            let target = by_cell.get(&key).copied().or_else(|| {
                kept.iter()
                    .min_by(|a, b| {
                        let da = (a.1.x - p.x).hypot(a.1.y - p.y);
                        let db = (b.1.x - p.x).hypot(b.1.y - p.y);
                        da.total_cmp(&db)
                    })
                    .map(|k| k.0)
            });
            match target {
                Some(t) => {
                    let tp = kept.iter().find(|k| k.0 == t).map(|k| k.1).unwrap_or(p);
                    (t, tp.between(&p))
                }
                None => (u32::MAX, Se2::IDENTITY),
            }
        })
        .collect();
    for a in anchors.iter_mut().flatten() {
        if let Some(&(node, rel)) = home.get(a.node as usize) {
            a.node = node;
            a.rel = rel.compose(&a.rel);
        }
    }
    let mut new_file_of = vec![0usize; g.node_count()];
    for (old, &new) in remap.iter().enumerate() {
        if new != u32::MAX {
            new_file_of[new as usize] = file_of[old];
        }
    }
    *file_of = new_file_of;
    Ok(())
}
