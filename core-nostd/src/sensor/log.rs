//! The compact binary sensor log (`.cloilog`) that carries a recorded run to the firmware.
//!
//! A robot without a file system still needs its test data: the host converts a recorded log
//! once (`cloi convert IN --to cloilog --out OUT.cloilog`) and the bare-metal firmware streams
//! the file through semihosting in fixed chunks. This module holds the format, an encoder and
//! a streaming decoder; neither allocates, and no input makes them panic.
//!
//! # Layout (version 1, every number little endian)
//! File header, [`HEADER_LEN`] bytes:
//!
//! | bytes  | field                                                               |
//! |--------|---------------------------------------------------------------------|
//! | 0..8   | magic `CLOILOG` followed by `0x1a` ([`MAGIC`])                      |
//! | 8..10  | `u16` version ([`VERSION`])                                         |
//! | 10..12 | `u16` header length (>= 16; a reader skips bytes it does not know)  |
//! | 12..16 | `u32` record count, `0xffff_ffff` when unknown ([`UNKNOWN_COUNT`])  |
//!
//! Then records, each framed as
//!
//! | bytes        | field                                                          |
//! |--------------|----------------------------------------------------------------|
//! | 0            | `u8` kind (1 odometry, 2 gyro, 3 scan; others are skipped)     |
//! | 1            | `u8` flags (scan: bit 0 = an odometry pose follows the offset) |
//! | 2..4         | `u16` reserved, written as 0                                   |
//! | 4..8         | `u32` payload length `L` (at most [`MAX_PAYLOAD`])             |
//! | 8..8+L       | payload                                                        |
//! | 8+L..12+L    | `u32` CRC-32 (IEEE) of bytes `0..8+L`                          |
//!
//! Payloads: odometry `t_ns: i64, x, y, theta: f64` (32 bytes); gyro `t_ns: i64, yaw_rate:
//! f64` (16 bytes); scan `t_ns: i64, angle_min, angle_increment, range_min, range_max: f32,
//! laser offset x, y, theta: f64, [odometry x, y, theta: f64], n: u16, n x range: f32`. The
//! length of a known kind must match its fields exactly, and a scan has at most [`MAX_BEAMS`]
//! beams. Floats are stored as their bits, so a round trip is exact (NaN included).
//!
//! # Reading
//! [`LogReader`] pulls bytes from a [`ByteSource`] into a buffer lent by the caller
//! (at least [`MIN_READER_BUFFER`] bytes) and yields [`LogRecord`]s that borrow that buffer;
//! scan ranges stay little-endian bytes until [`ScanRecord::range`] or
//! [`ScanRecord::ranges_into`] decodes them. The lower-level [`decode_header`],
//! [`frame_len`] and [`decode_frame`] work on plain slices.

use core::fmt;

use super::{ScanGeometry, Timestamp};
use crate::geom::Se2;

/// First eight bytes of every log.
pub const MAGIC: [u8; 8] = *b"CLOILOG\x1a";
/// Format version written by this encoder and read by this decoder.
pub const VERSION: u16 = 1;
/// Length of the version-1 file header.
pub const HEADER_LEN: usize = 16;
/// Header record count meaning "not known when the header was written".
pub const UNKNOWN_COUNT: u32 = u32::MAX;
/// Record framing: 8 header bytes before the payload and the 4-byte CRC after it.
pub const FRAME_OVERHEAD: usize = 12;
/// Most beams a scan record may hold (a 270 degree scanner at a quarter degree: Hokuyo
/// UTM-30LX), equal to the front-end's point capacity.
pub const MAX_BEAMS: usize = crate::frontend::scan::MAX_POINTS;
/// Fixed part of a scan payload without the odometry pose.
const SCAN_FIXED: usize = 8 + 4 * 4 + 3 * 8 + 2;
/// Largest payload of any record (a full scan with its odometry pose).
pub const MAX_PAYLOAD: usize = SCAN_FIXED + 3 * 8 + 4 * MAX_BEAMS;
/// Largest framed record.
pub const MAX_FRAME: usize = FRAME_OVERHEAD + MAX_PAYLOAD;
/// Smallest buffer a [`LogReader`] accepts: one largest record, whatever its alignment in
/// the stream, plus the file header.
pub const MIN_READER_BUFFER: usize = MAX_FRAME + HEADER_LEN;

/// Record kind of [`OdometryRecord`].
pub const KIND_ODOMETRY: u8 = 1;
/// Record kind of [`GyroRecord`].
pub const KIND_GYRO: u8 = 2;
/// Record kind of [`ScanRecord`].
pub const KIND_SCAN: u8 = 3;
/// Scan flag: the payload holds the odometry pose at the scan's time.
const SCAN_HAS_ODOM: u8 = 1;

const ODOMETRY_LEN: usize = 32;
const GYRO_LEN: usize = 16;

/// Why a log (or part of it) cannot be read or written.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum LogError {
    /// The file does not start with [`MAGIC`].
    BadMagic,
    /// The version is not one this decoder reads.
    UnsupportedVersion {
        /// Version in the file.
        version: u16,
    },
    /// The header length field is below [`HEADER_LEN`].
    BadHeaderLength {
        /// Header length in the file.
        len: u16,
    },
    /// The stream ended inside the header or a record.
    Truncated {
        /// Bytes of the unfinished part that were present.
        have: usize,
        /// Bytes it needs at least.
        need: usize,
    },
    /// A record announces a payload longer than [`MAX_PAYLOAD`].
    RecordTooLarge {
        /// Announced payload length.
        len: u32,
    },
    /// A scan holds more than [`MAX_BEAMS`] beams.
    TooManyBeams {
        /// Beams in the record.
        beams: usize,
    },
    /// A known record's payload length does not match its fields.
    BadLength {
        /// Record kind.
        kind: u8,
        /// Payload length in the record.
        len: usize,
        /// Length its fields need.
        expected: usize,
    },
    /// The record's CRC does not match its bytes.
    BadChecksum {
        /// CRC stored in the record.
        stored: u32,
        /// CRC of the bytes read.
        computed: u32,
    },
    /// The stream ended cleanly but holds another number of records than its header says.
    CountMismatch {
        /// Count in the header.
        expected: u32,
        /// Records read.
        found: u32,
    },
    /// A caller buffer is too small (for encoding, for a reader, or for decoded ranges).
    BufferTooSmall {
        /// Bytes (or ranges) needed.
        need: usize,
        /// Bytes (or ranges) available.
        have: usize,
    },
}

