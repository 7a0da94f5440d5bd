//! Writing ROS 2 bags as MCAP files (CDR messages, `ros2msg` schemas, zstd chunks).
//!
//! ```no_run
//! use cloi_io::bag::BagWriter;
//! use cloi_io::ros2::{Header, LaserScan, Time};
//! # fn main() -> anyhow::Result<()> {
//! let mut bag = BagWriter::create("out.mcap".as_ref())?;
//! let t = 1_700_000_000_000_000_000; // nanoseconds
//! let scan = LaserScan { header: Header::new(Time::from_nanos(t), "laser"), ..Default::default() };
//! bag.write("/scan", t, &scan)?;
//! bag.finish()?; // the file appears only now (atomic rename)
//! # Ok(())
//! # }
//! ```

use std::collections::{BTreeMap, HashMap};
use std::io::{BufWriter, Seek, Write};
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use tempfile::NamedTempFile;

use crate::atomic::AtomicFile;
use crate::ros2::RosMessage;

/// Chunk compression of written bags.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum BagCompression {
    /// zstd chunks (what rosbag2 writes by default with `-s mcap` and compression on).
    #[default]
    Zstd,
    /// lz4 chunks.
    Lz4,
    /// Uncompressed chunks.
    None,
}

/// Writes typed ROS 2 messages to topics of an MCAP file.
///
/// A topic gets its channel (and its type's schema) on its first message; writing another type
/// to the same topic later is an error. Messages should be written in time order (readers
/// reorder within a window, but not across a whole file).
pub struct BagWriter<W: Write + Seek = BufWriter<NamedTempFile>> {
    mcap: mcap::Writer<W>,
    /// topic -> (channel id, type name, next sequence number)
    channels: HashMap<String, (u16, &'static str, u32)>,
    schemas: HashMap<&'static str, u16>,
    target: Option<PathBuf>,
    messages: u64,
}

impl<W: Write + Seek> std::fmt::Debug for BagWriter<W> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BagWriter")
            .field("topics", &self.channels.len())
            .field("messages", &self.messages)
            .field("target", &self.target)
            .finish()
    }
}

fn write_options(compression: BagCompression) -> mcap::WriteOptions {
    let compression = match compression {
        BagCompression::Zstd => Some(mcap::Compression::Zstd),
        BagCompression::Lz4 => Some(mcap::Compression::Lz4),
        BagCompression::None => None,
    };
    mcap::WriteOptions::new()
        .profile("ros2")
        .library(concat!("cloi-mapper/", env!("CARGO_PKG_VERSION")))
        .compression(compression)
        // One compressor on the calling thread: zstd's worker threads each buffer whole jobs
        // (42 MB for a map's result bag), more than the mapper's own pools on a small robot.
        .compression_threads(0)
}

impl BagWriter<BufWriter<NamedTempFile>> {
    /// Starts a zstd-compressed bag at `path`; the file appears on [`BagWriter::finish`].
    ///
    /// # Errors
    /// The folder is not writable.
    pub fn create(path: &Path) -> Result<Self> {
        Self::create_with(path, BagCompression::default())
    }

    /// Starts a bag at `path` with the given chunk compression.
    ///
    /// # Errors
    /// The folder is not writable.
    pub fn create_with(path: &Path, compression: BagCompression) -> Result<Self> {
        let (target, temp) = AtomicFile::create(path)?.into_parts();
        let mut bag = Self::new_with(temp, compression)?;
        bag.target = Some(target);
        Ok(bag)
    }

    /// Writes the summary and index, then renames the file to its path.
    ///
    /// # Errors
    /// Any IO error.
    pub fn finish(self) -> Result<u64> {
        let messages = self.messages;
        let target = self.target.clone();
        let name = self.name();
        let inner = self.finish_into_inner()?;
        let temp = inner
            .into_inner()
            .map_err(|e| e.into_error())
            .with_context(|| format!("writing {name}"))?;
        match target {
            Some(target) => AtomicFile::persist(temp, &target)?,
            None => bail!("bag writer has no target path"),
        }
        Ok(messages)
    }
}

impl<W: Write + Seek> BagWriter<W> {
    /// A bag on any seekable writer (e.g. a `Cursor<Vec<u8>>` in tests).
    ///
    /// # Errors
    /// Writing the MCAP header fails.
    pub fn new_with(writer: W, compression: BagCompression) -> Result<Self> {
        let mcap = write_options(compression)
            .create(writer)
            .context("starting the MCAP file")?;
        Ok(Self {
            mcap,
            channels: HashMap::new(),
            schemas: HashMap::new(),
            target: None,
            messages: 0,
        })
    }

    /// The bag's path for messages ("the bag" without one).
    fn name(&self) -> String {
        self.target
            .as_ref()
            .map_or_else(|| "the bag".to_owned(), |p| p.display().to_string())
    }

    /// Messages written so far.
    pub fn message_count(&self) -> u64 {
        self.messages
    }

