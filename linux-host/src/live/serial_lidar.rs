//! A serial LiDAR as a stream of scans: a thread reads the port, decodes what the device sends
//! with the core's parser for its protocol and gathers the points into revolutions of
//! [`BEAMS`] beams ([`Revolution`]), each sent on as one scan.
//!
//! * **Protocols**: the LDRobot LD06 / LD19 streams 47-byte packets as soon as it is powered
//!   ([`cloi_core::sensor::ld06`]); the Slamtec RPLIDAR (A1, A2, C1) is asked for a standard
//!   scan (stop, then scan, then its 7-byte descriptor is checked) and streams 5-byte nodes
//!   ([`cloi_core::sensor::rplidar`]); it is told to stop when the run ends. A turn ends where
//!   the LD06's angle passes zero or the RPLIDAR flags a new turn.
//! * **Time**: a revolution is stamped with the host's clock when its last point arrived, less
//!   half a turn (the time its beams were measured around; the turn's length from the LD06's
//!   speed field, or from the host's clock between turns); the devices' own counters are not
//!   used. The beams are not deskewed: the heads turn clockwise while the beams count
//!   counter-clockwise from angle zero, so their times do not follow their order and a scan's
//!   `time_increment` cannot describe them.
//! * **Damage**: bytes before a packet start, CRC failures and impossible angles (LD06), bytes
//!   off the node grid (RPLIDAR) are counted; the first revolution (the device was mid-turn
//!   when reading began) and revolutions with fewer than [`MIN_POINTS`] returns are counted
//!   and dropped.
//! * **Recording** (`cloi run --record FILE.mcap`): every scan sent on is also written to the
//!   run's recording (module [`super::record`]).
//! * **A device that goes away** (unplugged, its port closed): the read error is counted and
//!   the port is opened (and an RPLIDAR started) again every [`port::REOPEN`] until it answers
//!   or the run stops; the mapper meanwhile waits for scans, and resumes with the next one.

use std::io::Write;
use std::sync::atomic::AtomicBool;
use std::sync::mpsc::SyncSender;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use cloi_core::sensor::ld06::{Ld06Counters, PacketReader, Revolution};
use cloi_core::sensor::rplidar::{self, NodeReader};
use cloi_core::sensor::urg::{self, ScanReader, UrgParams};
use cloi_core::Se2;
use serde::Serialize;

use super::port::{self, Port, PortEvent};
use super::record::{self, SharedRecorder};
use crate::map::input::{ScanEvent, SensorEvent};

/// Beams of a scan: one per degree (the LD06 measures about 450 points a turn, an RPLIDAR A1
/// about 360 to 1,450; the nearer of two in one beam is kept).
pub const BEAMS: usize = 360;
/// Fewer returns than this in a revolution: no scan (a blocked or stopping head).
pub const MIN_POINTS: u32 = 60;
/// Shortest and longest ranges of the LD06 and LD19, metres.
pub const RANGE_MIN: f32 = 0.02;
/// See [`RANGE_MIN`].
pub const RANGE_MAX: f32 = 12.0;
/// Shortest and longest ranges of an RPLIDAR A1 / A2 / C1, metres (the C1's and A2's 12 m).
pub const RPLIDAR_RANGE: [f32; 2] = [0.15, 12.0];
/// How long an RPLIDAR may take to answer a scan request with its descriptor.
const DESCRIPTOR_WAIT: Duration = Duration::from_secs(2);

/// What the device thread met, for the run's report.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct DeviceCounters {
    /// Bytes read from the port.
    pub bytes: u64,
    /// Valid packets.
    pub packets: u64,
    /// Packets whose CRC did not match.
    pub crc_errors: u64,
    /// Bytes skipped while looking for a packet start.
    pub skipped_bytes: u64,
    /// Packets with an angle of a full turn or more.
    pub bad_angles: u64,
    /// RPLIDAR nodes decoded.
    pub nodes: u64,
    /// Hokuyo lines read (their failed checks count as CRC errors).
    pub lines: u64,
    /// Whole revolutions sent on as scans.
    pub scans: u64,
    /// Revolutions dropped: the partial first one after (re)opening, too few returns, or (a
    /// Hokuyo) a damaged scan.
    pub revolutions_dropped: u64,
    /// Reads that failed (the device went away).
    pub read_errors: u64,
    /// Times the port was opened again after a failure.
    pub reopened: u64,
    /// Scans written to the recording.
    pub recorded: u64,
}

