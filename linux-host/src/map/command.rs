//! Arguments of `cloi map` and the command itself.

use std::io::Write;
use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

use super::config::{MapConfig, Profile};
use super::input::InputArgs;
use super::output::MapReport;
use super::run::{default_out, run, LocalizeIn, MapSettings, StampPolicy};
use cloi_core::geom::Se2;

/// Arguments of `cloi map`.
#[derive(Debug, Args)]
pub struct MapArgs {
    /// A CARMEN log (`.clf`, `.log`, optionally gzip/bzip2) or a ROS 2 bag (`.mcap`); without
    /// it, the built-in simulated home is mapped.
    pub input: Option<PathBuf>,
    /// Memory profile: fixes the static resources and the submap grid (default: `office` for
    /// a file, the world's own for a built-in simulated world, `office` for other worlds).
    #[arg(long)]
    pub profile: Option<Profile>,
    /// TOML file overriding parts of the profile's preset (see `docs/map-config.toml`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Overrides one key of the configuration after `--config`, as a dotted TOML key and a
    /// value (`--set loop_closure.min_score=0.6 --set icp.huber=0.1`); repeatable.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    /// Also save the final map (pose graph and submaps) to this `.cloimap` file, for later
    /// sessions; `cloi show-map` reads it back.
    #[arg(long, value_name = "FILE")]
    pub save: Option<PathBuf>,
    /// Extend a map saved with `--save` (a new session of the same place): the run localizes
    /// in it first (from `--initial-pose`, else by searching the whole map), then maps on
    /// from the first fix, adding to it; `--save` writes the grown map. The profile defaults
    /// to the one whose submap grid the map was made with.
    #[arg(long, value_name = "FILE")]
    pub load: Option<PathBuf>,
    /// The robot's pose in the saved map at the first scan, `X,Y,THETA` (m, m, rad), for
    /// `--load` and `cloi localize`; without it the whole map is searched (global
    /// localization).
    #[arg(long, value_name = "X,Y,THETA", value_parser = crate::io::parse_pose, allow_hyphen_values = true)]
    pub initial_pose: Option<Se2>,
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
    /// Most Gauss-Newton iterations of each solve the back-end starts (a back-end step runs
    /// after each scan in the deterministic schedule, bounded by `backend.work_budget`).
    #[arg(long, default_value_t = 5)]
    pub backend_iterations: u32,
    /// Stop after this many scans.
    #[arg(long)]
    pub max_scans: Option<u64>,
    /// Drop the input's first SECONDS of data (by time stamp): start anywhere along a
    /// recording.
    #[arg(long, value_name = "SECONDS", default_value_t = 0.0)]
    pub skip: f64,
    /// Time stamps that step back: `file-order` gives the mapper the stamp moved to 1 µs after
    /// the previous one (the outputs keep the original; counted as `stamps_repaired`),
    /// `reject` lets the mapper reject the event (counted).
    #[arg(long, value_enum, default_value = "file-order")]
    pub stamps: StampPolicy,
    /// How the input is read (laser, mounting, topics, simulator).
    #[command(flatten)]
    pub input_args: InputArgs,
    /// Also print the JSON report (written to `report.json` in any case) on stdout, alone,
    /// for piping into other tools; the human summary goes to stderr.
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `cloi localize`.
#[derive(Debug, Args)]
pub struct LocalizeArgs {
    /// The saved map (`.cloimap`, from `cloi map --save`).
    pub map: PathBuf,
    /// The input and the options `cloi map` takes (the profile defaults to the one whose
    /// submap grid the map was made with; `--load` is `cloi map`'s).
    #[command(flatten)]
    pub run: MapArgs,
}

/// Runs `cloi localize`: `cloi map`'s run over a saved map that stays as it is, the pose
/// tracked in it; the same outputs, with a `localization` section in the report.
///
/// # Errors
/// As [`run_command`], and a map file that cannot be read or fits no profile.
pub fn run_localize(args: &LocalizeArgs, quiet: bool, out: &mut dyn Write) -> Result<()> {
    if args.run.load.is_some() {
        anyhow::bail!("cloi localize takes its map as its first argument, not --load");
    }
    let profile = profile_of_map(&args.map, args.run.profile)?;
    let target = LocalizeIn {
        map: args.map.clone(),
        initial_pose: args.run.initial_pose,
        extend: false,
    };
    execute(&args.run, profile, Some(target), quiet, out)
}

/// The profile a run in the saved map `map` uses: `given`, else the one whose submap grid the
/// map was made with.
fn profile_of_map(map: &std::path::Path, given: Option<Profile>) -> Result<Profile> {
    let grid = crate::io::map_file::map_grid(map)?;
    match given {
        Some(p) => Ok(p),
        None => [Profile::Home, Profile::Office, Profile::Airport]
            .into_iter()
            .find(|p| p.core_config().grid == grid)
            .ok_or_else(|| {
                anyhow::anyhow!(
                    "{}: its submap grid ({} cells of {} m) is no profile's; give --profile and \
                     a --config with that grid",
                    map.display(),
                    grid.side,
                    grid.resolution
                )
            }),
    }
}

/// Runs `cloi map`: the JSON report to `out` with `--json`, warnings and a summary to
/// stderr; `quiet` drops the progress bar and the summary.
///
/// # Errors
/// Unreadable input or configuration, or outputs that cannot be written.
pub fn run_command(args: &MapArgs, quiet: bool, out: &mut dyn Write) -> Result<()> {
    let Some(map) = &args.load else {
        if args.initial_pose.is_some() {
            anyhow::bail!("--initial-pose is the robot's pose in a saved map: give --load too");
        }
        let profile = args.profile.unwrap_or_else(|| default_profile(args));
        return execute(args, profile, None, quiet, out);
    };
    let profile = profile_of_map(map, args.profile)?;
    let target = LocalizeIn {
        map: map.clone(),
        initial_pose: args.initial_pose,
        extend: true,
    };
    execute(args, profile, Some(target), quiet, out)
}

fn execute(
    args: &MapArgs,
    profile: Profile,
    localize: Option<LocalizeIn>,
    quiet: bool,
    out: &mut dyn Write,
) -> Result<()> {
    let input = args
        .input_args
        .open(args.input.as_deref())?
        .skip_seconds(args.skip);
    execute_input(args, profile, localize, input, quiet, out).map(|_| ())
}

/// [`execute`] on an input already opened (a live device's stream for `cloi run`); returns
/// the report it wrote.
pub(crate) fn execute_input(
    args: &MapArgs,
    profile: Profile,
    localize: Option<LocalizeIn>,
    input: crate::map::input::InputStream,
    quiet: bool,
    out: &mut dyn Write,
) -> Result<MapReport> {
    let mut config = MapConfig::load(profile, args.config.as_deref(), &args.set)?;
    if args.deterministic {
        config.run.deterministic = true;
    }
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
        progress: !quiet,
        keep_gpe: false,
        save_map: args.save.clone(),
        localize,
        visual: args.input_args.visual_calibration(args.input.as_deref())?,
    };
    let result = run(input, &settings)?;
    for w in &result.warnings {
        log::warn!("{w}");
    }
    if args.json {
        writeln!(out, "{}", serde_json::to_string_pretty(&result.report)?)?;
    }
    if !quiet {
        eprintln!("{}", summary(&result.report, &settings.out));
        if let Some(l) = result.report.extra.get("localization") {
            eprintln!(
                "localized {:.1} % of the scans, first fix after {} s, lost {} times",
                l["localized_fraction"].as_f64().unwrap_or(0.0) * 100.0,
                l["time_to_first_fix_s"],
                l["lost"]
            );
        }
        if let Some(first) = result
            .report
            .extra
            .get("session")
            .map(|s| &s["first_serial"])
        {
            if let Some(first) = first.as_u64() {
                eprintln!("extended the saved map from keyframe {first} on");
            }
        }
        if let Some(path) = &settings.save_map {
            eprintln!("saved the map to {}", path.display());
        }
    }
    Ok(result.report)
}