    fn channel_for<M: RosMessage>(&mut self, topic: &str) -> Result<(u16, u32)> {
        if let Some((id, ty, seq)) = self.channels.get_mut(topic) {
            if *ty != M::TYPE_NAME {
                bail!(
                    "topic {topic} has type {ty}, cannot also write {}",
                    M::TYPE_NAME
                );
            }
            *seq = seq.wrapping_add(1);
            return Ok((*id, *seq));
        }
        let schema_id = match self.schemas.get(M::TYPE_NAME) {
            Some(&id) => id,
            None => {
                let id = self
                    .mcap
                    .add_schema(M::TYPE_NAME, "ros2msg", M::schema_text().as_bytes())
                    .with_context(|| format!("adding schema {}", M::TYPE_NAME))?;
                self.schemas.insert(M::TYPE_NAME, id);
                id
            }
        };
        let metadata = BTreeMap::new();
        let id = self
            .mcap
            .add_channel(schema_id, topic, "cdr", &metadata)
            .with_context(|| format!("adding channel {topic}"))?;
        self.channels
            .insert(topic.to_owned(), (id, M::TYPE_NAME, 0));
        Ok((id, 0))
    }

    /// Writes `msg` to `topic`, logged at `log_time_ns` (nanoseconds since the epoch; also
    /// used as publish time).
    ///
    /// # Errors
    /// A negative time, a topic used with another type, or an IO error.
    pub fn write<M: RosMessage>(&mut self, topic: &str, log_time_ns: i64, msg: &M) -> Result<()> {
        let data = msg.to_cdr()?;
        self.write_cdr::<M>(topic, log_time_ns, &data)
    }

    /// Writes an already CDR-encoded message of type `M`.
    ///
    /// # Errors
    /// As [`BagWriter::write`].
    pub fn write_cdr<M: RosMessage>(
        &mut self,
        topic: &str,
        log_time_ns: i64,
        data: &[u8],
    ) -> Result<()> {
        let log_time = u64::try_from(log_time_ns)
            .map_err(|_| anyhow!("negative log time {log_time_ns} ns on {topic}"))?;
        let (channel_id, sequence) = self.channel_for::<M>(topic)?;
        self.mcap
            .write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id,
                    sequence,
                    log_time,
                    publish_time: log_time,
                },
                data,
            )
            .with_context(|| format!("writing a message to {topic} in {}", self.name()))?;
        self.messages += 1;
        Ok(())
    }

    /// Writes the summary and returns the underlying writer.
    ///
    /// # Errors
    /// Any IO error.
    pub fn finish_into_inner(mut self) -> Result<W> {
        let name = self.name();
        self.mcap
            .finish()
            .with_context(|| format!("finishing the MCAP file {name}"))?;
        Ok(self.mcap.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use std::io::Cursor;

    use super::*;
    use crate::ros2::{Header, LaserScan, Odometry, Pose, Time};

    #[test]
    fn written_bag_reads_back_with_the_mcap_crate() {
        let mut bag = BagWriter::new_with(Cursor::new(Vec::new()), BagCompression::Zstd).unwrap();
        for i in 0..5_i64 {
            let t = 1_000_000_000 + i * 100_000_000;
            let scan = LaserScan {
                header: Header::new(Time::from_nanos(t), "laser"),
                ranges: vec![i as f32; 4],
                ..Default::default()
            };
            bag.write("/scan", t, &scan).unwrap();
            let mut odom = Odometry::default();
            odom.pose.pose = Pose::planar(i as f64, 0.0, 0.0);
            bag.write("/odom", t, &odom).unwrap();
        }
        assert!(bag
            .write("/scan", 2_000_000_000, &Odometry::default())
            .is_err());
        assert!(bag.write("/odom", -1, &Odometry::default()).is_err());
        let bytes = bag.finish_into_inner().unwrap().into_inner();

        let mut scans = 0;
        let mut odoms = 0;
        for msg in mcap::MessageStream::new(&bytes).unwrap() {
            let msg = msg.unwrap();
            let schema = msg.channel.schema.as_ref().unwrap();
            assert_eq!(schema.encoding, "ros2msg");
            assert_eq!(msg.channel.message_encoding, "cdr");
            match msg.channel.topic.as_str() {
                "/scan" => {
                    assert_eq!(schema.name, "sensor_msgs/msg/LaserScan");
                    let s = LaserScan::from_cdr(&msg.data).unwrap();
                    assert_eq!(s.ranges, vec![scans as f32; 4]);
                    assert_eq!(msg.sequence, scans);
                    scans += 1;
                }
                "/odom" => {
                    let o = Odometry::from_cdr(&msg.data).unwrap();
                    assert_eq!(o.pose.pose.position.x, f64::from(odoms));
                    odoms += 1;
                }
                other => panic!("unexpected topic {other}"),
            }
        }
        assert_eq!((scans, odoms), (5, 5));
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        assert_eq!(summary.stats.unwrap().message_count, 10);
    }

    #[test]
    fn file_bag_is_atomic() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("b.mcap");
        let mut bag = BagWriter::create_with(&path, BagCompression::Lz4).unwrap();
        bag.write("/odom", 5, &Odometry::default()).unwrap();
        assert!(!path.exists());
        assert_eq!(bag.finish().unwrap(), 1);
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(mcap::MessageStream::new(&bytes).unwrap().count(), 1);
    }
}