impl DeviceCounters {
    /// Adds what a decoder met between two readings of its counters.
    fn add(&mut self, before: DecoderCounters, after: DecoderCounters) {
        self.packets += after.ld06.packets - before.ld06.packets;
        self.crc_errors += after.ld06.crc_errors - before.ld06.crc_errors;
        self.bad_angles += after.ld06.bad_angles - before.ld06.bad_angles;
        self.nodes += after.rplidar.nodes - before.rplidar.nodes;
        self.skipped_bytes += (after.ld06.skipped_bytes + after.rplidar.skipped_bytes)
            - (before.ld06.skipped_bytes + before.rplidar.skipped_bytes);
        self.lines += after.urg.lines - before.urg.lines;
        self.crc_errors += after.urg.check_errors - before.urg.check_errors;
        self.revolutions_dropped += after.urg.scans_dropped - before.urg.scans_dropped;
    }
}

/// The counters of any decoder.
#[derive(Clone, Copy, Debug, Default)]
struct DecoderCounters {
    ld06: Ld06Counters,
    rplidar: rplidar::NodeCounters,
    urg: urg::UrgCounters,
}

/// Where and how to read the device.
#[derive(Clone, Debug)]
pub struct SerialLidar {
    /// Its protocol.
    pub kind: super::LidarKind,
    /// Device path (`/dev/ttyUSB0`, a pseudo-terminal).
    pub path: String,
    /// Serial speed.
    pub baud: u32,
    /// Pose of the LiDAR on the robot.
    pub mounting: Se2,
    /// The run's recording (see [`super::record`]).
    pub recorder: Arc<SharedRecorder>,
}

impl SerialLidar {
    /// Opens the port and, for an RPLIDAR, starts its scan; a Hokuyo is asked for its
    /// parameters, then for continuous scans of its whole span.
    fn open(&self) -> Result<(Port, Option<UrgParams>)> {
        let mut port = port::open(&self.path, self.baud)?;
        let mut urg = None;
        match self.kind {
            super::LidarKind::Rplidar => start_rplidar(port.as_mut())?,
            super::LidarKind::Urg => urg = Some(start_urg(port.as_mut())?),
            super::LidarKind::Ld06 => {}
        }
        Ok((port, urg))
    }

    /// Opens the port (a clear error if it cannot be) and starts the thread that reads it and
    /// sends its scans on `tx` until `stop` is set; `counters` follows what it met.
    ///
    /// # Errors
    /// The port cannot be opened, or the thread cannot be started.
    pub fn start(
        self,
        tx: SyncSender<Result<SensorEvent>>,
        stop: Arc<AtomicBool>,
        counters: Arc<Mutex<DeviceCounters>>,
    ) -> Result<std::thread::JoinHandle<Result<()>>> {
        let (port, urg) = self
            .open()
            .with_context(|| format!("opening the LiDAR's serial port {}", self.path))?;
        std::thread::Builder::new()
            .name("cloi-lidar".into())
            .spawn(move || {
                let mut port = self.read_until_stopped(port, urg, &tx, &stop, &counters);
                // Leave the motor or laser stopped (best effort: the device may be gone).
                match (port.as_mut(), self.kind) {
                    (Some(p), super::LidarKind::Rplidar) => {
                        let _ = p.write_all(&rplidar::request(rplidar::STOP));
                    }
                    (Some(p), super::LidarKind::Urg) => {
                        let _ = p.write_all(urg::QT);
                    }
                    _ => {}
                }
                Ok(())
            })
            .context("starting the LiDAR thread")
    }

