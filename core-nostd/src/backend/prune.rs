//! Batch pruning of a pose graph (the paper's section III-D.2): pick one node per grid cell,
//! marginalize every other node into its Markov blanket, and sparsify each dense result into a
//! Chow-Liu tree of relative-pose edges.
//!
//! The graph is pruned in place. Elimination goes node by node in index order; each one
//! linearizes its live edges at the current estimate (robust edges with the weight their model
//! gives now, max-mixture edges with their active component, and an edge whose null hypothesis
//! is active is dropped as an outlier), replaces them by the tree edges, and merges a tree edge
//! into an existing plain edge between the same two nodes (information added, measurement the
//! information-weighted mean), which keeps the graph near the paper's three edges per node.
//! Nodes that cannot be eliminated (a blanket beyond [`MAX_BLANKET`], a singular marginal) are
//! kept and counted. Protected nodes (fixed, with a prior, the first node when it holds the
//! gauge, or any the caller names) are never eliminated.
//!
//! Pruning is meant for an optimized graph: tree edges measure the current estimate, so the
//! pruned graph's optimum stays where the full graph's was.
//!
//! Memory: the caller lends a [`PruneScratch`] (per node and per edge arrays, see
//! [`PruneStorage`]); the graph needs some free edge slots for the new edges (when it runs out,
//! dead edges are compacted away and pruning goes on).

use heapless::Vec;
use nalgebra::Matrix3;

use super::cells::{self, CellCandidate, CellKey, CellMoments, CellParams, CellScratch, CellStats};
use super::marginalize::{chow_liu_edges, marginalize, LocalFactor, MAX_BLANKET};
use crate::geom::{spd_inverse, symmetrize, Info3, Se2};
use crate::graph::{EdgeKind, PoseEdge, PoseGraph, RobustKernel};
use crate::storage::NodeId;

const NONE: u32 = u32::MAX;

/// How the information term of a node's weight is computed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Weighting {
    /// Eq. (4): the sum of the information of the node's edges (cheap).
    EdgeInformation,
    /// Eq. (3): the trace of the node's marginal information, supplied by the caller in
    /// [`PruneScratch::node_information`] (see `solver::marginal_information_traces`).
    NodeInformation,
}

/// Parameters of [`prune`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PruneParams {
    /// Cell size and the share `s` of the information term.
    pub cells: CellParams,
    /// Which information term.
    pub weighting: Weighting,
    /// Nodes with an index at or above this are protected (the current window); `usize::MAX`
    /// protects none.
    pub protect_from: usize,
    /// A max-mixture edge whose active component scales the information below this is treated
    /// as an outlier and dropped when an endpoint is eliminated.
    pub outlier_scale: f64,
    /// Most nodes eliminated in this call (a work budget; the rest of the cell rule's choice is
    /// kept for a later call). `usize::MAX` for no limit.
    pub max_eliminations: usize,
}

impl Default for PruneParams {
    fn default() -> Self {
        PruneParams {
            cells: CellParams::default(),
            weighting: Weighting::EdgeInformation,
            protect_from: usize::MAX,
            outlier_scale: 0.5,
            max_eliminations: usize::MAX,
        }
    }
}

/// What [`prune`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PruneReport {
    /// Nodes before.
    pub nodes_before: usize,
    /// Edges before.
    pub edges_before: usize,
    /// Nodes after.
    pub nodes_after: usize,
    /// Edges after.
    pub edges_after: usize,
    /// Occupied cells.
    pub cells: usize,
    /// Nodes eliminated.
    pub eliminated: usize,
    /// Nodes the cell rule would drop but that were kept (blanket too large or singular).
    pub kept_not_eliminable: usize,
    /// Cells whose representative became a node that could not be eliminated (the winner was
    /// eliminated in its place).
    pub swapped_representatives: usize,
    /// Tree edges added as new edges.
    pub tree_edges_added: usize,
    /// Tree edges merged into an existing edge.
    pub tree_edges_merged: usize,
    /// Outlier (null-hypothesis) edges dropped.
    pub outliers_dropped: usize,
    /// Statistics of the cell selection.
    pub cell_stats: CellStats,
}

