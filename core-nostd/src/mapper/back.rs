//! The mapper's back-end (block (c) of the paper's block diagram, section III-D) as one value:
//! the pose graph with its per-node metadata, the solver's workspace, the pruning scratch and
//! the optimization schedule.
//!
//! The real-time part (front-end, GPE, frame nodes, submaps and the loop searches) reaches the
//! back-end only through the narrow API below: it adds frame nodes with their odometry or map
//! edge and loop edges, asks for an optimization or for room in a full pool (naming the
//! serials that must survive the pruning), steps the optimizer, and reads node estimates and
//! counts. Nodes are named by their keyframe serial wherever the graph's indices could have
//! changed under a pruning in between.

use super::frames::{node_index, NodeMeta};
use super::mirror::MirroredNode;
use super::MapperConfig;
use crate::backend::consistency::{Round, RoundProgress, GAP};
use crate::backend::prune::{PruneReport, PruneScratch};
use crate::backend::schedule::{
    counts_nearly_full, make_room, BackendCounters, BackendSchedule, BackendStep, PoolPruning,
};
use crate::frontend::lidar::{MotionNoise, Travel};
use crate::geom::{Info3, Se2};
use crate::gpe::{choose_anchor, AnchorCandidate, NodeTie};
use crate::graph::{EdgeKind, PoseEdge, PoseGraph, RobustKernel};
use crate::solver::SolverBuffers;
use crate::storage::NodeId;

/// The sizes and capacities of the graph's pools.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct GraphCounts {
    pub(crate) nodes: usize,
    pub(crate) node_capacity: usize,
    pub(crate) edges: usize,
    pub(crate) edge_capacity: usize,
}

impl GraphCounts {
    /// No graph.
    pub(crate) const ZERO: GraphCounts = GraphCounts {
        nodes: 0,
        node_capacity: 0,
        edges: 0,
        edge_capacity: 0,
    };

    /// True when the next frame node might not fit.
    pub(crate) fn nearly_full(&self) -> bool {
        counts_nearly_full(
            self.nodes,
            self.node_capacity,
            self.edges,
            self.edge_capacity,
        )
    }

    /// Whether a frame node (with one edge when `with_edge`) fits now.
    pub(crate) fn has_room(&self, with_edge: bool) -> bool {
        self.nodes < self.node_capacity && (!with_edge || self.edges < self.edge_capacity)
    }
}

/// Where the edge of a new frame node starts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum EdgeFrom {
    /// The newest node (an odometry edge).
    Newest,
    /// The keyframe with this serial (a match with a saved map).
    Keyframe(u32),
}

/// The edge that ties a new frame node to the graph.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct NewEdge {
    pub(crate) from: EdgeFrom,
    /// Pose of the new node seen from `from`.
    pub(crate) z: Se2,
    pub(crate) information: Info3,
    pub(crate) kind: EdgeKind,
}

/// Why a frame node was not added.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum AddNodeError {
    /// The node its edge starts from is not in the graph.
    Unlinked,
    /// The node or edge pool is full.
    Full,
}

/// The back-end's storage and state (see the module documentation).
pub(crate) struct BackEnd<'r> {
    graph: PoseGraph<'r>,
    solver: SolverBuffers<'r>,
    /// One entry per graph node, in the graph's order (sorted by serial).
    meta: &'r mut [NodeMeta],
    prune: PruneScratch<'r>,
    schedule: &'r mut BackendSchedule,
    /// Frame nodes added since the last round of consistency tests ended.
    since_test: u32,
    /// The last round removed a group: test every group after the next optimization.
    retest: bool,
    /// The round of consistency tests in progress.
    round: Option<Round>,
}

impl<'r> BackEnd<'r> {
    /// The back-end over its parts, as they are.
    pub(crate) fn new(
        graph: PoseGraph<'r>,
        solver: SolverBuffers<'r>,
        meta: &'r mut [NodeMeta],
        prune: PruneScratch<'r>,
        schedule: &'r mut BackendSchedule,
    ) -> Self {
        BackEnd {
            graph,
            solver,
            meta,
            prune,
            schedule,
            since_test: 0,
            retest: false,
            round: None,
        }
    }

