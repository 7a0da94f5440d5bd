//! Reading ROS 2 bags (MCAP files with CDR messages) as a stream of typed sensor messages.
//!
//! * Streams with the `mcap` crate's linear reader: memory grows with the largest chunk and
//!   the reorder window, not with the file. Chunks may be zstd or lz4 compressed.
//! * Delivers messages in log-time order: messages wait in a window (default 2 s of log time,
//!   at most 100,000 messages) and leave it oldest first. A message older than one already
//!   delivered (a file whose disorder exceeds the window) is still delivered, counted, and
//!   reported; it is an error in strict mode.
//! * Picks topics by message type (`sensor_msgs/msg/LaserScan`, `nav_msgs/msg/Odometry`,
//!   `sensor_msgs/msg/Imu`, `sensor_msgs/msg/Image`, `sensor_msgs/msg/CompressedImage`,
//!   `tf2_msgs/msg/TFMessage`, `geometry_msgs/msg/PoseWithCovarianceStamped`); a
//!   [`TopicSelection`] override keeps only the named topic for its type.
//! * Nothing read from the file sizes memory unchecked: a record, a chunk and a chunk's
//!   decompressed content longer than [`MAX_RECORD_BYTES`] are damage, and chunk CRCs are
//!   checked before any message of the chunk is used (a flipped bit is damage, not data).
//! * A damaged or truncated file yields the messages of the complete chunks before the damage
//!   and a warning with the byte offset, or an error in strict mode. Messages that do not decode are counted and
//!   skipped (an error in strict mode). ROS 1 messages (`ros1` encoding) are counted and
//!   skipped: the project reads ROS 2 bags only.

use std::collections::{BTreeMap, BinaryHeap, HashMap};
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, Context, Result};

use crate::ros2::{
    CompressedImage, Image, Imu, LaserScan, Odometry, PoseWithCovarianceStamped, RosMessage,
    TfMessage,
};

/// Longest record, chunk or decompressed chunk accepted, bytes: far above what a recorder
/// writes (rosbag2 closes chunks near 768 KiB; one 1080p colour image is 6 MiB), far below
/// what would exhaust the host's memory ceiling.
pub const MAX_RECORD_BYTES: usize = 32 << 20;

/// A decoded message of a type the mapper uses.
#[derive(Debug, Clone, PartialEq)]
pub enum SensorMsg {
    /// A laser scan.
    Scan(LaserScan),
    /// Wheel odometry (boxed: it is large).
    Odom(Box<Odometry>),
    /// An inertial sample (boxed: it is large).
    Imu(Box<Imu>),
    /// A raw picture.
    Image(Image),
    /// An encoded picture.
    CompressedImage(CompressedImage),
    /// Transforms; `is_static` for `/tf_static`-like topics (name ending in `_static`).
    Tf {
        /// The transforms.
        msg: TfMessage,
        /// From a static topic.
        is_static: bool,
    },
    /// A pose estimate (e.g. `/amcl_pose`; boxed: it is large).
    PoseEstimate(Box<PoseWithCovarianceStamped>),
}

/// The kinds of topic a reader selects.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum TopicKind {
    /// `sensor_msgs/msg/LaserScan`.
    Scan,
    /// `nav_msgs/msg/Odometry`.
    Odom,
    /// `sensor_msgs/msg/Imu`.
    Imu,
    /// `sensor_msgs/msg/Image`.
    Image,
    /// `sensor_msgs/msg/CompressedImage`.
    CompressedImage,
    /// `tf2_msgs/msg/TFMessage`.
    Tf,
    /// `geometry_msgs/msg/PoseWithCovarianceStamped`.
    PoseEstimate,
}

