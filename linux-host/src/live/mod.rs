//! The live path (issue 18): `cloi run` maps from devices on the robot. A device thread
//! turns what the device sends into the same events a file gives `cloi map` (module
//! [`serial_lidar`]: an LDRobot LD06 / LD19 or a Slamtec RPLIDAR on a serial port), and the run goes through the same
//! feeding path, mapper and outputs ([`crate::map::command`]), in the two-thread schedule.
//! It ends after `--duration` seconds or at SIGINT / SIGTERM (Ctrl-C), and writes what
//! `cloi map` writes, with the device's counters under `device` in `report.json`.
//!
//! [`emulate`] is a simulated LD06 on a pseudo-terminal, to try it without the device.

pub mod emulate;
pub mod serial_lidar;

use std::io::Write;
use std::path::PathBuf;
use std::str::FromStr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Args;
use cloi_core::Se2;

use crate::io::parse_pose;
use crate::map::command::{execute_input, MapArgs};
use crate::map::config::Profile;
use crate::map::input::{thread_input, InputArgs, InputSize};
use crate::map::run::StampPolicy;
use serial_lidar::{DeviceCounters, SerialLidar};

/// Events waiting between the device thread and the mapper (a few seconds of scans).
const CHANNEL: usize = 64;

/// A LiDAR given as `KIND:PATH[@BAUD]`.
#[derive(Clone, Debug, PartialEq)]
pub struct LidarSpec {
    /// The protocol (`ld06`, `ld19`: the same protocol; `rplidar`).
    pub kind: LidarKind,
    /// Device path.
    pub path: String,
    /// Serial speed.
    pub baud: u32,
}

/// Protocols `cloi run` reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LidarKind {
    /// LDRobot LD06 or LD19 (47-byte packets, CRC-8; 230400 baud).
    Ld06,
    /// Slamtec RPLIDAR A1, A2 or C1, standard scan (5-byte nodes; 115200 baud, the A1's and
    /// the A2M8's; give `@460800` for a C1, `@256000` for an A2M12).
    Rplidar,
}

impl LidarKind {
    /// The serial speed when none is given.
    pub fn default_baud(self) -> u32 {
        match self {
            LidarKind::Ld06 => 230_400,
            LidarKind::Rplidar => 115_200,
        }
    }
}

impl FromStr for LidarSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let (kind, rest) = s
            .split_once(':')
            .ok_or_else(|| format!("`{s}`: expected KIND:PATH[@BAUD], e.g. ld06:/dev/ttyUSB0"))?;
        let kind = match kind {
            "ld06" | "ld19" => LidarKind::Ld06,
            "rplidar" => LidarKind::Rplidar,
            other => {
                return Err(format!(
                    "unknown LiDAR kind `{other}` (known: ld06, ld19, rplidar)"
                ))
            }
        };
        let (path, baud) = match rest.rsplit_once('@') {
            Some((path, baud)) => (
                path,
                baud.parse::<u32>()
                    .ok()
                    .filter(|&b| b > 0)
                    .ok_or_else(|| format!("`{baud}` is not a serial speed"))?,
            ),
            None => (rest, kind.default_baud()),
        };
        if path.is_empty() {
            return Err(format!("`{s}`: the device path is missing"));
        }
        Ok(LidarSpec {
            kind,
            path: path.to_owned(),
            baud,
        })
    }
}

/// Arguments of `cloi run`.
#[derive(Debug, Args)]
pub struct RunArgs {
    /// The LiDAR, `KIND:PATH[@BAUD]`: `ld06:/dev/ttyUSB0` (LDRobot LD06 or LD19, 230400
    /// baud unless given) or `rplidar:/dev/ttyUSB0` (Slamtec RPLIDAR A1/A2/C1, 115200).
    #[arg(long, value_name = "KIND:PATH[@BAUD]")]
    pub lidar: LidarSpec,
    /// Pose of the LiDAR on the robot, `X,Y,THETA` (m, m, rad).
    #[arg(long, value_name = "X,Y,THETA", value_parser = parse_pose, allow_hyphen_values = true)]
    pub lidar_offset: Option<Se2>,
    /// Also record every scan to this ROS 2 bag (`cloi map FILE` replays it).
    #[arg(long, value_name = "FILE.mcap")]
    pub record: Option<PathBuf>,
    /// Stop after this many seconds (default: at SIGINT or SIGTERM).
    #[arg(long)]
    pub duration: Option<f64>,
    /// Memory profile (default `home`: the LD06's 12 m suit a home or a small office).
    #[arg(long, default_value = "home")]
    pub profile: Profile,
    /// TOML file overriding parts of the profile's preset (see `docs/map-config.toml`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Overrides one key of the configuration, as `cloi map --set`; repeatable.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    /// Also save the final map to this `.cloimap` file.
    #[arg(long, value_name = "FILE")]
    pub save: Option<PathBuf>,
    /// Output directory.
    #[arg(long, default_value = "out/live")]
    pub out: PathBuf,
    /// Also print the JSON report on stdout.
    #[arg(long)]
    pub json: bool,
}

