//! The mapper's input: one time-ordered stream of [`SensorEvent`]s from a CARMEN log, a ROS 2
//! bag (MCAP) or the simulator, read with constant memory.
//!
//! * **CARMEN** (`.clf`, `.log`, also gzip/bzip2-compressed; recognised as "not MCAP"):
//!   `ODOM` lines become [`SensorEvent::Odometry`]; the chosen laser's lines become
//!   [`SensorEvent::Scan`] (see [`LaserChoice`]) carrying the odometry pose of the line in
//!   [`ScanEvent::odom`]. When no `ODOM` line came since the previous scan (mit-csail has none
//!   at all), the line's odometry pose is also emitted as an `Odometry` event just before the
//!   scan. The laser's mounting is [`InputOptions::laser_offset`] if given, else the log's
//!   `PARAM robot_frontlaser_offset` / `robot_frontlaser_side_offset` /
//!   `robot_frontlaser_angular_offset` (`robot_rearlaser_*` for the rear laser, which faces
//!   backwards) if any came before the first scan, else the offset between the first scan
//!   line's laser pose and odometry pose, else the identity; it is fixed at the first scan.
//!   `range_max` is [`InputOptions::range_max`], else the line's own (`ROBOTLASER1`,
//!   `RAWLASER`), else `PARAM robot_front_laser_max`, else
//!   [`crate::io::convert::DEFAULT_RANGE_MAX`] (the logs' "no return" value 81.83 m lies
//!   beyond it); `range_min` is 0.
//! * **ROS 2 bags** (an `.mcap` file, or a bag directory holding one): `LaserScan` ->
//!   `Scan`, `Odometry` -> `Odometry`, `Imu` -> `Gyro` (`angular_velocity.z`), all stamped
//!   with their header time. One topic per kind is used: the one named in
//!   [`InputOptions::topics`], else the first that delivers a message (messages on other
//!   topics of that kind are counted as skipped); an odometry topic in a global frame (`map`,
//!   `world`: a simulator's ground truth) is only taken when named. The laser's mounting is
//!   [`InputOptions::laser_offset`] if given, else the chain of static transforms
//!   (`/tf_static`) from the scan's frame up to the robot frame (the odometry's child frame,
//!   else [`InputOptions::base_frame`]), else the identity (with a warning).
//! * **`.cloilog`** (the firmware's binary sensor log that `cloi convert --to cloilog` writes,
//!   recognised by its magic): odometry records -> `Odometry`, gyro records -> `Gyro`, scan
//!   records -> `Scan` with the record's geometry, laser offset and odometry pose (in
//!   [`ScanEvent::odom`]); [`InputOptions::laser_offset`] and [`InputOptions::range_max`]
//!   override the record's. Records of unknown kinds are skipped (counted); a damaged record
//!   (CRC, length) ends the stream with an error, since the framing cannot be trusted after it.
//! * **Simulator** ([`sim_input`]): the built-in worlds of `cloi sim` with a LiDAR, wheel
//!   odometry and gyro, run on a background thread that feeds a bounded channel.
//!
//! Events are delivered in the order the source has them. Time stamps that step back are
//! passed through unchanged (the mapper rejects and counts them) and counted here, per
//! kind of event, in [`InputStats::backwards_stamps`]. NaN and infinite ranges are passed
//! through.
//!
//! **Statistics.** [`InputStream::stats`] returns a snapshot of the counts at any time;
//! [`InputStream::stats_handle`] gives a shared handle that stays valid after the stream
//! has been moved into a loop or another owner (read it once the stream has ended for the
//! final counts).

use std::collections::{HashMap, VecDeque};
use std::fs::File;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, SyncSender};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

use anyhow::{bail, Context, Result};
use cloi_core::frontend::visual::{
    CameraExtrinsic, CameraModel, Intrinsics, Kb4, Pinhole, VoConfig,
};
use cloi_core::mapper::MAX_CAMERAS;
use cloi_core::sensor::PixelFormat;
use cloi_core::Se2;

use super::resources::VisualCalibration;
use crate::io::bag_read::{BagReadOptions, BagReader, SensorMsg, TopicSelection};
use crate::io::camera_frame::{self, Pixels};
use crate::io::carmen::{CarmenLaser, CarmenReader, CarmenRecord, LaserSource};
use crate::io::convert::DEFAULT_RANGE_MAX;
pub use crate::io::parse_pose;
use crate::io::ros2::{LaserScan, TfMessage};
use crate::sim::engine::{Payload, Sample, SampleSink};
use crate::sim::output::EPOCH_NS;
use crate::sim::{SensorSet, SimConfig, Simulation};

/// One sensor measurement for the mapper.
#[derive(Debug, Clone, PartialEq)]
pub enum SensorEvent {
    /// Wheel odometry pose (robot frame in the odometry frame).
    Odometry {
        /// Time stamp (ns).
        t_ns: i64,
        /// The pose.
        pose: Se2,
    },
    /// Gyro yaw rate, rad/s.
    Gyro {
        /// Time stamp (ns).
        t_ns: i64,
        /// Rate about the robot's z axis, rad/s.
        yaw_rate: f64,
    },
    /// A planar laser scan.
    Scan(ScanEvent),
    /// A camera picture.
    Image(ImageEvent),
}

impl SensorEvent {
    /// The event's time stamp (ns).
    pub fn t_ns(&self) -> i64 {
        match self {
            SensorEvent::Odometry { t_ns, .. } | SensorEvent::Gyro { t_ns, .. } => *t_ns,
            SensorEvent::Scan(s) => s.t_ns,
            SensorEvent::Image(i) => i.t_ns,
        }
    }
}

/// A camera picture, uncompressed.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageEvent {
    /// Time stamp (ns).
    pub t_ns: i64,
    /// Which camera: 0 for the first image topic or simulated camera, 1 for the second.
    pub camera: u8,
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Bytes per row.
    pub stride: usize,
    /// Pixel layout.
    pub format: PixelFormat,
    /// The pixels, `stride * height` bytes.
    pub data: Vec<u8>,
}

/// A planar laser scan.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanEvent {
    /// Time stamp (ns).
    pub t_ns: i64,
    /// Ranges, metres (NaN, infinite and out-of-limit values are passed through).
    pub ranges: Vec<f32>,
    /// Bearing of the first beam in the laser frame, radians.
    pub angle_min: f32,
    /// Bearing step, radians.
    pub angle_increment: f32,
    /// Closest valid range, metres.
    pub range_min: f32,
    /// Farthest valid range, metres.
    pub range_max: f32,
    /// Time between beams, seconds, the first beam at `t_ns` (0: the source gives no beam
    /// times, as CARMEN logs do not).
    pub time_increment: f32,
    /// Pose of the laser on the robot.
    pub laser_offset: Se2,
    /// Odometry pose attached to the scan line if the source has one (CARMEN `FLASER`,
    /// `RLASER`, `ROBOTLASER1`).
    pub odom: Option<Se2>,
    /// When a live device's last byte of the scan arrived (host's monotonic clock), for the
    /// run's latency; `None` from files and the simulator.
    pub received: Option<std::time::Instant>,
}

/// Which laser of a CARMEN log is used.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LaserChoice {
    /// The front laser: `FLASER` or `ROBOTLASER1`, whichever comes first (the other is
    /// skipped).
    #[default]
    Front,
    /// `FLASER` only.
    Flaser,
    /// `ROBOTLASER1` only.
    RobotLaser,
    /// The rear laser, `RLASER`.
    Rear,
    /// `RAWLASER1..4`.
    Raw(u8),
}

impl std::str::FromStr for LaserChoice {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        Ok(match s.to_ascii_lowercase().as_str() {
            "front" => LaserChoice::Front,
            "flaser" => LaserChoice::Flaser,
            "robotlaser" | "robotlaser1" => LaserChoice::RobotLaser,
            "rear" | "rlaser" => LaserChoice::Rear,
            "rawlaser1" | "raw1" => LaserChoice::Raw(1),
            "rawlaser2" | "raw2" => LaserChoice::Raw(2),
            "rawlaser3" | "raw3" => LaserChoice::Raw(3),
            "rawlaser4" | "raw4" => LaserChoice::Raw(4),
            _ => {
                return Err(format!(
                    "unknown laser {s:?}; use front, flaser, robotlaser, rear or raw1..raw4"
                ))
            }
        })
    }
}

/// How an input is read.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct InputOptions {
    /// Damage in the file is an error (else damaged records are skipped and counted).
    pub strict: bool,
    /// The CARMEN laser to use.
    pub laser: LaserChoice,
    /// The laser's pose on the robot, overriding what the input says.
    pub laser_offset: Option<Se2>,
    /// `range_max` of every scan, overriding what the input says (m).
    pub range_max: Option<f32>,
    /// Bag topics (scan, odometry, IMU) to use; `None` takes the first of each kind.
    pub topics: TopicSelection,
    /// Robot frame for the laser's static transform when the bag has no odometry telling it
    /// (`None`: `base_link`).
    pub base_frame: Option<String>,
}

/// Counts of what an input delivered.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct InputStats {
    /// Scan events.
    pub scans: u64,
    /// Odometry events (including those made from CARMEN laser lines).
    pub odometry: u64,
    /// Odometry events made from the odometry pose of a CARMEN laser line.
    pub odometry_from_scans: u64,
    /// Gyro events.
    pub gyro: u64,
    /// Camera images (all cameras).
    pub images: u64,
    /// Events whose stamp is earlier than the previous event's of the same kind.
    pub backwards_stamps: u64,
    /// Records not delivered: damaged or undecodable records, lasers or topics not chosen,
    /// unknown line types, images of encodings or topics not taken, other messages the mapper
    /// does not use.
    pub skipped: u64,
    /// Earliest stamp delivered (ns).
    pub first_ns: Option<i64>,
    /// Latest stamp delivered (ns).
    pub last_ns: Option<i64>,
    /// Bytes read from the file so far (decompressed text for CARMEN logs).
    pub bytes_read: u64,
    /// The laser mounting used (once the first scan has been read).
    pub laser_offset: Option<Se2>,
    /// Where the laser mounting came from (`option`, `PARAM`, `laser line`, `tf_static`,
    /// `simulator`, `identity`).
    pub laser_offset_source: Option<String>,
    /// Warnings of the reader (damage, truncation, a missing transform).
    pub warnings: Vec<String>,
}

