//! CARMEN log files (`.clf`, `.log`, optionally `.gz` or `.bz2`), read line by line.
//!
//! Handled lines (fields after the message name, each followed by `ipc_timestamp ipc_host
//! logger_timestamp`; the IPC time stamp is the one used, as in the benchmark's relation files):
//! * `FLASER n r1..rn x y theta odom_x odom_y odom_theta` (front laser), `RLASER` (rear laser):
//!   ranges with the laser's pose and the odometry pose. The old format has no angles: `n` beams
//!   span 180 degrees from -90 degrees, the ends included when `n` is odd (181, 361 beams) and
//!   `pi / n` apart when it is even (180, 360 beams).
//! * `ROBOTLASER1 type start_angle fov resolution max_range accuracy remission_mode n r1..rn
//!   m e1..em laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv forward_safety
//!   side_safety turn_axis`
//! * `RAWLASER1..4 type start_angle fov resolution max_range accuracy remission_mode n r1..rn
//!   m e1..em` (no poses)
//! * `ODOM x y theta tv rv accel`
//! * `PARAM name value` (e.g. `robot_frontlaser_offset`, the laser's x offset on the robot)
//! * `#` comments and blank lines are skipped; `SYNC`, `TRUEPOS`, `NMEA*` are known and skipped;
//!   any other line type is counted, and the counts are reported once at the end.
//!
//! The reader streams (memory does not grow with the log), and reports damage with the file and
//! line number. A damaged line is skipped with a warning, or is an error in strict mode; a file
//! that ends in the middle of a line or of its compressed stream yields everything before the
//! damage and a warning (an error in strict mode).

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

use crate::parse_stamp_ns;

/// Which laser a scan comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LaserSource {
    /// `FLASER`.
    Front,
    /// `RLASER`.
    Rear,
    /// `ROBOTLASER1`.
    Robot,
    /// `RAWLASER1..4` (the number).
    Raw(u8),
}

/// A planar pose `(x, y, theta)` from a log.
pub type Pose2 = (f64, f64, f64);

/// One laser scan of a CARMEN log.
#[derive(Debug, Clone, PartialEq)]
pub struct CarmenLaser {
    /// Line type.
    pub source: LaserSource,
    /// IPC time stamp (ns).
    pub stamp_ns: i64,
    /// Angle of the first beam in the laser frame (rad).
    pub angle_min: f32,
    /// Angle between beams (rad).
    pub angle_increment: f32,
    /// Maximum range of the scanner if the line gives it (`ROBOTLASER1`, `RAWLASER`).
    pub max_range: Option<f32>,
    /// Ranges (m).
    pub ranges: Vec<f32>,
    /// Remission values (empty if none).
    pub remissions: Vec<f32>,
    /// Pose of the laser in the world (odometry-integrated) frame, if the line has it.
    pub laser_pose: Option<Pose2>,
    /// Pose of the robot (odometry) if the line has it.
    pub odom_pose: Option<Pose2>,
}

/// One `ODOM` line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CarmenOdom {
    /// IPC time stamp (ns).
    pub stamp_ns: i64,
    /// Pose (m, m, rad).
    pub pose: Pose2,
    /// Forward speed (m/s).
    pub tv: f64,
    /// Turn rate (rad/s).
    pub rv: f64,
    /// Acceleration (m/s^2).
    pub accel: f64,
}

/// One message of a CARMEN log.
#[derive(Debug, Clone, PartialEq)]
pub enum CarmenRecord {
    /// A laser scan.
    Laser(CarmenLaser),
    /// Wheel odometry.
    Odom(CarmenOdom),
    /// A parameter.
    Param {
        /// Name.
        name: String,
        /// Value as written.
        value: String,
    },
}