/// Why pruning could not run (the graph is unchanged).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum PruneError {
    /// The scratch is smaller than the graph's capacity.
    ScratchTooSmall,
    /// Cell parameters out of range.
    BadParams,
}

impl core::fmt::Display for PruneError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            PruneError::ScratchTooSmall => "pruning scratch smaller than the graph's capacity",
            PruneError::BadParams => "cell size must be positive and s within 0..=1",
        })
    }
}

impl core::error::Error for PruneError {}

/// Borrowed scratch of [`prune`]: per-node arrays at least as long as the graph's node
/// capacity, per-edge arrays at least its edge capacity.
#[derive(Debug)]
pub struct PruneScratch<'a> {
    /// Per node: the information term for [`Weighting::NodeInformation`] (input); otherwise
    /// overwritten.
    pub node_information: &'a mut [f64],
    /// Per node: cell candidates.
    pub candidates: &'a mut [CellCandidate],
    /// Per node: index scratch / renumbering.
    pub order: &'a mut [u32],
    /// Per node: cell keys.
    pub keys: &'a mut [CellKey],
    /// Per node: geometric terms.
    pub geometric: &'a mut [f64],
    /// Per node: cell moments.
    pub cells: &'a mut [CellMoments],
    /// Per node: survives.
    pub keep: &'a mut [bool],
    /// Per node: head of its incidence list.
    pub head: &'a mut [u32],
    /// Per edge: alive.
    pub edge_alive: &'a mut [bool],
    /// Per edge end (two per edge): next entry of the incidence list.
    pub next: &'a mut [u32],
}

/// Owned storage for a [`PruneScratch`] of `N` nodes and `E` edges.
#[derive(Debug)]
pub struct PruneStorage<const N: usize, const E: usize> {
    node_information: [f64; N],
    candidates: [CellCandidate; N],
    order: [u32; N],
    keys: [CellKey; N],
    geometric: [f64; N],
    cells: [CellMoments; N],
    keep: [bool; N],
    head: [u32; N],
    edge_alive: [bool; E],
    next: [[u32; 2]; E],
}

impl<const N: usize, const E: usize> PruneStorage<N, E> {
    /// Zeroed storage, usable as a `static` initialiser.
    pub const fn new() -> Self {
        PruneStorage {
            node_information: [0.0; N],
            candidates: [CellCandidate {
                x: 0.0,
                y: 0.0,
                information: 0.0,
                protected: false,
            }; N],
            order: [0; N],
            keys: [CellKey { ix: 0, iy: 0 }; N],
            geometric: [0.0; N],
            cells: [CellMoments::EMPTY; N],
            keep: [false; N],
            head: [0; N],
            edge_alive: [false; E],
            next: [[0; 2]; E],
        }
    }

    /// The scratch view.
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
            next: self.next.as_flattened_mut(),
        }
    }
}

impl<const N: usize, const E: usize> Default for PruneStorage<N, E> {
    fn default() -> Self {
        Self::new()
    }
}

/// Scalar information of an edge, eq. (1) applied to its covariance: the Frobenius norm of its
/// information matrix.
pub fn edge_information(edge: &PoseEdge) -> f64 {
    edge.information.norm()
}

/// Information of the reversed relation `z^-1` in the g2o error convention: with
/// `e' = -Adj(z) e`, `Omega' = Adj^-T Omega Adj^-1`.
pub fn reversed_information(z: &Se2, information: &Info3) -> Info3 {
    let (c, s) = (libm::cos(z.theta), libm::sin(z.theta));
    // Adj(z) = [R  [y, -x]^T; 0 1]; its inverse is [R^T  -R^T [y, -x]^T; 0 1].
    let (ty, tx) = (z.y, -z.x);
    let inv = Matrix3::new(
        c,
        s,
        -(c * ty + s * tx),
        -s,
        c,
        -(-s * ty + c * tx),
        0.0,
        0.0,
        1.0,
    );
    symmetrize(&(inv.transpose() * information * inv))
}

