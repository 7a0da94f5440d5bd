//! The back-end of the paper's section III-D: grid-cell pruning, marginalization with
//! Chow-Liu sparsification, (with the solver) max-mixture optimization of the pruned graph,
//! and the schedule that decides when each runs.
//!
//! The temporal node of eqs. 8-9 (a new frame node entering the optimized graph with a mean
//! and covariance propagated from the last optimized node) has no module of its own: a new
//! frame node enters the graph at its GPE pose, which already composes the reference node's
//! estimate with the front-end motion since it, and its odometry edge carries the covariance
//! compounded along that motion.

pub mod cells;
pub mod chow_liu;
pub mod consistency;
pub mod dense;
pub mod marginalize;
pub mod prune;
pub mod schedule;
