//! `cloi emulate ld06` and `cloi emulate rplidar`: a simulated LD06 or RPLIDAR on a
//! pseudo-terminal, for trying `cloi run` (and testing it) without the device. The simulator
//! drives its robot through a world; each simulated scan (the simulator's model of the LD06:
//! 10 Hz, 12 m) is sent as one turn of the device, paced by the scans' time stamps, on the
//! master side of a fresh pseudo-terminal whose slave path is printed first (`ld06 on
//! /dev/pts/N`):
//! * an LD06 streams from the start, clockwise, [`PACKETS_PER_TURN`] packets of 12 points with
//!   their CRC-8;
//! * an RPLIDAR answers the requests of the standard scan (scan, stop, reset, health) as the
//!   real one does; its turn is 360 nodes, one a degree, the first flagged as a new turn;
//! * a Hokuyo (`urg`) answers SCIP 2.0 requests: its parameters (`PP`, a URG-04LX's:
//!   [`URG_PARAMS`]), and once asked for continuous scans (`MD`) each turn as one response of
//!   682 steps over 240 degrees, 5.6 m at most.
//!
//! `--base create2` also emulates the robot's base on a second terminal (`create2 on
//! /dev/pts/M`): an iRobot Create 2 that, once its interface is started and its stream asked
//! for, sends the wheel encoder counts of the simulated wheel odometry every time the
//! simulator measures it. Without it `cloi run` maps from scans alone.
//!
//! `--corrupt-every N` flips a bit in every N-th packet (every N-th scan of a Hokuyo) and every
//! N-th frame of the base (the reader must count the failed check and keep the rest). The
//! emulator ends after `--duration` seconds of data, which closes the terminals as unplugged
//! devices would, and prints on stderr how many turns (and base frames) it wrote whole.

use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Args;
use cloi_core::sensor::create2::{self, EncoderCounts, WheelGeometry};
use cloi_core::sensor::ld06::{Ld06Packet, Ld06Point, POINTS};
use cloi_core::Se2;

use super::serial_lidar::{RANGE_MAX, RANGE_MIN, RPLIDAR_RANGE};
use super::LidarKind;
use crate::map::input::{sim_input_with, ScanEvent, SensorEvent};
use crate::sim::lidar::LidarParams;
use crate::sim::{SensorSet, SimConfig};
use cloi_core::sensor::{rplidar, urg};

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
    /// Also emulate the robot's base on a second terminal (printed second, `create2 on
    /// PATH`): `create2`, an iRobot Create 2 that streams its wheel encoder counts once asked.
    #[arg(long, value_name = "KIND")]
    pub base: Option<BaseKind>,
    /// Also write the path of the base's terminal to this file.
    #[arg(long)]
    pub base_path_file: Option<PathBuf>,
}