impl InputStats {
    /// Seconds of data between the first and the last stamp.
    pub fn data_seconds(&self) -> f64 {
        match (self.first_ns, self.last_ns) {
            (Some(a), Some(b)) => (b - a) as f64 * 1e-9,
            _ => 0.0,
        }
    }
}

/// A shared handle on the statistics of an [`InputStream`].
pub type StatsHandle = Arc<Mutex<InputStats>>;

/// What the whole input amounts to, for a progress bar.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum InputSize {
    /// Bytes of the file ([`InputStats::bytes_read`] counts up to it).
    Bytes(u64),
    /// Seconds of data (simulation: [`InputStats::data_seconds`] counts up to it).
    Seconds(f64),
    /// Unknown (compressed input).
    Unknown,
}

/// A source of events (one per input kind).
trait EventSource {
    /// The next event, `None` at the end.
    fn next_event(&mut self, stats: &mut InputStats) -> Option<Result<SensorEvent>>;
}

/// The stream of events of one input, with its statistics.
pub struct InputStream {
    source: Box<dyn EventSource>,
    stats: StatsHandle,
    last: [Option<i64>; 5],
    size: InputSize,
    done: bool,
    /// Events this long after the input's first one are dropped, ns (`--skip`).
    skip_ns: i64,
    first: Option<i64>,
}

impl std::fmt::Debug for InputStream {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("InputStream")
            .field("size", &self.size)
            .field("done", &self.done)
            .finish_non_exhaustive()
    }
}

impl InputStream {
    fn new(source: Box<dyn EventSource>, size: InputSize) -> Self {
        Self {
            source,
            stats: Arc::new(Mutex::new(InputStats::default())),
            last: [None; 5],
            size,
            done: false,
            skip_ns: 0,
            first: None,
        }
    }

    /// A snapshot of the counts so far (final once the stream has ended).
    pub fn stats(&self) -> InputStats {
        lock(&self.stats).clone()
    }

    /// A shared handle on the counts, valid after the stream is moved or dropped.
    pub fn stats_handle(&self) -> StatsHandle {
        Arc::clone(&self.stats)
    }

    /// The size of the whole input, for progress reporting.
    pub fn size(&self) -> InputSize {
        self.size
    }
}

fn lock(stats: &StatsHandle) -> std::sync::MutexGuard<'_, InputStats> {
    // A panic elsewhere while holding the lock leaves plain counters: still usable.
    stats
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl Iterator for InputStream {
    type Item = Result<SensorEvent>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            let item = self.next_read()?;
            let Ok(event) = &item else {
                return Some(item);
            };
            if self.skip_ns == 0 {
                return Some(item);
            }
            let first = *self.first.get_or_insert(event.t_ns());
            if event.t_ns() >= first.saturating_add(self.skip_ns) {
                return Some(item);
            }
        }
    }
}

impl InputStream {
    /// Drops the events of the input's first `seconds` (by their stamps), as if it started
    /// there: a run that begins anywhere along a recorded route.
    pub fn skip_seconds(mut self, seconds: f64) -> Self {
        self.skip_ns = (seconds.max(0.0) * 1e9) as i64;
        self
    }

    /// The next event as read, counted.
    fn next_read(&mut self) -> Option<Result<SensorEvent>> {
        if self.done {
            return None;
        }
        let mut stats = lock(&self.stats);
        let item = self.source.next_event(&mut stats);
        match &item {
            None | Some(Err(_)) => self.done = true,
            Some(Ok(event)) => {
                let t = event.t_ns();
                let kind = match event {
                    SensorEvent::Scan(_) => {
                        stats.scans += 1;
                        0
                    }
                    SensorEvent::Odometry { .. } => {
                        stats.odometry += 1;
                        1
                    }
                    SensorEvent::Gyro { .. } => {
                        stats.gyro += 1;
                        2
                    }
                    SensorEvent::Image(i) => {
                        stats.images += 1;
                        3 + usize::from(i.camera.min(1))
                    }
                };
                if self.last[kind].is_some_and(|l| t < l) {
                    stats.backwards_stamps += 1;
                }
                self.last[kind] = Some(t);
                stats.first_ns = Some(stats.first_ns.map_or(t, |f| f.min(t)));
                stats.last_ns = Some(stats.last_ns.map_or(t, |l| l.max(t)));
            }
        }
        item
    }
}

/// The MCAP magic bytes.
const MCAP_MAGIC: &[u8] = b"\x89MCAP0\r\n";

/// Resolves a bag directory (holding exactly one `.mcap` file) to that file.
fn resolve_path(path: &Path) -> Result<PathBuf> {
    if !path.is_dir() {
        return Ok(path.to_owned());
    }
    let mut found = Vec::new();
    for entry in std::fs::read_dir(path).with_context(|| format!("reading {}", path.display()))? {
        let p = entry?.path();
        if p.extension().is_some_and(|e| e == "mcap") {
            found.push(p);
        }
    }
    found.sort();
    match found.len() {
        1 => Ok(found.remove(0)),
        0 => bail!("{}: a directory without an .mcap file", path.display()),
        n => bail!(
            "{}: a directory with {n} .mcap files; name one of them",
            path.display()
        ),
    }
}

/// Opens a CARMEN log, a ROS 2 bag or a `.cloilog` (recognised by its content) as a stream of events.
///
/// # Errors
/// The file cannot be opened.
pub fn open_input(path: &Path, opts: &InputOptions) -> Result<InputStream> {
    let path = resolve_path(path)?;
    let mut head = [0u8; 8];
    let mut file = File::open(&path).with_context(|| format!("opening {}", path.display()))?;
    let n = file
        .read(&mut head)
        .with_context(|| format!("reading {}", path.display()))?;
    let len = file.metadata().map(|m| m.len()).ok();
    drop(file);
    if head[..n] == cloi_core::sensor::log::MAGIC {
        let file = File::open(&path).with_context(|| format!("opening {}", path.display()))?;
        let size = len.map_or(InputSize::Unknown, InputSize::Bytes);
        return Ok(InputStream::new(
            Box::new(CloilogSource::new(
                std::io::BufReader::with_capacity(1 << 16, file),
                opts,
            )),
            size,
        ));
    }
    if head[..n] == *MCAP_MAGIC {
        let options = BagReadOptions {
            strict: opts.strict,
            topics: opts.topics.clone(),
            ..BagReadOptions::default()
        };
        let reader = BagReader::open(&path, options)?;
        let size = len.map_or(InputSize::Unknown, InputSize::Bytes);
        Ok(InputStream::new(
            Box::new(BagSource::new(reader, opts)),
            size,
        ))
    } else {
        let compressed = head.starts_with(&[0x1f, 0x8b]) || head.starts_with(b"BZh");
        let reader = CarmenReader::open(&path, opts.strict)?;
        let size = match (compressed, len) {
            (false, Some(l)) => InputSize::Bytes(l),
            _ => InputSize::Unknown,
        };
        Ok(InputStream::new(
            Box::new(CarmenSource::new(reader, opts)),
            size,
        ))
    }
}

/// A CARMEN log from a reader already opened (tests, in-memory logs).
pub fn carmen_input(reader: CarmenReader, opts: &InputOptions) -> InputStream {
    InputStream::new(
        Box::new(CarmenSource::new(reader, opts)),
        InputSize::Unknown,
    )
}

// ---------------------------------------------------------------------------------------
// CARMEN

/// `PARAM`s describing a laser's mounting.
#[derive(Debug, Clone, Copy, Default)]
struct MountParams {
    x: Option<f64>,
    y: Option<f64>,
    theta: Option<f64>,
}

impl MountParams {
    fn any(&self) -> bool {
        self.x.is_some() || self.y.is_some() || self.theta.is_some()
    }

    /// The mounting; `facing` is the heading of a laser mounted without an angular offset.
    fn pose(&self, facing: f64) -> Se2 {
        Se2::new(
            self.x.unwrap_or(0.0),
            self.y.unwrap_or(0.0),
            cloi_core::geom::wrap_angle(facing + self.theta.unwrap_or(0.0)),
        )
    }
}

struct CarmenSource {
    reader: CarmenReader,
    choice: LaserChoice,
    /// The source locked onto by [`LaserChoice::Front`].
    locked: Option<LaserSource>,
    offset_override: Option<Se2>,
    range_max_override: Option<f32>,
    front_params: MountParams,
    rear_params: MountParams,
    front_laser_max: Option<f32>,
    offset: Option<Se2>,
    odom_since_scan: bool,
    pending: VecDeque<SensorEvent>,
    ignored: u64,
    warned_offsets: bool,
}

fn pose_of(p: (f64, f64, f64)) -> Se2 {
    Se2::new(p.0, p.1, p.2)
}

impl CarmenSource {
    fn new(reader: CarmenReader, opts: &InputOptions) -> Self {
        Self {
            reader,
            choice: opts.laser,
            locked: None,
            offset_override: opts.laser_offset,
            range_max_override: opts.range_max,
            front_params: MountParams::default(),
            rear_params: MountParams::default(),
            front_laser_max: None,
            offset: None,
            odom_since_scan: false,
            pending: VecDeque::with_capacity(2),
            ignored: 0,
            warned_offsets: false,
        }
    }

    fn wanted(&mut self, source: LaserSource) -> bool {
        match self.choice {
            LaserChoice::Front => match self.locked {
                Some(l) => l == source,
                None if matches!(source, LaserSource::Front | LaserSource::Robot) => {
                    self.locked = Some(source);
                    true
                }
                None => false,
            },
            LaserChoice::Flaser => source == LaserSource::Front,
            LaserChoice::RobotLaser => source == LaserSource::Robot,
            LaserChoice::Rear => source == LaserSource::Rear,
            LaserChoice::Raw(k) => source == LaserSource::Raw(k),
        }
    }