fn protected(graph: &PoseGraph<'_>, params: &PruneParams, keep: &mut [bool]) {
    let n = graph.node_count();
    let mut has_prior = false;
    for (i, node) in graph.nodes().iter().enumerate() {
        if let Some(k) = keep.get_mut(i) {
            *k = node.fixed || i >= params.protect_from;
        }
    }
    for e in graph.edges() {
        if e.kind == EdgeKind::Prior {
            has_prior = true;
            if let Some(k) = keep.get_mut(e.from.0 as usize) {
                *k = true;
            }
        }
    }
    // Without a prior the solver holds the first node fixed: it must stay.
    if !has_prior && n > 0 {
        if let Some(k) = keep.get_mut(0) {
            *k = true;
        }
    }
}

/// Rebuilds the incidence lists of live edges.
fn build_incidence(graph: &PoseGraph<'_>, s: &mut PruneScratch<'_>) {
    for h in s.head.iter_mut() {
        *h = NONE;
    }
    for (k, e) in graph.edges().iter().enumerate() {
        if !s.edge_alive.get(k).copied().unwrap_or(false) || e.kind == EdgeKind::Prior {
            continue;
        }
        for (side, node) in [e.from, e.to].into_iter().enumerate() {
            let slot = 2 * k + side;
            if let (Some(h), Some(nx)) =
                (s.head.get(node.0 as usize).copied(), s.next.get_mut(slot))
            {
                *nx = h;
                if let Some(hh) = s.head.get_mut(node.0 as usize) {
                    *hh = slot as u32;
                }
            }
        }
    }
}

/// Live non-prior edges touching `node`: their indices, at most `N`.
fn incident<const N: usize>(
    node: usize,
    graph: &PoseGraph<'_>,
    s: &PruneScratch<'_>,
) -> Option<Vec<u32, N>> {
    let mut out = Vec::new();
    let mut slot = s.head.get(node).copied().unwrap_or(NONE);
    while slot != NONE {
        let k = slot / 2;
        if s.edge_alive.get(k as usize).copied().unwrap_or(false)
            && graph
                .edges()
                .get(k as usize)
                .is_some_and(|e| e.kind != EdgeKind::Prior)
        {
            out.push(k).ok()?;
        }
        slot = s.next.get(slot as usize).copied().unwrap_or(NONE);
    }
    Some(out)
}

/// Compacts dead edges out of the graph (nodes untouched) and rebuilds the incidence lists.
fn compact_edges(graph: &mut PoseGraph<'_>, s: &mut PruneScratch<'_>) {
    let m = graph.edge_count();
    let mut write = 0usize;
    {
        let edges = graph.edges_mut();
        for k in 0..m {
            if s.edge_alive.get(k).copied().unwrap_or(false) {
                if let (Some(e), true) = (edges.get(k).copied(), write < edges.len()) {
                    if let Some(slot) = edges.get_mut(write) {
                        *slot = e;
                    }
                    write += 1;
                }
            }
        }
    }
    graph.truncate_edges(write);
    for (k, a) in s.edge_alive.iter_mut().enumerate() {
        *a = k < write;
    }
    build_incidence(graph, s);
}

/// Adds a new edge, compacting dead edges first when the graph is full.
fn push_edge(graph: &mut PoseGraph<'_>, s: &mut PruneScratch<'_>, edge: PoseEdge) -> bool {
    if graph.edge_count() >= graph.edge_capacity() {
        compact_edges(graph, s);
    }
    let Ok(id) = graph.add_edge(edge) else {
        return false;
    };
    let k = id.0 as usize;
    if let Some(a) = s.edge_alive.get_mut(k) {
        *a = true;
    }
    for (side, node) in [edge.from, edge.to].into_iter().enumerate() {
        let slot = 2 * k + side;
        if let (Some(h), Some(nx)) = (s.head.get(node.0 as usize).copied(), s.next.get_mut(slot)) {
            *nx = h;
            if let Some(hh) = s.head.get_mut(node.0 as usize) {
                *hh = slot as u32;
            }
        }
    }
    true
}

