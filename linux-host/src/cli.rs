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
    /// Convert a CARMEN log to a ROS 2 bag (.mcap), or a bag's odometry to a TUM trajectory.
    Convert(crate::io::cli::ConvertArgs),
    /// Evaluate trajectories: relations, ATE, RPE, GMapping reference poses.
    #[command(subcommand)]
    Eval(crate::eval::cli::EvalCommand),
}

/// Runs a parsed command line, writing normal output to `out`.
///
/// # Errors
/// Whatever the subcommand reports; the caller prints it and exits non-zero.
pub fn run(cli: Cli, out: &mut dyn Write) -> Result<()> {
    match cli.command {
        Command::Budget(args) => cloi_budget::cli::run(&args, out),
        Command::Convert(args) => crate::io::cli::run(&args, out),
        Command::Eval(cmd) => crate::eval::cli::run(&cmd, out),
    }
}