    fn param(&mut self, name: &str, value: &str) {
        let Ok(v) = value.parse::<f64>() else {
            return;
        };
        match name {
            "robot_frontlaser_offset" => self.front_params.x = Some(v),
            "robot_frontlaser_side_offset" => self.front_params.y = Some(v),
            "robot_frontlaser_angular_offset" => self.front_params.theta = Some(v),
            "robot_rearlaser_offset" => self.rear_params.x = Some(v),
            "robot_rearlaser_side_offset" => self.rear_params.y = Some(v),
            "robot_rearlaser_angular_offset" => self.rear_params.theta = Some(v),
            "robot_front_laser_max" => self.front_laser_max = Some(v as f32),
            _ => {}
        }
    }

    /// The mounting of the chosen laser, fixed at its first scan.
    fn offset(&mut self, laser: &CarmenLaser, stats: &mut InputStats) -> Se2 {
        if let Some(o) = self.offset {
            return o;
        }
        let derived = match (laser.laser_pose, laser.odom_pose) {
            (Some(l), Some(o)) => Some(pose_of(o).between(&pose_of(l))),
            _ => None,
        };
        let params = match laser.source {
            LaserSource::Rear => Some((self.rear_params, std::f64::consts::PI)),
            LaserSource::Front | LaserSource::Robot => Some((self.front_params, 0.0)),
            LaserSource::Raw(_) => None,
        }
        .filter(|(p, _)| p.any())
        .map(|(p, facing)| p.pose(facing));
        let (offset, from) = if let Some(o) = self.offset_override {
            (o, "option")
        } else if let Some(p) = params {
            if let Some(d) = derived {
                let diff = p.between(&d);
                if !self.warned_offsets && (diff.x.hypot(diff.y) > 0.01 || diff.theta.abs() > 0.01)
                {
                    self.warned_offsets = true;
                    let msg = format!(
                        "laser offset: PARAM gives ({:.3}, {:.3}, {:.3}) but the first scan line's \
                         poses give ({:.3}, {:.3}, {:.3}); using the PARAM",
                        p.x, p.y, p.theta, d.x, d.y, d.theta
                    );
                    log::warn!("{msg}");
                    stats.warnings.push(msg);
                }
            }
            (p, "PARAM")
        } else if let Some(d) = derived {
            (d, "laser line")
        } else {
            (Se2::IDENTITY, "identity")
        };
        self.offset = Some(offset);
        stats.laser_offset = Some(offset);
        stats.laser_offset_source = Some(from.into());
        offset
    }

    fn refresh(&self, stats: &mut InputStats) {
        let r = self.reader.stats();
        stats.bytes_read = r.bytes;
        stats.skipped = self.ignored + r.damaged + r.unknown.values().sum::<u64>();
        if stats.warnings.len() < r.warnings.len() {
            // The reader only ever appends.
            let start = stats.warnings.len().min(r.warnings.len());
            stats.warnings.extend_from_slice(&r.warnings[start..]);
        }
    }
}

impl EventSource for CarmenSource {
    fn next_event(&mut self, stats: &mut InputStats) -> Option<Result<SensorEvent>> {
        loop {
            if let Some(e) = self.pending.pop_front() {
                return Some(Ok(e));
            }
            let record = self.reader.next();
            self.refresh(stats);
            let record = match record? {
                Ok(r) => r,
                Err(e) => return Some(Err(e)),
            };
            match record {
                CarmenRecord::Param { name, value } => self.param(&name, &value),
                CarmenRecord::Odom(o) => {
                    self.odom_since_scan = true;
                    return Some(Ok(SensorEvent::Odometry {
                        t_ns: o.stamp_ns,
                        pose: pose_of(o.pose),
                    }));
                }
                CarmenRecord::Laser(laser) => {
                    if !self.wanted(laser.source) {
                        self.ignored += 1;
                        continue;
                    }
                    let laser_offset = self.offset(&laser, stats);
                    let odom = laser.odom_pose.map(pose_of);
                    if let (Some(pose), false) = (odom, self.odom_since_scan) {
                        stats.odometry_from_scans += 1;
                        self.pending.push_back(SensorEvent::Odometry {
                            t_ns: laser.stamp_ns,
                            pose,
                        });
                    }
                    self.odom_since_scan = false;
                    let range_max = self
                        .range_max_override
                        .or(laser.max_range)
                        .or(self.front_laser_max)
                        .unwrap_or(DEFAULT_RANGE_MAX);
                    self.pending.push_back(SensorEvent::Scan(ScanEvent {
                        t_ns: laser.stamp_ns,
                        ranges: laser.ranges,
                        angle_min: laser.angle_min,
                        angle_increment: laser.angle_increment,
                        range_min: 0.0,
                        range_max,
                        time_increment: 0.0,
                        laser_offset,
                        odom,
                        received: None,
                    }));
                }
            }
        }
    }
}

// ---------------------------------------------------------------------------------------
// .cloilog

/// A `.cloilog` read frame by frame with the core's decoder.
struct CloilogSource<R> {
    reader: R,
    /// The current frame's bytes (at most [`cloi_core::sensor::log::MAX_FRAME`]).
    frame: Vec<u8>,
    offset_override: Option<Se2>,
    range_max_override: Option<f32>,
    /// Bytes consumed so far.
    offset: u64,
    header: Option<cloi_core::sensor::log::LogHeader>,
    records: u32,
    ignored: u64,
    failed: bool,
}

impl<R: Read> CloilogSource<R> {
    fn new(reader: R, opts: &InputOptions) -> Self {
        Self {
            reader,
            frame: Vec::with_capacity(cloi_core::sensor::log::MAX_FRAME),
            offset_override: opts.laser_offset,
            range_max_override: opts.range_max,
            offset: 0,
            header: None,
            records: 0,
            ignored: 0,
            failed: false,
        }
    }

    /// Reads exactly `n` more bytes onto `frame`; `Ok(false)` at a clean end before any byte.
    fn fill(&mut self, n: usize) -> Result<bool> {
        let start = self.frame.len();
        self.frame.resize(start + n, 0);
        let mut got = 0;
        while got < n {
            match self.reader.read(&mut self.frame[start + got..]) {
                Ok(0) => break,
                Ok(k) => got += k,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e).context("reading the cloilog"),
            }
        }
        self.frame.truncate(start + got);
        if got == 0 && start == 0 {
            return Ok(false);
        }
        if got < n {
            bail!(
                "cloilog at byte {}: {}",
                self.offset,
                cloi_core::sensor::log::LogError::Truncated {
                    have: start + got,
                    need: start + n,
                }
            );
        }
        Ok(true)
    }

    fn next_record(&mut self, stats: &mut InputStats) -> Result<Option<SensorEvent>> {
        use cloi_core::sensor::log::{
            decode_frame, decode_header, frame_len, LogError, LogRecord, HEADER_LEN,
        };
        let damaged = |offset: u64, e: LogError| anyhow::anyhow!("cloilog at byte {offset}: {e}");
        if self.header.is_none() {
            self.frame.clear();
            if !self.fill(HEADER_LEN)? {
                bail!("cloilog: empty file");
            }
            let (header, len) = decode_header(&self.frame)
                .map_err(|e| damaged(0, e))?
                .ok_or_else(|| damaged(0, LogError::BadMagic))?;
            // A longer header of a later minor revision: skip what this reader does not know.
            if len > HEADER_LEN {
                self.frame.clear();
                self.fill(len - HEADER_LEN)?;
            }
            self.header = Some(header);
            self.offset = len as u64;
        }
        loop {
            self.frame.clear();
            if !self.fill(8)? {
                if let Some(expected) = self.header.and_then(|h| h.record_count) {
                    if expected != self.records {
                        return Err(damaged(
                            self.offset,
                            LogError::CountMismatch {
                                expected,
                                found: self.records,
                            },
                        ));
                    }
                }
                return Ok(None);
            }
            let total = frame_len(&self.frame)
                .map_err(|e| damaged(self.offset, e))?
                .unwrap_or(8);
            self.fill(total - 8)?;
            let at = self.offset;
            self.offset += total as u64;
            stats.bytes_read = self.offset;
            let (record, _) = decode_frame(&self.frame).map_err(|e| damaged(at, e))?;
            self.records = self.records.saturating_add(1);
            let event = match record {
                LogRecord::Odometry(o) => SensorEvent::Odometry {
                    t_ns: o.stamp.as_nanos(),
                    pose: o.pose,
                },
                LogRecord::Gyro(g) => SensorEvent::Gyro {
                    t_ns: g.stamp.as_nanos(),
                    yaw_rate: g.yaw_rate,
                },
                LogRecord::Scan(s) => {
                    let m = s.meta;
                    let laser_offset = self.offset_override.unwrap_or(m.laser_offset);
                    if stats.laser_offset.is_none() {
                        stats.laser_offset = Some(laser_offset);
                        stats.laser_offset_source = Some(
                            if self.offset_override.is_some() {
                                "option"
                            } else {
                                "cloilog"
                            }
                            .into(),
                        );
                    }
                    SensorEvent::Scan(ScanEvent {
                        t_ns: m.stamp.as_nanos(),
                        ranges: s.ranges().collect(),
                        angle_min: m.geometry.angle_min,
                        angle_increment: m.geometry.angle_increment,
                        range_min: m.geometry.range_min,
                        range_max: self.range_max_override.unwrap_or(m.geometry.range_max),
                        time_increment: 0.0,
                        laser_offset,
                        odom: m.odom,
                        received: None,
                    })
                }
                LogRecord::Unknown { .. } => {
                    self.ignored += 1;
                    stats.skipped = self.ignored;
                    continue;
                }
            };
            return Ok(Some(event));
        }
    }
}

