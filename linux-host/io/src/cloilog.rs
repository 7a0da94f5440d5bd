//! CARMEN logs to the compact binary sensor log of the firmware (`.cloilog`, format in
//! [`cloi_core::sensor::log`]): `cloi convert IN.clf --to cloilog --out OUT.cloilog`.
//!
//! The records are the ones the ROS 2 conversion ([`crate::convert::CarmenToRos`]) makes, so a
//! run on the `.cloilog` sees the same events as a run on the bag or the CARMEN log:
//! * every `/odom` message becomes an odometry record (the `ODOM` lines; a log without them
//!   gets the odometry pose of each front scan, until the first `ODOM` line);
//! * every front scan (`FLASER`, `ROBOTLASER1`) becomes a scan record with the same angles and
//!   limits as the bag's `/scan` message, the laser offset the bag puts on `/tf_static`, and
//!   the odometry pose of the line (if it has one);
//! * rear and raw lasers are skipped (counted).
//!
//! Odometry headings and the laser offset come through the ROS messages' quaternions (as for
//! a run on the bag); the scan's own odometry pose is the line's numbers as written.
//!
//! `max_scans` stops after that many scans (for short CI logs). The record count is written
//! into the header when the file is complete.

use std::io::{Seek, SeekFrom, Write};
use std::path::Path;

use anyhow::{bail, Context, Result};
use cloi_core::sensor::log::{
    encode_header, encode_odometry, encode_scan, OdometryRecord, ScanMeta, HEADER_LEN, MAX_BEAMS,
    MAX_FRAME,
};
use cloi_core::sensor::{ScanGeometry, Timestamp};
use cloi_core::Se2;

use crate::atomic::AtomicFile;
use crate::carmen::{CarmenReader, CarmenRecord, CarmenStats};
use crate::convert::{CarmenToRos, RosOut};
use crate::ros2::Transform;

/// Counts of a conversion to `.cloilog`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CloilogReport {
    /// Scan records written.
    pub scans: u64,
    /// Odometry records written.
    pub odometry: u64,
    /// Scans of other lasers (rear, raw) skipped.
    pub other_lasers: u64,
    /// Bytes written.
    pub bytes: u64,
    /// The conversion stopped at `max_scans`.
    pub cut: bool,
    /// What the CARMEN reader saw.
    pub input: CarmenStats,
}

/// The planar pose of a transform.
fn planar(t: &Transform) -> Se2 {
    Se2 {
        x: t.translation.x,
        y: t.translation.y,
        theta: t.rotation.yaw(),
    }
}

