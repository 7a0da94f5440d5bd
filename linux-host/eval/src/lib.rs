//! # cloi-eval
//!
//! The evaluation behind `cloi eval`: how far a trajectory or a pose graph is from a reference.
//! The relation metric of Kuemmerle et al. (2009), ATE and RPE as `evo` computes them, relative
//! errors against GMapping reference poses, loop edges against ground truth, and the ARPS of a
//! pruned pose graph.
//!
//! * [`arps`]: the average relative pose shift of a pruned pose graph (the paper's Table III).
//! * [`traj`]: loading, time association, Umeyama alignment, error statistics.
//! * [`metrics`]: ATE and RPE.
//! * [`relations`]: the relation metric and relations from reference poses.
//! * [`loops`]: loop edges of a pose graph that disagree with ground truth.
//! * [`cli`]: the `cloi eval` subcommands (a group, so more metrics can join).

pub mod arps;
pub mod cli;
pub mod loops;
pub mod metrics;
pub mod relations;
pub mod traj;
