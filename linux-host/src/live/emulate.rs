//! `cloi emulate ld06` and `cloi emulate rplidar`: a simulated LD06 or RPLIDAR on a
//! pseudo-terminal, for trying `cloi run` (and testing it) without the device. An RPLIDAR
//! answers the requests of the standard scan (scan, stop, reset, health) as the real one does;
//! its turn is 360 nodes, one a degree, the first flagged as a new turn. The simulator drives its robot through a world; each
//! simulated scan (the simulator's model of the LD06: 10 Hz, 12 m) is sent as one turn of LD06 packets (clockwise, [`PACKETS_PER_TURN`] packets
//! of 12 points, CRC-8), paced by the scans' time stamps, on the master side of a fresh
//! pseudo-terminal whose slave path is printed first (`ld06 on /dev/pts/N`). Only the LiDAR is
//! emulated: `cloi run` then maps from scans alone.
//!
//! `--corrupt-every N` flips a bit in every N-th packet (the reader must count the CRC
//! failure and keep the rest); the emulator ends after `--duration` seconds of data, which
//! closes the terminal as an unplugged device would.

use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Args;
use cloi_core::sensor::ld06::{Ld06Packet, Ld06Point, POINTS};

use super::serial_lidar::{RANGE_MAX, RANGE_MIN, RPLIDAR_RANGE};
use super::LidarKind;
use crate::map::input::{sim_input_with, ScanEvent, SensorEvent};
use crate::sim::lidar::LidarParams;
use crate::sim::{SensorSet, SimConfig};
use cloi_core::sensor::rplidar;

/// Packets of one emulated turn (456 points, 0.79 degree apart, as the LD06 measures).
pub const PACKETS_PER_TURN: usize = 38;

/// Arguments of `cloi emulate ld06` and `cloi emulate rplidar`.
#[derive(Debug, Args)]
pub struct EmulateArgs {
    /// World the simulated robot drives through (`home`, `office`, `airport`, `gen:SEED:...`
    /// or a TOML world file).
    #[arg(long, default_value = "home")]
    pub world: String,
    /// Seconds of data to send; the terminal closes after them.
    #[arg(long, default_value_t = 600.0)]
    pub duration: f64,
    /// Seed of the simulation.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Data seconds per wall-clock second.
    #[arg(long, default_value_t = 1.0)]
    pub speed: f64,
    /// Flip a bit in every N-th packet (0: none).
    #[arg(long, default_value_t = 0)]
    pub corrupt_every: u64,
    /// Also write the path of the terminal to this file (for scripts).
    #[arg(long)]
    pub path_file: Option<PathBuf>,
}

/// Runs the emulator of `kind` until its data ends.
///
/// # Errors
/// No pseudo-terminal, an unknown world, or a write that fails.
pub fn run(kind: LidarKind, args: &EmulateArgs, out: &mut dyn Write) -> Result<()> {
    if !(args.speed > 0.0 && args.speed.is_finite()) {
        anyhow::bail!("--speed must be a positive number");
    }
    let name = match kind {
        LidarKind::Ld06 => "ld06",
        LidarKind::Rplidar => "rplidar",
    };
    let (mut master, slave) = serialport::TTYPort::pair()
        .with_context(|| format!("opening a pseudo-terminal for the emulated {name}"))?;
    let path = serialport::SerialPort::name(&slave).context("the pseudo-terminal has no path")?;
    writeln!(out, "{name} on {path}")?;
    out.flush()?;
    if let Some(file) = &args.path_file {
        std::fs::write(file, &path).with_context(|| format!("writing {}", file.display()))?;
    }
    let started = Instant::now();
    let mut first: Option<i64> = None;
    let mut packets = 0u64;
    let mut previous: Option<i64> = None;
    // An LD06 streams from power-up; an RPLIDAR only once asked to scan.
    let mut commands = Commands::default();
    let mut scanning = kind == LidarKind::Ld06;
    let sim = SimConfig {
        duration: args.duration,
        seed: args.seed,
        sensors: SensorSet::Lidar,
        lidar: Some(LidarParams::ld06()),
        // The world's sensor outages and slips are not the device's: its own damage is
        // `--corrupt-every` and the end of the data.
        faults: false,
        ..SimConfig::default()
    };
    for event in sim_input_with(&args.world, sim)? {
        let SensorEvent::Scan(scan) = event? else {
            continue;
        };
        let t0 = *first.get_or_insert(scan.t_ns);
        let due = Duration::from_secs_f64((scan.t_ns - t0) as f64 * 1e-9 / args.speed);
        std::thread::sleep(due.saturating_sub(started.elapsed()));
        let mut bytes = Vec::new();
        if kind == LidarKind::Rplidar {
            for command in commands.read(&mut master) {
                match command {
                    rplidar::SCAN => {
                        scanning = true;
                        bytes.extend_from_slice(&rplidar::SCAN_DESCRIPTOR);
                    }
                    rplidar::STOP | rplidar::RESET => {
                        scanning = false;
                        bytes.clear();
                    }
                    rplidar::GET_HEALTH => {
                        bytes.extend_from_slice(&[rplidar::SYNC, rplidar::SYNC2, 3, 0, 0, 0, 6]);
                        bytes.extend_from_slice(&[0, 0, 0]);
                    }
                    _ => {}
                }
            }
        }
        // One turn per simulated scan: the head turns at the simulated LiDAR's rate.
        let turn_s = previous.map_or(0.1, |p| (scan.t_ns - p) as f64 * 1e-9);
        previous = Some(scan.t_ns);
        if scanning {
            match kind {
                LidarKind::Ld06 => {
                    let stamp_ms = (started.elapsed().as_millis() % 30_000) as u16;
                    let speed_dps = (360.0 / turn_s.max(1e-3)).clamp(1.0, 65_535.0) as u16;
                    for packet in turn(&scan, speed_dps, stamp_ms) {
                        let mut b = packet.encode();
                        packets += 1;
                        if args.corrupt_every > 0 && packets.is_multiple_of(args.corrupt_every) {
                            b[20] ^= 0x04;
                        }
                        bytes.extend_from_slice(&b);
                    }
                }
                LidarKind::Rplidar => {
                    for node in rplidar_turn(&scan) {
                        let mut b = node.encode();
                        packets += 1;
                        if args.corrupt_every > 0 && packets.is_multiple_of(args.corrupt_every) {
                            // Breaks the check bit: the reader must find the grid again.
                            b[1] &= 0xFE;
                        }
                        bytes.extend_from_slice(&b);
                    }
                }
            }
        }
        // Nobody reading (yet): like a device's UART, the turn is lost, not queued.
        match master.write_all(&bytes) {
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
            r => r.context("writing to the terminal")?,
        }
    }
    drop(slave);
    Ok(())
}

