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

//!
//! # Modules
//! * `error`: [`LogError`], what can be wrong with a log or a buffer.
//! * `record`: the decoded records ([`LogRecord`] and its kinds).
//! * `crc`: the CRC-32 that guards every record.
//! * `frame`: the header and record codec on plain slices.
//! * `reader`: [`LogReader`], the streaming decoder over a [`ByteSource`].

mod crc;
mod error;
mod frame;
mod reader;
mod record;

pub use crc::crc32;
pub use error::LogError;
pub use frame::{
    decode_frame, decode_header, encode_gyro, encode_header, encode_odometry, encode_record,
    encode_scan, frame_len,
};
pub use reader::{ByteSource, LogReader, ReadError};
pub use record::{GyroRecord, LogHeader, LogRecord, OdometryRecord, ScanMeta, ScanRecord};

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
/// Most beams a scan record may hold: the sensor layer's limit, re-exported here because the
/// record sizes below follow from it.
pub use super::MAX_BEAMS;
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

#[cfg(test)]
mod tests;
