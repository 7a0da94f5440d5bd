//! # cloi-budget
//!
//! Proofs that CLOi-Mapper's memory is bounded and fits its budget:
//! * [`footprint`]: the static size of every profile's resources, pool by pool, with
//!   compile-time assertions that each profile fits its budget (the crate does not build
//!   otherwise);
//! * [`elf`]: checks of a firmware image: section sizes, and that no heap allocator is linked;
//! * [`stack`]: the static worst-case stack of a firmware image, from its call graph;
//! * [`cli`]: the `cloi budget` / `cargo run -p cloi-budget` command.

pub mod cli;
pub mod elf;
pub mod footprint;
pub mod stack;