/// Counts of what a reader saw, and its warnings.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CarmenStats {
    /// Lines read.
    pub lines: u64,
    /// Bytes of text read (after decompression).
    pub bytes: u64,
    /// Laser scans yielded.
    pub lasers: u64,
    /// Odometry messages yielded.
    pub odoms: u64,
    /// Parameters yielded.
    pub params: u64,
    /// Known line types that are skipped (`SYNC`, `TRUEPOS`, `NMEA*`), by name.
    pub skipped: BTreeMap<String, u64>,
    /// Unknown line types, by name.
    pub unknown: BTreeMap<String, u64>,
    /// Damaged lines skipped.
    pub damaged: u64,
    /// Laser or odometry lines whose time stamp is earlier than the previous line's of the
    /// same kind (intel.clf has about 600 of each).
    pub stamps_stepping_back: u64,
    /// Warnings, e.g. damaged lines (the first few) and truncation.
    pub warnings: Vec<String>,
    /// The file ended inside a line or compressed stream.
    pub truncated: bool,
}

/// At most this many damaged lines are described one by one.
const MAX_LINE_WARNINGS: u64 = 10;

impl CarmenStats {
    /// A one-line account of the unknown line types, if any (for reporting once).
    pub fn unknown_summary(&self) -> Option<String> {
        if self.unknown.is_empty() {
            return None;
        }
        let list: Vec<String> = self
            .unknown
            .iter()
            .map(|(k, v)| format!("{k} x{v}"))
            .collect();
        Some(format!(
            "skipped unknown CARMEN line types: {}",
            list.join(", ")
        ))
    }
}

/// Streams the records of a CARMEN log.
pub struct CarmenReader {
    input: Box<dyn BufRead>,
    path: PathBuf,
    strict: bool,
    line: String,
    stats: CarmenStats,
    done: bool,
    last_laser_ns: Option<i64>,
    last_odom_ns: Option<i64>,
}

impl std::fmt::Debug for CarmenReader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CarmenReader")
            .field("path", &self.path)
            .field("strict", &self.strict)
            .field("stats", &self.stats)
            .finish()
    }
}

/// Opens a file, undoing gzip or bzip2 compression (recognised by their magic bytes).
///
/// # Errors
/// The file cannot be opened.
pub fn open_maybe_compressed(path: &Path) -> Result<Box<dyn BufRead>> {
    let file = File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let mut buffered = BufReader::with_capacity(1 << 16, file);
    let head = buffered
        .fill_buf()
        .with_context(|| format!("reading {}", path.display()))?;
    let reader: Box<dyn BufRead> = if head.starts_with(&[0x1f, 0x8b]) {
        Box::new(BufReader::with_capacity(
            1 << 16,
            flate2::bufread::MultiGzDecoder::new(buffered),
        ))
    } else if head.starts_with(b"BZh") {
        Box::new(BufReader::with_capacity(
            1 << 16,
            bzip2::bufread::MultiBzDecoder::new(buffered),
        ))
    } else {
        Box::new(buffered)
    };
    Ok(reader)
}

impl CarmenReader {
    /// Opens a log (plain, `.gz` or `.bz2`). In `strict` mode damage is an error.
    ///
    /// # Errors
    /// The file cannot be opened.
    pub fn open(path: &Path, strict: bool) -> Result<Self> {
        let input = open_maybe_compressed(path)?;
        Ok(Self::from_reader(input, path, strict))
    }

    /// Reads a log from any buffered reader; `path` is used in messages.
    pub fn from_reader(input: Box<dyn BufRead>, path: &Path, strict: bool) -> Self {
        Self {
            input,
            path: path.to_owned(),
            strict,
            line: String::with_capacity(8192),
            stats: CarmenStats::default(),
            done: false,
            last_laser_ns: None,
            last_odom_ns: None,
        }
    }

    /// What was seen so far (complete once the iterator has ended).
    pub fn stats(&self) -> &CarmenStats {
        &self.stats
    }

    fn warn(&mut self, message: String) {
        log::warn!("{message}");
        self.stats.warnings.push(message);
    }

