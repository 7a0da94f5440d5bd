//! # cloi-host
//!
//! The `cloi` command of CLOi-Mapper on Linux: it wires the crates that do the work and
//! drives the mapper. The algorithms live in [`cloi_core`], the file formats in [`cloi_io`],
//! the simulator in [`cloi_sim`] and the evaluation in [`cloi_eval`]. Those three are
//! re-exported here (`cloi_host::io`, `graph_io`, `dataset`, `sim`, `eval`), so tests, examples
//! and outside tools reach the whole host through one crate.
//!
//! * [`cli`]: the subcommands and their dispatch;
//! * [`map`]: `cloi map`, the mapping driver (inputs, configuration, threads, outputs);
//! * [`optimize`], [`prune`], [`prune_online`], [`corrupt`]: pose-graph files;
//! * [`vocab`]: `cloi vocab`, the place-recognition vocabulary (training, evaluation).

pub mod cli;
pub mod corrupt;
pub mod live;
pub mod map;
pub mod optimize;
pub mod prune;
pub mod prune_online;
pub mod vocab;

/// The evaluation: the crate [`cloi_eval`].
pub use cloi_eval as eval;
/// The file formats: the crate [`cloi_io`].
pub use cloi_io as io;
pub use cloi_io::{dataset, graph_io};
/// The simulator: the crate [`cloi_sim`].
pub use cloi_sim as sim;