impl<R: Read> EventSource for CloilogSource<R> {
    fn next_event(&mut self, stats: &mut InputStats) -> Option<Result<SensorEvent>> {
        if self.failed {
            return None;
        }
        let item = self.next_record(stats).transpose();
        if matches!(item, Some(Err(_))) {
            self.failed = true;
        }
        item
    }
}

// ---------------------------------------------------------------------------------------
// ROS 2 bags

struct BagSource {
    reader: BagReader,
    offset_override: Option<Se2>,
    range_max_override: Option<f32>,
    base_frame: Option<String>,
    /// Static transforms: child frame -> (parent frame, pose of the child in the parent).
    statics: HashMap<String, (String, Se2)>,
    /// Mounting per scan frame, found at the frame's first scan.
    offsets: HashMap<String, Se2>,
    /// Chosen topic per kind: scan, odometry, IMU.
    topics: [Option<Arc<str>>; 3],
    /// The odometry topic was named by the user (then any frame is taken).
    odom_named: bool,
    /// Odometry topics passed over for their global frame.
    passed_over: Vec<Arc<str>>,
    /// Image topics in order of their first message: camera 0, camera 1.
    cameras: Vec<Arc<str>>,
    /// Reasons images were refused, each warned about once.
    image_refusals: Vec<String>,
    ignored: u64,
}

impl BagSource {
    fn new(reader: BagReader, opts: &InputOptions) -> Self {
        Self {
            reader,
            offset_override: opts.laser_offset,
            range_max_override: opts.range_max,
            base_frame: opts.base_frame.clone(),
            statics: HashMap::new(),
            offsets: HashMap::new(),
            topics: [None, None, None],
            odom_named: opts.topics.odom.is_some(),
            passed_over: Vec::new(),
            cameras: Vec::new(),
            image_refusals: Vec::new(),
            ignored: 0,
        }
    }

    /// Whether an odometry message on `topic` in frame `frame` is the wheel odometry to use.
    /// Without a named topic, messages in a global frame (`map`, `world`) are passed over:
    /// REP 105 puts odometry in the `odom` frame, and a `nav_msgs/Odometry` in a global frame
    /// is a global pose (a simulator's ground truth, another localizer), which must not stand
    /// in for the wheels.
    fn odometry_topic(&mut self, topic: &Arc<str>, frame: &str) -> bool {
        if !self.odom_named && self.topics[1].is_none() && matches!(strip(frame), "map" | "world") {
            if !self.passed_over.iter().any(|t| t == topic) {
                let msg = format!(
                    "odometry topic {topic} is in the global frame {frame:?}, not wheel odometry; \
                     passed over (name it with --odom-topic to use it)"
                );
                log::info!("{msg}");
                self.passed_over.push(Arc::clone(topic));
            }
            return false;
        }
        self.chosen(1, topic)
    }

    /// Whether `topic` is the chosen topic of `kind` (locking onto the first one seen).
    fn chosen(&mut self, kind: usize, topic: &Arc<str>) -> bool {
        match &self.topics[kind] {
            Some(t) => t == topic,
            None => {
                self.topics[kind] = Some(Arc::clone(topic));
                true
            }
        }
    }

    /// The camera index of image topic `topic`: the first two image topics are cameras 0 and
    /// 1 (as many as the mapper tracks); a third is not taken (warned once).
    fn camera_of(&mut self, topic: &Arc<str>, stats: &mut InputStats) -> Option<u8> {
        if let Some(i) = self.cameras.iter().position(|t| t == topic) {
            return u8::try_from(i).ok();
        }
        if self.cameras.len() < MAX_CAMERAS {
            self.cameras.push(Arc::clone(topic));
            return u8::try_from(self.cameras.len() - 1).ok();
        }
        self.refuse_image(
            format!("image topic {topic:?} not taken: the mapper tracks {MAX_CAMERAS} cameras"),
            stats,
        );
        None
    }

    /// Counts a refused image and warns once per distinct reason.
    fn refuse_image(&mut self, why: String, stats: &mut InputStats) {
        self.ignored += 1;
        if !self.image_refusals.contains(&why) {
            log::warn!("{why}");
            stats.warnings.push(why.clone());
            self.image_refusals.push(why);
        }
    }

    /// The event of an image message of camera `camera` stamped `t_ns`, or `None` (counted)
    /// when its pixels cannot be read.
    fn image_event(
        &mut self,
        camera: u8,
        t_ns: i64,
        pixels: Result<Pixels>,
        stats: &mut InputStats,
    ) -> Option<SensorEvent> {
        match pixels {
            Ok(p) => Some(SensorEvent::Image(ImageEvent {
                t_ns,
                camera,
                width: p.width,
                height: p.height,
                stride: p.stride,
                format: p.format,
                data: p.data,
            })),
            Err(e) => {
                self.refuse_image(format!("camera {camera}: {e:#}"), stats);
                None
            }
        }
    }

    fn add_statics(&mut self, msg: &TfMessage) {
        for t in &msg.transforms {
            let tr = &t.transform;
            let pose = Se2::new(tr.translation.x, tr.translation.y, tr.rotation.yaw());
            self.statics.insert(
                strip(&t.child_frame_id).to_owned(),
                (strip(&t.header.frame_id).to_owned(), pose),
            );
        }
    }

    /// The pose of `frame` in the robot frame through the static transforms.
    fn chain(&self, frame: &str, base: &str) -> Option<Se2> {
        let mut pose = Se2::IDENTITY;
        let mut at = frame;
        for _ in 0..32 {
            if at == base {
                return Some(pose);
            }
            let (parent, p) = self.statics.get(at)?;
            pose = p.compose(&pose);
            at = parent;
        }
        None
    }

    fn scan_offset(&mut self, scan: &LaserScan, stats: &mut InputStats) -> Se2 {
        if let Some(o) = self.offset_override {
            if stats.laser_offset.is_none() {
                stats.laser_offset = Some(o);
                stats.laser_offset_source = Some("option".into());
            }
            return o;
        }
        let frame = strip(&scan.header.frame_id);
        if let Some(o) = self.offsets.get(frame) {
            return *o;
        }
        let base = self.base_frame.as_deref().unwrap_or("base_link").to_owned();
        let (offset, from) = match self.chain(frame, &base) {
            Some(o) => (o, "tf_static"),
            None => {
                let msg = format!(
                    "no static transform from {base:?} to the scan frame {frame:?}; the laser \
                     is taken to sit at the robot's origin"
                );
                log::warn!("{msg}");
                stats.warnings.push(msg);
                (Se2::IDENTITY, "identity")
            }
        };
        self.offsets.insert(frame.to_owned(), offset);
        if stats.laser_offset.is_none() {
            stats.laser_offset = Some(offset);
            stats.laser_offset_source = Some(from.into());
        }
        offset
    }

    fn refresh(&self, stats: &mut InputStats) {
        let r = self.reader.stats();
        stats.bytes_read = r.bytes_read;
        stats.skipped = self.ignored + r.undecodable + r.foreign_encoding + r.unknown_channel;
        if stats.warnings.len() < r.warnings.len() {
            let start = stats.warnings.len().min(r.warnings.len());
            stats.warnings.extend_from_slice(&r.warnings[start..]);
        }
    }
}

/// A frame name without a leading `/` (ROS 1 habit).
fn strip(frame: &str) -> &str {
    frame.trim_start_matches('/')
}

impl EventSource for BagSource {
    fn next_event(&mut self, stats: &mut InputStats) -> Option<Result<SensorEvent>> {
        loop {
            let item = self.reader.next();
            self.refresh(stats);
            let message = match item? {
                Ok(m) => m,
                Err(e) => return Some(Err(e)),
            };
            match message.msg {
                SensorMsg::Tf {
                    msg,
                    is_static: true,
                } => self.add_statics(&msg),
                SensorMsg::Scan(scan) if self.chosen(0, &message.topic) => {
                    let laser_offset = self.scan_offset(&scan, stats);
                    return Some(Ok(SensorEvent::Scan(ScanEvent {
                        t_ns: scan.header.stamp.to_nanos(),
                        laser_offset,
                        angle_min: scan.angle_min,
                        angle_increment: scan.angle_increment,
                        range_min: scan.range_min,
                        range_max: self.range_max_override.unwrap_or(scan.range_max),
                        time_increment: scan.time_increment,
                        ranges: scan.ranges,
                        odom: None,
                        received: None,
                    })));
                }
                SensorMsg::Odom(odom)
                    if self.odometry_topic(&message.topic, &odom.header.frame_id) =>
                {
                    if self.base_frame.is_none() && !odom.child_frame_id.is_empty() {
                        self.base_frame = Some(strip(&odom.child_frame_id).to_owned());
                    }
                    let (x, y, theta) = odom.pose.pose.to_planar();
                    return Some(Ok(SensorEvent::Odometry {
                        t_ns: odom.header.stamp.to_nanos(),
                        pose: Se2::new(x, y, theta),
                    }));
                }
                SensorMsg::Imu(imu) if self.chosen(2, &message.topic) => {
                    return Some(Ok(SensorEvent::Gyro {
                        t_ns: imu.header.stamp.to_nanos(),
                        yaw_rate: imu.angular_velocity.z,
                    }));
                }
                SensorMsg::Image(img) => {
                    let t_ns = img.header.stamp.to_nanos();
                    if let Some(cam) = self.camera_of(&message.topic, stats) {
                        let ev = self.image_event(cam, t_ns, camera_frame::from_raw(img), stats);
                        if let Some(ev) = ev {
                            return Some(Ok(ev));
                        }
                    }
                }
                SensorMsg::CompressedImage(img) => {
                    let t_ns = img.header.stamp.to_nanos();
                    if let Some(cam) = self.camera_of(&message.topic, stats) {
                        let pixels = camera_frame::from_compressed(&img);
                        if let Some(ev) = self.image_event(cam, t_ns, pixels, stats) {
                            return Some(Ok(ev));
                        }
                    }
                }
                _ => self.ignored += 1,
            }
        }
    }
}

