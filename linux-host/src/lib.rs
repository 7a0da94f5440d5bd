//! # cloi-host
//!
//! Everything of CLOi-Mapper that needs an operating system: the `cloi` command line, file
//! formats, the simulator and evaluation. The algorithms live in [`cloi_core`].

pub mod cli;
pub mod dataset;
pub mod io;
pub mod sim;
