//! Pose-graph files: g2o (`VERTEX_SE2` / `EDGE_SE2`) and TORO (`VERTEX2` / `EDGE2`).
//!
//! Both readers produce a [`GraphFile`]: dense node indices (vertex ids sorted), the initial
//! guess, and the edges in file order. Quirks of real files that they accept:
//! * no vertex lines at all: the nodes are the ids the edges name, and the initial guess
//!   chains the odometry edges `i -> i+1` from the origin ([`GraphFile::odometry_guess`]);
//! * the same node pair measured twice: both edges are kept, as g2o does;
//! * angles outside `(-pi, pi]`: wrapped;
//! * subnormal junk such as `1e-320`: flushed to zero;
//! * the two information orders (g2o row-major upper triangle, TORO `I11 I12 I22 I33 I13 I23`);
//! * `#` comments, blank lines, CRLF line ends, `FIX id` lines.
//!
//! Anything else (unknown tags, missing or extra numbers, NaN, a non-positive-definite
//! information, an edge to an unknown vertex, a repeated vertex id) is an error naming the
//! file and the line.

mod g2o;
mod ground_truth;
mod toro;

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use anyhow::{bail, Context, Result};
use cloi_core::geom::{Info3, Se2};
use cloi_core::graph::{EdgeKind, PoseEdge, PoseNode};
use cloi_core::storage::NodeId;

pub use g2o::{read_g2o, write_g2o};
pub use ground_truth::{aligned_rmse, read_ground_truth};
pub use toro::{read_toro, write_toro};

/// The two supported formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum GraphFormat {
    /// g2o text format.
    G2o,
    /// TORO text format.
    Toro,
}

impl GraphFormat {
    /// Guesses the format from the first tag of the file's content (falls back to g2o).
    pub fn sniff(text: &str) -> GraphFormat {
        for line in text.lines() {
            let t = line.trim();
            if t.is_empty() || t.starts_with('#') {
                continue;
            }
            if t.starts_with("VERTEX2") || t.starts_with("EDGE2") {
                return GraphFormat::Toro;
            }
            return GraphFormat::G2o;
        }
        GraphFormat::G2o
    }
}

/// An edge as read from a file.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FileEdge {
    /// Dense index of the first node.
    pub from: usize,
    /// Dense index of the second node.
    pub to: usize,
    /// Measured relative pose (angle wrapped).
    pub measurement: Se2,
    /// Information matrix (symmetric).
    pub information: Info3,
}

impl FileEdge {
    /// Odometry when the nodes are consecutive, else a loop closure.
    pub fn kind(&self) -> EdgeKind {
        if self.from.abs_diff(self.to) == 1 {
            EdgeKind::Odometry
        } else {
            EdgeKind::Loop
        }
    }
}

/// A pose graph read from a file.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GraphFile {
    /// Original vertex id of each dense node index, ascending.
    pub ids: Vec<i64>,
    /// Initial guess per node (from the vertex lines, or chained odometry).
    pub poses: Vec<Se2>,
    /// `FIX` flags per node.
    pub fixed: Vec<bool>,
    /// Whether the file had vertex lines.
    pub has_vertices: bool,
    /// Edges in file order.
    pub edges: Vec<FileEdge>,
    /// Edges whose node pair had already been measured (kept).
    pub duplicate_pairs: usize,
}

/// A parse position, for messages.
pub(crate) struct Where<'a> {
    pub path: &'a Path,
    pub line: usize,
}

impl std::fmt::Display for Where<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}:{}", self.path.display(), self.line)
    }
}

/// Parses one number; subnormals become zero.
pub(crate) fn number(tok: Option<&str>, what: &str, at: &Where<'_>) -> Result<f64> {
    let Some(tok) = tok else {
        bail!("{at}: missing {what}");
    };
    let v: f64 = tok
        .parse()
        .with_context(|| format!("{at}: {what} is not a number: {tok:?}"))?;
    if !v.is_finite() {
        bail!("{at}: {what} is not finite: {tok:?}");
    }
    Ok(if v.abs() < f64::MIN_POSITIVE { 0.0 } else { v })
}

/// Parses one vertex id.
pub(crate) fn vertex_id(tok: Option<&str>, what: &str, at: &Where<'_>) -> Result<i64> {
    let Some(tok) = tok else {
        bail!("{at}: missing {what}");
    };
    tok.parse()
        .with_context(|| format!("{at}: {what} is not an integer: {tok:?}"))
}

/// Checks that a symmetric information matrix is positive definite.
pub(crate) fn check_information(m: &Info3, at: &Where<'_>) -> Result<()> {
    if m.cholesky().is_none() {
        bail!("{at}: information matrix is not positive definite");
    }
    Ok(())
}

/// Raw records collected by a reader before node numbering.
#[derive(Default)]
pub(crate) struct RawGraph {
    pub vertices: BTreeMap<i64, (Se2, usize)>,
    pub fixed: Vec<(i64, usize)>,
    pub edges: Vec<(i64, i64, Se2, Info3, usize)>,
}

impl RawGraph {
    pub fn add_vertex(&mut self, id: i64, pose: Se2, at: &Where<'_>) -> Result<()> {
        if let Some((_, first)) = self.vertices.insert(id, (pose, at.line)) {
            bail!("{at}: vertex {id} already defined on line {first}");
        }
        Ok(())
    }

