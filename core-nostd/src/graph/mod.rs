//! A fixed-capacity SE(2) pose graph: the problem that the back-end optimizes (the paper's
//! eq. 10: odometry terms plus robust loop-closure terms).
//!
//! Nodes hold a pose and a fixed flag; edges hold a measured relative pose, its 3x3 information,
//! a kind and a robust model. The graph does not own its memory: [`PoseGraph`] borrows the
//! arrays of a [`GraphStorage`] (or any two slices the caller provides), so its capacity is set
//! at the edge of the program and the code inside compiles once.
//!
//! Residual convention (the same as g2o's `EDGE_SE2`): for an edge `i -> j` with measurement
//! `z`, the error is `e = z^-1 (+) (x_i^-1 (+) x_j)` as `[x, y, theta]` with the angle wrapped,
//! and the edge's cost is `e^T Omega e`. A prior on node `i` uses `e = z^-1 (+) x_i`.

pub(crate) mod residual;
mod robust;

pub use robust::{MixtureComponent, RobustKernel, MAX_MIXTURE_COMPONENTS};

use core::fmt;

use crate::geom::{Info3, Se2};
use crate::storage::{EdgeId, NodeId};

/// A pose-graph node.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseNode {
    /// Current estimate.
    pub pose: Se2,
    /// A fixed node is not moved by the solver.
    pub fixed: bool,
}

impl PoseNode {
    /// A free node at `pose`.
    pub const fn new(pose: Se2) -> PoseNode {
        PoseNode { pose, fixed: false }
    }

    /// A placeholder for storage initialisers.
    pub const EMPTY: PoseNode = PoseNode::new(Se2::IDENTITY);
}

/// What an edge stands for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum EdgeKind {
    /// Consecutive poses linked by odometry.
    Odometry,
    /// A loop closure between non-consecutive poses.
    Loop,
    /// Two nodes of synchronized sensors tied at (nearly) the identity.
    ZeroConstraint,
    /// An absolute pose for one node (`from == to`).
    Prior,
}

/// A measurement between two nodes (or on one node, for a [`EdgeKind::Prior`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseEdge {
    /// First node.
    pub from: NodeId,
    /// Second node (equal to `from` for a prior).
    pub to: NodeId,
    /// Measured pose of `to` seen from `from` (for a prior: the absolute pose of `from`).
    pub measurement: Se2,
    /// Information (inverse covariance) of the measurement, symmetric positive definite.
    pub information: Info3,
    /// What the edge stands for.
    pub kind: EdgeKind,
    /// How large residuals are weighted.
    pub robust: RobustKernel,
}

impl PoseEdge {
    /// A plain (non-robust) edge.
    pub fn new(
        from: NodeId,
        to: NodeId,
        measurement: Se2,
        information: Info3,
        kind: EdgeKind,
    ) -> Self {
        PoseEdge {
            from,
            to,
            measurement,
            information,
            kind,
            robust: RobustKernel::None,
        }
    }

    /// A prior on `node`.
    pub fn prior(node: NodeId, pose: Se2, information: Info3) -> Self {
        PoseEdge::new(node, node, pose, information, EdgeKind::Prior)
    }

    /// A placeholder for storage initialisers.
    pub const EMPTY: PoseEdge = PoseEdge {
        from: NodeId(0),
        to: NodeId(0),
        measurement: Se2::IDENTITY,
        information: Info3::new(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0),
        kind: EdgeKind::Odometry,
        robust: RobustKernel::None,
    };

    /// The residual `[x, y, theta]` of this edge at the given poses (`xj` is ignored for a
    /// prior).
    #[inline]
    pub fn residual(&self, xi: &Se2, xj: &Se2) -> [f64; 3] {
        let (cz, sz) = (
            libm::cos(self.measurement.theta),
            libm::sin(self.measurement.theta),
        );
        if self.kind == EdgeKind::Prior {
            residual::prior_residual(xi, &self.measurement, cz, sz)
        } else {
            let (ci, si) = (libm::cos(xi.theta), libm::sin(xi.theta));
            residual::relative_residual(xi, ci, si, xj, &self.measurement, cz, sz).0
        }
    }

    /// Whether the edge's own measurement explains it at the poses `xi`, `xj`: for a
    /// max-mixture, the nominal component (information scale 1) wins over the wider ones, i.e.
    /// the optimizer has not switched the edge off; other kernels always count.
    pub fn is_active_at(&self, xi: &Se2, xj: &Se2) -> bool {
        let chi2 = self.chi2_of(&self.residual(xi, xj));
        match self.robust {
            RobustKernel::MaxMixture { .. } => self.robust.weigh(chi2).0 >= 1.0,
            _ => true,
        }
    }

