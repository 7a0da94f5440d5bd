//! What the mapper does when its node or edge pool runs full: prune the graph (the paper's
//! section III-D) instead of failing.
//!
//! The graph is first optimized to convergence (pruning linearizes at the current estimate),
//! then [`backend::prune`](crate::backend::prune) keeps one node per grid cell of
//! `backend.prune_cell` metres, marginalizes the others into their neighbours and sparsifies
//! the result into Chow-Liu tree edges. Protected from elimination: the newest
//! `backend.prune_keep_recent` keyframes (the front-end's and the GPE's reference lives there),
//! every submap's anchor (the submap's grid hangs off it), and the GPE's anchor. Their
//! protection is passed to the pruner as the `fixed` flag for the duration of the call (the
//! mapper never fixes nodes otherwise). The node metadata is then compacted with the graph.

use super::Mapper;
use crate::backend::cells::CellParams;
use crate::backend::prune::{prune, PruneParams, Weighting};
use crate::solver::{self, Method, SolverOptions};

/// Free edge slots kept for the loop closures of one keyframe and the pruner's tree edges.
const EDGE_MARGIN: usize = 16;

impl Mapper<'_> {
    /// True when the next keyframe might not fit.
    pub(crate) fn pool_nearly_full(&self) -> bool {
        let g = &self.graph;
        g.node_count() + 1 > g.node_capacity() || g.edge_count() + EDGE_MARGIN > g.edge_capacity()
    }

    /// Prunes the graph to make room (see the module documentation).
    pub(crate) fn prune_pool(&mut self) {
        let n = self.graph.node_count();
        if n < 3 {
            return;
        }
        let options = SolverOptions {
            method: Method::GaussNewton,
            max_iterations: self.cfg.backend.max_iterations,
            linear_init: false,
            ..SolverOptions::default()
        };
        let _ = solver::solve(&mut self.graph, &mut self.solver, &options);
        self.st.optimizing = false;
        // Protection through the fixed flag (cleared again below).
        for i in 0..self.submaps.len() {
            let Some(m) = self.submaps.get(i).copied() else {
                continue;
            };
            if !m.in_use {
                continue;
            }
            if let Some(k) = self.node_of(m.anchor_serial) {
                if let Some(node) = self.graph.nodes_mut().get_mut(k) {
                    node.fixed = true;
                }
            }
        }
        if let Some(k) = self.st.anchor.and_then(|s| self.node_of(s)) {
            if let Some(node) = self.graph.nodes_mut().get_mut(k) {
                node.fixed = true;
            }
        }
        let keep_recent = (self.cfg.backend.prune_keep_recent as usize).min(n - 1);
        let params = PruneParams {
            cells: CellParams {
                cell_size: self.cfg.backend.prune_cell,
                s: self.cfg.backend.prune_s,
            },
            weighting: Weighting::EdgeInformation,
            protect_from: n - keep_recent,
            ..PruneParams::default()
        };
        let result = prune(&mut self.graph, &params, &mut self.prune);
        for node in self.graph.nodes_mut() {
            node.fixed = false;
        }
        let Ok(report) = result else {
            return;
        };
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
        self.st.stats.prunes += 1;
        self.st.stats.nodes_pruned += report.eliminated as u32;
        self.solver.invalidate();
    }
}
