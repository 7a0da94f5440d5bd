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
//! [`MAX_BLANKET`]: crate::backend::marginalize::MAX_BLANKET
//!
//! Pruning is meant for an optimized graph: tree edges measure the current estimate, so the
//! pruned graph's optimum stays where the full graph's was.
//!
//! Memory: the caller lends a [`PruneScratch`] (per node and per edge arrays, see
//! [`PruneStorage`]); the graph needs some free edge slots for the new edges (when it runs out,
//! dead edges are compacted away and pruning goes on).
//!
//! The per-node work (incidence lists, elimination of one node, merging tree edges into the
//! graph) lives in module `eliminate`; this module holds the parameters, the scratch memory
//! and the pass that picks the cell representatives and eliminates the rest.

use nalgebra::Matrix3;

use super::cells::{self, CellCandidate, CellKey, CellMoments, CellParams, CellScratch, CellStats};
use crate::geom::{symmetrize, Info3, Se2};
use crate::graph::{PoseEdge, PoseGraph};
use eliminate::{blanket_size, build_incidence, eliminate, protected, ELIMINATION_PASSES};

mod eliminate;

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
mod tests;