impl fmt::Display for LogError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::BadMagic => f.write_str("not a cloilog file (bad magic)"),
            Self::UnsupportedVersion { version } => {
                write!(f, "cloilog version {version} is not supported")
            }
            Self::BadHeaderLength { len } => write!(f, "cloilog header length {len} < 16"),
            Self::Truncated { have, need } => {
                write!(f, "the log ends inside a record ({have} of {need} bytes)")
            }
            Self::RecordTooLarge { len } => {
                write!(f, "record payload of {len} bytes exceeds {MAX_PAYLOAD}")
            }
            Self::TooManyBeams { beams } => {
                write!(f, "scan of {beams} beams exceeds {MAX_BEAMS}")
            }
            Self::BadLength {
                kind,
                len,
                expected,
            } => write!(
                f,
                "record kind {kind} has a {len}-byte payload, its fields need {expected}"
            ),
            Self::BadChecksum { stored, computed } => write!(
                f,
                "record checksum {stored:08x} does not match its bytes ({computed:08x})"
            ),
            Self::CountMismatch { expected, found } => {
                write!(
                    f,
                    "the header announces {expected} records, the log has {found}"
                )
            }
            Self::BufferTooSmall { need, have } => {
                write!(f, "buffer of {have} too small, {need} needed")
            }
        }
    }
}

impl core::error::Error for LogError {}

/// The file header.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LogHeader {
    /// Format version.
    pub version: u16,
    /// Number of records, when the writer knew it.
    pub record_count: Option<u32>,
}

/// Wheel odometry: the robot's pose in the odometry frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OdometryRecord {
    /// Time of the pose.
    pub stamp: Timestamp,
    /// Pose (x, y in metres, heading in radians), stored as written.
    pub pose: Se2,
}

/// A yaw-rate gyro sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GyroRecord {
    /// Time of the sample.
    pub stamp: Timestamp,
    /// Rate of turn about the vertical axis, rad/s.
    pub yaw_rate: f64,
}

/// Everything of a scan but its ranges.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScanMeta {
    /// Time of the scan.
    pub stamp: Timestamp,
    /// Beam angles and range limits.
    pub geometry: ScanGeometry,
    /// Pose of the laser in the robot frame.
    pub laser_offset: Se2,
    /// Odometry pose of the robot at the scan's time, when the source log has it.
    pub odom: Option<Se2>,
}

/// A scan whose ranges are still little-endian `f32` bytes inside the reader's buffer.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScanRecord<'a> {
    /// Time, geometry, mounting and odometry.
    pub meta: ScanMeta,
    ranges_le: &'a [u8],
}

impl<'a> ScanRecord<'a> {
    /// A scan over little-endian `f32` range bytes.
    ///
    /// # Errors
    /// [`LogError::BadLength`] when the byte count is not a multiple of 4,
    /// [`LogError::TooManyBeams`] above [`MAX_BEAMS`].
    pub fn new(meta: ScanMeta, ranges_le: &'a [u8]) -> Result<Self, LogError> {
        if !ranges_le.len().is_multiple_of(4) {
            return Err(LogError::BadLength {
                kind: KIND_SCAN,
                len: ranges_le.len(),
                expected: ranges_le.len() / 4 * 4,
            });
        }
        if ranges_le.len() / 4 > MAX_BEAMS {
            return Err(LogError::TooManyBeams {
                beams: ranges_le.len() / 4,
            });
        }
        Ok(Self { meta, ranges_le })
    }

    /// Number of beams.
    pub fn beams(&self) -> usize {
        self.ranges_le.len() / 4
    }

    /// Range of beam `i`, or `None` past the end.
    pub fn range(&self, i: usize) -> Option<f32> {
        let at = i.checked_mul(4)?;
        let bytes = self.ranges_le.get(at..at.checked_add(4)?)?;
        Some(f32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]))
    }

    /// The ranges, decoded one by one.
    pub fn ranges(&self) -> impl Iterator<Item = f32> + 'a {
        self.ranges_le
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    /// Decodes the ranges into the front of `out` and returns that part.
    ///
    /// # Errors
    /// [`LogError::BufferTooSmall`] when `out` holds fewer than [`Self::beams`] values.
    pub fn ranges_into<'o>(&self, out: &'o mut [f32]) -> Result<&'o [f32], LogError> {
        let n = self.beams();
        let have = out.len();
        let Some(dst) = out.get_mut(..n) else {
            return Err(LogError::BufferTooSmall { need: n, have });
        };
        for (d, r) in dst.iter_mut().zip(self.ranges()) {
            *d = r;
        }
        Ok(dst)
    }

    /// The raw little-endian range bytes.
    pub fn ranges_le(&self) -> &'a [u8] {
        self.ranges_le
    }
}

/// One decoded record.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LogRecord<'a> {
    /// Wheel odometry.
    Odometry(OdometryRecord),
    /// Yaw-rate gyro.
    Gyro(GyroRecord),
    /// A laser scan.
    Scan(ScanRecord<'a>),
    /// A record of a kind this decoder does not know (checked, then handed over unread).
    Unknown {
        /// Record kind.
        kind: u8,
        /// Record flags.
        flags: u8,
        /// Its payload.
        payload: &'a [u8],
    },
}