    /// Reads the next line into `self.line`; `Ok(false)` at the end.
    fn next_line(&mut self) -> Result<bool> {
        self.line.clear();
        match self.input.read_line(&mut self.line) {
            Ok(0) => Ok(false),
            Ok(n) => {
                self.stats.lines += 1;
                self.stats.bytes += n as u64;
                Ok(true)
            }
            Err(err) => {
                let what = format!(
                    "{}: after line {}: the file is damaged or truncated ({err})",
                    self.path.display(),
                    self.stats.lines
                );
                self.stats.truncated = true;
                if self.strict {
                    bail!(what);
                }
                self.warn(format!("{what}; kept what came before"));
                Ok(false)
            }
        }
    }

    fn next_record(&mut self) -> Result<Option<CarmenRecord>> {
        loop {
            if !self.next_line()? {
                return Ok(None);
            }
            let complete = self.line.ends_with('\n');
            let text = self.line.trim();
            if text.is_empty() || text.starts_with('#') {
                continue;
            }
            let line_no = self.stats.lines;
            match parse_line(text) {
                Ok(Parsed::Record(record)) => {
                    let (last, stamp) = match &record {
                        CarmenRecord::Laser(l) => {
                            self.stats.lasers += 1;
                            (&mut self.last_laser_ns, l.stamp_ns)
                        }
                        CarmenRecord::Odom(o) => {
                            self.stats.odoms += 1;
                            (&mut self.last_odom_ns, o.stamp_ns)
                        }
                        CarmenRecord::Param { .. } => {
                            self.stats.params += 1;
                            return Ok(Some(record));
                        }
                    };
                    if last.is_some_and(|l| stamp < l) {
                        self.stats.stamps_stepping_back += 1;
                    }
                    *last = Some(stamp);
                    return Ok(Some(record));
                }
                Ok(Parsed::Skipped(name)) => {
                    *self.stats.skipped.entry(name).or_default() += 1;
                }
                Ok(Parsed::Unknown(name)) => {
                    *self.stats.unknown.entry(name).or_default() += 1;
                }
                Err(reason) => {
                    let what = format!("{}:{line_no}: {reason}", self.path.display());
                    if !complete {
                        // The last line stops short: the file was cut.
                        self.stats.truncated = true;
                        if self.strict {
                            bail!("{what} (the file ends inside this line)");
                        }
                        self.warn(format!(
                            "{what}: the file ends inside this line (truncated); kept the {} lines before it",
                            line_no - 1
                        ));
                        return Ok(None);
                    }
                    if self.strict {
                        bail!(what);
                    }
                    self.stats.damaged += 1;
                    if self.stats.damaged <= MAX_LINE_WARNINGS {
                        self.warn(format!("{what}; line skipped"));
                    }
                }
            }
        }
    }
}

impl Iterator for CarmenReader {
    type Item = Result<CarmenRecord>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        let item = self.next_record();
        match item {
            Ok(Some(record)) => Some(Ok(record)),
            Ok(None) => {
                self.done = true;
                if self.stats.damaged > MAX_LINE_WARNINGS {
                    let n = self.stats.damaged;
                    self.warn(format!(
                        "{}: {n} damaged lines skipped in all",
                        self.path.display()
                    ));
                }
                if let Some(summary) = self.stats.unknown_summary() {
                    let msg = format!("{}: {summary}", self.path.display());
                    self.warn(msg);
                }
                None
            }
            Err(err) => {
                self.done = true;
                Some(Err(err))
            }
        }
    }
}

enum Parsed {
    Record(CarmenRecord),
    Skipped(String),
    Unknown(String),
}

/// Tokens of a line with typed, located errors.
struct Fields<'a> {
    iter: std::str::SplitAsciiWhitespace<'a>,
    index: usize,
}

