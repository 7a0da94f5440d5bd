//! CARMEN logs to ROS 2 messages, and on to a bag (`cloi convert IN.clf OUT.mcap`).
//!
//! Mapping (streaming, one CARMEN record at a time):
//! * `FLASER`/`RLASER`/`ROBOTLASER1`/`RAWLASER*` -> `sensor_msgs/msg/LaserScan` on `/scan`
//!   (front and robot lasers; frame `laser`) or `/scan_rear` (rear; frame `laser_rear`), and
//!   `/scan_raw<k>` for raw lasers. `range_min` is 0; `range_max` is `--range-max` if given,
//!   else the line's maximum range (`ROBOTLASER1`, `RAWLASER`), else the log's
//!   `PARAM robot_front_laser_max`, else 80 m, so the logs' "no return" value 81.83 m lies
//!   beyond it.
//! * `ODOM` -> `nav_msgs/msg/Odometry` on `/odom` (`odom` -> `base_link`, velocity `tv`, `rv`)
//!   and the same transform on `/tf`.
//! * The odometry pose inside a front or robot laser line (`FLASER`, `ROBOTLASER1`) is the
//!   robot's odometry at the scan's own time, as the robot recorded it: it goes to `/odom` and
//!   `/tf` too, stamped like the scan and written before it (velocity zero: the line has
//!   none). A log without `ODOM` lines (mit-csail) has only these; in the others they sit
//!   between the `ODOM` samples, so a mapper fed in stamp order seeds each scan with the pose
//!   logged for it rather than one interpolated between `ODOM` samples. The bag gets them for
//!   every scan ([`CarmenToRos::every_scan_odometry`]); the `.cloilog` writer, whose scan
//!   records carry that pose themselves, only until the first `ODOM` line.
//! * The laser's mounting (`base_link` -> `laser`) goes once to `/tf_static` with the first
//!   scan: `PARAM robot_frontlaser_offset` (an x offset) if it came before, else the offset
//!   between the first front scan's laser pose and odometry pose.

use std::path::Path;

use anyhow::Result;

use crate::bag::BagWriter;
use crate::carmen::{CarmenLaser, CarmenReader, CarmenRecord, CarmenStats, LaserSource};
use crate::ros2::{
    Header, LaserScan, Odometry, Pose, TfMessage, Time, Transform, TransformStamped,
};

/// Default `range_max` for lasers whose lines give none (m).
pub const DEFAULT_RANGE_MAX: f32 = 80.0;

/// A ROS message made from a CARMEN record.
#[derive(Debug, Clone, PartialEq)]
pub enum RosOut {
    /// A scan.
    Scan(LaserScan),
    /// Odometry (boxed: it is large).
    Odom(Box<Odometry>),
    /// Transforms.
    Tf(TfMessage),
}

/// One output message with its topic and log time.
#[derive(Debug, Clone, PartialEq)]
pub struct Stamped {
    /// Topic.
    pub topic: &'static str,
    /// Log time (ns).
    pub log_time_ns: i64,
    /// The message.
    pub msg: RosOut,
}

/// Conversion state.
#[derive(Debug, Clone, Default)]
pub struct CarmenToRos {
    /// `--range-max` override.
    pub range_max_override: Option<f32>,
    front_laser_max: Option<f32>,
    front_laser_offset: Option<f64>,
    /// Every front scan's odometry pose becomes an odometry message (else only until the
    /// first `ODOM` line).
    pub every_scan_odometry: bool,
    seen_odom_line: bool,
    tf_static_done: bool,
}

fn relative(from: (f64, f64, f64), to: (f64, f64, f64)) -> (f64, f64, f64) {
    let (c, s) = (from.2.cos(), from.2.sin());
    let (dx, dy) = (to.0 - from.0, to.1 - from.1);
    let dth = (to.2 - from.2).sin().atan2((to.2 - from.2).cos());
    (c * dx + s * dy, -s * dx + c * dy, dth)
}

fn odometry(stamp_ns: i64, pose: (f64, f64, f64), tv: f64, rv: f64) -> Odometry {
    let mut odom = Odometry {
        header: Header::new(Time::from_nanos(stamp_ns), "odom"),
        child_frame_id: "base_link".into(),
        ..Default::default()
    };
    odom.pose.pose = Pose::planar(pose.0, pose.1, pose.2);
    odom.twist.twist.linear.x = tv;
    odom.twist.twist.angular.z = rv;
    odom
}