impl LogRecord<'_> {
    /// The record's time stamp (`None` for unknown kinds).
    pub fn stamp(&self) -> Option<Timestamp> {
        match self {
            Self::Odometry(o) => Some(o.stamp),
            Self::Gyro(g) => Some(g.stamp),
            Self::Scan(s) => Some(s.meta.stamp),
            Self::Unknown { .. } => None,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// CRC-32 (IEEE 802.3, reflected polynomial 0xEDB88320), table-driven.

const CRC_TABLE: [u32; 256] = {
    let mut table = [0u32; 256];
    let mut i = 0;
    while i < 256 {
        let mut c = i as u32;
        let mut k = 0;
        while k < 8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
            k += 1;
        }
        table[i] = c;
        i += 1;
    }
    table
};

/// CRC-32 (IEEE) of `bytes`, as in zlib and PNG.
pub fn crc32(bytes: &[u8]) -> u32 {
    let mut c = !0u32;
    for &b in bytes {
        c = CRC_TABLE[((c ^ u32::from(b)) & 0xff) as usize] ^ (c >> 8);
    }
    !c
}

// ---------------------------------------------------------------------------------------------
// Little-endian field access that never panics.

/// Reads fixed-size fields from a slice front to back; every read past the end gives `None`.
struct Fields<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Fields<'a> {
    fn new(bytes: &'a [u8]) -> Self {
        Self { bytes, at: 0 }
    }

    fn take<const N: usize>(&mut self) -> Option<[u8; N]> {
        let end = self.at.checked_add(N)?;
        let chunk = self.bytes.get(self.at..end)?;
        self.at = end;
        let mut out = [0u8; N];
        out.copy_from_slice(chunk);
        Some(out)
    }

    fn u16(&mut self) -> Option<u16> {
        self.take().map(u16::from_le_bytes)
    }

    fn u32(&mut self) -> Option<u32> {
        self.take().map(u32::from_le_bytes)
    }

    fn i64(&mut self) -> Option<i64> {
        self.take().map(i64::from_le_bytes)
    }

    fn f32(&mut self) -> Option<f32> {
        self.take().map(f32::from_le_bytes)
    }

    fn f64(&mut self) -> Option<f64> {
        self.take().map(f64::from_le_bytes)
    }

    /// Poses are read field by field, without wrapping the angle, so the bits survive.
    fn pose(&mut self) -> Option<Se2> {
        Some(Se2 {
            x: self.f64()?,
            y: self.f64()?,
            theta: self.f64()?,
        })
    }

    fn rest(&self) -> &'a [u8] {
        self.bytes.get(self.at..).unwrap_or(&[])
    }
}

/// Writes fields front to back into a slice whose length was checked beforehand.
struct Emit<'a> {
    out: &'a mut [u8],
    at: usize,
}

impl Emit<'_> {
    fn put(&mut self, bytes: &[u8]) {
        let end = self.at + bytes.len();
        if let Some(dst) = self.out.get_mut(self.at..end) {
            dst.copy_from_slice(bytes);
        }
        self.at = end;
    }

    fn pose(&mut self, p: &Se2) {
        self.put(&p.x.to_le_bytes());
        self.put(&p.y.to_le_bytes());
        self.put(&p.theta.to_le_bytes());
    }
}

// ---------------------------------------------------------------------------------------------
// Header.

/// Decodes the file header from the front of `input`: `Ok(None)` when fewer bytes than the
/// header are present, else the header and its length (to skip).
///
/// # Errors
/// [`LogError::BadMagic`], [`LogError::UnsupportedVersion`], [`LogError::BadHeaderLength`].
pub fn decode_header(input: &[u8]) -> Result<Option<(LogHeader, usize)>, LogError> {
    // Check the magic on whatever is there, so a wrong file fails on its first bytes.
    let n = input.len().min(MAGIC.len());
    if input.get(..n) != MAGIC.get(..n) {
        return Err(LogError::BadMagic);
    }
    let mut f = Fields::new(input);
    let Some(_magic) = f.take::<8>() else {
        return Ok(None);
    };
    let (Some(version), Some(len), Some(count)) = (f.u16(), f.u16(), f.u32()) else {
        return Ok(None);
    };
    if version != VERSION {
        return Err(LogError::UnsupportedVersion { version });
    }
    if usize::from(len) < HEADER_LEN {
        return Err(LogError::BadHeaderLength { len });
    }
    if input.len() < usize::from(len) {
        return Ok(None);
    }
    let header = LogHeader {
        version,
        record_count: (count != UNKNOWN_COUNT).then_some(count),
    };
    Ok(Some((header, usize::from(len))))
}

/// Writes a version-1 header with `record_count` into `out`; returns [`HEADER_LEN`].
///
/// # Errors
/// [`LogError::BufferTooSmall`] when `out` is shorter than [`HEADER_LEN`].
pub fn encode_header(record_count: Option<u32>, out: &mut [u8]) -> Result<usize, LogError> {
    if out.len() < HEADER_LEN {
        return Err(LogError::BufferTooSmall {
            need: HEADER_LEN,
            have: out.len(),
        });
    }
    let mut e = Emit { out, at: 0 };
    e.put(&MAGIC);
    e.put(&VERSION.to_le_bytes());
    e.put(&(HEADER_LEN as u16).to_le_bytes());
    e.put(&record_count.unwrap_or(UNKNOWN_COUNT).to_le_bytes());
    Ok(HEADER_LEN)
}

// ---------------------------------------------------------------------------------------------
// Records.

/// Length of the framed record at the front of `input`: `Ok(None)` while its 8-byte frame
/// header is incomplete. The payload length is checked before any of it is read, so a
/// corrupted length cannot make a reader wait for gigabytes.
///
/// # Errors
/// [`LogError::RecordTooLarge`] above [`MAX_PAYLOAD`].
pub fn frame_len(input: &[u8]) -> Result<Option<usize>, LogError> {
    let mut f = Fields::new(input);
    let (Some(_head), Some(len)) = (f.take::<4>(), f.u32()) else {
        return Ok(None);
    };
    if len as usize > MAX_PAYLOAD {
        return Err(LogError::RecordTooLarge { len });
    }
    Ok(Some(FRAME_OVERHEAD + len as usize))
}