/// The information an edge contributes at the current estimate, or `None` for an outlier.
fn effective_information(edge: &PoseEdge, xi: &Se2, xj: &Se2, outlier_scale: f64) -> Option<Info3> {
    if edge.robust == RobustKernel::None {
        return Some(edge.information);
    }
    let chi2 = edge.chi2_of(&edge.residual(xi, xj));
    let (w, _) = edge.robust.weigh(chi2);
    if matches!(edge.robust, RobustKernel::MaxMixture { .. }) && w < outlier_scale {
        return None;
    }
    Some(edge.information * w)
}

fn pose_of(graph: &PoseGraph<'_>, id: NodeId) -> Se2 {
    graph.node(id).map(|n| n.pose).unwrap_or(Se2::IDENTITY)
}

/// Blanket-size limits of the elimination passes.
const ELIMINATION_PASSES: [usize; 5] = [2, 3, 4, 6, MAX_BLANKET];

/// Number of distinct neighbours of `node` over live edges; `None` beyond [`MAX_BLANKET`].
fn blanket_size(node: usize, graph: &PoseGraph<'_>, s: &PruneScratch<'_>) -> Option<usize> {
    let mut seen: Vec<NodeId, MAX_BLANKET> = Vec::new();
    let mut slot = s.head.get(node).copied().unwrap_or(NONE);
    while slot != NONE {
        let k = (slot / 2) as usize;
        if s.edge_alive.get(k).copied().unwrap_or(false) {
            if let Some(e) = graph.edges().get(k) {
                let other = if e.from.0 as usize == node {
                    e.to
                } else {
                    e.from
                };
                if e.kind != EdgeKind::Prior && !seen.contains(&other) {
                    seen.push(other).ok()?;
                }
            }
        }
        slot = s.next.get(slot as usize).copied().unwrap_or(NONE);
    }
    Some(seen.len())
}

/// Tries to eliminate `m`; returns `false` (graph unchanged) when it cannot.
fn eliminate(
    m: usize,
    graph: &mut PoseGraph<'_>,
    s: &mut PruneScratch<'_>,
    params: &PruneParams,
    report: &mut PruneReport,
) -> bool {
    const MAX_INCIDENT: usize = 32;
    let Some(edges) = incident::<MAX_INCIDENT>(m, graph, s) else {
        return false;
    };
    let mut blanket: Vec<NodeId, MAX_BLANKET> = Vec::new();
    let mut poses: Vec<Se2, { MAX_BLANKET + 1 }> = Vec::new();
    let _ = poses.push(pose_of(graph, NodeId(m as u32)));
    let mut factors: Vec<LocalFactor, MAX_INCIDENT> = Vec::new();
    let mut outliers = 0;
    for &k in &edges {
        let Some(e) = graph.edges().get(k as usize).copied() else {
            return false;
        };
        let other = if e.from.0 as usize == m { e.to } else { e.from };
        let local = match blanket.iter().position(|b| *b == other) {
            Some(p) => p + 1,
            None => {
                if blanket.push(other).is_err() || poses.push(pose_of(graph, other)).is_err() {
                    return false;
                }
                blanket.len()
            }
        };
        let (xi, xj) = (pose_of(graph, e.from), pose_of(graph, e.to));
        let Some(info) = effective_information(&e, &xi, &xj, params.outlier_scale) else {
            outliers += 1;
            continue;
        };
        let (from, to) = if e.from.0 as usize == m {
            (0, local)
        } else {
            (local, 0)
        };
        if factors
            .push(LocalFactor {
                from: from as u8,
                to: to as u8,
                measurement: e.measurement,
                information: info,
            })
            .is_err()
        {
            return false;
        }
    }
    let tree = if factors.is_empty() {
        Vec::new()
    } else {
        let Ok(marginal) = marginalize(&poses, &factors) else {
            return false;
        };
        let Ok(tree) = chow_liu_edges(poses.get(1..).unwrap_or(&[]), &marginal) else {
            return false;
        };
        tree
    };
    // Commit: kill the node's edges, then add or merge the tree edges.
    for &k in &edges {
        if let Some(a) = s.edge_alive.get_mut(k as usize) {
            *a = false;
        }
    }
    report.outliers_dropped += outliers;
    for t in tree {
        let (Some(&a), Some(&b)) = (
            blanket.get(usize::from(t.from)),
            blanket.get(usize::from(t.to)),
        ) else {
            continue;
        };
        if merge_into_existing(a, b, &t.measurement, &t.information, graph, s) {
            report.tree_edges_merged += 1;
        } else if push_edge(
            graph,
            s,
            PoseEdge::new(a, b, t.measurement, t.information, EdgeKind::Odometry),
        ) {
            report.tree_edges_added += 1;
        }
    }
    true
}

