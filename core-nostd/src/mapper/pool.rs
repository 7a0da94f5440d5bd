//! What the mapper does when its node or edge pool runs full: the back-end prunes the graph
//! ([`BackEnd::make_room`](super::back::BackEnd::make_room)) instead of failing.
//!
//! Protected from elimination besides the newest `backend.prune_keep_recent` nodes (the
//! front-end's and the GPE's reference lives there): every submap's anchor (the submap's grid
//! hangs off it) and the GPE's anchor.

use super::Mapper;
use crate::backend::schedule::PoolPruning;

impl Mapper<'_> {
    /// Prunes the graph to make room (see the module documentation).
    pub(crate) fn prune_pool(&mut self) {
        let params = PoolPruning {
            cell_size: self.cfg.backend.prune_cell,
            s: self.cfg.backend.prune_s,
            keep_recent: self.cfg.backend.prune_keep_recent,
            max_iterations: self.cfg.backend.max_iterations,
        };
        let submap_anchors = self
            .submaps
            .iter()
            .filter(|m| m.in_use)
            .map(|m| m.anchor_serial);
        let gpe_anchor = self.st.gpe.anchor();
        let report = self
            .back
            .make_room(&params, submap_anchors.chain(gpe_anchor));
        // The optimization before the pruning moved the estimates even when nothing was pruned.
        self.refresh_mirror();
        let Some(report) = report else {
            return;
        };
        self.st.stats.prunes += 1;
        self.st.stats.nodes_pruned += report.eliminated as u32;
    }
}
