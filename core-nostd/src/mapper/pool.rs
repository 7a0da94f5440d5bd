//! What the mapper does when its node or edge pool runs full: the back-end prunes the graph
//! ([`make_room`]) instead of failing, and the node metadata follows the graph's new order.
//!
//! Protected from elimination besides the newest `backend.prune_keep_recent` nodes (the
//! front-end's and the GPE's reference lives there): every submap's anchor (the submap's grid
//! hangs off it) and the GPE's anchor.

use super::frames::node_index;
use super::Mapper;
use crate::backend::schedule::{make_room, PoolPruning};

impl Mapper<'_> {
    /// Prunes the graph to make room (see the module documentation).
    pub(crate) fn prune_pool(&mut self) {
        let n = self.graph.node_count();
        let params = PoolPruning {
            cell_size: self.cfg.backend.prune_cell,
            s: self.cfg.backend.prune_s,
            keep_recent: self.cfg.backend.prune_keep_recent,
            max_iterations: self.cfg.backend.max_iterations,
        };
        let nodes = self.meta.get(..n).unwrap_or_default();
        let submap_anchors = self
            .submaps
            .iter()
            .filter(|m| m.in_use)
            .filter_map(|m| node_index(nodes, m.anchor_serial));
        let gpe_anchor = self.st.gpe.anchor().and_then(|s| node_index(nodes, s));
        let Some(report) = make_room(
            &mut self.graph,
            &mut self.solver,
            &mut self.prune,
            &mut self.st.backend,
            &params,
            submap_anchors.chain(gpe_anchor),
        ) else {
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
    }
}
