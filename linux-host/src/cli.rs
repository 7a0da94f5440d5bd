//! The `cloi` command line.

use std::io::Write;

use anyhow::Result;
use clap::{Parser, Subcommand};

/// CLOi-Mapper: consistent, lightweight, robust and incremental 2D SLAM for service robots.
#[derive(Debug, Parser)]
#[command(name = "cloi", version, about, long_about = None, propagate_version = true)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// The subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Print the static memory footprint of every profile and check it against its budget.
    Budget(cloi_budget::cli::BudgetArgs),
    /// Simulate a robot in a world and write a ROS 2 bag with exact ground truth.
    Sim(crate::sim::command::SimArgs),
}

/// Runs a parsed command line, writing normal output to `out`.
///
/// # Errors
/// Whatever the subcommand reports; the caller prints it and exits non-zero.
pub fn run(cli: Cli, out: &mut dyn Write) -> Result<()> {
    match cli.command {
        Command::Budget(args) => cloi_budget::cli::run(&args, out),
        Command::Sim(args) => crate::sim::command::run(&args, out),
    }
}