impl TopicKind {
    /// The kind of a ROS 2 type name (`pkg/msg/Name`; `pkg/Name` is accepted too).
    pub fn of_type(type_name: &str) -> Option<Self> {
        let short = type_name.replacen("/msg/", "/", 1);
        Some(match short.as_str() {
            "sensor_msgs/LaserScan" => Self::Scan,
            "nav_msgs/Odometry" => Self::Odom,
            "sensor_msgs/Imu" => Self::Imu,
            "sensor_msgs/Image" => Self::Image,
            "sensor_msgs/CompressedImage" => Self::CompressedImage,
            "tf2_msgs/TFMessage" => Self::Tf,
            "geometry_msgs/PoseWithCovarianceStamped" => Self::PoseEstimate,
            _ => return None,
        })
    }
}

/// Topic overrides: when set, only that topic is read for its type.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct TopicSelection {
    /// Laser scan topic.
    pub scan: Option<String>,
    /// Odometry topic.
    pub odom: Option<String>,
    /// IMU topic.
    pub imu: Option<String>,
    /// Camera topic (raw or compressed).
    pub image: Option<String>,
}

impl TopicSelection {
    fn accepts(&self, kind: TopicKind, topic: &str) -> bool {
        let wanted = match kind {
            TopicKind::Scan => &self.scan,
            TopicKind::Odom => &self.odom,
            TopicKind::Imu => &self.imu,
            TopicKind::Image | TopicKind::CompressedImage => &self.image,
            TopicKind::Tf | TopicKind::PoseEstimate => &None,
        };
        wanted.as_deref().is_none_or(|w| w == topic)
    }
}

/// Reader options.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BagReadOptions {
    /// Make damage, undecodable messages and order violations errors.
    pub strict: bool,
    /// Topic overrides.
    pub topics: TopicSelection,
    /// Log-time span (ns) of the reorder window.
    pub reorder_window_ns: u64,
    /// Most messages held in the reorder window.
    pub reorder_capacity: usize,
}

impl Default for BagReadOptions {
    fn default() -> Self {
        Self {
            strict: false,
            topics: TopicSelection::default(),
            reorder_window_ns: 2_000_000_000,
            reorder_capacity: 100_000,
        }
    }
}

/// One delivered message.
#[derive(Debug, Clone, PartialEq)]
pub struct BagMessage {
    /// Log time (ns since the epoch).
    pub log_time_ns: u64,
    /// Topic.
    pub topic: Arc<str>,
    /// The decoded message.
    pub msg: SensorMsg,
}

/// Per-topic counts.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct TopicStats {
    /// Type name.
    pub type_name: String,
    /// Messages delivered.
    pub delivered: u64,
    /// Messages skipped (type not used, not selected, not decodable, or not ROS 2).
    pub skipped: u64,
}

/// What a reader saw.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BagStats {
    /// Per topic.
    pub topics: BTreeMap<String, TopicStats>,
    /// Messages that failed to decode.
    pub undecodable: u64,
    /// Messages in a non-ROS 2 encoding.
    pub foreign_encoding: u64,
    /// Messages that arrived after a later one had been delivered.
    pub out_of_order: u64,
    /// Messages on a channel id without a channel record (skipped).
    pub unknown_channel: u64,
    /// Bytes read from the file.
    pub bytes_read: u64,
    /// Warnings (damage, truncation, decode failures).
    pub warnings: Vec<String>,
    /// The file ended early or was damaged.
    pub truncated: bool,
}

#[derive(Debug)]
struct Pending {
    log_time: u64,
    order: u64,
    msg: BagMessage,
}

impl PartialEq for Pending {
    fn eq(&self, other: &Self) -> bool {
        (self.log_time, self.order) == (other.log_time, other.order)
    }
}
impl Eq for Pending {}
impl PartialOrd for Pending {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Pending {
    // Reversed: BinaryHeap is a max-heap, we want the oldest first.
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        (other.log_time, other.order).cmp(&(self.log_time, self.order))
    }
}

/// What is known about a channel.
#[derive(Debug, Clone)]
struct ChannelInfo {
    topic: Arc<str>,
    type_name: String,
    encoding: String,
}