    /// The pose graph (read-only).
    pub(crate) fn graph(&self) -> &PoseGraph<'r> {
        &self.graph
    }

    /// Metadata of the graph's nodes (same indices as the graph).
    pub(crate) fn nodes(&self) -> &[NodeMeta] {
        self.meta.get(..self.graph.node_count()).unwrap_or_default()
    }

    /// Graph index of the keyframe `serial`, if it is in the graph.
    pub(crate) fn node_of(&self, serial: u32) -> Option<usize> {
        node_index(self.nodes(), serial)
    }

    /// Current estimate of the node at graph index `index`.
    pub(crate) fn pose(&self, index: usize) -> Option<Se2> {
        self.graph.nodes().get(index).map(|n| n.pose)
    }

    /// Metadata of the node at graph index `index`.
    pub(crate) fn meta(&self, index: usize) -> Option<&NodeMeta> {
        self.nodes().get(index)
    }

    /// The node at graph index `index` as the real-time part mirrors it.
    pub(crate) fn mirrored(&self, index: usize) -> Option<MirroredNode> {
        let (estimate, meta) = (self.pose(index)?, self.meta(index)?);
        Some(MirroredNode {
            serial: meta.serial,
            tie: NodeTie {
                estimate,
                frontend: meta.frontend,
                travel: meta.travel,
            },
        })
    }

    /// Current estimate of the keyframe `serial`.
    pub(crate) fn pose_of(&self, serial: u32) -> Option<Se2> {
        self.pose(self.node_of(serial)?)
    }

    /// The newest node's graph index.
    pub(crate) fn newest(&self) -> Option<usize> {
        self.graph.node_count().checked_sub(1)
    }

    /// The graph's sizes and capacities.
    pub(crate) fn counts(&self) -> GraphCounts {
        GraphCounts {
            nodes: self.graph.node_count(),
            node_capacity: self.graph.node_capacity(),
            edges: self.graph.edge_count(),
            edge_capacity: self.graph.edge_capacity(),
        }
    }

    /// Adds a frame node at `global` with its metadata `meta`, tied by `edge` to the newest
    /// node or to a keyframe, and counts it towards the next optimization. The node and its
    /// metadata arrive together so that the serials stay sorted at every moment (a lookup by
    /// serial between the two would search a stale entry). Its submap follows with
    /// [`BackEnd::set_submap`].
    ///
    /// # Errors
    /// [`AddNodeError`]; then nothing changed.
    pub(crate) fn add_frame_node(
        &mut self,
        global: Se2,
        meta: NodeMeta,
        edge: Option<NewEdge>,
    ) -> Result<(), AddNodeError> {
        let n = self.graph.node_count();
        let edge = match edge {
            Some(e) => {
                let from = match e.from {
                    EdgeFrom::Newest => n.checked_sub(1),
                    EdgeFrom::Keyframe(serial) => self.node_of(serial),
                };
                let from = from.ok_or(AddNodeError::Unlinked)?;
                Some(PoseEdge::new(
                    NodeId(from as u32),
                    NodeId(n as u32),
                    e.z,
                    e.information,
                    e.kind,
                ))
            }
            None => None,
        };
        if !self.counts().has_room(edge.is_some()) || n >= self.meta.len() {
            return Err(AddNodeError::Full);
        }
        let id = self
            .graph
            .add_node(global)
            .map_err(|_| AddNodeError::Full)?;
        if let Some(e) = edge {
            if self.graph.add_edge(e).is_err() {
                self.graph.truncate_nodes(n);
                return Err(AddNodeError::Full);
            }
        }
        if let Some(m) = self.meta.get_mut(id.0 as usize) {
            *m = meta;
        }
        self.schedule.keyframe_added();
        self.since_test = self.since_test.saturating_add(1);
        Ok(())
    }

    /// Records that keyframe `serial`'s scan went into the submap in `slot`.
    pub(crate) fn set_submap(&mut self, serial: u32, slot: u16) {
        if let Some(m) = self.node_of(serial).and_then(|i| self.meta.get_mut(i)) {
            m.submap = slot;
        }
    }

    /// Adds a loop edge from keyframe `anchor` to keyframe `serial` measuring `z` with `info`
    /// and `robust`, and asks for an optimization; whether it was added (both keyframes must
    /// be in the graph).
    pub(crate) fn add_loop_edge(
        &mut self,
        anchor: u32,
        serial: u32,
        z: Se2,
        info: Info3,
        robust: RobustKernel,
    ) -> bool {
        let (Some(from), Some(to)) = (self.node_of(anchor), self.node_of(serial)) else {
            return false;
        };
        let mut edge = PoseEdge::new(
            NodeId(from as u32),
            NodeId(to as u32),
            z,
            info,
            EdgeKind::Loop,
        );
        edge.robust = robust;
        if self.graph.add_edge(edge).is_err() {
            return false;
        }
        self.schedule.loop_added();
        true
    }

    /// Asks for an optimization at the next step even without new loop closures.
    pub(crate) fn request_optimization(&mut self) {
        self.schedule.loop_added();
    }

    /// Optimizes and prunes the graph to make room, the keyframes `protected` (serials) and
    /// the newest `params.keep_recent` nodes exempt; the node metadata follows the graph's new
    /// order. The pruner's report, `None` when nothing was pruned.
    pub(crate) fn make_room(
        &mut self,
        params: &PoolPruning,
        protected: impl IntoIterator<Item = u32>,
    ) -> Option<PruneReport> {
        // The pruning needs its scratch and changes the graph under a round of tests.
        self.round = None;
        let n = self.graph.node_count();
        let nodes = self.meta.get(..n).unwrap_or_default();
        let protected = protected.into_iter().filter_map(|s| node_index(nodes, s));
        let report = make_room(
            &mut self.graph,
            &mut self.solver,
            &mut self.prune,
            self.schedule,
            params,
            protected,
        )?;
        // Compact the metadata like the graph: `order[i]` is node i's new index.
        for old in 0..n {
            let Some(&new) = self.prune.order.get(old) else {
                break;
            };
            if new == u32::MAX || new as usize == old {
                continue;
            }
            if let (Some(m), true) = (self.meta.get(old).copied(), (new as usize) < old) {
                if let Some(slot) = self.meta.get_mut(new as usize) {
                    *slot = m;
                }
            }
        }
        Some(report)
    }

    /// One step of the due optimization (see
    /// [`BackendSchedule::step`](crate::backend::schedule::BackendSchedule::step)). At the
    /// optimum a finished optimization leaves, a round of consistency tests of the loop groups
    /// (module [`consistency`](crate::backend::consistency)) begins when [`GAP`] frame nodes
    /// were added since the last round ended or the last one removed a group; the round runs
    /// in the turns nothing else wants ([`BackEnd::step_round`]), and an optimization that
    /// starts before it ends moves the estimates it tests at, so it is dropped (the next
    /// optimum begins a new one).
    pub(crate) fn step(&mut self, cfg: &MapperConfig, iterations: u32) -> BackendStep {
        let params = cfg.schedule();
        let step = self
            .schedule
            .step(&mut self.graph, &mut self.solver, &params, iterations);
        if step != BackendStep::Idle {
            self.round = None;
        }
        if step == BackendStep::Finished
            && cfg.backend.consistency_test
            && (self.retest || self.since_test >= GAP)
        {
            self.round = Round::start(&self.graph, &self.solver, &mut self.prune);
        }
        step
    }

    /// One step of the round of consistency tests in progress, for a turn that neither the
    /// optimizer nor the far loop search wanted: the tests take only the back-end's spare
    /// time, so a round that removes nothing leaves the map as it would be without it. A
    /// removed group asks for the optimization without it. Whether there was a round.
    pub(crate) fn step_round(&mut self, cfg: &MapperConfig) -> bool {
        let Some(round) = &mut self.round else {
            return false;
        };
        let progress = round.advance(
            &mut self.graph,
            &mut self.solver,
            &mut self.prune,
            cfg.schedule().work_budget,
        );
        if let RoundProgress::Done(removed) = progress {
            let tested = round.tested();
            self.round = None;
            self.since_test = 0;
            self.retest = removed.is_some();
            self.schedule
                .consistency_round(tested, removed.map_or(0, |r| r.edges));
            if let Some(r) = removed {
                debug!(
                    "removed a group of {} loop edges inconsistent with the graph (ratio {})",
                    r.edges, r.ratio
                );
                self.schedule.loop_added();
            }
        }
        true
    }

    /// The GPE's anchor after an optimization: the node whose estimate agrees best with the
    /// newest one's under the motion model.
    pub(crate) fn choose_anchor(&self, noise: &impl MotionNoise) -> Option<u32> {
        let candidates = self.nodes().iter().zip(self.graph.nodes()).rev();
        choose_anchor(
            candidates.map(|(m, n)| AnchorCandidate {
                serial: m.serial,
                estimate: n.pose,
                travel: m.travel,
            }),
            noise,
        )
    }

    /// Counters of the schedule.
    pub(crate) fn counters(&self) -> BackendCounters {
        self.schedule.counters()
    }

    /// Re-expresses the stored front-end poses and travels of every node in another
    /// session's front-end frame: a node's front-end pose becomes `to_session` composed with
    /// its estimate, its travel `travel` (a map rebased into the session that extends it).
    pub(crate) fn rebase(&mut self, to_session: Se2, travel: Travel) {
        let n = self.graph.node_count();
        for (m, node) in self.meta.iter_mut().zip(self.graph.nodes()).take(n) {
            m.frontend = to_session.compose(&node.pose);
            m.travel = travel;
        }
    }
}