    /// Numbers the nodes and builds the graph.
    pub fn finish(self, path: &Path) -> Result<GraphFile> {
        let has_vertices = !self.vertices.is_empty();
        let ids: Vec<i64> = if has_vertices {
            self.vertices.keys().copied().collect()
        } else {
            let mut ids: Vec<i64> = self.edges.iter().flat_map(|e| [e.0, e.1]).collect();
            ids.sort_unstable();
            ids.dedup();
            ids
        };
        let index: HashMap<i64, usize> = ids.iter().enumerate().map(|(i, &id)| (id, i)).collect();
        let mut edges = Vec::with_capacity(self.edges.len());
        let mut seen = std::collections::HashSet::new();
        let mut duplicate_pairs = 0;
        for (a, b, z, info, line) in self.edges {
            let at = Where { path, line };
            let (Some(&from), Some(&to)) = (index.get(&a), index.get(&b)) else {
                let missing = if index.contains_key(&a) { b } else { a };
                bail!("{at}: edge refers to vertex {missing}, which the file does not define");
            };
            if from == to {
                bail!("{at}: edge joins vertex {a} to itself");
            }
            if !seen.insert((from.min(to), from.max(to))) {
                duplicate_pairs += 1;
            }
            edges.push(FileEdge {
                from,
                to,
                measurement: z,
                information: info,
            });
        }
        let mut fixed = vec![false; ids.len()];
        for (id, line) in self.fixed {
            let Some(&i) = index.get(&id) else {
                bail!("{}:{line}: FIX names unknown vertex {id}", path.display());
            };
            fixed[i] = true;
        }
        let mut g = GraphFile {
            poses: if has_vertices {
                self.vertices.values().map(|(p, _)| *p).collect()
            } else {
                Vec::new()
            },
            ids,
            fixed,
            has_vertices,
            edges,
            duplicate_pairs,
        };
        if !has_vertices {
            g.poses = g.odometry_guess();
        }
        Ok(g)
    }
}

impl GraphFile {
    /// Number of nodes.
    pub fn node_count(&self) -> usize {
        self.ids.len()
    }

    /// The initial guess that chains odometry from the origin: node 0 at the origin, node
    /// `k+1` at node `k` composed with the edge `k -> k+1` (or the inverse of `k+1 -> k`).
    /// A node without such an edge is reached through any edge from an already placed node
    /// (breadth first); a node not connected at all stays at the previous node's pose.
    pub fn odometry_guess(&self) -> Vec<Se2> {
        let n = self.node_count();
        let mut next: Vec<Option<Se2>> = vec![None; n];
        let mut adj: Vec<Vec<(usize, Se2)>> = vec![Vec::new(); n];
        for e in &self.edges {
            if e.to == e.from + 1 && next[e.from].is_none() {
                next[e.from] = Some(e.measurement);
            } else if e.from == e.to + 1 && next[e.to].is_none() {
                next[e.to] = Some(e.measurement.inverse());
            }
            adj[e.from].push((e.to, e.measurement));
            adj[e.to].push((e.from, e.measurement.inverse()));
        }
        let mut poses: Vec<Option<Se2>> = vec![None; n];
        if n == 0 {
            return Vec::new();
        }
        poses[0] = Some(Se2::IDENTITY);
        for k in 0..n.saturating_sub(1) {
            if let (Some(p), Some(z)) = (poses[k], next[k]) {
                poses[k + 1] = Some(p.compose(&z));
            } else if poses[k + 1].is_none() {
                // Breadth-first from everything placed so far.
                let mut queue: std::collections::VecDeque<usize> =
                    (0..n).filter(|&i| poses[i].is_some()).collect();
                while let Some(i) = queue.pop_front() {
                    let Some(p) = poses[i] else { continue };
                    for &(j, z) in &adj[i] {
                        if poses[j].is_none() {
                            poses[j] = Some(p.compose(&z));
                            queue.push_back(j);
                        }
                    }
                }
                if poses[k + 1].is_none() {
                    poses[k + 1] = poses[k];
                }
            }
        }
        poses.into_iter().map(|p| p.unwrap_or_default()).collect()
    }

    /// The core's node records at the given poses.
    pub fn pose_nodes(&self, poses: &[Se2]) -> Vec<PoseNode> {
        poses
            .iter()
            .zip(&self.fixed)
            .map(|(p, &fixed)| PoseNode { pose: *p, fixed })
            .collect()
    }

    /// The core's edge records (robust model `None`).
    pub fn pose_edges(&self) -> Vec<PoseEdge> {
        self.edges
            .iter()
            .map(|e| {
                PoseEdge::new(
                    NodeId(e.from as u32),
                    NodeId(e.to as u32),
                    e.measurement,
                    e.information,
                    e.kind(),
                )
            })
            .collect()
    }
}

/// Reads a graph in the given format, or the sniffed one.
///
/// # Errors
/// The file cannot be read, or a line is malformed (the message names file and line).
pub fn read_graph(path: &Path, format: Option<GraphFormat>) -> Result<GraphFile> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    match format.unwrap_or_else(|| GraphFormat::sniff(&text)) {
        GraphFormat::G2o => read_g2o(&text, path),
        GraphFormat::Toro => read_toro(&text, path),
    }
}

#[cfg(test)]
mod tests;