/// Channel bookkeeping, statistics and decoding; apart from the byte reader so a record
/// borrowed from the reader can be decoded in place.
#[derive(Debug)]
struct Decoder {
    path: PathBuf,
    options: BagReadOptions,
    schemas: HashMap<u16, String>,
    channels: HashMap<u16, ChannelInfo>,
    stats: BagStats,
    warned_decode: u64,
}

impl Decoder {
    fn warn(&mut self, message: String) {
        log::warn!("{message}");
        self.stats.warnings.push(message);
    }

    /// Decodes one message, or `None` if it is skipped.
    fn decode(
        &mut self,
        header: &mcap::records::MessageHeader,
        data: &[u8],
        offset: u64,
    ) -> Result<Option<BagMessage>> {
        let Some(channel) = self.channels.get(&header.channel_id).cloned() else {
            self.stats.unknown_channel += 1;
            if self.stats.unknown_channel == 1 {
                let msg = format!(
                    "{}: message on channel {} which has no channel record (near byte {offset}); \
                     such messages are skipped",
                    self.path.display(),
                    header.channel_id
                );
                if self.options.strict {
                    bail!(msg);
                }
                self.warn(msg);
            }
            return Ok(None);
        };
        let topic_stats = self
            .stats
            .topics
            .entry(channel.topic.to_string())
            .or_insert_with(|| TopicStats {
                type_name: channel.type_name.clone(),
                ..Default::default()
            });
        let kind = TopicKind::of_type(&channel.type_name)
            .filter(|&kind| self.options.topics.accepts(kind, &channel.topic));
        let Some(kind) = kind else {
            topic_stats.skipped += 1;
            return Ok(None);
        };
        if channel.encoding != "cdr" {
            topic_stats.skipped += 1;
            self.stats.foreign_encoding += 1;
            if self.stats.foreign_encoding == 1 {
                let msg = format!(
                    "{}: topic {} is in {:?} encoding; only ROS 2 (cdr) messages are read",
                    self.path.display(),
                    channel.topic,
                    channel.encoding
                );
                self.warn(msg);
            }
            return Ok(None);
        }
        let decoded = match kind {
            TopicKind::Scan => LaserScan::from_cdr(data).map(SensorMsg::Scan),
            TopicKind::Odom => Odometry::from_cdr(data).map(|m| SensorMsg::Odom(Box::new(m))),
            TopicKind::Imu => Imu::from_cdr(data).map(|m| SensorMsg::Imu(Box::new(m))),
            TopicKind::Image => Image::from_cdr(data).map(SensorMsg::Image),
            TopicKind::CompressedImage => {
                CompressedImage::from_cdr(data).map(SensorMsg::CompressedImage)
            }
            TopicKind::Tf => TfMessage::from_cdr(data).map(|msg| SensorMsg::Tf {
                msg,
                is_static: channel.topic.ends_with("_static"),
            }),
            TopicKind::PoseEstimate => PoseWithCovarianceStamped::from_cdr(data)
                .map(|m| SensorMsg::PoseEstimate(Box::new(m))),
        };
        match decoded {
            Ok(msg) => {
                topic_stats.delivered += 1;
                Ok(Some(BagMessage {
                    log_time_ns: header.log_time,
                    topic: channel.topic,
                    msg,
                }))
            }
            Err(err) => {
                topic_stats.skipped += 1;
                self.stats.undecodable += 1;
                let what = format!(
                    "{}: message {} on {} (log time {} ns, near byte {offset}) does not decode: {err:#}",
                    self.path.display(),
                    header.sequence,
                    channel.topic,
                    header.log_time,
                );
                if self.options.strict {
                    bail!(what);
                }
                self.warned_decode += 1;
                if self.warned_decode <= 10 {
                    self.warn(what);
                }
                Ok(None)
            }
        }
    }
}

/// Streams the sensor messages of a ROS 2 bag in log-time order.
pub struct BagReader {
    linear: mcap::sans_io::LinearReader,
    /// The chunk whose records are being read, once `linear` has handed it over whole.
    chunk: Option<OpenChunk>,
    source: Box<dyn Read>,
    bytes: u64,
    decoder: Decoder,
    window: BinaryHeap<Pending>,
    newest: u64,
    last_delivered: Option<u64>,
    order: u64,
    source_done: bool,
    failed: bool,
}