/// Adds the tree edge's information to a live plain edge between `a` and `b`, if there is one.
fn merge_into_existing(
    a: NodeId,
    b: NodeId,
    measurement: &Se2,
    information: &Info3,
    graph: &mut PoseGraph<'_>,
    s: &mut PruneScratch<'_>,
) -> bool {
    let Some(edges) = incident::<64>(a.0 as usize, graph, s) else {
        return false;
    };
    for k in edges {
        let Some(e) = graph.edges().get(k as usize).copied() else {
            continue;
        };
        if e.robust != RobustKernel::None
            || !((e.from == a && e.to == b) || (e.from == b && e.to == a))
        {
            continue;
        }
        // The tree edge in the existing edge's direction.
        let (zt, ot) = if e.from == a {
            (*measurement, *information)
        } else {
            (
                measurement.inverse(),
                reversed_information(measurement, information),
            )
        };
        // Information-weighted mean of the two measurements, in the tangent space at `zt`.
        let combined = symmetrize(&(e.information + ot));
        let Some(cov) = spd_inverse(&combined) else {
            return false;
        };
        let d_old = zt.inverse().compose(&e.measurement).to_vector();
        let d = cov * (e.information * d_old);
        if let Some(slot) = graph.edges_mut().get_mut(k as usize) {
            slot.measurement = zt.compose(&Se2::from_vector(&d));
            slot.information = combined;
        }
        return true;
    }
    false
}

