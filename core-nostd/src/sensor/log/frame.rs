//! The `.cloilog` codec on plain slices: the file header, record framing with its CRC, and the
//! payload layout of each record kind (see the parent module for the byte layout).

use super::crc::crc32;
use super::{
    GyroRecord, LogError, LogHeader, LogRecord, OdometryRecord, ScanMeta, ScanRecord,
    FRAME_OVERHEAD, GYRO_LEN, HEADER_LEN, KIND_GYRO, KIND_ODOMETRY, KIND_SCAN, MAGIC, MAX_BEAMS,
    MAX_PAYLOAD, ODOMETRY_LEN, SCAN_FIXED, SCAN_HAS_ODOM, UNKNOWN_COUNT, VERSION,
};
use crate::geom::Se2;
use crate::sensor::{ScanGeometry, Timestamp};

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
