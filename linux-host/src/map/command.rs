//! Arguments of `cloi map` and the command itself.

use std::io::Write;
use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

use super::config::{MapConfig, Profile};
use super::input::InputArgs;
use super::run::{default_out, run, MapSettings, StampPolicy};

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
    #[arg(long)]
    pub backend_delay: Option<f64>,
    /// Back-end Gauss-Newton iterations after each scan in the deterministic schedule.
    #[arg(long, default_value_t = 5)]
    pub backend_iterations: u32,
    /// Stop after this many scans.
    #[arg(long)]
    pub max_scans: Option<u64>,
    /// Time stamps that step back: `file-order` gives the mapper the stamp moved to 1 µs after
    /// the previous one (the outputs keep the original; counted as `stamps_repaired`),
    /// `reject` lets the mapper reject the event (counted).
    #[arg(long, value_enum, default_value = "file-order")]
    pub stamps: StampPolicy,
    /// How the input is read (laser, mounting, topics, simulator).
    #[command(flatten)]
    pub input_args: InputArgs,
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
    let input = args.input_args.open(args.input.as_deref())?;
    let backend_delay_s = args.backend_delay.unwrap_or(config.run.backend_delay_s);
    let settings = MapSettings {
        profile,
        deterministic: config.run.deterministic,
        config,
        out: args
            .out
            .clone()
            .unwrap_or_else(|| default_out(args.input.as_deref())),
        backend_delay_s,
        backend_iterations_per_scan: args.backend_iterations,
        max_scans: args.max_scans,
        stamps: args.stamps,
        progress: !args.quiet,
    };
    let result = run(input, &settings)?;
    for w in &result.warnings {
        eprintln!("warning: {w}");
    }
    writeln!(out, "{}", serde_json::to_string_pretty(&result.report)?)?;
    writeln!(
        out,
        "wrote map.pgm, map.yaml, map.png, trajectory.tum, gpe.tum, graph.g2o, report.json to {}",
        settings.out.display()
    )?;
    Ok(())
}
