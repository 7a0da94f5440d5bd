//! `cloi sim`: simulate, then write the bag, the TUM ground truth, the sidecar and a preview.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;

use crate::builtin;
use crate::engine::{Rig, SensorSet, SimConfig, Simulation, Summary};
use crate::generate;
use crate::output::{self, BagSink, Tee, TumSink};
use crate::path;
use crate::preview;
use crate::world::{World, WorldFile};

/// Arguments of `cloi sim`.
#[derive(Debug, Args)]
pub struct SimArgs {
    /// `home`, `office`, `airport`, a generated building `gen:SEED[:SIZE][:nogyro]` (SIZE: `s`
    /// 200-800 m^2, `m` 800-3,000, `l` 3,000-8,000, `xl` 8,000-20,000; drawn from the seed
    /// when absent; `nogyro`: a robot without gyro) or a TOML world file (see
    /// docs/sim/world-format.md).
    #[arg(long, default_value = "home")]
    pub world: String,
    /// Mapping session N: the world with the changes that its `[[changes]]` tables list for
    /// sessions 1 to N applied (furniture moved, doors opened or closed, clutter). 0 is the
    /// world as written; a session past the last one shows the last one's world. The route
    /// must stay clear. `--dump-world` writes the world as written, changes included.
    #[arg(long, default_value_t = 0)]
    pub session: u32,
    /// Simulated seconds.
    #[arg(long, default_value_t = 60.0)]
    pub duration: f64,
    /// Simulate this many laps of the world's route instead of `--duration` seconds.
    #[arg(long)]
    pub laps: Option<f64>,
    /// Seed of every random draw (same seed, same bytes).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Sensors: L, C, 2C or C+L.
    #[arg(long, default_value = "C+L")]
    pub sensors: SensorSet,
    /// Output bag (`X.mcap`); `X.gt.tum` and `X.sim.json` are written beside it.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Write a PNG of the floor plan with the path and one camera frame.
    #[arg(long)]
    pub preview: Option<PathBuf>,
    /// Time of the preview's camera frame, seconds (default: the middle of the run).
    #[arg(long)]
    pub preview_at: Option<f64>,
    /// Longer side of the preview's floor plan, pixels.
    #[arg(long, default_value_t = 640)]
    pub preview_size: u32,
    /// Camera lens: `fisheye` (Kannala-Brandt) or `pinhole`.
    #[arg(long, default_value = "fisheye", value_parser = ["fisheye", "pinhole"])]
    pub lens: String,
    /// Image size WIDTHxHEIGHT.
    #[arg(long, default_value = "320x240")]
    pub resolution: String,
    /// Camera frames per second.
    #[arg(long, default_value_t = 10.0)]
    pub camera_rate: f64,
    /// Average three sub-exposures per frame (slower).
    #[arg(long)]
    pub motion_blur: bool,
    /// Ignore the world's fault schedule.
    #[arg(long)]
    pub no_faults: bool,
    /// Write the world as TOML to this file (a starting point for your own worlds).
    #[arg(long)]
    pub dump_world: Option<PathBuf>,
}

fn parse_resolution(s: &str) -> Result<(u32, u32)> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .with_context(|| format!("--resolution {s:?}: expected WIDTHxHEIGHT"))?;
    let w: u32 = w
        .trim()
        .parse()
        .with_context(|| format!("--resolution {s:?}"))?;
    let h: u32 = h
        .trim()
        .parse()
        .with_context(|| format!("--resolution {s:?}"))?;
    if !(16..=4096).contains(&w) || !(16..=4096).contains(&h) {
        bail!("--resolution {s:?}: sides must be 16..4096 pixels");
    }
    Ok((w, h))
}

/// Loads a built-in world by name or a world file.
///
/// # Errors
/// Unknown name, unreadable or invalid file (naming the file and line).
pub fn load_world(spec: &str, duration: f64) -> Result<WorldFile> {
    if let Some(w) = builtin::builtin(spec, duration) {
        return Ok(w);
    }
    if let Some(g) = generate::parse_spec(spec).map_err(anyhow::Error::msg)? {
        return generate::generate(&g, duration).map_err(anyhow::Error::msg);
    }
    let path = Path::new(spec);
    if !path.exists() {
        bail!(
            "--world {spec:?}: neither a built-in world ({}), a generated one (gen:SEED) nor an \
             existing file",
            builtin::NAMES.join(", ")
        );
    }
    Ok(WorldFile::load(path)?)
}