fn odom_tf(odom: &Odometry) -> TfMessage {
    let p = odom.pose.pose;
    TfMessage {
        transforms: vec![TransformStamped {
            header: odom.header.clone(),
            child_frame_id: odom.child_frame_id.clone(),
            transform: Transform {
                translation: crate::ros2::Vector3 {
                    x: p.position.x,
                    y: p.position.y,
                    z: p.position.z,
                },
                rotation: p.orientation,
            },
        }],
    }
}

/// Topic and frame of a laser source.
pub fn laser_topic(source: LaserSource) -> (&'static str, &'static str) {
    match source {
        LaserSource::Front | LaserSource::Robot => ("/scan", "laser"),
        LaserSource::Rear => ("/scan_rear", "laser_rear"),
        LaserSource::Raw(1) => ("/scan_raw1", "laser_raw1"),
        LaserSource::Raw(2) => ("/scan_raw2", "laser_raw2"),
        LaserSource::Raw(3) => ("/scan_raw3", "laser_raw3"),
        LaserSource::Raw(_) => ("/scan_raw4", "laser_raw4"),
    }
}

impl CarmenToRos {
    /// A converter with an optional `range_max` override.
    pub fn new(range_max_override: Option<f32>) -> Self {
        Self {
            range_max_override,
            ..Default::default()
        }
    }

    /// The scan message of a CARMEN laser line.
    pub fn scan(&self, laser: &CarmenLaser) -> LaserScan {
        let (_, frame) = laser_topic(laser.source);
        let n = laser.ranges.len();
        let range_max = self
            .range_max_override
            .or(laser.max_range)
            .or(self.front_laser_max)
            .unwrap_or(DEFAULT_RANGE_MAX);
        LaserScan {
            header: Header::new(Time::from_nanos(laser.stamp_ns), frame),
            angle_min: laser.angle_min,
            angle_max: laser.angle_min + laser.angle_increment * n.saturating_sub(1) as f32,
            angle_increment: laser.angle_increment,
            time_increment: 0.0,
            scan_time: 0.0,
            range_min: 0.0,
            range_max,
            ranges: laser.ranges.clone(),
            intensities: laser.remissions.clone(),
        }
    }

    /// The ROS messages of one CARMEN record, in time order.
    pub fn convert(&mut self, record: &CarmenRecord) -> Vec<Stamped> {
        let mut out = Vec::new();
        match record {
            CarmenRecord::Param { name, value } => match name.as_str() {
                "robot_front_laser_max" => self.front_laser_max = value.parse().ok(),
                "robot_frontlaser_offset" => self.front_laser_offset = value.parse().ok(),
                _ => {}
            },
            CarmenRecord::Odom(o) => {
                self.seen_odom_line = true;
                let odom = odometry(o.stamp_ns, o.pose, o.tv, o.rv);
                out.push(Stamped {
                    topic: "/tf",
                    log_time_ns: o.stamp_ns,
                    msg: RosOut::Tf(odom_tf(&odom)),
                });
                out.push(Stamped {
                    topic: "/odom",
                    log_time_ns: o.stamp_ns,
                    msg: RosOut::Odom(Box::new(odom)),
                });
            }
            CarmenRecord::Laser(laser) => {
                let front = matches!(laser.source, LaserSource::Front | LaserSource::Robot);
                if front && !self.tf_static_done {
                    self.tf_static_done = true;
                    let mount = match (self.front_laser_offset, laser.laser_pose, laser.odom_pose) {
                        (Some(dx), _, _) => (dx, 0.0, 0.0),
                        (None, Some(l), Some(o)) => relative(o, l),
                        _ => (0.0, 0.0, 0.0),
                    };
                    out.push(Stamped {
                        topic: "/tf_static",
                        log_time_ns: laser.stamp_ns,
                        msg: RosOut::Tf(TfMessage {
                            transforms: vec![TransformStamped {
                                header: Header::new(Time::from_nanos(laser.stamp_ns), "base_link"),
                                child_frame_id: "laser".into(),
                                transform: Transform::planar(mount.0, mount.1, mount.2),
                            }],
                        }),
                    });
                }
                if front && (self.every_scan_odometry || !self.seen_odom_line) {
                    if let Some(pose) = laser.odom_pose {
                        let odom = odometry(laser.stamp_ns, pose, 0.0, 0.0);
                        out.push(Stamped {
                            topic: "/tf",
                            log_time_ns: laser.stamp_ns,
                            msg: RosOut::Tf(odom_tf(&odom)),
                        });
                        out.push(Stamped {
                            topic: "/odom",
                            log_time_ns: laser.stamp_ns,
                            msg: RosOut::Odom(Box::new(odom)),
                        });
                    }
                }
                let (topic, _) = laser_topic(laser.source);
                out.push(Stamped {
                    topic,
                    log_time_ns: laser.stamp_ns,
                    msg: RosOut::Scan(self.scan(laser)),
                });
            }
        }
        out
    }
}

