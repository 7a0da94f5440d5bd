//! The decoded `.cloilog` records: odometry, gyro and scan values, the scan's ranges kept as
//! borrowed little-endian bytes until the caller decodes them.

use super::{LogError, KIND_SCAN, MAX_BEAMS};
use crate::geom::Se2;
use crate::sensor::{ScanGeometry, Timestamp};

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