// ---------------------------------------------------------------------------------------
// Simulator

/// Events in flight between the simulation thread and the stream.
const SIM_CHANNEL: usize = 256;

fn sim_ns(t: f64) -> i64 {
    EPOCH_NS + (t * 1e9).round() as i64
}

/// Sends the mapper's samples into a bounded channel.
struct ChannelSink {
    tx: SyncSender<Result<SensorEvent>>,
    laser_offset: Se2,
}

/// The receiving end has gone: the simulation stops quietly.
#[derive(Debug)]
struct ReceiverGone;

impl std::fmt::Display for ReceiverGone {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("the event stream was dropped")
    }
}

impl std::error::Error for ReceiverGone {}

impl SampleSink for ChannelSink {
    fn accept(&mut self, s: &Sample) -> Result<()> {
        let t_ns = sim_ns(s.stamp);
        let event = match &s.payload {
            Payload::Odometry(o) => SensorEvent::Odometry { t_ns, pose: o.pose },
            Payload::Imu(i) => SensorEvent::Gyro {
                t_ns,
                yaw_rate: i.yaw_rate,
            },
            Payload::Scan(scan) => SensorEvent::Scan(ScanEvent {
                t_ns,
                ranges: scan.ranges.clone(),
                angle_min: scan.angle_min,
                angle_increment: scan.angle_increment,
                range_min: scan.range_min,
                range_max: scan.range_max,
                time_increment: scan.time_increment,
                laser_offset: self.laser_offset,
                odom: None,
                received: None,
            }),
            Payload::Image(cam, f) => SensorEvent::Image(ImageEvent {
                t_ns,
                camera: *cam,
                width: f.width as usize,
                height: f.height as usize,
                stride: f.width as usize,
                format: PixelFormat::Mono8,
                data: f.pixels.clone(),
            }),
            Payload::GroundTruth(_) | Payload::Fault(_) => return Ok(()),
        };
        self.tx
            .send(Ok(event))
            .map_err(|_| anyhow::Error::new(ReceiverGone))
    }
}

/// Events produced on another thread (the simulator, a live device) and handed over through
/// a bounded channel; at its end, the thread's error if it failed.
struct ThreadSource {
    rx: Receiver<Result<SensorEvent>>,
    thread: Option<JoinHandle<Result<()>>>,
}

/// The events a producer thread sends on `rx`, in the order sent; the stream ends when the
/// thread drops its sender, with the thread's error if it returns one. `size` is what the
/// progress bar shows (`Unknown` for a live device).
pub fn thread_input(
    rx: Receiver<Result<SensorEvent>>,
    thread: JoinHandle<Result<()>>,
    size: InputSize,
) -> InputStream {
    InputStream::new(
        Box::new(ThreadSource {
            rx,
            thread: Some(thread),
        }),
        size,
    )
}

impl EventSource for ThreadSource {
    fn next_event(&mut self, _stats: &mut InputStats) -> Option<Result<SensorEvent>> {
        if let Ok(item) = self.rx.recv() {
            return Some(item);
        }
        // The producer ended: report its failure, if any.
        let thread = self.thread.take()?;
        match thread.join() {
            Ok(Ok(())) => None,
            Ok(Err(e)) => Some(Err(e)),
            Err(_) => Some(Err(anyhow::anyhow!("the input thread panicked"))),
        }
    }
}

/// The simulated robot of `cloi sim --world WORLD --duration DURATION --seed SEED --sensors
/// L` (the world's fault schedule included) as a stream of events: wheel odometry, gyro and
/// LiDAR, stamped with [`EPOCH_NS`] plus the simulated header stamp, in order of arrival.
///
/// `world` is `home`, `office`, `airport` or a TOML world file. The simulation runs on a
/// background thread and waits when the consumer falls behind (a channel of 256 events);
/// dropping the stream stops it.
///
/// # Errors
/// Unknown world, an invalid world file or a bad duration.
pub fn sim_input(world: &str, duration: f64, seed: u64) -> Result<InputStream> {
    sim_session_input(world, 0, duration, seed)
}

/// [`sim_input`] of mapping session `session` of the world (its changes up to that session
/// applied; 0 is the world as written).
///
/// # Errors
/// See [`sim_input`], and changes that do not apply or block the route.
pub fn sim_session_input(
    world: &str,
    session: u32,
    duration: f64,
    seed: u64,
) -> Result<InputStream> {
    sim_input_with(
        world,
        session,
        SimConfig {
            duration,
            seed,
            sensors: SensorSet::Lidar,
            ..SimConfig::default()
        },
    )
}

/// [`sim_input`] with a full simulator configuration (sensor set L, C or C+L).
///
/// # Errors
/// See [`sim_input`].
pub fn sim_input_with(world: &str, session: u32, cfg: SimConfig) -> Result<InputStream> {
    if !(cfg.duration > 0.0 && cfg.duration.is_finite()) {
        bail!("the simulated duration must be a positive number of seconds");
    }
    if !cfg.sensors.has_lidar() && cfg.sensors != SensorSet::Camera {
        bail!("the mapper takes the simulated sensor sets L, C and C+L");
    }
    let file = crate::sim::command::load_world(world, cfg.duration)?;
    let world = crate::sim::command::session_world(&file, session, &mut std::io::sink())?;
    let sim = Simulation::new(world, cfg);
    let laser_offset = sim
        .rig
        .lidar
        .as_ref()
        .map_or(Se2::IDENTITY, |l| Se2::new(l.mount_x, 0.0, 0.0));
    let (tx, rx) = std::sync::mpsc::sync_channel(SIM_CHANNEL);
    let thread = std::thread::Builder::new()
        .name("cloi-sim".into())
        .spawn(move || {
            let mut sink = ChannelSink { tx, laser_offset };
            match sim.run(&mut sink) {
                Ok(_) => Ok(()),
                Err(e) if e.is::<ReceiverGone>() => Ok(()),
                Err(e) => Err(e),
            }
        })
        .context("starting the simulation thread")?;
    let stream = thread_input(rx, thread, InputSize::Seconds(cfg.duration));
    {
        let mut stats = lock(&stream.stats);
        stats.laser_offset = Some(laser_offset);
        stats.laser_offset_source = Some("simulator".into());
    }
    Ok(stream)
}

// ---------------------------------------------------------------------------------------
// Command-line options

/// The input options of `cloi map` (flatten into the subcommand with `#[command(flatten)]`).
#[derive(Debug, Clone, Default, PartialEq, clap::Args)]
pub struct InputArgs {
    /// CARMEN laser: front (FLASER or ROBOTLASER1, whichever comes first), flaser,
    /// robotlaser, rear, raw1..raw4.
    #[arg(long, default_value = "front")]
    pub laser: LaserChoice,
    /// Pose of the laser on the robot, `X,Y,THETA` (m, m, rad), overriding the input's PARAM
    /// lines or static transform.
    #[arg(long, value_name = "X,Y,THETA", value_parser = parse_pose, allow_hyphen_values = true)]
    pub laser_offset: Option<Se2>,
    /// `range_max` of every scan (m), overriding the input's.
    #[arg(long)]
    pub range_max: Option<f32>,
    /// Bag topic of the laser scans (default: the first `sensor_msgs/LaserScan` topic).
    #[arg(long)]
    pub scan_topic: Option<String>,
    /// Bag topic of the wheel odometry (default: the first `nav_msgs/Odometry` topic).
    #[arg(long)]
    pub odom_topic: Option<String>,
    /// Bag topic of the IMU (default: the first `sensor_msgs/Imu` topic).
    #[arg(long)]
    pub imu_topic: Option<String>,
    /// Bag topic of the only camera to track (default: the first two `sensor_msgs/Image` or
    /// `CompressedImage` topics, as cameras 0 and 1).
    #[arg(long, conflicts_with = "no_images")]
    pub image_topic: Option<String>,
    /// Leave the bag's camera images out (they do not change the LiDAR map yet; tracking
    /// them costs a few milliseconds per image).
    #[arg(long)]
    pub no_images: bool,
    /// Which sensors map: `L` (the LiDAR; images left out), `C` (camera 0 with the wheels and
    /// gyro: its visual keyframes are the frame nodes; scans left out), or `C+L` (the LiDAR
    /// maps, the images are tracked). Default: what the input has, as `C+L`.
    #[arg(long, value_parser = parse_sensors)]
    pub sensors: Option<SensorSet>,
    /// Camera 0's calibration for `--sensors C`: the sidecar `cloi sim` writes beside its bag
    /// (`X.sim.json`). Default: the sidecar beside INPUT, or the simulated robot's without
    /// INPUT.
    #[arg(long, value_name = "FILE")]
    pub camera_calibration: Option<PathBuf>,
    /// Robot frame of a bag without odometry, for the laser's static transform.
    #[arg(long)]
    pub base_frame: Option<String>,
    /// Damaged input is an error (default: skip and count it).
    #[arg(long)]
    pub strict: bool,
    /// Without INPUT: the simulated world (`home`, `office`, `airport` or a world file).
    #[arg(long, default_value = "home")]
    pub sim_world: String,
    /// Without INPUT: simulated seconds.
    #[arg(long, default_value_t = 120.0)]
    pub sim_duration: f64,
    /// Without INPUT: the simulator's seed.
    #[arg(long, default_value_t = 0)]
    pub sim_seed: u64,
    /// Without INPUT: the mapping session of the simulated world (its furniture moved, doors
    /// opened or closed, clutter added as its `[[changes]]` say; 0: the world as written).
    #[arg(long, default_value_t = 0)]
    pub sim_session: u32,
}

impl InputArgs {
    /// The reading options.
    pub fn options(&self) -> InputOptions {
        InputOptions {
            strict: self.strict,
            laser: self.laser,
            laser_offset: self.laser_offset,
            range_max: self.range_max,
            topics: TopicSelection {
                scan: self.scan_topic.clone(),
                odom: self.odom_topic.clone(),
                imu: self.imu_topic.clone(),
                // No topic has an empty name, so this takes none.
                image: if self.no_images || self.sensors == Some(SensorSet::Lidar) {
                    Some(String::new())
                } else {
                    self.image_topic.clone()
                },
            },
            base_frame: self.base_frame.clone(),
        }
    }