/// The world of mapping session `session`. A session's changes must leave the route
/// passable: a drive that the world as written leaves clear but the session blocks is an
/// error naming the item in the way.
///
/// # Errors
/// A change that does not apply, or one that blocks the route.
pub fn session_world(file: &WorldFile, session: u32, out: &mut dyn Write) -> Result<World> {
    if session == 0 {
        return Ok(World::from_file(file));
    }
    let world = World::at_session(file, session)?;
    let written = World::from_file(file);
    let c = generate::clearance(file.robot);
    for pair in path::route_points(&world.route).windows(2) {
        let (a, b) = (pair[0], pair[1]);
        if let Some(seg) = world.path_blocker(a, b, c) {
            if written.path_is_clear(a, b, c) {
                let what = file
                    .describe_segment(session, seg)
                    .unwrap_or_else(|| format!("segment {seg}"));
                bail!(
                    "{}: session {session} blocks the route: the drive {a:?} -> {b:?} passes \
                     closer than {c} m to {what}",
                    file.name
                );
            }
        }
    }
    let applied = file
        .changes
        .iter()
        .filter(|ch| ch.get_ref().session() <= session)
        .count();
    let last = file.last_session();
    let note = if last == 0 {
        " (the world has no changes)".to_string()
    } else if session > last {
        format!(" (the world of session {last}, the last with changes)")
    } else {
        String::new()
    };
    writeln!(out, "session {session}: {applied} change(s) applied{note}")?;
    Ok(world)
}

/// The path beside `out` with its extension replaced by `ext` (`run.mcap` -> `run.gt.tum`).
pub fn beside(out: &Path, ext: &str) -> PathBuf {
    out.with_extension(ext)
}