fn expect_len(kind: u8, len: usize, expected: usize) -> Result<(), LogError> {
    if len == expected {
        Ok(())
    } else {
        Err(LogError::BadLength {
            kind,
            len,
            expected,
        })
    }
}

fn bad_length(kind: u8, len: usize) -> LogError {
    LogError::BadLength {
        kind,
        len,
        expected: 0,
    }
}

/// Decodes the framed record at the front of `input` (which may hold more bytes after it):
/// checks its length and CRC, then its fields. Returns the record and the bytes it used.
///
/// # Errors
/// [`LogError::Truncated`] when `input` ends inside the record; [`LogError::RecordTooLarge`],
/// [`LogError::BadChecksum`], [`LogError::BadLength`] or [`LogError::TooManyBeams`] for a
/// damaged record.
pub fn decode_frame(input: &[u8]) -> Result<(LogRecord<'_>, usize), LogError> {
    let Some(total) = frame_len(input)? else {
        return Err(LogError::Truncated {
            have: input.len(),
            need: FRAME_OVERHEAD,
        });
    };
    let Some(frame) = input.get(..total) else {
        return Err(LogError::Truncated {
            have: input.len(),
            need: total,
        });
    };
    let body_len = total - 4;
    let (body, crc) = frame.split_at(body_len);
    let stored = u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]);
    let computed = crc32(body);
    if stored != computed {
        return Err(LogError::BadChecksum { stored, computed });
    }
    let (kind, flags) = (body[0], body[1]);
    let payload = &body[8..];
    let len = payload.len();
    let mut f = Fields::new(payload);
    let record = match kind {
        KIND_ODOMETRY => {
            expect_len(kind, len, ODOMETRY_LEN)?;
            let (Some(t), Some(pose)) = (f.i64(), f.pose()) else {
                return Err(bad_length(kind, len));
            };
            LogRecord::Odometry(OdometryRecord {
                stamp: Timestamp::from_nanos(t),
                pose,
            })
        }
        KIND_GYRO => {
            expect_len(kind, len, GYRO_LEN)?;
            let (Some(t), Some(yaw_rate)) = (f.i64(), f.f64()) else {
                return Err(bad_length(kind, len));
            };
            LogRecord::Gyro(GyroRecord {
                stamp: Timestamp::from_nanos(t),
                yaw_rate,
            })
        }
        KIND_SCAN => LogRecord::Scan(decode_scan(flags, payload)?),
        _ => LogRecord::Unknown {
            kind,
            flags,
            payload,
        },
    };
    Ok((record, total))
}

fn decode_scan(flags: u8, payload: &[u8]) -> Result<ScanRecord<'_>, LogError> {
    let has_odom = flags & SCAN_HAS_ODOM != 0;
    let fixed = SCAN_FIXED + if has_odom { 24 } else { 0 };
    let len = payload.len();
    let mut f = Fields::new(payload);
    let short = || LogError::BadLength {
        kind: KIND_SCAN,
        len,
        expected: fixed,
    };
    let stamp = Timestamp::from_nanos(f.i64().ok_or_else(short)?);
    let geometry = ScanGeometry {
        angle_min: f.f32().ok_or_else(short)?,
        angle_increment: f.f32().ok_or_else(short)?,
        range_min: f.f32().ok_or_else(short)?,
        range_max: f.f32().ok_or_else(short)?,
    };
    let laser_offset = f.pose().ok_or_else(short)?;
    let odom = if has_odom {
        Some(f.pose().ok_or_else(short)?)
    } else {
        None
    };
    let n = usize::from(f.u16().ok_or_else(short)?);
    if n > MAX_BEAMS {
        return Err(LogError::TooManyBeams { beams: n });
    }
    expect_len(KIND_SCAN, len, fixed + 4 * n)?;
    ScanRecord::new(
        ScanMeta {
            stamp,
            geometry,
            laser_offset,
            odom,
        },
        f.rest(),
    )
}