    fn read_until_stopped(
        &self,
        port: Port,
        urg: Option<UrgParams>,
        tx: &SyncSender<Result<SensorEvent>>,
        stop: &AtomicBool,
        counters: &Mutex<DeviceCounters>,
    ) -> Option<Port> {
        let count = |f: &mut dyn FnMut(&mut DeviceCounters)| port::update(counters, f);
        let mut assembler = Assembler::new(self.kind, self.mounting, urg);
        let handle = |event: PortEvent<'_>| {
            let bytes = match event {
                PortEvent::Bytes(bytes) => bytes,
                PortEvent::Lost => {
                    count(&mut |c| c.read_errors += 1);
                    return true;
                }
                PortEvent::Reopened => {
                    count(&mut |c| c.reopened += 1);
                    assembler = Assembler::new(self.kind, self.mounting, urg);
                    return true;
                }
            };
            let before = assembler.counters();
            let mut scans = Vec::new();
            let mut dropped = 0;
            for &b in bytes {
                match assembler.push(b) {
                    Some(Ok(scan)) => scans.push(scan),
                    Some(Err(())) => dropped += 1,
                    None => {}
                }
            }
            let after = assembler.counters();
            count(&mut |c| {
                c.bytes += bytes.len() as u64;
                c.add(before, after);
                c.revolutions_dropped += dropped;
                c.scans += scans.len() as u64;
            });
            for scan in scans {
                if record::record(&self.recorder, |r| r.scan(&scan)) {
                    count(&mut |c| c.recorded += 1);
                }
                if tx.send(Ok(SensorEvent::Scan(scan))).is_err() {
                    return false;
                }
            }
            true
        };
        port::read_until_stopped(
            &self.path,
            "LiDAR",
            port,
            stop,
            &|| self.open().map(|(p, _)| p),
            handle,
        )
    }
}

/// Stops whatever an RPLIDAR was doing, asks for a standard scan and checks its descriptor.
fn start_rplidar(port: &mut dyn serialport::SerialPort) -> Result<()> {
    port.write_all(&rplidar::request(rplidar::STOP))?;
    // The device needs a millisecond to stop; what it sent meanwhile is stale.
    std::thread::sleep(Duration::from_millis(10));
    port.clear(serialport::ClearBuffer::Input)?;
    port.write_all(&rplidar::request(rplidar::SCAN))?;
    let until = Instant::now() + DESCRIPTOR_WAIT;
    let mut got = Vec::with_capacity(rplidar::SCAN_DESCRIPTOR.len());
    let mut byte = [0u8];
    while got.len() < rplidar::SCAN_DESCRIPTOR.len() {
        if Instant::now() > until {
            anyhow::bail!("no scan descriptor from the RPLIDAR within {DESCRIPTOR_WAIT:?}");
        }
        match port.read(&mut byte) {
            Ok(1) => {
                got.push(byte[0]);
                // Resynchronize on the descriptor's first byte.
                if got[0] != rplidar::SYNC {
                    got.clear();
                }
            }
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
            Err(e) => return Err(e.into()),
        }
    }
    if got != rplidar::SCAN_DESCRIPTOR {
        anyhow::bail!("the RPLIDAR answered a scan request with {got:02X?}");
    }
    Ok(())
}

/// How long a Hokuyo may take to answer a request.
const URG_ANSWER_WAIT: Duration = Duration::from_secs(2);

/// Switches a Hokuyo to SCIP 2.0, stops what it was doing, reads its parameters (`PP`) and
/// asks for continuous scans of its whole span (`MD`).
fn start_urg(port: &mut dyn serialport::SerialPort) -> Result<UrgParams> {
    // A device already in SCIP 2.0 refuses the switch; either answer will do.
    port.write_all(urg::SCIP2)?;
    let _ = urg_answer(port);
    port.write_all(urg::QT)?;
    let _ = urg_answer(port);
    port.write_all(urg::PP)?;
    let mut params = UrgParams::default();
    for line in urg_answer(port)? {
        params.take_line(&line);
    }
    if !params.usable() {
        anyhow::bail!("the Hokuyo's parameters (PP) are not usable: {params:?}");
    }
    let (first, last) = (params.amin as u16, params.amax as u16);
    port.write_all(&urg::md_request(first, last))?;
    Ok(params)
}