impl<'a> Fields<'a> {
    fn next_str(&mut self, what: &str) -> std::result::Result<&'a str, String> {
        self.index += 1;
        self.iter
            .next()
            .ok_or_else(|| format!("missing field {} ({what})", self.index))
    }

    fn f64(&mut self, what: &str) -> std::result::Result<f64, String> {
        let s = self.next_str(what)?;
        s.parse()
            .map_err(|_| format!("field {} ({what}) is not a number: {s:?}", self.index))
    }

    fn f32(&mut self, what: &str) -> std::result::Result<f32, String> {
        let s = self.next_str(what)?;
        s.parse()
            .map_err(|_| format!("field {} ({what}) is not a number: {s:?}", self.index))
    }

    fn count(&mut self, what: &str) -> std::result::Result<usize, String> {
        let s = self.next_str(what)?;
        let n: usize = s
            .parse()
            .map_err(|_| format!("field {} ({what}) is not a count: {s:?}", self.index))?;
        // No scanner has more beams; a larger count is damage, not a reason to allocate.
        if n > 100_000 {
            return Err(format!(
                "field {} ({what}) is implausibly large: {n}",
                self.index
            ));
        }
        Ok(n)
    }

    fn f32s(&mut self, n: usize, what: &str) -> std::result::Result<Vec<f32>, String> {
        (0..n).map(|_| self.f32(what)).collect()
    }

    fn pose(&mut self, what: &str) -> std::result::Result<Pose2, String> {
        Ok((self.f64(what)?, self.f64(what)?, self.f64(what)?))
    }

    /// `ipc_timestamp host logger_timestamp`: the IPC time in ns.
    fn stamp(&mut self) -> std::result::Result<i64, String> {
        let s = self.next_str("timestamp")?;
        let ns = parse_stamp_ns(s)
            .ok_or_else(|| format!("field {} (timestamp) is not a time: {s:?}", self.index))?;
        self.next_str("host")?;
        let s = self.next_str("logger timestamp")?;
        if parse_stamp_ns(s).is_none() {
            return Err(format!(
                "field {} (logger timestamp) is not a time: {s:?}",
                self.index
            ));
        }
        Ok(ns)
    }

    /// Checks that the line ends here: a field more means the counts before it were wrong
    /// and every field after the beams was read from the wrong place.
    fn end(&mut self) -> std::result::Result<(), String> {
        let extra = self.iter.clone().count();
        if extra > 0 {
            return Err(format!(
                "{extra} field(s) after the last one (field {}); the line is damaged",
                self.index
            ));
        }
        Ok(())
    }
}

/// Beam angles of the old `FLASER`/`RLASER` lines (no angles given): 180 degrees from -90.
pub fn old_laser_angles(beams: usize) -> (f32, f32) {
    let fov = std::f64::consts::PI;
    let increment = if beams % 2 == 1 && beams > 1 {
        fov / (beams - 1) as f64
    } else {
        fov / beams.max(1) as f64
    };
    ((-fov / 2.0) as f32, increment as f32)
}