/// Converts a CARMEN log to a `.cloilog` (written atomically).
///
/// # Errors
/// Unreadable input, damage in strict mode, a scan with more than
/// [`cloi_core::sensor::log::MAX_BEAMS`] beams, or an unwritable output.
pub fn carmen_to_cloilog(
    input: &Path,
    output: &Path,
    strict: bool,
    range_max: Option<f32>,
    max_scans: Option<u64>,
) -> Result<CloilogReport> {
    let mut reader = CarmenReader::open(input, strict)?;
    let mut file = AtomicFile::create(output)?;
    let mut conv = CarmenToRos::new(range_max);
    let mut report = CloilogReport::default();
    let mut frame = vec![0u8; MAX_FRAME];
    let mut header = [0u8; HEADER_LEN];
    encode_header(None, &mut header)?;
    let writing = || format!("writing {}", output.display());
    let w = file.writer();
    w.write_all(&header).with_context(writing)?;
    report.bytes = HEADER_LEN as u64;
    let mut mount = Se2::IDENTITY;
    'records: for record in reader.by_ref() {
        let record = record?;
        let laser_odom = match &record {
            CarmenRecord::Laser(l) => l.odom_pose.map(|(x, y, theta)| Se2 { x, y, theta }),
            _ => None,
        };
        for out in conv.convert(&record) {
            if max_scans.is_some_and(|m| report.scans >= m) {
                report.cut = true;
                break 'records;
            }
            let n = match (&out.msg, out.topic) {
                (RosOut::Tf(tf), "/tf_static") => {
                    if let Some(t) = tf.transforms.first() {
                        mount = planar(&t.transform);
                    }
                    continue;
                }
                (RosOut::Odom(o), _) => {
                    report.odometry += 1;
                    let (x, y, theta) = o.pose.pose.to_planar();
                    let stamp = Timestamp::from_nanos(out.log_time_ns);
                    let pose = Se2 { x, y, theta };
                    encode_odometry(&OdometryRecord { stamp, pose }, &mut frame)?
                }
                (RosOut::Scan(scan), "/scan") => {
                    if scan.ranges.len() > MAX_BEAMS {
                        bail!(
                            "a scan at {} ns has {} beams; the cloilog format holds at most {MAX_BEAMS}",
                            out.log_time_ns,
                            scan.ranges.len()
                        );
                    }
                    report.scans += 1;
                    let meta = ScanMeta {
                        stamp: Timestamp::from_nanos(out.log_time_ns),
                        geometry: ScanGeometry {
                            angle_min: scan.angle_min,
                            angle_increment: scan.angle_increment,
                            range_min: scan.range_min,
                            range_max: scan.range_max,
                        },
                        laser_offset: mount,
                        odom: laser_odom,
                    };
                    encode_scan(&meta, &scan.ranges, &mut frame)?
                }
                (RosOut::Scan(_), _) => {
                    report.other_lasers += 1;
                    continue;
                }
                (RosOut::Tf(_), _) => continue,
            };
            w.write_all(&frame[..n]).with_context(writing)?;
            report.bytes += n as u64;
        }
    }
    let count = u32::try_from(report.scans + report.odometry)
        .context("too many records for the cloilog header")?;
    encode_header(Some(count), &mut header)?;
    w.seek(SeekFrom::Start(0)).with_context(writing)?;
    w.write_all(&header).with_context(writing)?;
    w.seek(SeekFrom::End(0)).with_context(writing)?;
    file.commit()?;
    report.input = reader.stats().clone();
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use cloi_core::sensor::log::{LogReader, LogRecord, MIN_READER_BUFFER};

    const LOG: &str = "PARAM robot_frontlaser_offset 0.1 h 0\n\
ODOM 0.0 0.0 0.0 0.0 0.0 0.0 100.0 h 0\n\
FLASER 3 1.0 2.0 3.0 0.1 0 0 0 0 0 100.05 h 0\n\
RLASER 3 1.0 2.0 3.0 0.1 0 0 0 0 0 100.06 h 0\n\
ODOM 1.0 0.0 0.5 0.5 0.0 0.0 100.1 h 0\n\
FLASER 3 1.0 2.0 3.0 1.1 0 0.5 1 0 0.5 100.15 h 0\n\
ODOM 2.0 0.0 0.0 0.5 0.0 0.0 100.2 h 0\n";

    fn convert(max_scans: Option<u64>) -> (CloilogReport, Vec<u8>) {
        let dir = tempfile::tempdir().unwrap();
        let clf = dir.path().join("t.clf");
        std::fs::write(&clf, LOG).unwrap();
        let out = dir.path().join("t.cloilog");
        let report = carmen_to_cloilog(&clf, &out, true, None, max_scans).unwrap();
        (report, std::fs::read(out).unwrap())
    }

    #[test]
    fn carmen_lines_become_records() {
        let (report, bytes) = convert(None);
        assert_eq!(
            (
                report.scans,
                report.odometry,
                report.other_lasers,
                report.cut
            ),
            (2, 3, 1, false)
        );
        assert_eq!(report.bytes, bytes.len() as u64);
        let mut buf = vec![0u8; MIN_READER_BUFFER];
        let mut reader = LogReader::new(&bytes[..], &mut buf).unwrap();
        let mut kinds = String::new();
        while let Some(r) = reader.next_record().unwrap() {
            match r {
                LogRecord::Odometry(o) => {
                    kinds.push('o');
                    if o.stamp.as_nanos() == 100_100_000_000 {
                        assert!(o.pose.x == 1.0 && (o.pose.theta - 0.5).abs() < 1e-15);
                    }
                }
                LogRecord::Scan(s) => {
                    kinds.push('s');
                    assert_eq!(s.beams(), 3);
                    assert!((s.meta.laser_offset.x - 0.1).abs() < 1e-12);
                    assert_eq!(s.meta.geometry.range_max, 80.0);
                    assert_eq!(s.range(2), Some(3.0));
                    if s.meta.stamp.as_nanos() == 100_150_000_000 {
                        assert_eq!(s.meta.odom, Some(Se2::new(1.0, 0.0, 0.5)));
                    }
                }
                other => panic!("{other:?}"),
            }
        }
        assert_eq!(kinds, "ososo");
        assert_eq!(reader.header().unwrap().record_count, Some(5));
    }

    #[test]
    fn max_scans_cuts_the_log() {
        let (report, bytes) = convert(Some(1));
        assert_eq!((report.scans, report.odometry, report.cut), (1, 1, true));
        let mut buf = vec![0u8; MIN_READER_BUFFER];
        let mut reader = LogReader::new(&bytes[..], &mut buf).unwrap();
        let mut n = 0;
        while reader.next_record().unwrap().is_some() {
            n += 1;
        }
        assert_eq!(n, 2);
    }
}