/// One chunk record of the file, read by a linear reader of its own.
///
/// The file's reader emits chunks whole and this one unpacks them, so that the chunk's records
/// can be checked first: the `mcap` crate trusts the lengths of the records of an uncompressed
/// chunk and counts down the chunk's remaining bytes with them.
struct OpenChunk {
    linear: mcap::sans_io::LinearReader,
    /// The chunk record (opcode, length, body), read once.
    bytes: std::io::Cursor<Vec<u8>>,
}

impl OpenChunk {
    /// Opens the chunk record `body` (with the header `header`).
    ///
    /// # Errors
    /// A record of an uncompressed chunk runs past the end of the chunk.
    fn new(header: &mcap::records::ChunkHeader, records: &[u8], body: &[u8]) -> Result<Self> {
        if header.compression.is_empty() {
            check_records_fit(records)?;
        }
        let mut bytes = Vec::with_capacity(9 + body.len());
        bytes.push(mcap::records::op::CHUNK);
        bytes.extend_from_slice(&(body.len() as u64).to_le_bytes());
        bytes.extend_from_slice(body);
        Ok(Self {
            linear: mcap::sans_io::LinearReader::new_with_options(reader_options(true)),
            bytes: std::io::Cursor::new(bytes),
        })
    }
}

/// Options of the linear readers: the file's (which emits chunks whole) and a chunk's.
fn reader_options(chunk: bool) -> mcap::sans_io::LinearReaderOptions {
    mcap::sans_io::LinearReaderOptions::default()
        .with_skip_start_magic(chunk)
        .with_skip_end_magic(chunk)
        .with_emit_chunks(!chunk)
        .with_prevalidate_chunk_crcs(true)
        .with_validate_data_section_crc(!chunk)
        .with_record_length_limit(MAX_RECORD_BYTES)
}

/// Checks that the records of an uncompressed chunk (opcode, `u64` length, body) tile it.
fn check_records_fit(mut records: &[u8]) -> Result<()> {
    let chunk_len = records.len();
    while let Some((opcode, rest)) = records.split_first() {
        let at = chunk_len - records.len();
        let Some((len, rest)) = rest.split_first_chunk::<8>() else {
            bail!("record (opcode {opcode:#x}) at byte {at} of a chunk: its length is cut");
        };
        let len = u64::from_le_bytes(*len);
        let Some(rest) = usize::try_from(len).ok().and_then(|len| rest.get(len..)) else {
            bail!(
                "record (opcode {opcode:#x}) at byte {at} of a chunk: {len} bytes long, \
                 past the chunk's end ({chunk_len} bytes)"
            );
        };
        records = rest;
    }
    Ok(())
}

impl std::fmt::Debug for BagReader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BagReader")
            .field("path", &self.decoder.path)
            .field("stats", &self.decoder.stats)
            .finish()
    }
}

impl BagReader {
    /// Opens a bag file.
    ///
    /// # Errors
    /// The file cannot be opened.
    pub fn open(path: &Path, options: BagReadOptions) -> Result<Self> {
        let file = File::open(path).with_context(|| format!("opening {}", path.display()))?;
        let input: Box<dyn Read> = Box::new(BufReader::with_capacity(1 << 16, file));
        Ok(Self::from_reader(input, path, options))
    }

    /// Reads a bag from any reader; `path` names it in messages.
    pub fn from_reader(input: Box<dyn Read>, path: &Path, options: BagReadOptions) -> Self {
        Self {
            linear: mcap::sans_io::LinearReader::new_with_options(reader_options(false)),
            chunk: None,
            source: input,
            bytes: 0,
            decoder: Decoder {
                path: path.to_owned(),
                options,
                schemas: HashMap::new(),
                channels: HashMap::new(),
                stats: BagStats::default(),
                warned_decode: 0,
            },
            window: BinaryHeap::new(),
            newest: 0,
            last_delivered: None,
            order: 0,
            source_done: false,
            failed: false,
        }
    }