fn parse_line(text: &str) -> std::result::Result<Parsed, String> {
    let mut tokens = text.split_ascii_whitespace();
    let Some(name) = tokens.next() else {
        return Ok(Parsed::Skipped(String::new()));
    };
    let mut f = Fields {
        iter: tokens,
        index: 1,
    };
    let record = match name {
        "FLASER" | "RLASER" => {
            let n = f.count("number of readings")?;
            let ranges = f.f32s(n, "range")?;
            let laser_pose = f.pose("laser pose")?;
            let odom_pose = f.pose("odometry pose")?;
            let stamp_ns = f.stamp()?;
            let (angle_min, angle_increment) = old_laser_angles(n);
            CarmenRecord::Laser(CarmenLaser {
                source: if name == "FLASER" {
                    LaserSource::Front
                } else {
                    LaserSource::Rear
                },
                stamp_ns,
                angle_min,
                angle_increment,
                max_range: None,
                ranges,
                remissions: Vec::new(),
                laser_pose: Some(laser_pose),
                odom_pose: Some(odom_pose),
            })
        }
        "ROBOTLASER1" | "RAWLASER1" | "RAWLASER2" | "RAWLASER3" | "RAWLASER4" => {
            let _laser_type = f.next_str("laser type")?;
            let start_angle = f.f32("start angle")?;
            let _fov = f.f32("field of view")?;
            let resolution = f.f32("angular resolution")?;
            let max_range = f.f32("maximum range")?;
            let _accuracy = f.f32("accuracy")?;
            let _remission_mode = f.next_str("remission mode")?;
            let n = f.count("number of readings")?;
            let ranges = f.f32s(n, "range")?;
            let m = f.count("number of remissions")?;
            let remissions = f.f32s(m, "remission")?;
            let (source, laser_pose, odom_pose) = if name == "ROBOTLASER1" {
                let laser = f.pose("laser pose")?;
                let robot = f.pose("robot pose")?;
                for what in ["tv", "rv", "forward safety", "side safety", "turn axis"] {
                    f.f64(what)?;
                }
                (LaserSource::Robot, Some(laser), Some(robot))
            } else {
                let k = name.as_bytes().last().map_or(0, |b| b - b'0');
                (LaserSource::Raw(k), None, None)
            };
            let stamp_ns = f.stamp()?;
            CarmenRecord::Laser(CarmenLaser {
                source,
                stamp_ns,
                angle_min: start_angle,
                angle_increment: resolution,
                max_range: Some(max_range),
                ranges,
                remissions,
                laser_pose,
                odom_pose,
            })
        }
        "ODOM" => {
            let pose = f.pose("pose")?;
            let tv = f.f64("tv")?;
            let rv = f.f64("rv")?;
            let accel = f.f64("accel")?;
            let stamp_ns = f.stamp()?;
            CarmenRecord::Odom(CarmenOdom {
                stamp_ns,
                pose,
                tv,
                rv,
                accel,
            })
        }
        "PARAM" => {
            let name = f.next_str("name")?.to_owned();
            let value = f.next_str("value")?.to_owned();
            CarmenRecord::Param { name, value }
        }
        "SYNC" | "TRUEPOS" => return Ok(Parsed::Skipped(name.to_owned())),
        other if other.starts_with("NMEA") => return Ok(Parsed::Skipped(other.to_owned())),
        other => return Ok(Parsed::Unknown(other.to_owned())),
    };
    if !matches!(record, CarmenRecord::Param { .. }) {
        f.end()?;
    }
    Ok(Parsed::Record(record))
}

/// Reads `Read` input fully as a CARMEN log (tests and small inputs).
pub fn reader_from_bytes(bytes: Vec<u8>, name: &str, strict: bool) -> CarmenReader {
    let input: Box<dyn BufRead> = Box::new(BufReader::new(std::io::Cursor::new(bytes)));
    CarmenReader::from_reader(input, Path::new(name), strict)
}

/// Wraps any reader (e.g. a decoder) for [`CarmenReader::from_reader`].
pub fn buffered(input: impl Read + 'static) -> Box<dyn BufRead> {
    Box::new(BufReader::with_capacity(1 << 16, input))
}

#[cfg(test)]
mod tests {
    use std::io::Write;

    use super::*;

    const LOG: &str = "# CARMEN Logfile\n\
PARAM robot_frontlaser_offset 0.12 nohost 0\n\
ODOM 1.0 2.0 0.5 0.3 0.1 0.0 100.250000 host 0.1\n\
FLASER 3 1.0 2.0 81.83 1.1 2.1 0.5 1.0 2.0 0.5 100.300001 host 0.2\n\
TRUEPOS 1 2 3 4 5 6 100.3 host 0.3\n\
FOO 1 2 3\n\
FOO 4\n\
RAWLASER1 0 -1.5708 3.1416 0.0175 81.9 0.01 0 2 1.5 2.5 0 100.4 host 0.4\n\
ROBOTLASER1 0 -1.5 3.1416 0.0175 81.9 0.01 0 2 1.5 2.5 2 7 8 0.1 0.2 0.3 0.4 0.5 0.6 0 0 0 0 0 100.5 host 0.5\n";