    /// Opens `input`, or the simulator when there is none.
    ///
    /// # Errors
    /// See [`open_input`] and [`sim_input`].
    pub fn open(&self, input: Option<&Path>) -> Result<InputStream> {
        match input {
            Some(path) => open_input(path, &self.options()),
            None => sim_input_with(
                &self.sim_world,
                self.sim_session,
                SimConfig {
                    duration: self.sim_duration,
                    seed: self.sim_seed,
                    sensors: match self.sensors {
                        Some(SensorSet::Camera) => SensorSet::Camera,
                        _ => SensorSet::Lidar,
                    },
                    ..SimConfig::default()
                },
            ),
        }
    }

    /// Camera 0's calibration when the camera maps (`--sensors C`), else `None`.
    ///
    /// # Errors
    /// Another sensor set the mapper cannot take yet (2C), or a calibration that cannot be
    /// read.
    pub fn visual_calibration(&self, input: Option<&Path>) -> Result<Option<VisualCalibration>> {
        match self.sensors {
            None | Some(SensorSet::Lidar | SensorSet::CameraLidar) => return Ok(None),
            Some(SensorSet::TwoCameras) => {
                bail!("--sensors 2C is not mapped yet (the zero-constraint of two cameras)")
            }
            Some(SensorSet::Camera) => {}
        }
        let config = VoConfig::default();
        let sidecar = match (&self.camera_calibration, input) {
            (Some(file), _) => file.clone(),
            (None, Some(path)) => path.with_extension("sim.json"),
            (None, None) => {
                let file = crate::sim::command::load_world(&self.sim_world, self.sim_duration)?;
                let world = crate::sim::command::session_world(&file, 0, &mut std::io::sink())?;
                let sim = Simulation::new(
                    world,
                    SimConfig {
                        duration: self.sim_duration,
                        seed: self.sim_seed,
                        sensors: SensorSet::Camera,
                        ..SimConfig::default()
                    },
                );
                let cam = sim
                    .rig
                    .cameras
                    .first()
                    .context("the simulated robot has no camera")?;
                return Ok(Some(VisualCalibration {
                    model: cam.core_model().context("the simulated camera's lens")?,
                    mount: cam.core_extrinsic(),
                    config,
                }));
            }
        };
        read_calibration(&sidecar, config).map(Some)
    }
}

/// `--sensors`: `L`, `C`, `2C` or `C+L`.
fn parse_sensors(s: &str) -> Result<SensorSet, String> {
    s.parse()
}