/// Prunes `graph` in place. See the module documentation.
///
/// # Errors
/// [`PruneError`]; the graph is then unchanged.
pub fn prune(
    graph: &mut PoseGraph<'_>,
    params: &PruneParams,
    s: &mut PruneScratch<'_>,
) -> Result<PruneReport, PruneError> {
    let (n, m) = (graph.node_count(), graph.edge_count());
    let (nc, ec) = (graph.node_capacity(), graph.edge_capacity());
    if s.node_information.len() < nc
        || s.candidates.len() < nc
        || s.order.len() < nc
        || s.keys.len() < nc
        || s.geometric.len() < nc
        || s.cells.len() < nc
        || s.keep.len() < nc
        || s.head.len() < nc
        || s.edge_alive.len() < ec
        || s.next.len() < 2 * ec
    {
        return Err(PruneError::ScratchTooSmall);
    }
    let mut report = PruneReport {
        nodes_before: n,
        edges_before: m,
        ..PruneReport::default()
    };

    // 1. Weights and the cell selection.
    if params.weighting == Weighting::EdgeInformation {
        for v in s.node_information.iter_mut().take(n) {
            *v = 0.0;
        }
        for e in graph.edges() {
            let w = edge_information(e);
            for id in [e.from, e.to] {
                if let Some(v) = s.node_information.get_mut(id.0 as usize) {
                    *v += w;
                }
            }
        }
    }
    protected(graph, params, s.keep);
    for (i, node) in graph.nodes().iter().enumerate() {
        if let Some(c) = s.candidates.get_mut(i) {
            *c = CellCandidate {
                x: node.pose.x,
                y: node.pose.y,
                information: s.node_information.get(i).copied().unwrap_or(0.0),
                protected: s.keep.get(i).copied().unwrap_or(false),
            };
        }
    }
    let stats = cells::select(
        s.candidates.get(..n).unwrap_or(&[]),
        &params.cells,
        &mut CellScratch {
            order: s.order,
            keys: s.keys,
            geometric: s.geometric,
            cells: s.cells,
        },
        s.keep,
    )
    .map_err(|e| match e {
        cells::CellError::ScratchTooSmall => PruneError::ScratchTooSmall,
        cells::CellError::BadParams => PruneError::BadParams,
    })?;
    report.cells = stats.cells;
    report.cell_stats = stats;

    // 2. Eliminate, in passes of growing blanket size: a cheap minimum-degree order that
    // keeps fill-in (and so blanket sizes and edge counts) low. Until compaction `order` marks
    // the nodes already eliminated.
    for (k, a) in s.edge_alive.iter_mut().enumerate() {
        *a = k < m;
    }
    build_incidence(graph, s);
    for o in s.order.iter_mut().take(n) {
        *o = 0;
    }
    for limit in ELIMINATION_PASSES {
        for i in 0..n {
            if s.keep.get(i).copied().unwrap_or(true) || s.order.get(i).copied().unwrap_or(1) != 0 {
                continue;
            }
            if report.eliminated >= params.max_eliminations {
                break;
            }
            if blanket_size(i, graph, s).is_none_or(|b| b > limit) {
                continue;
            }
            if eliminate(i, graph, s, params, &mut report) {
                report.eliminated += 1;
                if let Some(o) = s.order.get_mut(i) {
                    *o = 1;
                }
            }
        }
    }
    // A node that cannot be eliminated (its blanket is too large) becomes its cell's
    // representative instead of the winner, when the winner itself can go: still one node per
    // cell.
    for i in 0..n {
        let pending = |s: &PruneScratch<'_>, i: usize| {
            !s.keep.get(i).copied().unwrap_or(true) && s.order.get(i).copied().unwrap_or(1) == 0
        };
        if !pending(s, i) {
            continue;
        }
        let cell = s.keys.get(i).copied();
        let winner = (0..n).find(|&w| {
            s.keep.get(w).copied().unwrap_or(false)
                && !s.candidates.get(w).is_none_or(|c| c.protected)
                && s.keys.get(w).copied() == cell
        });
        let swapped = winner.is_some_and(|w| {
            report.eliminated < params.max_eliminations
                && blanket_size(w, graph, s).is_some()
                && eliminate(w, graph, s, params, &mut report)
        });
        if let (true, Some(w)) = (swapped, winner) {
            report.eliminated += 1;
            report.swapped_representatives += 1;
            if let Some(k) = s.keep.get_mut(w) {
                *k = false;
            }
            if let Some(o) = s.order.get_mut(w) {
                *o = 1;
            }
        } else if report.eliminated < params.max_eliminations {
            report.kept_not_eliminable += 1;
        }
        if let Some(k) = s.keep.get_mut(i) {
            *k = true;
        }
    }

    // 3. Compact.
    let m_now = graph.edge_count();
    let (keep, alive, order) = (&*s.keep, &*s.edge_alive, &mut *s.order);
    let _ = graph.retain(
        keep.get(..n).unwrap_or(&[]),
        alive.get(..m_now).unwrap_or(&[]),
        order,
    );
    report.nodes_after = graph.node_count();
    report.edges_after = graph.edge_count();
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::GraphStorage;
    use crate::solver::{solve, SolverOptions, SolverWorkspace};
    use nalgebra::Vector3;

    #[test]
    fn reversed_information_matches_numeric_propagation() {
        let z = Se2::new(1.2, -0.7, 0.9);
        let cov = Matrix3::new(0.02, 0.003, 0.001, 0.003, 0.05, -0.002, 0.001, -0.002, 0.01);
        let info = spd_inverse(&cov).unwrap();
        // e' as a function of e: z^-1 seen reversed is (z (+) e)^-1, measured against z^-1.
        let f = |e: Vector3<f64>| {
            let zi = z.inverse();
            zi.inverse()
                .compose(&z.compose(&Se2::from_vector(&e)).inverse())
                .to_vector()
        };
        let h = 1e-7;
        let mut a = Matrix3::zeros();
        for k in 0..3 {
            let mut d = Vector3::zeros();
            d[k] = h;
            a.set_column(k, &((f(d) - f(-d)) / (2.0 * h)));
        }
        let expected = spd_inverse(&(a * cov * a.transpose())).unwrap();
        let got = reversed_information(&z, &info);
        assert!(
            (got - expected).amax() < 1e-5 * expected.amax(),
            "{got} vs {expected}"
        );
    }

    /// A square loop of side 4 m walked in 0.25 m steps with a loop closure, noise-free.
    fn square_loop(g: &mut PoseGraph<'_>) {
        let info = Matrix3::from_diagonal(&Vector3::new(100.0, 100.0, 400.0));
        let mut pose = Se2::IDENTITY;
        let mut n = 0u32;
        g.add_node(pose).unwrap();
        for side in 0..4 {
            for step in 0..16 {
                let turn = if step == 15 && side < 3 {
                    core::f64::consts::FRAC_PI_2
                } else {
                    0.0
                };
                let z = Se2::new(0.25, 0.0, turn);
                pose = pose.compose(&z);
                g.add_node(pose).unwrap();
                g.add_edge(PoseEdge::new(
                    NodeId(n),
                    NodeId(n + 1),
                    z,
                    info,
                    EdgeKind::Odometry,
                ))
                .unwrap();
                n += 1;
            }
        }
        let first = g.node(NodeId(0)).unwrap().pose;
        let z = pose.between(&first);
        g.add_edge(PoseEdge::new(NodeId(n), NodeId(0), z, info, EdgeKind::Loop))
            .unwrap();
    }

    #[test]
    fn pruning_a_loop_keeps_one_node_per_cell_and_the_optimum() {
        let mut storage = GraphStorage::<128, 256>::new();
        let mut g = storage.graph();
        square_loop(&mut g);
        let before: std::vec::Vec<Se2> = g.nodes().iter().map(|n| n.pose).collect();
        extern crate std;
        let mut scratch = PruneStorage::<128, 256>::new();
        let params = PruneParams {
            cells: CellParams {
                cell_size: 1.0,
                s: 0.5,
            },
            ..PruneParams::default()
        };
        let report = prune(&mut g, &params, &mut scratch.scratch()).unwrap();
        assert_eq!(report.nodes_before, 65);
        assert_eq!(
            report.nodes_after, report.cells,
            "one node per cell: {report:?}"
        );
        assert_eq!(report.kept_not_eliminable, 0);
        assert!(report.edges_after <= report.nodes_after + 1, "{report:?}");
        // The pruned graph is consistent: zero chi2 at the current estimate, and optimizing it
        // does not move anything.
        assert!(g.chi2() < 1e-12, "chi2 {}", g.chi2());
        let kept: std::vec::Vec<Se2> = g.nodes().iter().map(|n| n.pose).collect();
        for p in &kept {
            assert!(before
                .iter()
                .any(|b| (b.to_vector() - p.to_vector()).amax() < 1e-12));
        }
        let mut ws = SolverWorkspace::<128, 256, 2048>::new();
        solve(&mut g, &mut ws.buffers(), &SolverOptions::default()).unwrap();
        for (a, b) in kept.iter().zip(g.nodes()) {
            assert!((a.to_vector() - b.pose.to_vector()).amax() < 1e-9);
        }
    }

    #[test]
    fn pruning_an_optimized_noisy_loop_barely_moves_the_kept_nodes() {
        extern crate std;
        let mut storage = GraphStorage::<128, 256>::new();
        let mut g = storage.graph();
        square_loop(&mut g);
        // Make the loop closure disagree with odometry by 20 cm and 2 degrees, plus a second
        // loop closure across the square, then optimize: every node carries some tension.
        let last = g.edge_count() - 1;
        let z = g.edges()[last]
            .measurement
            .compose(&Se2::new(0.2, -0.1, 0.035));
        g.edges_mut()[last].measurement = z;
        let cross = g
            .node(NodeId(8))
            .unwrap()
            .pose
            .between(&g.node(NodeId(40)).unwrap().pose);
        let info = Matrix3::from_diagonal(&Vector3::new(50.0, 50.0, 200.0));
        g.add_edge(PoseEdge::new(
            NodeId(8),
            NodeId(40),
            cross.compose(&Se2::new(0.1, 0.05, -0.02)),
            info,
            EdgeKind::Loop,
        ))
        .unwrap();
        let mut ws = SolverWorkspace::<128, 256, 4096>::new();
        solve(&mut g, &mut ws.buffers(), &SolverOptions::default()).unwrap();
        let full: std::vec::Vec<Se2> = g.nodes().iter().map(|n| n.pose).collect();
        let mut scratch = PruneStorage::<128, 256>::new();
        let params = PruneParams {
            cells: CellParams {
                cell_size: 1.0,
                s: 0.5,
            },
            ..PruneParams::default()
        };
        prune(&mut g, &params, &mut scratch.scratch()).unwrap();
        let remap: std::vec::Vec<u32> = scratch.order[..65].to_vec();
        solve(&mut g, &mut ws.buffers(), &SolverOptions::default()).unwrap();
        let mut worst: f64 = 0.0;
        for (old, &new) in remap.iter().enumerate() {
            if new != u32::MAX {
                let a = full[old];
                let b = g.node(NodeId(new)).unwrap().pose;
                worst = worst.max((a.x - b.x).hypot(a.y - b.y));
            }
        }
        // Tree edges measure the current estimate (the and Kretzschmar's choice; see
        // the module docs), so the residual pull of the eliminated edges is dropped and the kept
        // nodes relax a little: by a small fraction of the loop's 20 cm inconsistency.
        assert!(worst < 0.02, "kept nodes moved by up to {worst} m");
    }

    #[test]
    fn pruned_graph_keeps_the_uncertainty_of_the_chain() {
        // A straight chain 0..8 with 0.5 m steps, cell 2 m: the kept nodes are linked by edges
        // whose covariance is the compounded covariance of the chain between them.
        let mut storage = GraphStorage::<16, 32>::new();
        let mut g = storage.graph();
        let info = Matrix3::from_diagonal(&Vector3::new(400.0, 400.0, 1000.0));
        g.add_node(Se2::new(0.1, 0.1, 0.0)).unwrap();
        for i in 0..8u32 {
            let p = Se2::new(0.1 + 0.5 * f64::from(i + 1), 0.1, 0.0);
            g.add_node(p).unwrap();
            g.add_edge(PoseEdge::new(
                NodeId(i),
                NodeId(i + 1),
                Se2::new(0.5, 0.0, 0.0),
                info,
                EdgeKind::Odometry,
            ))
            .unwrap();
        }
        let mut scratch = PruneStorage::<16, 32>::new();
        let params = PruneParams {
            cells: CellParams {
                cell_size: 2.0,
                s: 0.5,
            },
            ..PruneParams::default()
        };
        let report = prune(&mut g, &params, &mut scratch.scratch()).unwrap();
        assert_eq!(report.nodes_after, 3, "{report:?}");
        assert_eq!(report.edges_after, 2, "a chain stays a chain: {report:?}");
        // Along x the variance adds up: 1/400 per step.
        for e in g.edges() {
            let steps = libm::round(e.measurement.x / 0.5);
            let cov = spd_inverse(&e.information).unwrap();
            assert!(
                (cov[(0, 0)] - steps / 400.0).abs() < 1e-9,
                "{} steps: {}",
                steps,
                cov[(0, 0)]
            );
        }
    }

    #[test]
    fn scratch_too_small_is_an_error_and_changes_nothing() {
        let mut storage = GraphStorage::<128, 256>::new();
        let mut g = storage.graph();
        square_loop(&mut g);
        let mut scratch = PruneStorage::<8, 8>::new();
        assert_eq!(
            prune(&mut g, &PruneParams::default(), &mut scratch.scratch()),
            Err(PruneError::ScratchTooSmall)
        );
        assert_eq!(g.node_count(), 65);
    }
}