    fn read_all(reader: CarmenReader) -> (Vec<CarmenRecord>, CarmenStats) {
        let mut reader = reader;
        let records: Vec<_> = reader.by_ref().map(|r| r.unwrap()).collect();
        (records, reader.stats().clone())
    }

    #[test]
    fn reads_every_line_type() {
        let (records, stats) = read_all(reader_from_bytes(LOG.into(), "t.clf", false));
        assert_eq!(records.len(), 5);
        assert_eq!(
            records[0],
            CarmenRecord::Param {
                name: "robot_frontlaser_offset".into(),
                value: "0.12".into()
            }
        );
        let CarmenRecord::Odom(odom) = &records[1] else {
            panic!()
        };
        assert_eq!(odom.stamp_ns, 100_250_000_000);
        assert_eq!(odom.pose, (1.0, 2.0, 0.5));
        assert_eq!((odom.tv, odom.rv), (0.3, 0.1));
        let CarmenRecord::Laser(laser) = &records[2] else {
            panic!()
        };
        assert_eq!(laser.source, LaserSource::Front);
        assert_eq!(laser.ranges, vec![1.0, 2.0, 81.83]);
        assert_eq!(laser.stamp_ns, 100_300_001_000);
        assert_eq!(laser.laser_pose, Some((1.1, 2.1, 0.5)));
        assert_eq!(laser.odom_pose, Some((1.0, 2.0, 0.5)));
        let CarmenRecord::Laser(raw) = &records[3] else {
            panic!()
        };
        assert_eq!(raw.source, LaserSource::Raw(1));
        assert_eq!(raw.max_range, Some(81.9));
        assert_eq!(raw.laser_pose, None);
        let CarmenRecord::Laser(robot) = &records[4] else {
            panic!()
        };
        assert_eq!(robot.source, LaserSource::Robot);
        assert_eq!(robot.remissions, vec![7.0, 8.0]);
        assert_eq!(robot.laser_pose, Some((0.1, 0.2, 0.3)));
        assert_eq!(robot.odom_pose, Some((0.4, 0.5, 0.6)));
        assert_eq!(robot.angle_min, -1.5);
        assert_eq!(stats.skipped.get("TRUEPOS"), Some(&1));
        assert_eq!(stats.unknown.get("FOO"), Some(&2));
        assert_eq!((stats.lasers, stats.odoms, stats.params), (3, 1, 1));
        // Unknown types are reported once, in one warning.
        assert_eq!(stats.warnings.len(), 1);
        assert!(stats.warnings[0].contains("FOO x2"));
        assert!(!stats.truncated);
    }

    #[test]
    fn old_laser_angle_conventions() {
        let (a, inc) = old_laser_angles(181);
        assert!((a + std::f32::consts::FRAC_PI_2).abs() < 1e-6);
        assert!((inc - 1f32.to_radians()).abs() < 1e-6);
        let (_, inc) = old_laser_angles(180);
        assert!((inc - 1f32.to_radians()).abs() < 1e-6);
        let (_, inc) = old_laser_angles(361);
        assert!((inc - 0.5f32.to_radians()).abs() < 1e-6);
    }