/// Camera 0 of a `cloi sim` sidecar (`X.sim.json`): its lens and mounting.
///
/// # Errors
/// A file that cannot be read, is not such a sidecar, or names no usable camera.
pub fn read_calibration(path: &Path, config: VoConfig) -> Result<VisualCalibration> {
    let text = std::fs::read_to_string(path).with_context(|| {
        format!(
            "reading the camera calibration {} (--sensors C needs one: give --camera-calibration)",
            path.display()
        )
    })?;
    let v: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
    let cam = &v["cameras"][0];
    let num = |key: &str| -> Result<f64> {
        cam[key].as_f64().with_context(|| {
            format!(
                "{}: cameras[0].{key} is missing or not a number",
                path.display()
            )
        })
    };
    let triple = |key: &str| -> Result<[f64; 3]> {
        let a = cam[key].as_array().filter(|a| a.len() == 3);
        let a =
            a.with_context(|| format!("{}: cameras[0].{key} is not [x, y, z]", path.display()))?;
        let mut out = [0.0; 3];
        for (o, x) in out.iter_mut().zip(a) {
            *o = x
                .as_f64()
                .with_context(|| format!("{}: cameras[0].{key}", path.display()))?;
        }
        Ok(out)
    };
    let k = Intrinsics {
        fx: num("fx")?,
        fy: num("fy")?,
        cx: num("cx")?,
        cy: num("cy")?,
    };
    let model = match cam["model"].as_str() {
        Some("pinhole") => CameraModel::Pinhole(Pinhole::new_checked(k)?),
        Some("kannala_brandt") => {
            let d = cam["k"]
                .as_array()
                .filter(|a| a.len() == 4)
                .with_context(|| {
                    format!("{}: cameras[0].k is not four coefficients", path.display())
                })?;
            let mut dist = [0.0; 4];
            for (o, x) in dist.iter_mut().zip(d) {
                *o = x
                    .as_f64()
                    .with_context(|| format!("{}: cameras[0].k", path.display()))?;
            }
            let max_theta = crate::sim::camera::FISHEYE_MAX_THETA_DEG.to_radians();
            CameraModel::Kb4(Kb4::new_checked(k, dist, max_theta)?)
        }
        other => bail!(
            "{}: cameras[0].model {other:?} is neither \"pinhole\" nor \"kannala_brandt\"",
            path.display()
        ),
    };
    let mount = CameraExtrinsic::mounted(
        triple("mount_xyz")?,
        num("yaw_deg")?.to_radians(),
        num("tilt_deg")?.to_radians(),
    );
    Ok(VisualCalibration {
        model,
        mount,
        config,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::bag::BagWriter;
    use crate::io::carmen::reader_from_bytes;
    use crate::io::ros2::{Header, Imu, Odometry, Pose, Time, Transform, TransformStamped};

    fn collect(stream: &mut InputStream) -> Vec<SensorEvent> {
        stream.by_ref().map(|e| e.expect("event")).collect()
    }

    fn scan_of(e: &SensorEvent) -> &ScanEvent {
        match e {
            SensorEvent::Scan(s) => s,
            other => panic!("expected a scan, got {other:?}"),
        }
    }

    /// Odometry, gyro and scan records written with the core's encoder come back as the same
    /// events, bit for bit; a cut file is an error, not a short stream.
    #[test]
    fn cloilog_records_become_events() {
        use cloi_core::sensor::log::{
            encode_gyro, encode_header, encode_odometry, encode_scan, GyroRecord, OdometryRecord,
            ScanMeta, MAX_FRAME,
        };
        use cloi_core::sensor::{ScanGeometry, Timestamp};
        let offset = Se2::new(0.12, -0.01, 0.03);
        let geometry = ScanGeometry {
            angle_min: -1.5,
            angle_increment: 0.25,
            range_min: 0.0,
            range_max: 50.0,
        };
        let ranges = [1.0f32, f32::NAN, 81.83, 2.5];
        let mut bytes = vec![0u8; 16];
        encode_header(Some(4), &mut bytes).unwrap();
        let mut frame = vec![0u8; MAX_FRAME];
        let odom = OdometryRecord {
            stamp: Timestamp::from_nanos(100),
            pose: Se2::new(1.0, 2.0, 0.3),
        };
        let n = encode_odometry(&odom, &mut frame).unwrap();
        bytes.extend_from_slice(&frame[..n]);
        let gyro = GyroRecord {
            stamp: Timestamp::from_nanos(120),
            yaw_rate: -0.25,
        };
        let n = encode_gyro(&gyro, &mut frame).unwrap();
        bytes.extend_from_slice(&frame[..n]);
        for (t, odom) in [(150, Some(Se2::new(1.1, 2.0, 0.31))), (250, None)] {
            let meta = ScanMeta {
                stamp: Timestamp::from_nanos(t),
                geometry,
                laser_offset: offset,
                odom,
            };
            let n = encode_scan(&meta, &ranges, &mut frame).unwrap();
            bytes.extend_from_slice(&frame[..n]);
        }
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.cloilog");
        std::fs::write(&path, &bytes).unwrap();
        let mut stream = open_input(&path, &InputOptions::default()).unwrap();
        let events = collect(&mut stream);
        assert_eq!(events.len(), 4);
        assert_eq!(
            events[0],
            SensorEvent::Odometry {
                t_ns: 100,
                pose: Se2::new(1.0, 2.0, 0.3)
            }
        );
        assert_eq!(
            events[1],
            SensorEvent::Gyro {
                t_ns: 120,
                yaw_rate: -0.25
            }
        );
        for (e, (t, odom)) in events[2..]
            .iter()
            .zip([(150, Some(Se2::new(1.1, 2.0, 0.31))), (250, None)])
        {
            let s = scan_of(e);
            assert_eq!((s.t_ns, s.odom, s.laser_offset), (t, odom, offset));
            assert_eq!(
                (s.angle_min, s.angle_increment, s.range_min, s.range_max),
                (-1.5, 0.25, 0.0, 50.0)
            );
            let bits: Vec<u32> = s.ranges.iter().map(|r| r.to_bits()).collect();
            let want: Vec<u32> = ranges.iter().map(|r| r.to_bits()).collect();
            assert_eq!(bits, want);
        }
        let stats = stream.stats();
        assert_eq!((stats.scans, stats.odometry, stats.gyro), (2, 1, 1));
        assert_eq!(stats.bytes_read, bytes.len() as u64);
        assert_eq!(stats.laser_offset_source.as_deref(), Some("cloilog"));

        // Overrides of the mounting and the range limit apply to cloilog scans too.
        let opts = InputOptions {
            laser_offset: Some(Se2::IDENTITY),
            range_max: Some(10.0),
            ..InputOptions::default()
        };
        let events = collect(&mut open_input(&path, &opts).unwrap());
        let s = scan_of(&events[2]);
        assert_eq!((s.laser_offset, s.range_max), (Se2::IDENTITY, 10.0));

        // Cut inside the last record: the events before it, then an error.
        std::fs::write(&path, &bytes[..bytes.len() - 3]).unwrap();
        let mut stream = open_input(&path, &InputOptions::default()).unwrap();
        let items: Vec<_> = stream.by_ref().collect();
        assert_eq!(items.len(), 4);
        assert!(items[..3].iter().all(Result::is_ok));
        let err = items[3].as_ref().unwrap_err().to_string();
        assert!(err.contains("ends inside a record"), "{err}");
        assert!(stream.next().is_none());
    }

    /// `cloi convert --to cloilog` output read back: the same scans, stamps and ranges as the
    /// CARMEN log it came from.
    #[test]
    fn converted_carmen_log_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        let clf = dir.path().join("t.clf");
        std::fs::write(&clf, LOG).unwrap();
        let out = dir.path().join("t.cloilog");
        crate::io::cloilog::carmen_to_cloilog(&clf, &out, false, None, None).unwrap();
        let from_clf = collect(&mut open_input(&clf, &InputOptions::default()).unwrap());
        let from_log = collect(&mut open_input(&out, &InputOptions::default()).unwrap());
        let scans = |v: &[SensorEvent]| -> Vec<(i64, Vec<u32>, Option<Se2>)> {
            v.iter()
                .filter_map(|e| match e {
                    SensorEvent::Scan(s) => Some((
                        s.t_ns,
                        s.ranges.iter().map(|r| r.to_bits()).collect(),
                        s.odom,
                    )),
                    _ => None,
                })
                .collect()
        };
        let a = scans(&from_clf);
        assert!(!a.is_empty());
        assert_eq!(a, scans(&from_log));
        let s = scan_of(
            from_log
                .iter()
                .find(|e| matches!(e, SensorEvent::Scan(_)))
                .unwrap(),
        );
        assert!(
            (s.laser_offset.x - 0.12).abs() < 1e-12,
            "{:?}",
            s.laser_offset
        );
    }

    /// A front laser 0.12 m ahead (PARAM), a rear laser, a stamp stepping back, a NaN
    /// range, a damaged line, a scan without an ODOM line before it.
    const LOG: &str = "# CARMEN Logfile\n\
PARAM robot_frontlaser_offset 0.12 nohost 0\n\
PARAM robot_front_laser_max 50.0 nohost 0\n\
ODOM 1.0 2.0 0.0 0.3 0.1 0.0 100.000000 host 0\n\
FLASER 3 1.0 nan 81.83 1.12 2.0 0.0 1.0 2.0 0.0 100.050000 host 0\n\
RLASER 3 1.0 2.0 3.0 0.9 2.0 3.1416 1.0 2.0 0.0 100.060000 host 0\n\
ODOM 1.1 2.0 0.0 0.3 0.1 0.0 100.100000 host 0\n\
ODOM 1.05 2.0 0.0 0.3 0.1 0.0 100.090000 host 0\n\
FLASER 3 1.0 2.0 3.0 1.32 2.0 0.0 1.2 2.0 0.0 100.150000 host 0\n\
FLASER 3 1.0 2.0 zz 1.32 2.0 0.0 1.2 2.0 0.0 100.170000 host 0\n\
FLASER 3 1.0 2.0 3.0 1.42 2.0 0.0 1.3 2.0 0.0 100.140000 host 0\n";

    #[test]
    fn carmen_log_becomes_events() {
        let reader = reader_from_bytes(LOG.into(), "t.clf", false);
        let mut stream = carmen_input(reader, &InputOptions::default());
        let handle = stream.stats_handle();
        let events = collect(&mut stream);
        let kinds: Vec<&str> = events
            .iter()
            .map(|e| match e {
                SensorEvent::Odometry { .. } => "odom",
                SensorEvent::Gyro { .. } => "gyro",
                SensorEvent::Scan(_) => "scan",
                SensorEvent::Image(_) => "image",
            })
            .collect();
        // The last scan has no ODOM line since the previous scan: its own odometry comes first.
        assert_eq!(
            kinds,
            ["odom", "scan", "odom", "odom", "scan", "odom", "scan"]
        );
        let first = scan_of(&events[1]);
        assert_eq!(first.t_ns, 100_050_000_000);
        assert_eq!(first.ranges.len(), 3);
        assert!(first.ranges[1].is_nan(), "NaN passes through");
        assert_eq!(first.ranges[2], 81.83);
        assert_eq!(first.range_max, 50.0);
        assert_eq!(first.range_min, 0.0);
        assert!((first.angle_min + std::f32::consts::FRAC_PI_2).abs() < 1e-6);
        assert_eq!(first.laser_offset, Se2::new(0.12, 0.0, 0.0));
        assert_eq!(first.odom, Some(Se2::new(1.0, 2.0, 0.0)));
        assert_eq!(
            events[5],
            SensorEvent::Odometry {
                t_ns: 100_140_000_000,
                pose: Se2::new(1.3, 2.0, 0.0)
            }
        );
        let stats = stream.stats();
        assert_eq!(*handle.lock().unwrap(), stats);
        assert_eq!(stats.scans, 3);
        assert_eq!(stats.odometry, 4);
        assert_eq!(stats.odometry_from_scans, 1);
        assert_eq!(stats.gyro, 0);
        // ODOM 100.09 after 100.10, and the last scan 100.14 after 100.15.
        assert_eq!(stats.backwards_stamps, 2);
        // The rear laser and the damaged line.
        assert_eq!(stats.skipped, 2);
        assert_eq!(stats.first_ns, Some(100_000_000_000));
        assert_eq!(stats.last_ns, Some(100_150_000_000));
        assert!((stats.data_seconds() - 0.15).abs() < 1e-9);
        assert_eq!(stats.laser_offset_source.as_deref(), Some("PARAM"));
        assert_eq!(stats.bytes_read, LOG.len() as u64);
        assert!(stats.warnings.iter().any(|w| w.contains("t.clf:10")));
    }

    #[test]
    fn carmen_laser_choice_and_derived_offset() {
        // No PARAM: the offset comes from the first line's laser and odometry poses.
        let log =
            "FLASER 2 1.0 2.0 -2.994295 8.292039 -3.120965 -3.034287 8.291214 -3.120965 5.0 h 0\n\
RLASER 2 3.0 4.0 1.0 2.0 3.14159 1.0 2.0 0.0 5.1 h 0\n";
        let mut stream = carmen_input(
            reader_from_bytes(log.into(), "a.clf", true),
            &InputOptions::default(),
        );
        let events = collect(&mut stream);
        let scan = scan_of(&events[1]);
        assert!(
            (scan.laser_offset.x + 0.04).abs() < 1e-5,
            "{:?}",
            scan.laser_offset
        );
        assert!(scan.laser_offset.y.abs() < 1e-5 && scan.laser_offset.theta.abs() < 1e-9);
        assert_eq!(scan.range_max, DEFAULT_RANGE_MAX);
        assert_eq!(
            stream.stats().laser_offset_source.as_deref(),
            Some("laser line")
        );

        // The rear laser on request, with an explicit range limit.
        let opts = InputOptions {
            laser: "rear".parse().unwrap(),
            range_max: Some(20.0),
            ..InputOptions::default()
        };
        let events = collect(&mut carmen_input(
            reader_from_bytes(log.into(), "a.clf", true),
            &opts,
        ));
        assert_eq!(events.len(), 2);
        let scan = scan_of(&events[1]);
        assert_eq!(scan.ranges, vec![3.0, 4.0]);
        assert_eq!(scan.range_max, 20.0);
        assert!((scan.laser_offset.theta.abs() - std::f64::consts::PI).abs() < 1e-4);

        // An explicit offset wins over everything.
        let opts = InputOptions {
            laser_offset: Some(Se2::new(0.3, 0.0, 0.0)),
            ..InputOptions::default()
        };
        let events = collect(&mut carmen_input(
            reader_from_bytes(log.into(), "a.clf", true),
            &opts,
        ));
        assert_eq!(scan_of(&events[1]).laser_offset, Se2::new(0.3, 0.0, 0.0));
        assert!("sideways".parse::<LaserChoice>().is_err());
    }

    #[test]
    fn compressed_carmen_file_is_opened_by_content() {
        use std::io::Write;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("log.clf.gz");
        let mut gz = flate2::write::GzEncoder::new(
            File::create(&path).unwrap(),
            flate2::Compression::fast(),
        );
        gz.write_all(LOG.as_bytes()).unwrap();
        gz.finish().unwrap();
        let mut stream = open_input(&path, &InputOptions::default()).unwrap();
        assert_eq!(stream.size(), InputSize::Unknown);
        assert_eq!(collect(&mut stream).len(), 7);
        // In strict mode the damaged line is an error, after the events before it.
        let strict = InputOptions {
            strict: true,
            ..InputOptions::default()
        };
        let items: Vec<_> = open_input(&path, &strict).unwrap().collect();
        assert_eq!(items.len(), 6);
        assert!(items[5].is_err());
    }

    fn write_bag(path: &Path) {
        let mut bag = BagWriter::create(path).unwrap();
        let t0 = 1_700_000_000_000_000_000i64;
        let tf = TfMessage {
            transforms: vec![
                TransformStamped {
                    header: Header::new(Time::from_nanos(t0), "base_link"),
                    child_frame_id: "laser_mount".into(),
                    transform: Transform::planar(0.2, 0.0, 0.0),
                },
                TransformStamped {
                    header: Header::new(Time::from_nanos(t0), "laser_mount"),
                    child_frame_id: "laser".into(),
                    transform: Transform::planar(0.0, 0.1, std::f64::consts::FRAC_PI_2),
                },
            ],
        };
        bag.write("/tf_static", t0, &tf).unwrap();
        for k in 0..3i64 {
            let t = t0 + k * 100_000_000;
            let mut odom = Odometry {
                header: Header::new(Time::from_nanos(t), "odom"),
                child_frame_id: "base_link".into(),
                ..Default::default()
            };
            odom.pose.pose = Pose::planar(0.1 * k as f64, 0.0, 0.0);
            bag.write("/odom", t, &odom).unwrap();
            let mut imu = Imu {
                header: Header::new(Time::from_nanos(t + 1_000), "imu"),
                ..Default::default()
            };
            imu.angular_velocity.z = 0.5;
            bag.write("/imu", t + 1_000, &imu).unwrap();
            // The second scan's header stamp lies before the first's.
            let stamp = if k == 1 { t0 - 5_000_000 } else { t + 2_000 };
            let scan = LaserScan {
                header: Header::new(Time::from_nanos(stamp), "laser"),
                angle_min: -1.0,
                angle_max: 1.0,
                angle_increment: 1.0,
                range_min: 0.05,
                range_max: 12.0,
                ranges: vec![1.0, f32::NAN, 3.0],
                ..Default::default()
            };
            bag.write("/scan", t + 2_000, &scan).unwrap();
            bag.write("/scan_rear", t + 3_000, &scan).unwrap();
        }
        bag.finish().unwrap();
    }

    #[test]
    fn skipping_drops_the_first_seconds_by_stamp() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.mcap");
        write_bag(&path);
        let all = collect(&mut open_input(&path, &InputOptions::default()).unwrap());
        let first = all[0].t_ns();
        // The events from 1 ms after the first one on, in their order.
        let kept: Vec<i64> = all
            .iter()
            .map(SensorEvent::t_ns)
            .filter(|&t| t >= first + 1_000_000)
            .collect();
        let mut stream = open_input(&path, &InputOptions::default())
            .unwrap()
            .skip_seconds(0.001);
        let skipped: Vec<i64> = collect(&mut stream).iter().map(SensorEvent::t_ns).collect();
        assert!(!kept.is_empty() && kept.len() < all.len());
        assert_eq!(skipped, kept);
    }

    #[test]
    fn bag_becomes_events_with_the_static_mounting() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.mcap");
        write_bag(&path);
        // A bag directory resolves to its one MCAP file.
        let mut stream = open_input(dir.path(), &InputOptions::default()).unwrap();
        assert!(matches!(stream.size(), InputSize::Bytes(n) if n > 0));
        let events = collect(&mut stream);
        let stats = stream.stats();
        assert_eq!((stats.scans, stats.odometry, stats.gyro), (3, 3, 3));
        // /scan_rear (3 messages) and the TF message are not events.
        assert_eq!(stats.skipped, 3);
        assert_eq!(stats.backwards_stamps, 1);
        assert_eq!(stats.laser_offset_source.as_deref(), Some("tf_static"));
        let scans: Vec<&ScanEvent> = events
            .iter()
            .filter_map(|e| match e {
                SensorEvent::Scan(s) => Some(s),
                _ => None,
            })
            .collect();
        let o = scans[0].laser_offset;
        assert!((o.x - 0.2).abs() < 1e-12 && (o.y - 0.1).abs() < 1e-12);
        assert!((o.theta - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert_eq!(scans[0].range_max, 12.0);
        assert_eq!(scans[0].range_min, 0.05);
        assert!(scans[0].ranges[1].is_nan());
        assert_eq!(scans[1].t_ns, 1_700_000_000_000_000_000 - 5_000_000);
        assert!(events.iter().any(|e| matches!(
            e,
            SensorEvent::Gyro { yaw_rate, .. } if *yaw_rate == 0.5
        )));
        assert!(events.iter().any(|e| matches!(
            e,
            SensorEvent::Odometry { pose, .. } if (pose.x - 0.2).abs() < 1e-12
        )));

        // Choosing the other scan topic; an explicit offset.
        let opts = InputOptions {
            topics: TopicSelection {
                scan: Some("/scan_rear".into()),
                ..TopicSelection::default()
            },
            laser_offset: Some(Se2::new(-0.3, 0.0, std::f64::consts::PI)),
            range_max: Some(8.0),
            ..InputOptions::default()
        };
        let mut stream = open_input(&path, &opts).unwrap();
        let events = collect(&mut stream);
        let scan = events
            .iter()
            .find_map(|e| match e {
                SensorEvent::Scan(s) => Some(s),
                _ => None,
            })
            .unwrap();
        assert_eq!(scan.laser_offset.x, -0.3);
        assert_eq!(scan.range_max, 8.0);
        assert_eq!(stream.stats().scans, 3);
        assert_eq!(
            stream.stats().laser_offset_source.as_deref(),
            Some("option")
        );
    }

    /// A simulator's bag carries ground truth as `nav_msgs/Odometry` in the `map` frame, ahead
    /// of the wheel odometry: it is passed over unless named.
    #[test]
    fn ground_truth_in_the_map_frame_is_not_taken_for_wheel_odometry() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sim.mcap");
        let mut bag = BagWriter::create(&path).unwrap();
        for k in 1..=3i64 {
            for (topic, frame, x) in [("/ground_truth", "map", 10.0), ("/odom", "odom", 1.0)] {
                let mut odom = Odometry {
                    header: Header::new(Time::from_nanos(k), frame),
                    child_frame_id: "base_link".into(),
                    ..Default::default()
                };
                odom.pose.pose = Pose::planar(x * k as f64, 0.0, 0.0);
                bag.write(topic, k, &odom).unwrap();
            }
        }
        bag.finish().unwrap();
        let xs = |opts: &InputOptions| -> Vec<f64> {
            let mut stream = open_input(&path, opts).unwrap();
            collect(&mut stream)
                .iter()
                .filter_map(|e| match e {
                    SensorEvent::Odometry { pose, .. } => Some(pose.x),
                    _ => None,
                })
                .collect()
        };
        assert_eq!(xs(&InputOptions::default()), [1.0, 2.0, 3.0]);
        let named = InputOptions {
            topics: TopicSelection {
                odom: Some("/ground_truth".into()),
                ..TopicSelection::default()
            },
            ..InputOptions::default()
        };
        assert_eq!(xs(&named), [10.0, 20.0, 30.0]);
    }

    #[test]
    fn bag_without_static_transform_uses_the_identity() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("b.mcap");
        let mut bag = BagWriter::create(&path).unwrap();
        let scan = LaserScan {
            header: Header::new(Time::from_nanos(5), "laser"),
            angle_increment: 0.1,
            range_max: 5.0,
            ranges: vec![1.0; 4],
            ..Default::default()
        };
        bag.write("/scan", 5, &scan).unwrap();
        bag.finish().unwrap();
        let mut stream = open_input(&path, &InputOptions::default()).unwrap();
        let events = collect(&mut stream);
        assert_eq!(scan_of(&events[0]).laser_offset, Se2::IDENTITY);
        let stats = stream.stats();
        assert_eq!(stats.laser_offset_source.as_deref(), Some("identity"));
        assert!(stats.warnings[0].contains("no static transform"));
    }

    #[derive(Debug, clap::Parser)]
    struct Cmd {
        input: Option<PathBuf>,
        #[command(flatten)]
        args: InputArgs,
    }

    #[test]
    fn command_line_options() {
        use clap::Parser;
        let cmd = Cmd::try_parse_from([
            "map",
            "x.mcap",
            "--laser",
            "rear",
            "--laser-offset",
            "-0.1,0,1.5",
            "--scan-topic",
            "/front",
            "--strict",
        ])
        .unwrap();
        let o = cmd.args.options();
        assert_eq!(o.laser, LaserChoice::Rear);
        assert_eq!(o.laser_offset, Some(Se2::new(-0.1, 0.0, 1.5)));
        assert_eq!(o.topics.scan.as_deref(), Some("/front"));
        assert!(o.strict && o.range_max.is_none());
        let cmd = Cmd::try_parse_from(["map", "--sim-duration", "1"]).unwrap();
        assert!(cmd.input.is_none());
        assert_eq!(cmd.args.options(), InputOptions::default());
        let mut stream = cmd.args.open(None).unwrap();
        assert!(matches!(stream.size(), InputSize::Seconds(s) if s == 1.0));
        assert!(stream.next().unwrap().is_ok());
        assert!(Cmd::try_parse_from(["map", "--laser-offset", "1,2"]).is_err());
        assert!(Cmd::try_parse_from(["map", "--laser", "side"]).is_err());
        assert!(parse_pose("1,nan,0").is_err());
    }

    #[test]
    fn simulated_home_streams_odometry_gyro_and_scans() {
        let run = || {
            let mut stream = sim_input("home", 1.0, 7).unwrap();
            let events = collect(&mut stream);
            (events, stream.stats())
        };
        let (events, stats) = run();
        // 5 Hz LiDAR, 50 Hz odometry, 20 Hz gyro over one second.
        assert!((4..=5).contains(&stats.scans), "{stats:?}");
        assert!(stats.odometry >= 45 && stats.gyro >= 18, "{stats:?}");
        assert_eq!(stats.laser_offset_source.as_deref(), Some("simulator"));
        let first_scan = events
            .iter()
            .find_map(|e| match e {
                SensorEvent::Scan(s) => Some(s),
                _ => None,
            })
            .unwrap();
        assert_eq!(first_scan.ranges.len(), 360);
        // The cleaning robot's LiDAR sits on its centre line, facing forward.
        assert_eq!(Some(first_scan.laser_offset), stats.laser_offset);
        assert!(first_scan.laser_offset.y == 0.0 && first_scan.laser_offset.theta == 0.0);
        assert!(first_scan.range_max > first_scan.range_min);
        assert!(first_scan.t_ns >= EPOCH_NS && first_scan.t_ns < EPOCH_NS + 1_000_000_000);
        assert!(matches!(
            events[0],
            SensorEvent::Odometry { .. } | SensorEvent::Gyro { .. }
        ));
        // The same seed gives the same stream.
        let (again, _) = run();
        assert_eq!(events.len(), again.len());
        assert!(events
            .iter()
            .zip(&again)
            .all(|(a, b)| format!("{a:?}") == format!("{b:?}")));
        // Dropping the stream early stops the simulation.
        let mut stream = sim_input("home", 30.0, 1).unwrap();
        assert!(stream.next().unwrap().is_ok());
        drop(stream);
        assert!(sim_input("moon", 1.0, 0).is_err());
        assert!(sim_input("home", -1.0, 0).is_err());
    }
}