/// The lines of one answer, up to its empty line.
fn urg_answer(port: &mut dyn serialport::SerialPort) -> Result<Vec<Vec<u8>>> {
    let until = Instant::now() + URG_ANSWER_WAIT;
    let (mut lines, mut line) = (Vec::new(), Vec::new());
    let mut byte = [0u8];
    loop {
        if Instant::now() > until {
            anyhow::bail!("no answer from the Hokuyo within {URG_ANSWER_WAIT:?}");
        }
        match port.read(&mut byte) {
            Ok(1) if byte[0] == b'\n' => {
                if line.is_empty() {
                    return Ok(lines);
                }
                lines.push(std::mem::take(&mut line));
            }
            Ok(1) => line.push(byte[0]),
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
            Err(e) => return Err(e.into()),
        }
    }
}

/// A device's protocol decoder.
#[derive(Debug)]
enum Decoder {
    Ld06(PacketReader),
    Rplidar(NodeReader),
    Urg(Box<ScanReader>, UrgParams),
}

/// Bytes to points to scans.
struct Assembler {
    decoder: Decoder,
    revolution: Revolution<BEAMS>,
    ranges: [f32; BEAMS],
    /// The first revolution after (re)opening began mid-turn.
    partial: bool,
    mounting: Se2,
    range: [f32; 2],
    last_stamp: i64,
    /// Host time of the last turn's end, ns (the RPLIDAR's turn length).
    last_turn: Option<i64>,
}

impl Assembler {
    fn new(kind: super::LidarKind, mounting: Se2, urg: Option<UrgParams>) -> Self {
        let (decoder, range) = match kind {
            super::LidarKind::Ld06 => (Decoder::Ld06(PacketReader::new()), [RANGE_MIN, RANGE_MAX]),
            super::LidarKind::Rplidar => (Decoder::Rplidar(NodeReader::new()), RPLIDAR_RANGE),
            super::LidarKind::Urg => {
                let p = urg.unwrap_or_default();
                (
                    Decoder::Urg(Box::new(ScanReader::new()), p),
                    [p.dmin as f32 / 1000.0, p.dmax as f32 / 1000.0],
                )
            }
        };
        Assembler {
            decoder,
            revolution: Revolution::new(),
            ranges: [f32::NAN; BEAMS],
            partial: true,
            mounting,
            range,
            last_stamp: i64::MIN,
            last_turn: None,
        }
    }

    fn counters(&self) -> DecoderCounters {
        match &self.decoder {
            Decoder::Ld06(r) => DecoderCounters {
                ld06: r.counters(),
                ..DecoderCounters::default()
            },
            Decoder::Rplidar(r) => DecoderCounters {
                rplidar: r.counters(),
                ..DecoderCounters::default()
            },
            Decoder::Urg(r, _) => DecoderCounters {
                urg: r.counters(),
                ..DecoderCounters::default()
            },
        }
    }

    /// A Hokuyo's next byte: its scans come whole, in the device's own steps.
    fn push_urg(&mut self, byte: u8) -> Option<Result<ScanEvent, ()>> {
        let Decoder::Urg(reader, p) = &mut self.decoder else {
            return None;
        };
        let scan = reader.push(byte)?;
        let p = *p;
        let turn = 2.0 * std::f64::consts::PI / f64::from(p.ares);
        let step_s = 60.0 / (f64::from(p.scan_rpm) * f64::from(p.ares));
        let ranges: Vec<f32> = reader
            .ranges_mm()
            .iter()
            .map(|&mm| {
                if (p.dmin..=p.dmax).contains(&mm) {
                    mm as f32 / 1000.0
                } else {
                    f32::NAN
                }
            })
            .collect();
        if ranges.iter().filter(|r| r.is_finite()).count() < MIN_POINTS as usize {
            return Some(Err(()));
        }
        // The scan was sent once its last step was measured: its first step came a span
        // earlier.
        let span_ns = (scan.steps as f64 * step_s * 1e9) as i64;
        let stamp = (port::now_ns() - span_ns).max(self.last_stamp.saturating_add(1));
        self.last_stamp = stamp;
        Some(Ok(ScanEvent {
            t_ns: stamp,
            ranges,
            angle_min: ((f64::from(p.amin) - f64::from(p.afrt)) * turn) as f32,
            angle_increment: turn as f32,
            range_min: self.range[0],
            range_max: self.range[1],
            time_increment: step_s as f32,
            laser_offset: self.mounting,
            odom: None,
            received: Some(Instant::now()),
        }))
    }