    /// What was seen so far (complete once the iterator has ended).
    pub fn stats(&self) -> &BagStats {
        &self.decoder.stats
    }

    fn damage(&mut self, err: &dyn std::fmt::Display) -> Result<bool> {
        let what = format!(
            "{}: the file is damaged or truncated near byte {}: {err}",
            self.decoder.path.display(),
            self.bytes
        );
        self.decoder.stats.truncated = true;
        if self.decoder.options.strict {
            bail!(what);
        }
        let kept: u64 = self
            .decoder
            .stats
            .topics
            .values()
            .map(|t| t.delivered)
            .sum();
        self.decoder
            .warn(format!("{what}; kept the {kept} messages before it"));
        Ok(false)
    }

    /// Reads records until one message is in the window; `Ok(false)` at the end.
    fn pull(&mut self) -> Result<bool> {
        use mcap::records::Record;
        use mcap::sans_io::LinearReadEvent;
        loop {
            let in_chunk = self.chunk.is_some();
            let event = match self.chunk.as_mut() {
                Some(chunk) => chunk.linear.next_event(),
                None => self.linear.next_event(),
            };
            let event = match event {
                None if in_chunk => {
                    self.chunk = None;
                    continue;
                }
                None => return Ok(false),
                Some(Ok(event)) => event,
                Some(Err(err)) => {
                    self.chunk = None;
                    return self.damage(&err);
                }
            };
            let (opcode, data) = match event {
                LinearReadEvent::ReadRequest(need) if in_chunk => {
                    if let Some(chunk) = self.chunk.as_mut() {
                        // A read from memory cannot fail; a short one is a cut chunk.
                        let read = chunk.bytes.read(chunk.linear.insert(need)).unwrap_or(0);
                        chunk.linear.notify_read(read);
                    }
                    continue;
                }
                LinearReadEvent::ReadRequest(need) => {
                    let read = loop {
                        match self.source.read(self.linear.insert(need)) {
                            Ok(n) => break n,
                            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                            Err(e) => {
                                let e = anyhow::Error::from(e);
                                return self.damage(&e);
                            }
                        }
                    };
                    self.bytes += read as u64;
                    self.decoder.stats.bytes_read = self.bytes;
                    self.linear.notify_read(read);
                    continue;
                }
                LinearReadEvent::Record { opcode, data } => (opcode, data),
            };
            // Only the records used below are parsed. The others (header, attachments,
            // metadata, indexes) carry nothing the mapper reads, and the `mcap` crate's
            // attachment parser panics on a record too short for its fixed fields.
            use mcap::records::op;
            if !matches!(
                opcode,
                op::SCHEMA | op::CHANNEL | op::MESSAGE | op::CHUNK | op::DATA_END
            ) {
                continue;
            }
            let record = match mcap::parse_record(opcode, data) {
                Ok(r) => r,
                Err(err) => {
                    let e = anyhow::anyhow!("bad record (opcode {opcode:#x}): {err}");
                    return self.damage(&e);
                }
            };
            let msg = match record {
                Record::Chunk {
                    header,
                    data: records,
                } if !in_chunk => {
                    match OpenChunk::new(&header, &records, data) {
                        Ok(chunk) => self.chunk = Some(chunk),
                        Err(e) => return self.damage(&e),
                    }
                    continue;
                }
                Record::Schema { header, .. } => {
                    self.decoder.schemas.insert(header.id, header.name);
                    continue;
                }
                Record::Channel(ch) => {
                    let type_name = self
                        .decoder
                        .schemas
                        .get(&ch.schema_id)
                        .cloned()
                        .unwrap_or_default();
                    self.decoder.channels.insert(
                        ch.id,
                        ChannelInfo {
                            topic: Arc::from(ch.topic.as_str()),
                            type_name,
                            encoding: ch.message_encoding,
                        },
                    );
                    continue;
                }
                // The summary after the data section only repeats what came before.
                Record::DataEnd(_) => return Ok(false),
                Record::Message { header, data } => {
                    match self.decoder.decode(&header, &data, self.bytes)? {
                        Some(msg) => msg,
                        None => continue,
                    }
                }
                _ => continue,
            };
            let log_time = msg.log_time_ns;
            if let Some(last) = self.last_delivered {
                if log_time < last {
                    self.decoder.stats.out_of_order += 1;
                    let what = format!(
                        "{}: message on {} at {log_time} ns arrives after one at {last} ns \
                         was delivered (disorder beyond the reorder window)",
                        self.decoder.path.display(),
                        msg.topic
                    );
                    if self.decoder.options.strict {
                        bail!(what);
                    }
                    if self.decoder.stats.out_of_order == 1 {
                        self.decoder.warn(what);
                    }
                }
            }
            self.newest = self.newest.max(log_time);
            self.order += 1;
            self.window.push(Pending {
                log_time,
                order: self.order,
                msg,
            });
            return Ok(true);
        }
    }