    #[test]
    fn a_beam_too_many_or_too_few_is_damage_not_a_shifted_stamp() {
        // Three beams announced; the good line, one with a beam missing, one with a beam more.
        let good = "FLASER 3 1 2 3 0 0 0 0 0 0 19.5 h 19.5";
        let short = "FLASER 3 1 2 0 0 0 0 0 0 19.6 h 19.6";
        let long = "FLASER 3 1 2 3 4 0 0 0 0 0 0 19.7 h 19.7";
        let trailing = "FLASER 3 1 2 3 0 0 0 0 0 0 19.8 h 19.8 7";
        let log = format!("{good}\n{short}\n{long}\n{trailing}\n");
        let (records, stats) = read_all(reader_from_bytes(log.into(), "b.clf", false));
        assert_eq!(records.len(), 1);
        assert_eq!(stats.damaged, 3);
        let w = &stats.warnings;
        assert!(
            w[0].starts_with("b.clf:2:") && w[0].contains("not a time"),
            "{w:?}"
        );
        assert!(
            w[1].starts_with("b.clf:3:") && w[1].contains("not a time"),
            "{w:?}"
        );
        assert!(
            w[2].starts_with("b.clf:4:") && w[2].contains("after the last"),
            "{w:?}"
        );
    }

    #[test]
    fn damaged_line_is_located_and_skipped_or_fatal() {
        let log = "ODOM 1 2 3 0 0 0 5.0 h 0\nODOM 1 x 3 0 0 0 6.0 h 0\nODOM 1 2 3 0 0 0 4.0 h 0\n";
        let (records, stats) = read_all(reader_from_bytes(log.into(), "d.clf", false));
        assert_eq!(records.len(), 2);
        assert_eq!(stats.stamps_stepping_back, 1);
        assert_eq!(stats.damaged, 1);
        assert!(
            stats.warnings[0].starts_with("d.clf:2: field 3 (pose) is not a number"),
            "{:?}",
            stats.warnings
        );
        let mut strict = reader_from_bytes(log.into(), "d.clf", true);
        assert!(strict.next().unwrap().is_ok());
        let err = strict.next().unwrap().unwrap_err().to_string();
        assert!(err.starts_with("d.clf:2:"), "{err}");
        assert!(strict.next().is_none());
    }

    #[test]
    fn truncated_file_keeps_what_came_before() {
        let log = "ODOM 1 2 3 0 0 0 5.0 h 0\nFLASER 3 1.0 2.0";
        let (records, stats) = read_all(reader_from_bytes(log.into(), "t.clf", false));
        assert_eq!(records.len(), 1);
        assert!(stats.truncated);
        assert!(
            stats.warnings[0].contains("truncated"),
            "{:?}",
            stats.warnings
        );
        let mut strict = reader_from_bytes(log.into(), "t.clf", true);
        assert!(strict.next().unwrap().is_ok());
        assert!(strict.next().unwrap().is_err());
    }

    #[test]
    fn gzip_and_bzip2_are_transparent() {
        let dir = tempfile::tempdir().unwrap();
        let gz = dir.path().join("a.clf.gz");
        let mut enc =
            flate2::write::GzEncoder::new(File::create(&gz).unwrap(), flate2::Compression::fast());
        enc.write_all(LOG.as_bytes()).unwrap();
        enc.finish().unwrap();
        let bz = dir.path().join("a.log.bz2");
        let mut enc =
            bzip2::write::BzEncoder::new(File::create(&bz).unwrap(), bzip2::Compression::fast());
        enc.write_all(LOG.as_bytes()).unwrap();
        enc.finish().unwrap();
        let (plain, _) = read_all(reader_from_bytes(LOG.into(), "p", false));
        for path in [&gz, &bz] {
            let (records, _) = read_all(CarmenReader::open(path, false).unwrap());
            assert_eq!(records, plain);
        }
        // A cut gzip stream: the lines before the cut, and a truncation warning.
        let bytes = std::fs::read(&gz).unwrap();
        let cut = dir.path().join("cut.clf.gz");
        std::fs::write(&cut, &bytes[..bytes.len() - 30]).unwrap();
        let mut reader = CarmenReader::open(&cut, false).unwrap();
        let n = reader.by_ref().filter(|r| r.is_ok()).count();
        assert!(n < plain.len());
        assert!(reader.stats().truncated);
        let mut strict = CarmenReader::open(&cut, true).unwrap();
        assert!(strict.any(|r| r.is_err()));
    }
}
