//! The live path (issue 18): `cloi run` maps from devices on the robot. A device thread
//! turns what the device sends into the same events a file gives `cloi map` (module
//! [`serial_lidar`]: an LDRobot LD06 / LD19 or a Slamtec RPLIDAR on a serial port), and the run goes through the same
//! feeding path, mapper and outputs ([`crate::map::command`]), in the two-thread schedule.
//! It ends after `--duration` seconds or at SIGINT / SIGTERM (Ctrl-C), and writes what
//! `cloi map` writes, with the device's counters under `device` in `report.json`.
//!
//! A robot base ([`serial_base`]: an iRobot Create 2) adds wheel odometry from a second thread
//! into the same channel; [`record`] writes what both send into one bag (`--record`), and
//! [`port`] is what the device threads share: reading, and reopening a device that went away.
//!
//! [`emulate`] is a simulated LD06 or RPLIDAR (and Create 2) on pseudo-terminals, to try it
//! without the devices.

pub mod emulate;
pub mod i2c_gyro;
pub mod port;
pub mod record;
pub mod serial_base;
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
use record::{Recorder, SharedRecorder};
use serial_base::{BaseCounters, SerialBase};
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
    /// Hokuyo URG-04LX, UTM-30LX or another SCIP 2.0 device (its USB port ignores the speed;
    /// 115200 on a serial one).
    Urg,
}

impl LidarKind {
    /// The serial speed when none is given.
    pub fn default_baud(self) -> u32 {
        match self {
            LidarKind::Ld06 => 230_400,
            LidarKind::Rplidar | LidarKind::Urg => 115_200,
        }
    }
}

/// A device given as `KIND:PATH[@BAUD]`: its kind, path and speed, if given.
fn split_spec(s: &str) -> Result<(&str, &str, Option<u32>), String> {
    let (kind, rest) = s
        .split_once(':')
        .ok_or_else(|| format!("`{s}`: expected KIND:PATH[@BAUD], e.g. ld06:/dev/ttyUSB0"))?;
    let (path, baud) = match rest.rsplit_once('@') {
        Some((path, baud)) => (
            path,
            Some(
                baud.parse::<u32>()
                    .ok()
                    .filter(|&b| b > 0)
                    .ok_or_else(|| format!("`{baud}` is not a serial speed"))?,
            ),
        ),
        None => (rest, None),
    };
    if path.is_empty() {
        return Err(format!("`{s}`: the device path is missing"));
    }
    Ok((kind, path, baud))
}

impl FromStr for LidarSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let (kind, path, baud) = split_spec(s)?;
        let kind = match kind {
            "ld06" | "ld19" => LidarKind::Ld06,
            "rplidar" => LidarKind::Rplidar,
            "urg" => LidarKind::Urg,
            other => {
                return Err(format!(
                    "unknown LiDAR kind `{other}` (known: ld06, ld19, rplidar, urg)"
                ))
            }
        };
        Ok(LidarSpec {
            kind,
            path: path.to_owned(),
            baud: baud.unwrap_or(kind.default_baud()),
        })
    }
}

/// A wheel-odometry source given as `KIND:PATH[@BAUD]`; the one kind is `create2`, an iRobot
/// Create 2 or Roomba 600 series on its serial port (115200 baud unless given).
#[derive(Clone, Debug, PartialEq)]
pub struct OdomSpec {
    /// Device path.
    pub path: String,
    /// Serial speed.
    pub baud: u32,
}