/// Frames `payload_len` payload bytes written by `fill` as a record of `kind` in `out`.
fn frame(
    kind: u8,
    flags: u8,
    payload_len: usize,
    out: &mut [u8],
    fill: impl FnOnce(&mut Emit<'_>),
) -> Result<usize, LogError> {
    if payload_len > MAX_PAYLOAD {
        return Err(LogError::RecordTooLarge {
            len: u32::try_from(payload_len).unwrap_or(u32::MAX),
        });
    }
    let total = FRAME_OVERHEAD + payload_len;
    let have = out.len();
    let Some(out) = out.get_mut(..total) else {
        return Err(LogError::BufferTooSmall { need: total, have });
    };
    let mut e = Emit { out, at: 0 };
    e.put(&[kind, flags, 0, 0]);
    e.put(&(payload_len as u32).to_le_bytes());
    fill(&mut e);
    let crc = crc32(e.out.get(..total - 4).unwrap_or(&[]));
    e.at = total - 4;
    e.put(&crc.to_le_bytes());
    Ok(total)
}

/// Encodes an odometry record into `out`; returns its length.
///
/// # Errors
/// [`LogError::BufferTooSmall`].
pub fn encode_odometry(r: &OdometryRecord, out: &mut [u8]) -> Result<usize, LogError> {
    frame(KIND_ODOMETRY, 0, ODOMETRY_LEN, out, |e| {
        e.put(&r.stamp.as_nanos().to_le_bytes());
        e.pose(&r.pose);
    })
}

/// Encodes a gyro record into `out`; returns its length.
///
/// # Errors
/// [`LogError::BufferTooSmall`].
pub fn encode_gyro(r: &GyroRecord, out: &mut [u8]) -> Result<usize, LogError> {
    frame(KIND_GYRO, 0, GYRO_LEN, out, |e| {
        e.put(&r.stamp.as_nanos().to_le_bytes());
        e.put(&r.yaw_rate.to_le_bytes());
    })
}

/// Encodes a scan from its metadata and `n` ranges produced by `ranges`.
fn encode_scan_with(
    meta: &ScanMeta,
    n: usize,
    ranges: impl Iterator<Item = f32>,
    out: &mut [u8],
) -> Result<usize, LogError> {
    if n > MAX_BEAMS {
        return Err(LogError::TooManyBeams { beams: n });
    }
    let (flags, odom_len) = match meta.odom {
        Some(_) => (SCAN_HAS_ODOM, 24),
        None => (0, 0),
    };
    frame(KIND_SCAN, flags, SCAN_FIXED + odom_len + 4 * n, out, |e| {
        e.put(&meta.stamp.as_nanos().to_le_bytes());
        let g = &meta.geometry;
        for v in [g.angle_min, g.angle_increment, g.range_min, g.range_max] {
            e.put(&v.to_le_bytes());
        }
        e.pose(&meta.laser_offset);
        if let Some(odom) = &meta.odom {
            e.pose(odom);
        }
        e.put(&(n as u16).to_le_bytes());
        for r in ranges.take(n) {
            e.put(&r.to_le_bytes());
        }
    })
}

/// Encodes a scan record from its metadata and ranges; returns its length.
///
/// # Errors
/// [`LogError::TooManyBeams`] above [`MAX_BEAMS`], [`LogError::BufferTooSmall`].
pub fn encode_scan(meta: &ScanMeta, ranges: &[f32], out: &mut [u8]) -> Result<usize, LogError> {
    encode_scan_with(meta, ranges.len(), ranges.iter().copied(), out)
}

/// Encodes any record (unknown kinds are framed as they are); returns its length.
///
/// # Errors
/// [`LogError::BufferTooSmall`], [`LogError::RecordTooLarge`], [`LogError::TooManyBeams`].
pub fn encode_record(record: &LogRecord<'_>, out: &mut [u8]) -> Result<usize, LogError> {
    match record {
        LogRecord::Odometry(r) => encode_odometry(r, out),
        LogRecord::Gyro(r) => encode_gyro(r, out),
        LogRecord::Scan(s) => encode_scan_with(&s.meta, s.beams(), s.ranges(), out),
        LogRecord::Unknown {
            kind,
            flags,
            payload,
        } => frame(*kind, *flags, payload.len(), out, |e| e.put(payload)),
    }
}

// ---------------------------------------------------------------------------------------------
// Streaming.

/// Where a [`LogReader`] gets its bytes: a file read in chunks, a serial link, a slice.
pub trait ByteSource {
    /// The source's own error.
    type Error;

    /// Fills the front of `buf` with the next bytes and returns how many; 0 means the end.
    ///
    /// # Errors
    /// The source's failure; the reader passes it on as [`ReadError::Source`].
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error>;
}

impl ByteSource for &[u8] {
    type Error = core::convert::Infallible;

    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let n = buf.len().min(self.len());
        let (head, tail) = self.split_at(n);
        if let Some(dst) = buf.get_mut(..n) {
            dst.copy_from_slice(head);
        }
        *self = tail;
        Ok(n)
    }
}

/// A failure of [`LogReader::next_record`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ReadError<E> {
    /// The log is damaged; `offset` is the stream position of the header or record at fault.
    Log {
        /// What is wrong.
        error: LogError,
        /// Byte offset in the stream.
        offset: u64,
    },
    /// The byte source failed.
    Source(E),
}

impl<E: fmt::Display> fmt::Display for ReadError<E> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Log { error, offset } => write!(f, "at byte {offset}: {error}"),
            Self::Source(e) => write!(f, "reading the log: {e}"),
        }
    }
}

impl<E: fmt::Debug + fmt::Display> core::error::Error for ReadError<E> {}

/// Streams records from a [`ByteSource`] through a buffer lent by the caller.
///
/// The reader asks the source for as many bytes as fit after the unread ones (a source may
/// return fewer: the firmware reads fixed chunks), moves the unread tail to the front when a
/// record would not fit, and yields each record borrowed from the buffer until the next call.
/// After an error it yields nothing more.
#[derive(Debug)]
pub struct LogReader<'b, S> {
    source: S,
    buf: &'b mut [u8],
    start: usize,
    end: usize,
    /// Stream offset of `buf[start]`.
    offset: u64,
    header: Option<LogHeader>,
    records: u32,
    source_done: bool,
    failed: bool,
}

/// What the buffer holds at its front.
enum Front {
    Ready(usize),
    Need(usize),
}

impl<'b, S: ByteSource> LogReader<'b, S> {
    /// A reader over `source` using `buf` (at least [`MIN_READER_BUFFER`] bytes).
    ///
    /// # Errors
    /// [`LogError::BufferTooSmall`].
    pub fn new(source: S, buf: &'b mut [u8]) -> Result<Self, LogError> {
        if buf.len() < MIN_READER_BUFFER {
            return Err(LogError::BufferTooSmall {
                need: MIN_READER_BUFFER,
                have: buf.len(),
            });
        }
        Ok(Self {
            source,
            buf,
            start: 0,
            end: 0,
            offset: 0,
            header: None,
            records: 0,
            source_done: false,
            failed: false,
        })
    }

    /// The file header, once the first record (or the end) has been read.
    pub fn header(&self) -> Option<LogHeader> {
        self.header
    }

    /// Records yielded so far.
    pub fn records(&self) -> u32 {
        self.records
    }

    /// Stream offset of the next unread byte.
    pub fn offset(&self) -> u64 {
        self.offset
    }

    /// The source (e.g. to close a file).
    pub fn into_source(self) -> S {
        self.source
    }

    fn fail<T>(&mut self, error: LogError) -> Result<T, ReadError<S::Error>> {
        self.failed = true;
        Err(ReadError::Log {
            error,
            offset: self.offset,
        })
    }