/// Robot bases `cloi emulate` plays.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum BaseKind {
    /// iRobot Create 2 (Open Interface, encoder packets 43 and 44).
    Create2,
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
        LidarKind::Urg => "urg",
    };
    let (mut master, slave) = terminal(name, args.path_file.as_deref(), out)?;
    let mut base = match args.base {
        Some(BaseKind::Create2) => Some(Create2::open(
            args.base_path_file.as_deref(),
            args.corrupt_every,
            out,
        )?),
        None => None,
    };
    let started = Instant::now();
    let mut first: Option<i64> = None;
    let (mut packets, mut turns_sent) = (0u64, 0u64);
    let mut previous: Option<i64> = None;
    // An LD06 streams from power-up; an RPLIDAR only once asked to scan.
    let mut commands = Commands::default();
    let mut urg_lines = UrgLines::default();
    let mut md_echo = Vec::new();
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
    for event in sim_input_with(&args.world, 0, sim)? {
        let event = event?;
        let t0 = *first.get_or_insert(event.t_ns());
        // Kinds are not exactly in stamp order (a scan is stamped at its sweep's start).
        let due =
            Duration::from_secs_f64(((event.t_ns() - t0) as f64 * 1e-9 / args.speed).max(0.0));
        let scan = match event {
            SensorEvent::Scan(scan) => scan,
            SensorEvent::Odometry { pose, .. } => {
                if let Some(b) = base.as_mut() {
                    std::thread::sleep(due.saturating_sub(started.elapsed()));
                    b.odometry(pose)?;
                }
                continue;
            }
            _ => continue,
        };
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
        if kind == LidarKind::Urg {
            for line in urg_lines.read(&mut master) {
                bytes.extend_from_slice(&line);
                bytes.push(b'\n');
                match line.as_slice() {
                    b"PP" => {
                        bytes.extend_from_slice(b"00P\n");
                        let mut l = [0u8; 24];
                        for (name, v) in URG_PARAMS {
                            let n = urg::UrgParams::line(name, v, &mut l);
                            bytes.extend_from_slice(&l[..n]);
                        }
                        bytes.push(b'\n');
                    }
                    l if l.starts_with(b"MD") => {
                        bytes.extend_from_slice(b"00P\n\n");
                        scanning = true;
                        md_echo = line.clone();
                        md_echo.push(b'\n');
                    }
                    l => {
                        bytes.extend_from_slice(b"00P\n\n");
                        if l == b"QT" || l == b"RS" {
                            scanning = false;
                        }
                    }
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
                LidarKind::Urg => {
                    let stamp_ms = (started.elapsed().as_millis() & 0xFF_FFFF) as u32;
                    let ranges = urg_scan(&scan);
                    let mut block = vec![0u8; md_echo.len() + 12 + 66 * (ranges.len() / 21 + 1)];
                    let n = urg::write_scan(&md_echo, stamp_ms, &ranges, &mut block);
                    block.truncate(n);
                    packets += 1;
                    if args.corrupt_every > 0 && packets.is_multiple_of(args.corrupt_every) {
                        // A character of the first data line: its check fails.
                        block[md_echo.len() + 4 + 6 + 2] ^= 0x01;
                    }
                    bytes.extend_from_slice(&block);
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
            r => {
                r.context("writing to the terminal")?;
                turns_sent += u64::from(scanning);
            }
        }
    }
    drop(slave);
    // What was sent, to compare with what the reader counted; on the terminal, not on the
    // output a script may have stopped reading after the paths.
    let frames = base.map(|b| format!(" and {} base frames", b.sent));
    let _ = writeln!(
        std::io::stderr(),
        "sent {turns_sent} turns{}",
        frames.unwrap_or_default()
    );
    Ok(())
}

/// A fresh pseudo-terminal for the emulated `name`: its path is printed (`NAME on PATH`) and
/// written to `path_file`; the master side and the slave (kept open until the data ends).
fn terminal(
    name: &str,
    path_file: Option<&std::path::Path>,
    out: &mut dyn Write,
) -> Result<(serialport::TTYPort, serialport::TTYPort)> {
    let (master, slave) = serialport::TTYPort::pair()
        .with_context(|| format!("opening a pseudo-terminal for the emulated {name}"))?;
    let path = serialport::SerialPort::name(&slave).context("the pseudo-terminal has no path")?;
    writeln!(out, "{name} on {path}")?;
    out.flush()?;
    if let Some(file) = path_file {
        std::fs::write(file, &path).with_context(|| format!("writing {}", file.display()))?;
    }
    Ok((master, slave))
}

/// An emulated iRobot Create 2: after the Open Interface is started and the encoder packets
/// are asked for, each simulated odometry pose is sent as one stream frame of the wheel
/// encoder counts that roll the robot there (the Create's geometry; counts wrap at 65,535).
struct Create2 {
    master: serialport::TTYPort,
    _slave: serialport::TTYPort,
    commands: Vec<u8>,
    started: bool,
    streaming: bool,
    last: Option<Se2>,
    /// Both wheels' counts, unrounded.
    counts: [f64; 2],
    frames: u64,
    /// Frames written whole to the terminal.
    sent: u64,
    corrupt_every: u64,
}

impl Create2 {
    fn open(
        path_file: Option<&std::path::Path>,
        corrupt_every: u64,
        out: &mut dyn Write,
    ) -> Result<Self> {
        let (master, slave) = terminal("create2", path_file, out)?;
        Ok(Create2 {
            master,
            _slave: slave,
            commands: Vec::new(),
            started: false,
            streaming: false,
            last: None,
            // Near the wrap, so that a run crosses it.
            counts: [65_000.0; 2],
            frames: 0,
            sent: 0,
            corrupt_every,
        })
    }

    /// Reads the requests sent so far: start, stream (of any packets: the encoders are sent),
    /// pause / resume, stop.
    fn read_commands(&mut self) {
        use serialport::SerialPort;
        let waiting = self.master.bytes_to_read().unwrap_or(0) as usize;
        if waiting > 0 {
            let mut buf = vec![0u8; waiting.min(256)];
            let n = std::io::Read::read(&mut self.master, &mut buf).unwrap_or(0);
            self.commands.extend_from_slice(&buf[..n]);
        }
        loop {
            let used = match self.commands.as_slice() {
                [create2::START, ..] => {
                    self.started = true;
                    1
                }
                [create2::STREAM, n, rest @ ..] if rest.len() >= usize::from(*n) => {
                    self.streaming = self.started;
                    2 + usize::from(*n)
                }
                [create2::STREAM, ..] | [create2::PAUSE_RESUME] => break,
                [create2::PAUSE_RESUME, on, ..] => {
                    self.streaming = self.started && *on == 1;
                    2
                }
                [STOP_OI, ..] => {
                    (self.started, self.streaming) = (false, false);
                    1
                }
                [_, ..] => 1,
                [] => break,
            };
            self.commands.drain(..used);
        }
    }

    /// The robot is at `pose` in its odometry frame: the wheels roll there and, when
    /// streaming, the counts are sent.
    fn odometry(&mut self, pose: Se2) -> Result<()> {
        self.read_commands();
        let step = self
            .last
            .replace(pose)
            .map_or(Se2::IDENTITY, |l| l.between(&pose));
        let twist = step.log();
        let g = WheelGeometry::CREATE2;
        let half_turn = 0.5 * twist[2] * g.track;
        self.counts[0] += (twist[0] - half_turn) / g.metres_per_count;
        self.counts[1] += (twist[0] + half_turn) / g.metres_per_count;
        if !self.streaming {
            return Ok(());
        }
        // Counts modulo 2^16, as the robot's 16-bit counters hold them.
        let wrap = |c: f64| (c.round() as i64).rem_euclid(65_536) as u16;
        let mut frame = EncoderCounts {
            left: wrap(self.counts[0]),
            right: wrap(self.counts[1]),
        }
        .encode();
        self.frames += 1;
        if self.corrupt_every > 0 && self.frames.is_multiple_of(self.corrupt_every) {
            frame[4] ^= 0x10;
        }
        match self.master.write_all(&frame) {
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => Ok(()),
            r => {
                r.context("writing to the base's terminal")?;
                self.sent += 1;
                Ok(())
            }
        }
    }
}

/// Open Interface opcode: stop the interface (back to the robot's own control).
const STOP_OI: u8 = 173;

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

/// The emulated Hokuyo's parameters (`PP`): a URG-04LX's, 240 degrees in 682 steps at 10 Hz,
/// 2 cm to 5.6 m.
pub const URG_PARAMS: [(&str, u32); 7] = [
    ("DMIN", 20),
    ("DMAX", 5600),
    ("ARES", 1024),
    ("AMIN", 44),
    ("AMAX", 725),
    ("AFRT", 384),
    ("SCAN", 600),
];

/// The distances (mm) of the emulated Hokuyo's steps showing `scan`; 0 (an error code) where
/// it shows nothing within the device's limits.
pub fn urg_scan(scan: &ScanEvent) -> Vec<u32> {
    let (ares, amin, amax, afrt) = (1024.0, 44, 725, 384);
    (amin..=amax)
        .map(|step| {
            // Steps count counter-clockwise from the right; `range_mm` takes clockwise angles.
            let ccw_deg = f64::from(step - afrt) * 360.0 / ares;
            let cw_cdeg = (-100.0 * ccw_deg).rem_euclid(36_000.0);
            u32::from(range_mm(scan, cw_cdeg, [0.02, 5.6]))
        })
        .collect()
}

/// Request lines an emulated Hokuyo has received.
#[derive(Debug, Default)]
struct UrgLines {
    partial: Vec<u8>,
}

impl UrgLines {
    /// The whole lines waiting on `port`, without their LF.
    fn read(&mut self, port: &mut serialport::TTYPort) -> Vec<Vec<u8>> {
        use serialport::SerialPort;
        let waiting = port.bytes_to_read().unwrap_or(0) as usize;
        let mut buf = vec![0u8; waiting.min(256)];
        let n = if buf.is_empty() {
            0
        } else {
            std::io::Read::read(port, &mut buf).unwrap_or(0)
        };
        let mut lines = Vec::new();
        for &b in &buf[..n] {
            if b == b'\n' {
                lines.push(std::mem::take(&mut self.partial));
            } else if self.partial.len() < 64 {
                self.partial.push(b);
            }
        }
        lines
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