/// Requests an emulated RPLIDAR has received, framed as `0xA5` and a command byte.
#[derive(Debug, Default)]
struct Commands {
    pending_sync: bool,
}

impl Commands {
    /// The commands waiting on `port` (none when nothing was sent).
    fn read(&mut self, port: &mut serialport::TTYPort) -> Vec<u8> {
        use serialport::SerialPort;
        let waiting = port.bytes_to_read().unwrap_or(0) as usize;
        let mut buf = vec![0u8; waiting.min(256)];
        let n = if buf.is_empty() {
            0
        } else {
            std::io::Read::read(port, &mut buf).unwrap_or(0)
        };
        let mut out = Vec::new();
        for &b in &buf[..n] {
            if self.pending_sync {
                out.push(b);
                self.pending_sync = false;
            } else if b == rplidar::SYNC {
                self.pending_sync = true;
            }
        }
        out
    }
}

/// One clockwise turn of RPLIDAR nodes showing `scan`, one a degree, the first flagged.
pub fn rplidar_turn(scan: &ScanEvent) -> Vec<rplidar::Node> {
    (0..360u32)
        .map(|k| {
            let mm = range_mm(scan, f64::from(k) * 100.0, RPLIDAR_RANGE);
            rplidar::Node {
                start: k == 0,
                quality: if mm > 0 { 47 } else { 0 },
                angle_q6: (k * 64) as u16,
                distance_q2: mm.saturating_mul(4),
            }
        })
        .collect()
}

/// The range `scan` shows at the clockwise device angle `cw_cdeg`, mm; 0 outside `limits`
/// (metres) or the scan's field of view.
fn range_mm(scan: &ScanEvent, cw_cdeg: f64, limits: [f32; 2]) -> u16 {
    let ccw = (36_000.0 - cw_cdeg).rem_euclid(36_000.0).to_radians() / 100.0;
    let rel = (ccw - f64::from(scan.angle_min)).rem_euclid(std::f64::consts::TAU);
    let i = (rel / f64::from(scan.angle_increment)).round() as usize;
    let r = scan.ranges.get(i).copied().unwrap_or(f32::NAN);
    if r.is_finite() && (limits[0]..=limits[1]).contains(&r) {
        (r * 1000.0).round() as u16
    } else {
        0
    }
}

/// One clockwise turn of packets showing `scan` (ranges outside the LD06's limits, or outside
/// the scan's field of view, read as no return).
pub fn turn(scan: &ScanEvent, speed_dps: u16, stamp_ms: u16) -> Vec<Ld06Packet> {
    let points = PACKETS_PER_TURN * POINTS;
    let step_cdeg = 36_000.0 / points as f64;
    let range_at = |cw_cdeg: f64| range_mm(scan, cw_cdeg, [RANGE_MIN, RANGE_MAX]);
    (0..PACKETS_PER_TURN)
        .map(|k| {
            let start = (k * POINTS) as f64 * step_cdeg;
            let mut pts = [Ld06Point::default(); POINTS];
            for (j, p) in pts.iter_mut().enumerate() {
                *p = Ld06Point {
                    distance_mm: range_at(start + j as f64 * step_cdeg),
                    intensity: 200,
                };
            }
            Ld06Packet {
                speed_dps,
                start_cdeg: start.round() as u16,
                end_cdeg: ((start + 11.0 * step_cdeg).round() as u16) % 36_000,
                stamp_ms,
                points: pts,
            }
        })
        .collect()
}