    /// Makes room for `need` bytes at the front and reads once from the source; returns
    /// false at the end of the source.
    fn refill(&mut self, need: usize) -> Result<bool, ReadError<S::Error>> {
        if self.source_done {
            return Ok(false);
        }
        if self.start + need > self.buf.len() || self.end == self.buf.len() {
            self.buf.copy_within(self.start..self.end, 0);
            self.end -= self.start;
            self.start = 0;
        }
        let Some(space) = self.buf.get_mut(self.end..) else {
            return Ok(false);
        };
        let n = match self.source.read(space) {
            Ok(n) => n.min(space.len()),
            Err(e) => {
                self.failed = true;
                return Err(ReadError::Source(e));
            }
        };
        if n == 0 {
            self.source_done = true;
            return Ok(false);
        }
        self.end += n;
        Ok(true)
    }

    fn front(&self) -> Result<Front, LogError> {
        let avail = self.buf.get(self.start..self.end).unwrap_or(&[]);
        if self.header.is_none() {
            return Ok(match decode_header(avail)? {
                Some((_, len)) => Front::Ready(len),
                None => Front::Need(HEADER_LEN.max(avail.len() + 1)),
            });
        }
        Ok(match frame_len(avail)? {
            Some(total) if total <= avail.len() => Front::Ready(total),
            Some(total) => Front::Need(total),
            None => Front::Need(8),
        })
    }

    /// Next record, `Ok(None)` at the clean end of the log.
    ///
    /// # Errors
    /// [`ReadError::Log`] for damaged or truncated data (including a record count that
    /// disagrees with the header), [`ReadError::Source`] when the source fails.
    pub fn next_record(&mut self) -> Result<Option<LogRecord<'_>>, ReadError<S::Error>> {
        if self.failed {
            return Ok(None);
        }
        let len = loop {
            let need = match self.front() {
                Ok(Front::Ready(len)) if self.header.is_some() => break len,
                Ok(Front::Ready(len)) => {
                    // The header: remember it, skip it and look again.
                    let avail = self.buf.get(self.start..self.end).unwrap_or(&[]);
                    match decode_header(avail) {
                        Ok(Some((h, _))) => self.header = Some(h),
                        Ok(None) => return self.fail(LogError::BadMagic),
                        Err(e) => return self.fail(e),
                    }
                    self.start += len;
                    self.offset += len as u64;
                    continue;
                }
                Ok(Front::Need(need)) => need,
                Err(e) => return self.fail(e),
            };
            if !self.refill(need)? {
                let have = self.end - self.start;
                if self.header.is_none() {
                    return self.fail(LogError::Truncated {
                        have,
                        need: HEADER_LEN,
                    });
                }
                if have > 0 {
                    return self.fail(LogError::Truncated { have, need });
                }
                if let Some(expected) = self.header.and_then(|h| h.record_count) {
                    if expected != self.records {
                        return self.fail(LogError::CountMismatch {
                            expected,
                            found: self.records,
                        });
                    }
                }
                return Ok(None);
            }
        };
        let at = self.start;
        let offset = self.offset;
        self.start += len;
        self.offset += len as u64;
        // Disjoint fields: the record borrows `buf` while `failed` and `records` change.
        let Self {
            buf,
            failed,
            records,
            ..
        } = self;
        let frame = buf.get(at..at + len).unwrap_or(&[]);
        match decode_frame(frame) {
            Ok((record, _)) => {
                *records = records.saturating_add(1);
                Ok(Some(record))
            }
            Err(error) => {
                *failed = true;
                Err(ReadError::Log { error, offset })
            }
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;

    use std::vec;
    use std::vec::Vec;

    use proptest::prelude::*;

    use super::*;

    fn geometry() -> ScanGeometry {
        ScanGeometry {
            angle_min: -1.5,
            angle_increment: 0.0175,
            range_min: 0.0,
            range_max: 80.0,
        }
    }

    fn meta(t: i64, odom: Option<Se2>) -> ScanMeta {
        ScanMeta {
            stamp: Timestamp::from_nanos(t),
            geometry: geometry(),
            laser_offset: Se2 {
                x: 0.1,
                y: 0.0,
                theta: 0.0,
            },
            odom,
        }
    }

    /// An owned record for the tests (ranges as values).
    #[derive(Clone, Debug)]
    enum Owned {
        Odometry(OdometryRecord),
        Gyro(GyroRecord),
        Scan(ScanMeta, Vec<f32>),
        Unknown(u8, u8, Vec<u8>),
    }

    fn encode(records: &[Owned], count: Option<u32>) -> Vec<u8> {
        let mut out = vec![0u8; HEADER_LEN];
        encode_header(count, &mut out).unwrap();
        let mut frame = vec![0u8; MAX_FRAME];
        for r in records {
            let n = match r {
                Owned::Odometry(o) => encode_odometry(o, &mut frame),
                Owned::Gyro(g) => encode_gyro(g, &mut frame),
                Owned::Scan(m, ranges) => encode_scan(m, ranges, &mut frame),
                Owned::Unknown(kind, flags, payload) => encode_record(
                    &LogRecord::Unknown {
                        kind: *kind,
                        flags: *flags,
                        payload,
                    },
                    &mut frame,
                ),
            }
            .unwrap();
            out.extend_from_slice(&frame[..n]);
        }
        out
    }

    /// A source handing out at most `chunk` bytes per read.
    struct Chunked<'a> {
        data: &'a [u8],
        chunk: usize,
    }