/// Runs `cloi run` until its duration ends or a stop signal arrives.
///
/// # Errors
/// A device that cannot be opened, a bad duration or configuration, or outputs that cannot
/// be written.
pub fn run(args: &RunArgs, quiet: bool, out: &mut dyn Write) -> Result<()> {
    if let Some(d) = args.duration {
        if !(d > 0.0 && d.is_finite()) {
            anyhow::bail!("--duration must be a positive number of seconds");
        }
    }
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = Arc::clone(&stop);
        // One handler per process: a second live run in the same process keeps the first's.
        if let Err(e) = ctrlc::set_handler(move || stop.store(true, Ordering::Release)) {
            log::warn!("SIGINT and SIGTERM will not stop the run cleanly: {e}");
        }
    }
    let counters = Arc::new(Mutex::new(DeviceCounters::default()));
    let (tx, rx) = std::sync::mpsc::sync_channel(CHANNEL);
    let device = SerialLidar {
        kind: args.lidar.kind,
        path: args.lidar.path.clone(),
        baud: args.lidar.baud,
        mounting: args.lidar_offset.unwrap_or(Se2::IDENTITY),
        record: args.record.clone(),
    };
    let thread = device.start(tx, Arc::clone(&stop), Arc::clone(&counters))?;
    if let Some(d) = args.duration {
        let stop = Arc::clone(&stop);
        let until = Instant::now() + Duration::from_secs_f64(d);
        std::thread::Builder::new()
            .name("cloi-duration".into())
            .spawn(move || {
                while Instant::now() < until && !stop.load(Ordering::Acquire) {
                    std::thread::sleep(Duration::from_millis(20));
                }
                stop.store(true, Ordering::Release);
            })
            .context("starting the run's timer")?;
    }
    if !quiet {
        eprintln!(
            "mapping from {} ({} baud){}",
            args.lidar.path,
            args.lidar.baud,
            match args.duration {
                Some(d) => format!(" for {d} s"),
                None => "; Ctrl-C stops and writes the map".into(),
            }
        );
    }
    let input = thread_input(rx, thread, InputSize::Unknown);
    let map_args = MapArgs {
        input: None,
        profile: Some(args.profile),
        config: args.config.clone(),
        set: args.set.clone(),
        save: args.save.clone(),
        out: Some(args.out.clone()),
        deterministic: false,
        backend_delay: None,
        backend_iterations: 5,
        max_scans: None,
        skip: 0.0,
        stamps: StampPolicy::FileOrder,
        input_args: InputArgs::default(),
        json: false,
    };
    let mut report = execute_input(&map_args, args.profile, None, input, quiet, out)?;
    let device = *counters
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    report
        .extra
        .insert("device".into(), serde_json::to_value(device)?);
    report.write(&args.out.join("report.json"))?;
    if device.crc_errors + device.read_errors > 0 {
        log::warn!(
            "the LiDAR sent {} damaged packets and went away {} times",
            device.crc_errors,
            device.read_errors
        );
    }
    if args.json {
        writeln!(out, "{}", serde_json::to_string_pretty(&report)?)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lidar_specs_parse_with_and_without_a_speed() {
        let s: LidarSpec = "ld06:/dev/ttyUSB0".parse().expect("parses");
        assert_eq!((s.path.as_str(), s.baud), ("/dev/ttyUSB0", 230_400));
        let s: LidarSpec = "ld19:/dev/pts/3@115200".parse().expect("parses");
        assert_eq!((s.path.as_str(), s.baud), ("/dev/pts/3", 115_200));
        let s: LidarSpec = "rplidar:/dev/ttyUSB1".parse().expect("parses");
        assert_eq!((s.kind, s.baud), (LidarKind::Rplidar, 115_200));
        for bad in [
            "ld06",
            "urg:/dev/x",
            "ld06:",
            "ld06:/dev/x@fast",
            "ld06:/dev/x@0",
        ] {
            assert!(bad.parse::<LidarSpec>().is_err(), "{bad}");
        }
    }
}
