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
    /// Only errors on stderr, and no progress bar.
    #[arg(short, long, global = true)]
    pub quiet: bool,
    /// More messages on stderr: `-v` adds progress notes, `-vv` debugging ones (`RUST_LOG`
    /// overrides both).
    #[arg(short, long, global = true, action = clap::ArgAction::Count)]
    pub verbose: u8,
}

impl Cli {
    /// Installs the logger that takes the host's and the core's messages to stderr: warnings
    /// and errors by default, errors only with `--quiet`, more with `-v`.
    pub fn init_logging(&self) {
        let level = match (self.quiet, self.verbose) {
            (true, _) => log::LevelFilter::Error,
            (false, 0) => log::LevelFilter::Warn,
            (false, 1) => log::LevelFilter::Info,
            (false, _) => log::LevelFilter::Debug,
        };
        let mut builder = env_logger::Builder::new();
        builder.filter_level(level).format_timestamp(None);
        if let Ok(spec) = std::env::var("RUST_LOG") {
            builder.parse_filters(&spec);
        }
        // A second call (tests running the command in process) keeps the first logger.
        let _ = builder.try_init();
    }
}

/// The subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Print the static memory footprint of every profile and check it against its budget.
    Budget(cloi_budget::cli::BudgetArgs),
    /// Optimize a 2D pose graph (g2o or TORO) and report chi2, time and accuracy.
    Optimize(crate::optimize::OptimizeArgs),
    /// Prune a pose graph to about one node per grid cell (marginalization and Chow-Liu trees),
    /// optimize it, and report sizes and ARPS (the paper's Table III).
    Prune(crate::prune::PruneArgs),
    /// Add seeded random false loop closures to a pose graph (robustness tests).
    Corrupt(crate::corrupt::CorruptArgs),
    /// Convert a CARMEN log to a ROS 2 bag (.mcap) or to the firmware's binary log (.cloilog),
    /// or a bag's odometry to a TUM trajectory.
    Convert(crate::io::cli::ConvertArgs),
    /// Evaluate trajectories: relations, ATE, RPE, GMapping reference poses.
    #[command(subcommand)]
    Eval(crate::eval::cli::EvalCommand),
    /// Build a map from a CARMEN log, a ROS 2 bag, or (without input) the simulated home:
    /// map.pgm/yaml/png, trajectory.tum, gpe.tum, graph.g2o and report.json.
    Map(crate::map::command::MapArgs),
    /// Localize in a map saved with `cloi map --save` without changing it: the same inputs
    /// and outputs as `cloi map`, the report telling how much of the run was localized.
    Localize(crate::map::command::LocalizeArgs),
    /// Check a map saved with `cloi map --save` and print what it holds (with `--out`, also
    /// its map.pgm/yaml/png).
    ShowMap(crate::map::show::ShowMapArgs),
    /// Simulate a robot in a world and write a ROS 2 bag with exact ground truth.
    Sim(crate::sim::command::SimArgs),
    /// Map live from a LiDAR on a serial port (`--lidar ld06:/dev/ttyUSB0`) until
    /// `--duration` ends or Ctrl-C; writes what `cloi map` writes.
    Run(crate::live::RunArgs),
    /// Emulate a device on a pseudo-terminal from a simulated robot (for `cloi run` without
    /// the hardware).
    #[command(subcommand)]
    Emulate(EmulateCommand),
    /// Train the place-recognition vocabulary of binary words from images (`train`), or
    /// measure place recognition against a ground-truth loop matrix (`eval`).
    #[command(subcommand)]
    Vocab(crate::vocab::VocabCommand),
}

/// The devices `cloi emulate` can play.
#[derive(Debug, Subcommand)]
pub enum EmulateCommand {
    /// An LDRobot LD06 (LD19): prints the terminal's path, then sends the simulated scans.
    Ld06(crate::live::emulate::EmulateArgs),
    /// A Slamtec RPLIDAR: prints the terminal's path, then answers scan requests with the
    /// simulated scans.
    Rplidar(crate::live::emulate::EmulateArgs),
    /// A Hokuyo URG-04LX (SCIP 2.0): prints the terminal's path, then answers requests for its
    /// parameters and for continuous scans with the simulated scans.
    Urg(crate::live::emulate::EmulateArgs),
}

/// Runs a parsed command line, writing normal output to `out`.
///
/// # Errors
/// Whatever the subcommand reports; the caller prints it and exits non-zero.
pub fn run(cli: Cli, out: &mut dyn Write) -> Result<()> {
    match cli.command {
        Command::Budget(args) => cloi_budget::cli::run(&args, out),
        Command::Optimize(args) => crate::optimize::run(&args, out),
        Command::Prune(args) => crate::prune::run(&args, out),
        Command::Corrupt(args) => crate::corrupt::run(&args, out),
        Command::Convert(args) => crate::io::cli::run(&args, out),
        Command::Eval(cmd) => crate::eval::cli::run(&cmd, &crate::prune::batch_optimum, out),
        Command::Sim(args) => crate::sim::command::run(&args, out),
        Command::Map(args) => crate::map::command::run_command(&args, cli.quiet, out),
        Command::Localize(args) => crate::map::command::run_localize(&args, cli.quiet, out),
        Command::ShowMap(args) => crate::map::show::run(&args, out),
        Command::Run(args) => crate::live::run(&args, cli.quiet, out),
        Command::Vocab(cmd) => crate::vocab::run(&cmd, out),
        Command::Emulate(EmulateCommand::Ld06(args)) => {
            crate::live::emulate::run(crate::live::LidarKind::Ld06, &args, out)
        }
        Command::Emulate(EmulateCommand::Rplidar(args)) => {
            crate::live::emulate::run(crate::live::LidarKind::Rplidar, &args, out)
        }
        Command::Emulate(EmulateCommand::Urg(args)) => {
            crate::live::emulate::run(crate::live::LidarKind::Urg, &args, out)
        }
    }
}