    /// `e^T Omega e` for residual `e`.
    #[inline]
    pub fn chi2_of(&self, e: &[f64; 3]) -> f64 {
        let m = &self.information;
        let [a, b, c] = *e;
        m[(0, 0)] * a * a
            + m[(1, 1)] * b * b
            + m[(2, 2)] * c * c
            + 2.0 * (m[(0, 1)] * a * b + m[(0, 2)] * a * c + m[(1, 2)] * b * c)
    }
}

/// Why an edge or node could not be added.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum GraphError {
    /// The node or edge storage is full.
    Full {
        /// `"nodes"` or `"edges"`.
        what: &'static str,
        /// Its capacity.
        capacity: usize,
    },
    /// An edge refers to a node that does not exist.
    UnknownNode(NodeId),
    /// A non-prior edge joins a node to itself, or a prior names two nodes.
    BadEndpoints(NodeId, NodeId),
    /// A pose or information value is not finite.
    NotFinite,
}

impl fmt::Display for GraphError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            GraphError::Full { what, capacity } => {
                write!(
                    f,
                    "the pose graph's {what} storage is full (capacity {capacity})"
                )
            }
            GraphError::UnknownNode(n) => write!(f, "edge refers to unknown node {}", n.0),
            GraphError::BadEndpoints(a, b) => {
                write!(f, "edge endpoints {} -> {} do not fit its kind", a.0, b.0)
            }
            GraphError::NotFinite => write!(f, "pose or information is not finite"),
        }
    }
}

impl core::error::Error for GraphError {}

/// Storage for a graph of up to `N` nodes and `E` edges; lend it to [`PoseGraph::new`].
#[derive(Debug)]
pub struct GraphStorage<const N: usize, const E: usize> {
    /// Node storage.
    pub nodes: [PoseNode; N],
    /// Edge storage.
    pub edges: [PoseEdge; E],
}

impl<const N: usize, const E: usize> GraphStorage<N, E> {
    /// Empty storage, usable as a `static` initialiser.
    pub const fn new() -> Self {
        GraphStorage {
            nodes: [PoseNode::EMPTY; N],
            edges: [PoseEdge::EMPTY; E],
        }
    }

    /// A graph over this storage.
    pub fn graph(&mut self) -> PoseGraph<'_> {
        PoseGraph::new(&mut self.nodes, &mut self.edges)
    }
}

impl<const N: usize, const E: usize> Default for GraphStorage<N, E> {
    fn default() -> Self {
        Self::new()
    }
}

/// A pose graph over borrowed storage. Node and edge ids are dense indices in insertion order.
#[derive(Debug)]
pub struct PoseGraph<'a> {
    nodes: &'a mut [PoseNode],
    edges: &'a mut [PoseEdge],
    node_count: usize,
    edge_count: usize,
}

impl<'a> PoseGraph<'a> {
    /// An empty graph over the given storage (its contents are overwritten as the graph grows).
    pub fn new(nodes: &'a mut [PoseNode], edges: &'a mut [PoseEdge]) -> Self {
        PoseGraph {
            nodes,
            edges,
            node_count: 0,
            edge_count: 0,
        }
    }

    /// Number of nodes.
    #[inline]
    pub fn node_count(&self) -> usize {
        self.node_count
    }

    /// Number of edges.
    #[inline]
    pub fn edge_count(&self) -> usize {
        self.edge_count
    }

    /// Node capacity.
    pub fn node_capacity(&self) -> usize {
        self.nodes.len()
    }

    /// Edge capacity.
    pub fn edge_capacity(&self) -> usize {
        self.edges.len()
    }

    /// Removes every node and edge.
    pub fn clear(&mut self) {
        self.node_count = 0;
        self.edge_count = 0;
    }

    /// Adds a free node.
    ///
    /// # Errors
    /// [`GraphError::Full`] or [`GraphError::NotFinite`].
    pub fn add_node(&mut self, pose: Se2) -> Result<NodeId, GraphError> {
        self.add_node_full(PoseNode::new(pose))
    }

    /// Adds a node with its fixed flag.
    ///
    /// # Errors
    /// [`GraphError::Full`] or [`GraphError::NotFinite`].
    pub fn add_node_full(&mut self, node: PoseNode) -> Result<NodeId, GraphError> {
        if !node.pose.is_finite() {
            return Err(GraphError::NotFinite);
        }
        let id = NodeId(self.node_count as u32);
        let capacity = self.nodes.len();
        let slot = self
            .nodes
            .get_mut(self.node_count)
            .ok_or(GraphError::Full {
                what: "nodes",
                capacity,
            })?;
        *slot = node;
        self.node_count += 1;
        Ok(id)
    }