/// Runs `cloi sim`.
///
/// # Errors
/// Bad arguments, world errors, IO errors.
pub fn run(args: &SimArgs, out: &mut dyn Write) -> Result<()> {
    if !(args.duration > 0.0 && args.duration.is_finite()) {
        bail!("--duration must be a positive number of seconds");
    }
    if args.laps.is_some_and(|l| !(l > 0.0 && l <= 1000.0)) {
        bail!("--laps must be in (0, 1000]");
    }
    if !(args.camera_rate > 0.0 && args.camera_rate <= 60.0) {
        bail!("--camera-rate must be in (0, 60] Hz");
    }
    let (width, height) = parse_resolution(&args.resolution)?;
    let mut duration = args.duration;
    let mut file = load_world(&args.world, duration)?;
    let limits = Rig::new(file.robot, &SimConfig::default()).limits;
    let (lap_m, lap_s) = path::lap(file.route.get_ref(), &limits);
    writeln!(
        out,
        "route: {lap_m:.1} m per lap, {lap_s:.1} s per lap at {} m/s",
        limits.speed
    )?;
    if let Some(laps) = args.laps {
        // Whole seconds, so the figure can be passed on to `cloi map --sim-duration`.
        duration = (laps * lap_s).ceil().max(1.0);
        file = load_world(&args.world, duration)?;
        writeln!(out, "duration: {duration} s")?;
    }
    if let Some(path) = &args.dump_world {
        output::write_text(path, &file.to_toml().context("serialising the world")?)?;
        writeln!(out, "world written to {}", path.display())?;
    }
    let cfg = SimConfig {
        duration,
        seed: args.seed,
        sensors: args.sensors,
        fisheye: args.lens == "fisheye",
        width,
        height,
        camera_rate: args.camera_rate,
        motion_blur: args.motion_blur,
        faults: !args.no_faults,
        lidar: None,
    };
    let world = session_world(&file, args.session, out)?;
    let sim = Simulation::new(world, cfg);
    if let Some(path) = &args.preview {
        let at = args.preview_at.unwrap_or(duration * 0.5);
        preview::write(&sim, path, args.preview_size.clamp(64, 4096), at)?;
        writeln!(out, "preview written to {}", path.display())?;
    }
    let Some(bag_path) = &args.out else {
        if args.preview.is_none() && args.dump_world.is_none() {
            bail!("nothing to do: give --out X.mcap and/or --preview P.png");
        }
        return Ok(());
    };
    let started = Instant::now();
    let mut bag = BagSink::create(bag_path, &sim)?;
    let mut tum = TumSink::default();
    let summary: Summary = sim.run(&mut Tee(&mut bag, &mut tum))?;
    let messages = bag.finish()?;
    let wall = started.elapsed().as_secs_f64();
    let gt_path = beside(bag_path, "gt.tum");
    output::write_text(&gt_path, &tum.text)?;
    let side_path = beside(bag_path, "sim.json");
    let side = serde_json::to_string_pretty(&output::sidecar(&sim))?;
    output::write_text(&side_path, &side)?;
    writeln!(
        out,
        "{}: {:.0} s simulated in {:.1} s ({:.1} sim-s per wall-s), {} messages: {} scans ({} lost \
         to outage), {} frames ({} dropped), {} odometry, {} imu, {} ground truth",
        sim.world.name,
        duration,
        wall,
        duration / wall.max(1e-9),
        messages,
        summary.scans,
        summary.lost_scans,
        summary.frames,
        summary.dropped_frames,
        summary.odometry,
        summary.imu,
        summary.ground_truth
    )?;
    writeln!(
        out,
        "wrote {}, {}, {}",
        bag_path.display(),
        gt_path.display(),
        side_path.display()
    )?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use cloi_io::ros2::{LaserScan, RosMessage};
    use std::collections::BTreeMap;

    fn args(out: &Path, seed: u64) -> SimArgs {
        SimArgs {
            world: "home".into(),
            session: 0,
            duration: 2.0,
            laps: None,
            seed,
            sensors: SensorSet::CameraLidar,
            out: Some(out.to_path_buf()),
            preview: None,
            preview_at: None,
            preview_size: 640,
            lens: "pinhole".into(),
            resolution: "64x48".into(),
            camera_rate: 10.0,
            motion_blur: false,
            no_faults: false,
            dump_world: None,
        }
    }

    #[test]
    fn bag_and_ground_truth_are_identical_for_a_seed_and_differ_otherwise() {
        let dir = tempfile::tempdir().expect("tempdir");
        let read = |name: &str, seed: u64| {
            let out = dir.path().join(name);
            run(&args(&out, seed), &mut Vec::new()).expect("sim runs");
            let bag = std::fs::read(&out).expect("bag");
            let gt = std::fs::read(beside(&out, "gt.tum")).expect("tum");
            (bag, gt)
        };
        let a = read("a.mcap", 3);
        let b = read("b.mcap", 3);
        let c = read("c.mcap", 4);
        assert_eq!(a, b);
        assert_ne!(a.0, c.0);
        // Ground truth does not depend on the seed: the route is fixed.
        assert_eq!(a.1, c.1);
        assert_eq!(String::from_utf8_lossy(&a.1).lines().count(), 100);
        // The bag reads back with the mcap crate and decodes.
        let mut topics: BTreeMap<String, usize> = BTreeMap::new();
        let mut last_log = 0;
        for m in mcap::MessageStream::new(&a.0).expect("mcap") {
            let m = m.expect("message");
            assert!(m.log_time >= last_log, "log times ordered");
            last_log = m.log_time;
            *topics.entry(m.channel.topic.clone()).or_default() += 1;
            if m.channel.topic == "/scan" {
                let scan = LaserScan::from_cdr(&m.data).expect("scan decodes");
                assert_eq!(scan.ranges.len(), 360);
            }
        }
        assert_eq!(topics["/ground_truth"], 100);
        assert!(
            topics["/scan"] >= 9 && topics["/camera0/image_raw"] >= 19,
            "{topics:?}"
        );
        assert!(topics.contains_key("/odom") && topics.contains_key("/imu"));
    }

    #[test]
    fn a_session_that_blocks_the_route_is_an_error_naming_the_item() {
        let text = r#"
name = "flat"
ceiling_height = 2.5

[[wall]]
points = [[0, 0], [10, 0], [10, 10], [0, 10]]
closed = true

[route]
start = [1, 1]
legs = [{ type = "waypoints", points = [[9, 1], [9, 9]] }]

[[changes]]
session = 1
kind = "add"
box = { name = "toys", min = [6, 2], max = [7, 2.5] }

[[changes]]
session = 2
kind = "add"
box = { name = "boxes", min = [5, 0.8], max = [6, 1.4] }
"#;
        let file = WorldFile::parse(text, "flat.toml").expect("valid");
        let mut out = Vec::new();
        let world = session_world(&file, 1, &mut out).expect("session 1 leaves the route free");
        assert_eq!(world.session, 1);
        assert_eq!(
            String::from_utf8_lossy(&out),
            "session 1: 1 change(s) applied\n"
        );
        for session in [2, 7] {
            let err = session_world(&file, session, &mut Vec::new())
                .expect_err("blocked")
                .to_string();
            assert!(
                err.contains(&format!("session {session} blocks the route"))
                    && err.contains("[1.0, 1.0] -> [9.0, 1.0]")
                    && err.contains("added box \"boxes\""),
                "{err}"
            );
        }
    }

    #[test]
    fn a_session_of_the_home_is_simulated_and_recorded_in_the_sidecar() {
        let dir = tempfile::tempdir().expect("tempdir");
        let side = |session: u32| {
            let out = dir.path().join(format!("s{session}.mcap"));
            let mut a = args(&out, 1);
            a.session = session;
            a.duration = 0.5;
            let mut text = Vec::new();
            run(&a, &mut text).expect("sim runs");
            let side = std::fs::read_to_string(beside(&out, "sim.json")).expect("sidecar");
            let json: serde_json::Value = serde_json::from_str(&side).expect("json");
            (String::from_utf8_lossy(&text).into_owned(), json)
        };
        let (text, json) = side(3);
        assert!(text.contains("session 3: 9 change(s) applied\n"), "{text}");
        assert_eq!(json["session"], 3);
        let (text, json) = side(0);
        assert!(!text.contains("session"), "{text}");
        assert!(json.get("session").is_none());
    }
}