    fn ready(&self) -> bool {
        match self.window.peek() {
            None => false,
            Some(oldest) => {
                self.source_done
                    || self.window.len() > self.decoder.options.reorder_capacity
                    || self.newest.saturating_sub(oldest.log_time)
                        > self.decoder.options.reorder_window_ns
            }
        }
    }

    fn next_message(&mut self) -> Result<Option<BagMessage>> {
        while !self.source_done && !self.ready() {
            if !self.pull()? {
                self.source_done = true;
            }
        }
        let Some(p) = self.window.pop() else {
            return Ok(None);
        };
        self.last_delivered = Some(
            self.last_delivered
                .map_or(p.log_time, |l| l.max(p.log_time)),
        );
        Ok(Some(p.msg))
    }
}

impl Iterator for BagReader {
    type Item = Result<BagMessage>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.failed {
            return None;
        }
        match self.next_message() {
            Ok(Some(m)) => Some(Ok(m)),
            Ok(None) => {
                let d = &mut self.decoder;
                if d.stats.out_of_order > 1 {
                    let msg = format!(
                        "{}: {} messages arrived out of log-time order in all",
                        d.path.display(),
                        d.stats.out_of_order
                    );
                    d.warn(msg);
                }
                if d.stats.unknown_channel > 1 {
                    let msg = format!(
                        "{}: {} messages on channels without a channel record were skipped",
                        d.path.display(),
                        d.stats.unknown_channel
                    );
                    d.warn(msg);
                }
                self.failed = true;
                None
            }
            Err(e) => {
                self.failed = true;
                Some(Err(e))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::io::Cursor;

    use super::*;
    use crate::bag::{BagCompression, BagWriter};
    use crate::ros2::{Header, Time};

    fn bag_bytes(times: &[i64], compression: BagCompression) -> Vec<u8> {
        let mut bag = BagWriter::new_with(Cursor::new(Vec::new()), compression).unwrap();
        for (i, &t) in times.iter().enumerate() {
            let scan = LaserScan {
                header: Header::new(Time::from_nanos(t), "laser"),
                ranges: vec![i as f32; 2000],
                ..Default::default()
            };
            bag.write("/scan", t, &scan).unwrap();
            let mut odom = Odometry::default();
            odom.pose.pose.position.x = i as f64;
            bag.write("/odom", t + 1, &odom).unwrap();
        }
        bag.finish_into_inner().unwrap().into_inner()
    }

    fn read(bytes: Vec<u8>, options: BagReadOptions) -> (Vec<Result<BagMessage>>, BagStats) {
        let mut reader =
            BagReader::from_reader(Box::new(Cursor::new(bytes)), Path::new("mem.mcap"), options);
        let out: Vec<_> = reader.by_ref().collect();
        (out, reader.stats().clone())
    }

    #[test]
    fn delivers_in_log_time_order_within_the_window() {
        // Written out of order by up to 0.5 s.
        let times = [1_000, 600_000_000, 200_000_000, 900_000_000, 700_000_000];
        for compression in [
            BagCompression::Zstd,
            BagCompression::Lz4,
            BagCompression::None,
        ] {
            let (msgs, stats) = read(bag_bytes(&times, compression), BagReadOptions::default());
            let stamps: Vec<u64> = msgs
                .iter()
                .map(|m| m.as_ref().unwrap().log_time_ns)
                .collect();
            let mut sorted = stamps.clone();
            sorted.sort_unstable();
            assert_eq!(stamps, sorted);
            assert_eq!(stamps.len(), 10);
            assert_eq!(stats.out_of_order, 0);
            assert_eq!(stats.topics["/scan"].delivered, 5);
            assert_eq!(stats.topics["/scan"].type_name, "sensor_msgs/msg/LaserScan");
        }
    }

    #[test]
    fn disorder_beyond_the_window_is_counted_or_fatal() {
        let times = [5_000_000_000, 9_000_000_000, 2_000_000_000];
        let options = BagReadOptions {
            reorder_window_ns: 100,
            ..Default::default()
        };
        let (msgs, stats) = read(bag_bytes(&times, BagCompression::None), options.clone());
        assert_eq!(msgs.len(), 6);
        assert!(stats.out_of_order > 0);
        let strict = BagReadOptions {
            strict: true,
            ..options
        };
        let (msgs, _) = read(bag_bytes(&times, BagCompression::None), strict);
        assert!(msgs.iter().any(|m| m.is_err()));
    }

    #[test]
    fn topic_override_selects_one_topic() {
        let options = BagReadOptions {
            topics: TopicSelection {
                scan: Some("/other".into()),
                ..Default::default()
            },
            ..Default::default()
        };
        let (msgs, stats) = read(bag_bytes(&[1, 2, 3], BagCompression::Zstd), options);
        assert_eq!(msgs.len(), 3);
        assert!(msgs
            .iter()
            .all(|m| matches!(m.as_ref().unwrap().msg, SensorMsg::Odom(_))));
        assert_eq!(stats.topics["/scan"].skipped, 3);
    }

    #[test]
    fn truncated_bag_keeps_earlier_messages() {
        let times: Vec<i64> = (0..200).map(|i| i * 10_000_000).collect();
        let full = bag_bytes(&times, BagCompression::None);
        // Past the first chunk (1 MiB) and into the second: the complete chunk's messages
        // are kept, none of the cut one's.
        let cut = full[..full.len() * 4 / 5].to_vec();
        let (msgs, stats) = read(cut.clone(), BagReadOptions::default());
        assert!(stats.truncated);
        assert!(!msgs.is_empty() && msgs.len() < 400);
        assert!(msgs.iter().all(|m| m.is_ok()));
        assert!(
            stats.warnings[0].contains("near byte"),
            "{:?}",
            stats.warnings
        );
        let strict = BagReadOptions {
            strict: true,
            ..Default::default()
        };
        let (msgs, _) = read(cut, strict);
        assert!(msgs.last().unwrap().is_err());
    }

    #[test]
    fn undecodable_message_is_skipped_with_a_warning() {
        let mut bag = BagWriter::new_with(Cursor::new(Vec::new()), BagCompression::None).unwrap();
        bag.write_cdr::<LaserScan>("/scan", 5, &[0, 1, 0, 0, 9])
            .unwrap();
        bag.write("/odom", 6, &Odometry::default()).unwrap();
        let bytes = bag.finish_into_inner().unwrap().into_inner();
        let (msgs, stats) = read(bytes.clone(), BagReadOptions::default());
        assert_eq!(msgs.len(), 1);
        assert_eq!(stats.undecodable, 1);
        assert!(stats.warnings[0].contains("/scan"));
        let strict = BagReadOptions {
            strict: true,
            ..Default::default()
        };
        let (msgs, _) = read(bytes, strict);
        assert!(msgs[0].is_err());
    }

    #[test]
    fn a_flipped_bit_in_a_chunk_is_damage_not_data() {
        let times: Vec<i64> = (0..50).map(|i| i * 10_000_000).collect();
        for compression in [BagCompression::None, BagCompression::Zstd] {
            let mut bytes = bag_bytes(&times, compression);
            let at = bytes.len() / 3;
            bytes[at] ^= 0x10;
            let (msgs, stats) = read(bytes.clone(), BagReadOptions::default());
            assert!(stats.truncated, "{compression:?}: the flip went unnoticed");
            assert!(msgs.iter().all(|m| m.is_ok()));
            assert!(msgs.len() < 2 * times.len(), "{compression:?}");
            assert!(stats.warnings.iter().any(|w| w.contains("damaged")));
            let strict = BagReadOptions {
                strict: true,
                ..Default::default()
            };
            let (msgs, _) = read(bytes, strict);
            assert!(msgs.last().is_some_and(|m| m.is_err()), "{compression:?}");
        }
    }

    #[test]
    fn a_record_longer_than_its_uncompressed_chunk_is_damage() {
        let times: Vec<i64> = (0..5).map(|i| i * 10_000_000).collect();
        let mut bytes = bag_bytes(&times, BagCompression::None);
        // Walk the file's records (opcode, u64 length) from the magic to the first chunk.
        let mut at = 8;
        while bytes[at] != mcap::records::op::CHUNK {
            at += 9 + u64::from_le_bytes(bytes[at + 1..at + 9].try_into().unwrap()) as usize;
        }
        // Chunk body: start and end times, uncompressed size, CRC, compression "" (a u32
        // length), compressed size, then the records. Drop the CRC so the length is what
        // is checked, and make the first record claim as many bytes as the chunk's records,
        // which with its own 9 is more than the chunk holds (and less than a record may be).
        let body = at + 9;
        bytes[body + 24..body + 28].fill(0);
        let records_len = bytes[body + 32..body + 40].to_vec();
        let first = body + 40;
        bytes[first + 1..first + 9].copy_from_slice(&records_len);
        let (msgs, stats) = read(bytes, BagReadOptions::default());
        assert!(stats.truncated);
        assert!(msgs.iter().all(|m| m.is_ok()));
        assert!(
            stats
                .warnings
                .iter()
                .any(|w| w.contains("past the chunk's end")),
            "{:?}",
            stats.warnings
        );
    }

    #[test]
    fn a_short_attachment_record_is_skipped() {
        let good = bag_bytes(&[1, 2], BagCompression::Zstd);
        // After the magic, an attachment (opcode 0x09) of 32 zero bytes: two times, two
        // empty strings and a data length, but no room for the CRC that ends the record.
        let mut bytes = good[..8].to_vec();
        bytes.push(mcap::records::op::ATTACHMENT);
        bytes.extend_from_slice(&32u64.to_le_bytes());
        bytes.extend_from_slice(&[0; 32]);
        bytes.extend_from_slice(&good[8..]);
        let (msgs, _) = read(bytes, BagReadOptions::default());
        assert_eq!(msgs.iter().filter(|m| m.is_ok()).count(), 4);
    }

    #[test]
    fn a_huge_record_length_is_damage_not_an_allocation() {
        let times: Vec<i64> = (0..5).map(|i| i * 10_000_000).collect();
        let good = bag_bytes(&times, BagCompression::None);
        // The first record after the 8-byte magic: opcode, then its u64 length.
        for len in [u64::MAX / 2, (MAX_RECORD_BYTES as u64) + 1, 0x7FFF_FFFF] {
            let mut bytes = good.clone();
            bytes[9..17].copy_from_slice(&len.to_le_bytes());
            let (msgs, stats) = read(bytes, BagReadOptions::default());
            assert!(stats.truncated, "length {len:#x}");
            assert!(msgs.is_empty());
        }
    }
}