impl FromStr for OdomSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let (kind, path, baud) = split_spec(s)?;
        if kind != "create2" {
            return Err(format!("unknown odometry source `{kind}` (known: create2)"));
        }
        Ok(OdomSpec {
            path: path.to_owned(),
            baud: baud.unwrap_or(115_200),
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
    /// Wheel odometry, `KIND:PATH[@BAUD]`: `create2:/dev/ttyUSB1` (iRobot Create 2 or Roomba
    /// 600 series, its encoder counts; 115200 baud unless given). Without it the LiDAR's own
    /// motion seeds each scan.
    #[arg(long, value_name = "KIND:PATH[@BAUD]")]
    pub odom: Option<OdomSpec>,
    /// Gyro on the robot's I2C bus, `KIND:PATH[@ADDRESS]`: `mpu6050:/dev/i2c-1` (InvenSense
    /// MPU-6050 family, address 0x68) or `lsm6ds:/dev/i2c-1` (STMicroelectronics LSM6DS
    /// family, 0x6a), mounted face up. The robot must stand still for its first second.
    #[arg(long, value_name = "KIND:PATH[@ADDRESS]")]
    pub imu: Option<i2c_gyro::ImuSpec>,
    /// Also record every scan and odometry pose to this ROS 2 bag (`cloi map FILE` replays
    /// it).
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
    let mounting = args.lidar_offset.unwrap_or(Se2::IDENTITY);
    let recorder: Arc<SharedRecorder> = Arc::new(Mutex::new(match &args.record {
        Some(path) => Some(Recorder::create(path, mounting)?),
        None => None,
    }));
    let counters = Arc::new(Mutex::new(DeviceCounters::default()));
    let base_counters = Arc::new(Mutex::new(BaseCounters::default()));
    let gyro_counters = Arc::new(Mutex::new(i2c_gyro::GyroCounters::default()));
    let (tx, rx) = std::sync::mpsc::sync_channel(CHANNEL);
    let gyro = match &args.imu {
        Some(imu) => Some(i2c_gyro::start(
            imu,
            Arc::clone(&recorder),
            tx.clone(),
            Arc::clone(&stop),
            Arc::clone(&gyro_counters),
        )?),
        None => None,
    };
    let base = match &args.odom {
        Some(odom) => Some(
            SerialBase {
                path: odom.path.clone(),
                baud: odom.baud,
                recorder: Arc::clone(&recorder),
            }
            .start(tx.clone(), Arc::clone(&stop), Arc::clone(&base_counters))?,
        ),
        None => None,
    };
    let device = SerialLidar {
        kind: args.lidar.kind,
        path: args.lidar.path.clone(),
        baud: args.lidar.baud,
        mounting,
        recorder: Arc::clone(&recorder),
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
            "mapping from {} ({} baud){}{}",
            args.lidar.path,
            args.lidar.baud,
            match &args.odom {
                Some(o) => format!(" with odometry from {} ({} baud)", o.path, o.baud),
                None => String::new(),
            },
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
        load: None,
        initial_pose: None,
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
    let mapped = execute_input(&map_args, args.profile, None, input, quiet, out);
    // However mapping ended, the devices stop and the recording is closed.
    stop.store(true, Ordering::Release);
    let base_ended = base.map(|b| {
        b.join()
            .unwrap_or_else(|_| Err(anyhow::anyhow!("the base's thread panicked")))
    });
    let gyro_ended = gyro.map(|g| {
        g.join()
            .unwrap_or_else(|_| Err(anyhow::anyhow!("the gyro's thread panicked")))
    });
    let recorded = record::finish(&recorder);
    let mut report = mapped?;
    recorded?;
    for ended in [base_ended, gyro_ended].into_iter().flatten() {
        ended?;
    }
    let device = *counters
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    report
        .extra
        .insert("device".into(), serde_json::to_value(device)?);
    if args.odom.is_some() {
        let base = *base_counters
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        report
            .extra
            .insert("base".into(), serde_json::to_value(base)?);
        if base.checksum_errors + base.read_errors > 0 {
            log::warn!(
                "the base sent {} damaged frames and went away {} times",
                base.checksum_errors,
                base.read_errors
            );
        }
    }
    if device.crc_errors + device.read_errors > 0 {
        log::warn!(
            "the LiDAR sent {} damaged packets and went away {} times",
            device.crc_errors,
            device.read_errors
        );
    }
    if args.imu.is_some() {
        let gyro = *gyro_counters
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        report
            .extra
            .insert("gyro".into(), serde_json::to_value(gyro)?);
        if gyro.read_errors > 0 {
            log::warn!("{} gyro readings failed", gyro.read_errors);
        }
    }
    report.write(&args.out.join("report.json"))?;
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
        let o: OdomSpec = "create2:/dev/ttyUSB2".parse().expect("parses");
        assert_eq!((o.path.as_str(), o.baud), ("/dev/ttyUSB2", 115_200));
        assert!("create2:/dev/x@57600".parse::<OdomSpec>().is_ok());
        assert!("kobuki:/dev/x".parse::<OdomSpec>().is_err());
        let u: LidarSpec = "urg:/dev/ttyACM0".parse().expect("parses");
        assert_eq!(u.kind, LidarKind::Urg);
        for bad in [
            "ld06",
            "sick:/dev/x",
            "ld06:",
            "ld06:/dev/x@fast",
            "ld06:/dev/x@0",
        ] {
            assert!(bad.parse::<LidarSpec>().is_err(), "{bad}");
        }
    }
}