    /// The next byte; a scan (or a dropped revolution) when it completed one.
    fn push(&mut self, byte: u8) -> Option<Result<ScanEvent, ()>> {
        let (points, speed_dps) = match &mut self.decoder {
            Decoder::Urg(..) => return self.push_urg(byte),
            Decoder::Ld06(r) => {
                let packet = r.push(byte)?;
                (
                    self.revolution.add(&packet, &mut self.ranges)?,
                    packet.speed_dps,
                )
            }
            Decoder::Rplidar(r) => {
                let n = r.push(byte)?;
                let points = self.revolution.point(
                    n.angle_cdeg(),
                    n.distance_mm(),
                    n.start,
                    &mut self.ranges,
                )?;
                (points, 0)
            }
        };
        let now = port::now_ns();
        let previous_turn = self.last_turn.replace(now);
        if std::mem::take(&mut self.partial) || points < MIN_POINTS {
            return Some(Err(()));
        }
        let turn_ns = if speed_dps > 0 {
            (360.0 / f64::from(speed_dps) * 1e9) as i64
        } else {
            previous_turn.map_or(100_000_000, |t| (now - t).clamp(1, 1_000_000_000))
        };
        // Half a turn back; never at or before the previous scan (the clock may step back).
        let stamp = (now - turn_ns / 2).max(self.last_stamp.saturating_add(1));
        self.last_stamp = stamp;
        Some(Ok(ScanEvent {
            t_ns: stamp,
            ranges: self.ranges.to_vec(),
            angle_min: 0.0,
            angle_increment: Revolution::<BEAMS>::INCREMENT,
            range_min: self.range[0],
            range_max: self.range[1],
            time_increment: 0.0,
            laser_offset: self.mounting,
            odom: None,
            received: Some(Instant::now()),
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use cloi_core::sensor::ld06::{Ld06Packet, Ld06Point, POINTS};

    /// The packets of `turns` revolutions of a head in a round room of radius `r_mm`.
    fn turns(turns: usize, r_mm: u16) -> Vec<u8> {
        let per_turn = 38;
        let step = 36_000 / (per_turn * POINTS) as u32;
        let mut bytes = Vec::new();
        for k in 0..turns * per_turn {
            let start = ((k % per_turn) * POINTS) as u32 * step;
            let p = Ld06Packet {
                speed_dps: 3600,
                start_cdeg: start as u16,
                end_cdeg: ((start + 11 * step) % 36_000) as u16,
                stamp_ms: 0,
                points: [Ld06Point {
                    distance_mm: r_mm,
                    intensity: 200,
                }; POINTS],
            };
            bytes.extend_from_slice(&p.encode());
        }
        bytes
    }

    #[test]
    fn whole_turns_become_scans_after_the_first_and_damage_is_counted() {
        let mut a = Assembler::new(super::super::LidarKind::Ld06, Se2::new(0.1, 0.0, 0.0), None);
        let mut bytes = turns(4, 2000);
        // One flipped bit in the third turn's first packet.
        bytes[2 * 38 * 47 + 10] ^= 0x10;
        let (mut scans, mut dropped) = (Vec::new(), 0);
        for b in bytes {
            match a.push(b) {
                Some(Ok(s)) => scans.push(s),
                Some(Err(())) => dropped += 1,
                None => {}
            }
        }
        // Turns end when the next one starts: three ends seen, the first dropped.
        assert_eq!((scans.len(), dropped), (2, 1));
        assert_eq!(a.counters().ld06.crc_errors, 1);
        for s in &scans {
            assert_eq!(s.ranges.len(), BEAMS);
            let seen: Vec<f32> = s.ranges.iter().copied().filter(|r| r.is_finite()).collect();
            assert!(seen.len() > 300, "{}", seen.len());
            assert!(seen.iter().all(|&r| (r - 2.0).abs() < 1e-6));
            assert_eq!(s.laser_offset, Se2::new(0.1, 0.0, 0.0));
        }
        assert!(scans[1].t_ns > scans[0].t_ns);
    }
}
