//! Eliminating one node of a pose graph during pruning (section III-D.2): its incidence list,
//! the local factors of its live edges at the current estimate, marginalization into its Markov
//! blanket, the Chow-Liu tree edges that replace the dense result, and their merge into existing
//! edges.

use heapless::Vec;

use super::{reversed_information, PruneParams, PruneReport, PruneScratch};
use crate::backend::marginalize::{chow_liu_edges, marginalize, LocalFactor, MAX_BLANKET};
use crate::geom::{spd_inverse, symmetrize, Info3, Se2};
use crate::graph::{EdgeKind, PoseEdge, PoseGraph, RobustKernel};
use crate::storage::NodeId;

/// End of an incidence list.
const NONE: u32 = u32::MAX;

pub(super) fn protected(graph: &PoseGraph<'_>, params: &PruneParams, keep: &mut [bool]) {
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
pub(super) fn build_incidence(graph: &PoseGraph<'_>, s: &mut PruneScratch<'_>) {
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
pub(super) const ELIMINATION_PASSES: [usize; 5] = [2, 3, 4, 6, MAX_BLANKET];

/// Number of distinct neighbours of `node` over live edges; `None` beyond [`MAX_BLANKET`].
pub(super) fn blanket_size(
    node: usize,
    graph: &PoseGraph<'_>,
    s: &PruneScratch<'_>,
) -> Option<usize> {
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
pub(super) fn eliminate(
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
