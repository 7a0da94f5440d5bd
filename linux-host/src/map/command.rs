//! Arguments of `cloi map` and the command itself.

use std::io::Write;
use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

use super::config::{MapConfig, Profile};
use super::input::{open_input, sim_input, InputOptions, LaserChoice};
use super::run::{default_out, run, MapSettings};

/// Arguments of `cloi map`.
#[derive(Debug, Args)]
pub struct MapArgs {
    /// A CARMEN log (`.clf`, `.log`, optionally gzip/bzip2) or a ROS 2 bag (`.mcap`); without
    /// it, the built-in simulated home is mapped.
    pub input: Option<PathBuf>,
    /// Memory profile: fixes the static resources and the submap grid (default: `office` for
    /// a file, `home` for the simulated home).
    #[arg(long)]
    pub profile: Option<Profile>,
    /// TOML file overriding parts of the profile's preset (see `docs/map-config.toml`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Output directory (default `out/<input stem>`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Run the back-end interleaved with fixed budgets on one thread: bit-identical results.
    #[arg(long)]
    pub deterministic: bool,
    /// Run the back-end only once per this many seconds of data (tests the real-time pose
    /// under a slow back-end); 0 runs it continuously.
    #[arg(long, default_value_t = 0.0)]
    pub backend_delay: f64,
    /// Back-end Gauss-Newton iterations after each scan in the deterministic schedule.
    #[arg(long, default_value_t = 5)]
    pub backend_iterations: u32,
    /// Stop after this many scans.
    #[arg(long)]
    pub max_scans: Option<u64>,
    /// CARMEN laser to use (front, rear, robotlaser, raw1..raw4).
    #[arg(long, default_value = "front")]
    pub laser: LaserChoice,
    /// Simulated duration of the built-in home when no input is given, seconds.
    #[arg(long, default_value_t = 120.0)]
    pub sim_duration: f64,
    /// Seed of the built-in simulation.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

/// Runs `cloi map`, printing the report to `out`.
///
/// # Errors
/// Unreadable input or configuration, or outputs that cannot be written.
pub fn run_command(args: &MapArgs, out: &mut dyn Write) -> Result<()> {
    let profile = args.profile.unwrap_or(if args.input.is_some() {
        Profile::Office
    } else {
        Profile::Home
    });
    let mut config = MapConfig::load(profile, args.config.as_deref())?;
    if args.deterministic {
        config.run.deterministic = true;
    }
    let input = match &args.input {
        Some(path) => open_input(
            path,
            &InputOptions {
                laser: args.laser,
                ..InputOptions::default()
            },
        )?,
        None => sim_input("home", args.sim_duration, args.seed)?,
    };
    let settings = MapSettings {
        profile,
        deterministic: config.run.deterministic,
        config,
        out: args
            .out
            .clone()
            .unwrap_or_else(|| default_out(args.input.as_deref())),
        backend_delay_s: args.backend_delay,
        backend_iterations_per_scan: args.backend_iterations,
        max_scans: args.max_scans,
        progress: !args.quiet,
    };
    let result = run(input, &settings)?;
    writeln!(out, "{}", serde_json::to_string_pretty(&result.report)?)?;
    writeln!(
        out,
        "wrote map.pgm, map.yaml, map.png, trajectory.tum, gpe.tum, graph.g2o, report.json to {}",
        settings.out.display()
    )?;
    Ok(())
}
