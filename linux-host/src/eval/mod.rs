//! Trajectory evaluation (`cloi eval`): the relation metric of Kuemmerle et al. (2009), ATE and
//! RPE as `evo` computes them, and relative errors against GMapping reference poses.
//!
//! * [`traj`]: loading, time association, Umeyama alignment, error statistics.
//! * [`metrics`]: ATE and RPE.
//! * [`relations`]: the relation metric and relations from reference poses.
//! * [`loops`]: loop edges of a pose graph that disagree with ground truth.
//! * [`cli`]: the `cloi eval` subcommands (a group, so more metrics can join).

pub mod cli;
pub mod loops;
pub mod metrics;
pub mod relations;
pub mod traj;