/// Counts of a conversion.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ConvertReport {
    /// Scans written.
    pub scans: u64,
    /// Odometry messages written.
    pub odoms: u64,
    /// TF messages written.
    pub tfs: u64,
    /// What the CARMEN reader saw.
    pub input: CarmenStats,
}

/// Converts a CARMEN log to a ROS 2 bag (written atomically).
///
/// # Errors
/// Unreadable input, damage in strict mode, or an unwritable output.
pub fn carmen_to_bag(
    input: &Path,
    output: &Path,
    strict: bool,
    range_max: Option<f32>,
) -> Result<ConvertReport> {
    let mut reader = CarmenReader::open(input, strict)?;
    let mut bag = BagWriter::create(output)?;
    let mut conv = CarmenToRos {
        every_scan_odometry: true,
        ..CarmenToRos::new(range_max)
    };
    let mut report = ConvertReport::default();
    for record in reader.by_ref() {
        for out in conv.convert(&record?) {
            match &out.msg {
                RosOut::Scan(m) => {
                    report.scans += 1;
                    bag.write(out.topic, out.log_time_ns, m)?;
                }
                RosOut::Odom(m) => {
                    report.odoms += 1;
                    bag.write(out.topic, out.log_time_ns, m.as_ref())?;
                }
                RosOut::Tf(m) => {
                    report.tfs += 1;
                    bag.write(out.topic, out.log_time_ns, m)?;
                }
            }
        }
    }
    bag.finish()?;
    report.input = reader.stats().clone();
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::carmen::reader_from_bytes;

    #[test]
    fn maps_lines_to_messages() {
        let log = "PARAM robot_front_laser_max 50.0 h 0\n\
FLASER 3 1.0 2.0 81.83 1.1 2.0 0.0 1.0 2.0 0.0 10.5 h 0\n\
ODOM 1.0 2.0 0.0 0.3 0.1 0.0 10.6 h 0\n\
FLASER 3 1.0 2.0 3.0 1.1 2.0 0.0 1.0 2.0 0.0 10.7 h 0\n";
        let mut conv = CarmenToRos {
            every_scan_odometry: true,
            ..CarmenToRos::new(None)
        };
        let mut all = Vec::new();
        for rec in reader_from_bytes(log.into(), "m.clf", true) {
            all.extend(conv.convert(&rec.unwrap()));
        }
        let topics: Vec<&str> = all.iter().map(|s| s.topic).collect();
        assert_eq!(
            topics,
            [
                "/tf_static",
                "/tf",
                "/odom",
                "/scan",
                "/tf",
                "/odom",
                "/tf",
                "/odom",
                "/scan"
            ]
        );
        let RosOut::Tf(tf) = &all[0].msg else {
            panic!()
        };
        assert!((tf.transforms[0].transform.translation.x - 0.1).abs() < 1e-12);
        let RosOut::Scan(scan) = &all[3].msg else {
            panic!()
        };
        assert_eq!(scan.range_max, 50.0);
        assert_eq!(scan.ranges, vec![1.0, 2.0, 81.83]);
        assert!((scan.angle_min + std::f32::consts::FRAC_PI_2).abs() < 1e-6);
        assert_eq!(scan.header.stamp.to_nanos(), 10_500_000_000);
        let RosOut::Odom(odom) = &all[5].msg else {
            panic!()
        };
        assert_eq!(odom.twist.twist.linear.x, 0.3);
        assert_eq!(odom.header.stamp.to_nanos(), 10_600_000_000);
        // The second scan's own odometry pose, at its stamp, after the ODOM line.
        let RosOut::Odom(odom) = &all[7].msg else {
            panic!()
        };
        assert_eq!(odom.header.stamp.to_nanos(), 10_700_000_000);
        assert_eq!(odom.pose.pose.to_planar().0, 1.0);
    }

    #[test]
    fn relative_pose_is_in_the_robot_frame() {
        let r = relative((1.0, 1.0, std::f64::consts::FRAC_PI_2), (1.0, 2.0, 0.0));
        assert!((r.0 - 1.0).abs() < 1e-12 && r.1.abs() < 1e-12);
        assert!((r.2 + std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    }
}