    impl ByteSource for Chunked<'_> {
        type Error = core::convert::Infallible;
        fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
            let n = buf.len().min(self.chunk).min(self.data.len());
            buf[..n].copy_from_slice(&self.data[..n]);
            self.data = &self.data[n..];
            Ok(n)
        }
    }

    /// Reads a whole log, re-encoding every record; returns the frames and the end result.
    fn read_all(
        data: &[u8],
        chunk: usize,
    ) -> (
        Vec<Vec<u8>>,
        Result<(), ReadError<core::convert::Infallible>>,
    ) {
        let mut buf = vec![0u8; MIN_READER_BUFFER];
        let mut reader = LogReader::new(Chunked { data, chunk }, &mut buf).unwrap();
        let mut frames = Vec::new();
        loop {
            match reader.next_record() {
                Ok(Some(r)) => {
                    let mut f = vec![0u8; MAX_FRAME];
                    let n = encode_record(&r, &mut f).unwrap();
                    f.truncate(n);
                    frames.push(f);
                }
                Ok(None) => return (frames, Ok(())),
                Err(e) => return (frames, Err(e)),
            }
        }
    }

    #[test]
    fn crc_matches_the_standard_check_value() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc32(b""), 0);
    }

    #[test]
    fn decodes_every_kind_with_exact_bits() {
        let odom = Se2 {
            x: 1.25,
            y: -2.5,
            theta: 4.0, // not wrapped: stored as written
        };
        let ranges = [1.0f32, f32::NAN, 81.83, f32::INFINITY];
        let records = [
            Owned::Odometry(OdometryRecord {
                stamp: Timestamp::from_nanos(-5),
                pose: odom,
            }),
            Owned::Gyro(GyroRecord {
                stamp: Timestamp::from_nanos(7),
                yaw_rate: -0.125,
            }),
            Owned::Scan(meta(9, Some(odom)), ranges.to_vec()),
            Owned::Scan(meta(10, None), Vec::new()),
            Owned::Unknown(200, 3, vec![1, 2, 3]),
        ];
        let data = encode(&records, Some(5));
        let mut buf = vec![0u8; MIN_READER_BUFFER];
        let mut reader = LogReader::new(&data[..], &mut buf).unwrap();
        match reader.next_record().unwrap().unwrap() {
            LogRecord::Odometry(o) => {
                assert_eq!(o.stamp.as_nanos(), -5);
                assert_eq!(o.pose.theta, 4.0);
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(
            reader.header(),
            Some(LogHeader {
                version: 1,
                record_count: Some(5)
            })
        );
        match reader.next_record().unwrap().unwrap() {
            LogRecord::Gyro(g) => assert_eq!(g.yaw_rate, -0.125),
            other => panic!("{other:?}"),
        }
        match reader.next_record().unwrap().unwrap() {
            LogRecord::Scan(s) => {
                assert_eq!(s.meta, meta(9, Some(odom)));
                assert_eq!(s.beams(), 4);
                let mut out = [0f32; 8];
                let got = s.ranges_into(&mut out).unwrap();
                for (a, b) in got.iter().zip(&ranges) {
                    assert_eq!(a.to_bits(), b.to_bits());
                }
                assert_eq!(s.range(2), Some(81.83));
                assert_eq!(s.range(4), None);
                assert_eq!(
                    s.ranges_into(&mut [0f32; 3]),
                    Err(LogError::BufferTooSmall { need: 4, have: 3 })
                );
            }
            other => panic!("{other:?}"),
        }
        match reader.next_record().unwrap().unwrap() {
            LogRecord::Scan(s) => assert_eq!((s.beams(), s.meta.odom), (0, None)),
            other => panic!("{other:?}"),
        }
        match reader.next_record().unwrap().unwrap() {
            LogRecord::Unknown {
                kind,
                flags,
                payload,
            } => assert_eq!((kind, flags, payload), (200, 3, &[1u8, 2, 3][..])),
            other => panic!("{other:?}"),
        }
        assert_eq!(reader.next_record().unwrap(), None);
        assert_eq!(reader.records(), 5);
        assert_eq!(reader.offset(), data.len() as u64);
    }

    #[test]
    fn damage_gives_typed_errors() {
        let scan = Owned::Scan(meta(1, None), vec![2.0; 10]);
        let good = encode(core::slice::from_ref(&scan), Some(1));
        let first_error = |data: &[u8]| read_all(data, 4096).1.unwrap_err();
        let log_error = |e: ReadError<core::convert::Infallible>| match e {
            ReadError::Log { error, .. } => error,
            ReadError::Source(never) => match never {},
        };

        let mut bad = good.clone();
        bad[0] = b'X';
        assert_eq!(log_error(first_error(&bad)), LogError::BadMagic);
        assert_eq!(log_error(first_error(b"PK")), LogError::BadMagic);

        let mut bad = good.clone();
        bad[8] = 9;
        assert_eq!(
            log_error(first_error(&bad)),
            LogError::UnsupportedVersion { version: 9 }
        );

        // A flipped range bit.
        let mut bad = good.clone();
        bad[good.len() - 10] ^= 0x40;
        assert!(matches!(
            log_error(first_error(&bad)),
            LogError::BadChecksum { .. }
        ));

        // Cut inside the record.
        let cut = &good[..good.len() - 3];
        let e = first_error(cut);
        assert_eq!(
            e,
            ReadError::Log {
                error: LogError::Truncated {
                    have: good.len() - HEADER_LEN - 3,
                    need: good.len() - HEADER_LEN
                },
                offset: HEADER_LEN as u64
            }
        );
        assert_eq!(
            log_error(first_error(&good[..10])),
            LogError::Truncated {
                have: 10,
                need: HEADER_LEN
            }
        );

        // Header count disagrees.
        let wrong = encode(core::slice::from_ref(&scan), Some(2));
        assert_eq!(
            log_error(first_error(&wrong)),
            LogError::CountMismatch {
                expected: 2,
                found: 1
            }
        );

        // An announced payload beyond the maximum is refused before it is waited for.
        let mut huge = encode(&[], None);
        huge.extend_from_slice(&[3, 0, 0, 0]);
        huge.extend_from_slice(&u32::MAX.to_le_bytes());
        assert_eq!(
            log_error(first_error(&huge)),
            LogError::RecordTooLarge { len: u32::MAX }
        );

        // A scan announcing too many beams (with a valid CRC).
        let mut frame = vec![0u8; MAX_FRAME];
        let n = encode_scan(&meta(1, None), &[1.0; 4], &mut frame).unwrap();
        let n_at = 8 + SCAN_FIXED - 2;
        frame[n_at..n_at + 2].copy_from_slice(&2000u16.to_le_bytes());
        let crc = crc32(&frame[..n - 4]);
        frame[n - 4..n].copy_from_slice(&crc.to_le_bytes());
        assert_eq!(
            decode_frame(&frame[..n]).unwrap_err(),
            LogError::TooManyBeams { beams: 2000 }
        );
        assert_eq!(
            encode_scan(&meta(1, None), &[0.0; MAX_BEAMS + 1], &mut frame),
            Err(LogError::TooManyBeams {
                beams: MAX_BEAMS + 1
            })
        );

        // A known kind with a wrong length (valid CRC).
        let mut frame = vec![0u8; 64];
        let n = encode_record(
            &LogRecord::Unknown {
                kind: KIND_ODOMETRY,
                flags: 0,
                payload: &[0; 31],
            },
            &mut frame,
        )
        .unwrap();
        assert_eq!(
            decode_frame(&frame[..n]).unwrap_err(),
            LogError::BadLength {
                kind: KIND_ODOMETRY,
                len: 31,
                expected: 32
            }
        );

        assert!(LogReader::new(&good[..], &mut [0u8; 100]).is_err());
        assert_eq!(
            encode_header(None, &mut [0u8; 15]),
            Err(LogError::BufferTooSmall { need: 16, have: 15 })
        );
    }

    #[test]
    fn an_unknown_count_accepts_any_number_of_records() {
        let data = encode(&[Owned::Scan(meta(1, None), vec![1.0])], None);
        let (frames, end) = read_all(&data, 3);
        assert_eq!((frames.len(), end), (1, Ok(())));
    }

    fn arb_f64() -> impl Strategy<Value = f64> {
        any::<u64>().prop_map(f64::from_bits)
    }

    fn arb_pose() -> impl Strategy<Value = Se2> {
        (arb_f64(), arb_f64(), arb_f64()).prop_map(|(x, y, theta)| Se2 { x, y, theta })
    }

    fn arb_record() -> impl Strategy<Value = Owned> {
        let stamp = any::<i64>().prop_map(Timestamp::from_nanos);
        prop_oneof![
            (stamp.clone(), arb_pose())
                .prop_map(|(stamp, pose)| Owned::Odometry(OdometryRecord { stamp, pose })),
            (stamp.clone(), arb_f64())
                .prop_map(|(stamp, yaw_rate)| Owned::Gyro(GyroRecord { stamp, yaw_rate })),
            (
                stamp,
                any::<[u32; 4]>(),
                arb_pose(),
                proptest::option::of(arb_pose()),
                proptest::collection::vec(any::<u32>().prop_map(f32::from_bits), 0..300),
            )
                .prop_map(|(stamp, g, laser_offset, odom, ranges)| {
                    let geometry = ScanGeometry {
                        angle_min: f32::from_bits(g[0]),
                        angle_increment: f32::from_bits(g[1]),
                        range_min: f32::from_bits(g[2]),
                        range_max: f32::from_bits(g[3]),
                    };
                    Owned::Scan(
                        ScanMeta {
                            stamp,
                            geometry,
                            laser_offset,
                            odom,
                        },
                        ranges,
                    )
                }),
            (
                4u8..=255,
                any::<u8>(),
                proptest::collection::vec(any::<u8>(), 0..64)
            )
                .prop_map(|(k, f, p)| Owned::Unknown(k, f, p)),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// Encode, read back in chunks of any size, re-encode: the same bytes, so every field
        /// (float bits included) survives.
        #[test]
        fn round_trip_in_any_chunking(
            records in proptest::collection::vec(arb_record(), 0..12),
            chunk in 1usize..5000,
            known in any::<bool>(),
        ) {
            let count = known.then_some(records.len() as u32);
            let data = encode(&records, count);
            let (frames, end) = read_all(&data, chunk);
            prop_assert_eq!(end, Ok(()));
            prop_assert_eq!(frames.len(), records.len());
            prop_assert_eq!(frames.concat(), data[HEADER_LEN..].to_vec());
        }

        /// A prefix of a log cut inside the header or a record is reported as truncated; a cut
        /// at a record boundary reads the records before it (the count is unknown here).
        #[test]
        fn truncation_is_reported(
            records in proptest::collection::vec(arb_record(), 1..6),
            cut in any::<proptest::sample::Index>(),
            chunk in 1usize..3000,
        ) {
            let data = encode(&records, None);
            let cut = cut.index(data.len());
            let (frames, end) = read_all(&data[..cut], chunk);
            prop_assert!(end.is_err() || cut >= HEADER_LEN && frames.concat().len() == cut - HEADER_LEN);
            if let Err(ReadError::Log { error, .. }) = end {
                let is_truncated = matches!(error, LogError::Truncated { .. });
                prop_assert!(is_truncated);
            }
        }

        /// Random bytes, with or without a valid header in front, never panic.
        #[test]
        fn random_bytes_never_panic(
            bytes in proptest::collection::vec(any::<u8>(), 0..3000),
            with_header in any::<bool>(),
            chunk in 1usize..600,
        ) {
            let mut data = if with_header { encode(&[], None) } else { Vec::new() };
            data.extend_from_slice(&bytes);
            let _ = read_all(&data, chunk);
            let _ = decode_frame(&bytes);
            let _ = decode_header(&bytes);
        }

        /// Flipping one bit of a record is always caught (CRC, length or magic checks).
        #[test]
        fn a_flipped_bit_is_caught(
            record in arb_record(),
            bit in any::<proptest::sample::Index>(),
        ) {
            let mut data = encode(core::slice::from_ref(&record), Some(1));
            let bit = bit.index((data.len() - HEADER_LEN) * 8) + HEADER_LEN * 8;
            data[bit / 8] ^= 1 << (bit % 8);
            let (_, end) = read_all(&data, 4096);
            prop_assert!(end.is_err());
        }
    }
}