    /// Adds an edge after checking its endpoints and values.
    ///
    /// # Errors
    /// [`GraphError::Full`], [`GraphError::UnknownNode`], [`GraphError::BadEndpoints`] or
    /// [`GraphError::NotFinite`].
    pub fn add_edge(&mut self, edge: PoseEdge) -> Result<EdgeId, GraphError> {
        for n in [edge.from, edge.to] {
            if n.0 as usize >= self.node_count {
                return Err(GraphError::UnknownNode(n));
            }
        }
        if (edge.kind == EdgeKind::Prior) != (edge.from == edge.to) {
            return Err(GraphError::BadEndpoints(edge.from, edge.to));
        }
        if !edge.measurement.is_finite() || edge.information.iter().any(|v| !v.is_finite()) {
            return Err(GraphError::NotFinite);
        }
        let id = EdgeId(self.edge_count as u32);
        let capacity = self.edges.len();
        let slot = self
            .edges
            .get_mut(self.edge_count)
            .ok_or(GraphError::Full {
                what: "edges",
                capacity,
            })?;
        *slot = edge;
        self.edge_count += 1;
        Ok(id)
    }

    /// The node `id`, if it exists.
    #[inline]
    pub fn node(&self, id: NodeId) -> Option<&PoseNode> {
        self.nodes().get(id.0 as usize)
    }

    /// The node `id` mutably, if it exists.
    #[inline]
    pub fn node_mut(&mut self, id: NodeId) -> Option<&mut PoseNode> {
        let n = self.node_count;
        self.nodes[..n].get_mut(id.0 as usize)
    }

    /// The edge `id`, if it exists.
    #[inline]
    pub fn edge(&self, id: EdgeId) -> Option<&PoseEdge> {
        self.edges().get(id.0 as usize)
    }

    /// The edge `id` mutably, if it exists.
    #[inline]
    pub fn edge_mut(&mut self, id: EdgeId) -> Option<&mut PoseEdge> {
        let n = self.edge_count;
        self.edges[..n].get_mut(id.0 as usize)
    }

    /// Every node, in id order.
    #[inline]
    pub fn nodes(&self) -> &[PoseNode] {
        &self.nodes[..self.node_count]
    }

    /// Every node mutably, in id order.
    #[inline]
    pub fn nodes_mut(&mut self) -> &mut [PoseNode] {
        &mut self.nodes[..self.node_count]
    }

    /// Every edge, in id order.
    #[inline]
    pub fn edges(&self) -> &[PoseEdge] {
        &self.edges[..self.edge_count]
    }

    /// Every edge mutably, in id order (endpoints must stay valid; the solver re-checks them).
    #[inline]
    pub fn edges_mut(&mut self) -> &mut [PoseEdge] {
        &mut self.edges[..self.edge_count]
    }

    /// Both node and edge slices at once (nodes mutable), for the solver.
    #[inline]
    pub(crate) fn split_mut(&mut self) -> (&mut [PoseNode], &[PoseEdge]) {
        (
            &mut self.nodes[..self.node_count],
            &self.edges[..self.edge_count],
        )
    }

    /// The sum of `e^T Omega e` over all edges (the g2o convention, robust models ignored).
    pub fn chi2(&self) -> f64 {
        let nodes = self.nodes();
        let mut sum = 0.0;
        for e in self.edges() {
            if let (Some(a), Some(b)) = (nodes.get(e.from.0 as usize), nodes.get(e.to.0 as usize)) {
                sum += e.chi2_of(&e.residual(&a.pose, &b.pose));
            }
        }
        sum
    }

    /// Drops every node from index `count` on, and every edge that touches one (no effect when
    /// `count` is not smaller than the node count).
    pub fn truncate_nodes(&mut self, count: usize) {
        if count >= self.node_count {
            return;
        }
        self.node_count = count;
        let mut kept = 0;
        for k in 0..self.edge_count {
            let e = self.edges[k];
            if (e.from.0 as usize) < count && (e.to.0 as usize) < count {
                self.edges[kept] = e;
                kept += 1;
            }
        }
        self.edge_count = kept;
    }

    /// Drops every edge from index `count` on (no effect when `count` is not smaller than
    /// the edge count).
    pub fn truncate_edges(&mut self, count: usize) {
        self.edge_count = self.edge_count.min(count);
    }