/// One human line about a finished run, from its report.
fn summary(r: &MapReport, out: &std::path::Path) -> String {
    // Sensor set C maps camera images, each a frame as a scan is for a LiDAR.
    let frames = if r.extra.contains_key("visual") {
        "camera frames"
    } else {
        "scans"
    };
    format!(
        "mapped {} {frames} ({} rejected) into {} keyframes with {} loop closures: {:.0} s of data \
         in {:.1} s; wrote map.pgm, map.yaml, map.png, result.mcap, trajectory.tum, gpe.tum, \
         graph.g2o, report.json to {}",
        r.scans,
        r.scans_rejected,
        r.keyframes,
        r.loop_closures,
        r.data_seconds,
        r.wall_seconds,
        out.display()
    )
}

/// The profile when none is given: `office` for a file; for the simulator, the profile of
/// the built-in world of that name, and `office` for another world (its size is unknown
/// here, and the office's pools hold a floor ten times a home's).
fn default_profile(args: &MapArgs) -> Profile {
    if args.input.is_some() {
        return Profile::Office;
    }
    args.input_args.sim_world.parse().unwrap_or(Profile::Office)
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    #[derive(Debug, Parser)]
    struct Cmd {
        #[command(flatten)]
        map: MapArgs,
    }

    fn profile(args: &[&str]) -> Profile {
        let cmd = Cmd::try_parse_from(std::iter::once("map").chain(args.iter().copied()))
            .expect("arguments parse");
        cmd.map.profile.unwrap_or_else(|| default_profile(&cmd.map))
    }

    #[test]
    fn the_profile_follows_the_input_unless_given() {
        assert_eq!(profile(&[]), Profile::Home);
        assert_eq!(profile(&["--sim-world", "office"]), Profile::Office);
        assert_eq!(profile(&["--sim-world", "airport"]), Profile::Airport);
        assert_eq!(profile(&["--sim-world", "my-world.toml"]), Profile::Office);
        assert_eq!(profile(&["log.clf"]), Profile::Office);
        assert_eq!(
            profile(&["--sim-world", "office", "--profile", "home"]),
            Profile::Home
        );
    }
}
