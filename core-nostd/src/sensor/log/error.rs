//! The errors of the `.cloilog` format: what a damaged log, an oversized record or a short
//! buffer reports instead of panicking.

use core::fmt;

use super::{MAX_BEAMS, MAX_PAYLOAD};

/// Why a log (or part of it) cannot be read or written.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum LogError {
    /// The file does not start with [`MAGIC`](super::MAGIC).
    BadMagic,
    /// The version is not one this decoder reads.
    UnsupportedVersion {
        /// Version in the file.
        version: u16,
    },
    /// The header length field is below [`HEADER_LEN`](super::HEADER_LEN).
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