    /// Removes nodes and edges in place, keeping order: node `i` stays when `keep_node[i]`,
    /// edge `k` when `keep_edge[k]` and both its endpoints stay. Surviving nodes are renumbered
    /// densely and the edges rewritten to match; `remap[i]` receives node `i`'s new index
    /// (`u32::MAX` for a removed node).
    ///
    /// # Errors
    /// [`GraphError::Full`] naming `"remap"` when `remap` or the flag slices are shorter than
    /// the graph.
    pub fn retain(
        &mut self,
        keep_node: &[bool],
        keep_edge: &[bool],
        remap: &mut [u32],
    ) -> Result<(), GraphError> {
        let (n, m) = (self.node_count, self.edge_count);
        if keep_node.len() < n || remap.len() < n || keep_edge.len() < m {
            return Err(GraphError::Full {
                what: "remap",
                capacity: remap.len(),
            });
        }
        let mut next = 0usize;
        for i in 0..n {
            if keep_node[i] {
                self.nodes[next] = self.nodes[i];
                remap[i] = next as u32;
                next += 1;
            } else {
                remap[i] = u32::MAX;
            }
        }
        self.node_count = next;
        let mut kept = 0usize;
        for (k, &keep) in keep_edge.iter().enumerate().take(m) {
            let mut e = self.edges[k];
            let at = |id: NodeId| {
                remap
                    .get(id.0 as usize)
                    .copied()
                    .filter(|_| (id.0 as usize) < n)
            };
            let (a, b) = (at(e.from).unwrap_or(u32::MAX), at(e.to).unwrap_or(u32::MAX));
            if keep && a != u32::MAX && b != u32::MAX {
                e.from = NodeId(a);
                e.to = NodeId(b);
                self.edges[kept] = e;
                kept += 1;
            }
        }
        self.edge_count = kept;
        Ok(())
    }

    /// Removes the edges for which `keep(index, edge)` is false, keeping the order of the
    /// others; returns how many were removed. Nodes are untouched.
    pub fn retain_edges(&mut self, mut keep: impl FnMut(usize, &PoseEdge) -> bool) -> usize {
        let m = self.edge_count;
        let mut kept = 0usize;
        for k in 0..m {
            let e = self.edges[k];
            if keep(k, &e) {
                self.edges[kept] = e;
                kept += 1;
            }
        }
        self.edge_count = kept;
        m - kept
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn add_and_check_edges() {
        let mut storage = GraphStorage::<3, 3>::new();
        let mut g = storage.graph();
        let a = g.add_node(Se2::IDENTITY).unwrap();
        let b = g.add_node(Se2::new(1.0, 0.0, 0.0)).unwrap();
        let info = Info3::identity();
        g.add_edge(PoseEdge::new(
            a,
            b,
            Se2::new(1.0, 0.0, 0.0),
            info,
            EdgeKind::Odometry,
        ))
        .unwrap();
        assert_eq!(
            g.add_edge(PoseEdge::new(
                a,
                NodeId(7),
                Se2::IDENTITY,
                info,
                EdgeKind::Loop
            )),
            Err(GraphError::UnknownNode(NodeId(7)))
        );
        assert_eq!(
            g.add_edge(PoseEdge::new(a, a, Se2::IDENTITY, info, EdgeKind::Loop)),
            Err(GraphError::BadEndpoints(a, a))
        );
        assert_eq!(g.chi2(), 0.0);
        g.add_edge(PoseEdge::prior(b, Se2::new(1.0, 0.5, 0.0), info))
            .unwrap();
        assert!((g.chi2() - 0.25).abs() < 1e-12);
        g.add_node(Se2::IDENTITY).unwrap();
        assert!(matches!(
            g.add_node(Se2::IDENTITY),
            Err(GraphError::Full { .. })
        ));
        g.add_edge(PoseEdge::new(a, b, Se2::IDENTITY, info, EdgeKind::Loop))
            .unwrap();
        assert!(matches!(
            g.add_edge(PoseEdge::new(a, b, Se2::IDENTITY, info, EdgeKind::Loop)),
            Err(GraphError::Full { .. })
        ));
    }

    #[test]
    fn residual_matches_g2o_convention() {
        let e = PoseEdge::new(
            NodeId(0),
            NodeId(1),
            Se2::new(1.0, 0.0, 0.5),
            Info3::identity(),
            EdgeKind::Loop,
        );
        let xi = Se2::new(2.0, 1.0, 0.3);
        let xj = xi.compose(&Se2::new(1.0, 0.0, 0.5));
        let r = e.residual(&xi, &xj);
        assert!(r.iter().all(|v| v.abs() < 1e-12));
    }

    #[test]
    fn a_max_mixture_edge_far_from_its_measurement_is_switched_off() {
        let mut e = PoseEdge::new(
            NodeId(0),
            NodeId(1),
            Se2::new(1.0, 0.0, 0.0),
            Info3::identity() * 100.0,
            EdgeKind::Loop,
        );
        let xi = Se2::IDENTITY;
        let near = Se2::new(1.05, 0.0, 0.0);
        let far = Se2::new(3.0, 1.0, 0.5);
        // Without a mixture an edge always acts, however far.
        assert!(e.is_active_at(&xi, &far));
        e.robust = RobustKernel::max_mixture_with_null(1e-3, 1e-4);
        assert!(e.is_active_at(&xi, &near));
        assert!(!e.is_active_at(&xi, &far));
    }
}
