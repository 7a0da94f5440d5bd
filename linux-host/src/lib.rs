//! # cloi-host
//!
//! Everything of CLOi-Mapper that needs an operating system: the `cloi` command line, file
//! formats, the simulator and evaluation. The algorithms live in [`cloi_core`].

pub mod cli;
pub mod corrupt;
pub mod map;
pub mod optimize;
pub mod prune;
pub mod prune_online;

/// The evaluation: the crate [`cloi_eval`].
pub use cloi_eval as eval;
/// The file formats: the crate [`cloi_io`].
pub use cloi_io as io;
pub use cloi_io::{dataset, graph_io};
/// The simulator: the crate [`cloi_sim`].
pub use cloi_sim as sim;
