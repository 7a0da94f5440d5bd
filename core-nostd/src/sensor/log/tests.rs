//! Tests of the `.cloilog` format: round trips, damaged input and streaming.

extern crate std;

use std::vec;
use std::vec::Vec;

use proptest::prelude::*;

use super::*;
use crate::geom::Se2;
use crate::sensor::{ScanGeometry, Timestamp};

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
