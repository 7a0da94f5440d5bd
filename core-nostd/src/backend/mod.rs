//! The back-end of the paper's section III-D: temporal node, grid-cell pruning,
//! marginalization with Chow-Liu sparsification, and (with the solver) max-mixture
//! optimization of the pruned graph.

pub mod cells;
pub mod chow_liu;
pub mod dense;
pub mod marginalize;
pub mod temporal;
