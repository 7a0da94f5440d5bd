//! `cloi run --record FILE.mcap`: what the devices send, written to a ROS 2 bag as they send
//! it, so that `cloi map FILE.mcap` replays the run: `/scan` (`sensor_msgs/LaserScan` in frame
//! `laser`), the LiDAR's mounting once on `/tf_static`, `/odom` (`nav_msgs/Odometry`, `odom` to
//! `base_link`) from a wheel-odometry device and `/imu` (`sensor_msgs/Imu`, the yaw rate) from a
//! gyro. Every device thread writes into the one
//! recording; a write that fails stops the recording with a warning, never the run.

use std::path::Path;
use std::sync::Mutex;

use anyhow::{Context, Result};
use cloi_core::Se2;

use crate::io::bag::BagWriter;
use crate::io::ros2::{
    Header, Imu, LaserScan, Odometry, Pose, PoseWithCovariance, TfMessage, Time, Transform,
    TransformStamped, Vector3,
};
use crate::map::input::ScanEvent;

/// The recording every device thread writes into; `None` once it stopped (or without
/// `--record`).
pub type SharedRecorder = Mutex<Option<Recorder>>;

/// The bag a live run is recorded into.
pub struct Recorder {
    bag: BagWriter,
    mounting: Se2,
    tf_written: bool,
    previous_scan: Option<i64>,
}

impl std::fmt::Debug for Recorder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recorder")
            .field("mounting", &self.mounting)
            .finish_non_exhaustive()
    }
}

impl Recorder {
    /// A new bag at `path`; the LiDAR sits at `mounting` on the robot.
    ///
    /// # Errors
    /// The file cannot be created.
    pub fn create(path: &Path, mounting: Se2) -> Result<Self> {
        Ok(Recorder {
            bag: BagWriter::create(path)
                .with_context(|| format!("creating the recording {}", path.display()))?,
            mounting,
            tf_written: false,
            previous_scan: None,
        })
    }

    /// Writes one scan (and, before the first, the mounting).
    ///
    /// # Errors
    /// The write fails.
    pub fn scan(&mut self, scan: &ScanEvent) -> Result<()> {
        if !std::mem::replace(&mut self.tf_written, true) {
            let m = self.mounting;
            let tf = TfMessage {
                transforms: vec![TransformStamped {
                    header: Header::new(Time::from_nanos(scan.t_ns), "base_link"),
                    child_frame_id: "laser".into(),
                    transform: Transform::planar(m.x, m.y, m.theta),
                }],
            };
            self.bag.write("/tf_static", scan.t_ns, &tf)?;
        }
        let scan_time = self
            .previous_scan
            .replace(scan.t_ns)
            .map_or(0.0, |p| (scan.t_ns - p) as f32 * 1e-9);
        let msg = LaserScan {
            header: Header::new(Time::from_nanos(scan.t_ns), "laser"),
            angle_min: scan.angle_min,
            angle_max: scan.angle_min + scan.angle_increment * (scan.ranges.len() - 1) as f32,
            angle_increment: scan.angle_increment,
            time_increment: scan.time_increment,
            scan_time,
            range_min: scan.range_min,
            range_max: scan.range_max,
            ranges: scan.ranges.clone(),
            intensities: Vec::new(),
        };
        self.bag.write("/scan", scan.t_ns, &msg)
    }

    /// Writes one wheel-odometry pose.
    ///
    /// # Errors
    /// The write fails.
    pub fn odometry(&mut self, t_ns: i64, pose: Se2) -> Result<()> {
        let msg = Odometry {
            header: Header::new(Time::from_nanos(t_ns), "odom"),
            child_frame_id: "base_link".into(),
            pose: PoseWithCovariance {
                pose: Pose::planar(pose.x, pose.y, pose.theta),
                ..PoseWithCovariance::default()
            },
            ..Odometry::default()
        };
        self.bag.write("/odom", t_ns, &msg)
    }

    /// Writes one yaw rate (rad/s) as an IMU message without orientation or acceleration.
    ///
    /// # Errors
    /// The write fails.
    pub fn gyro(&mut self, t_ns: i64, yaw_rate: f64) -> Result<()> {
        // -1 in a covariance's first element: the quantity is not measured.
        let mut unknown = [0.0; 9];
        unknown[0] = -1.0;
        let msg = Imu {
            header: Header::new(Time::from_nanos(t_ns), "imu"),
            orientation_covariance: unknown,
            angular_velocity: Vector3 {
                x: 0.0,
                y: 0.0,
                z: yaw_rate,
            },
            linear_acceleration_covariance: unknown,
            ..Imu::default()
        };
        self.bag.write("/imu", t_ns, &msg)
    }

    /// Closes the bag.
    ///
    /// # Errors
    /// The last write fails.
    pub fn finish(self) -> Result<()> {
        self.bag.finish().map(|_| ())
    }
}

/// Writes with `write` into `shared` if it still records; a failure stops the recording with a
/// warning. Whether the write went in.
pub fn record(shared: &SharedRecorder, write: impl FnOnce(&mut Recorder) -> Result<()>) -> bool {
    let mut guard = shared
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let Some(r) = guard.as_mut() else {
        return false;
    };
    match write(r) {
        Ok(()) => true,
        Err(e) => {
            log::warn!("recording stopped: {e:#}");
            *guard = None;
            false
        }
    }
}

/// Closes the recording, if there is one.
///
/// # Errors
/// The bag cannot be finished.
pub fn finish(shared: &SharedRecorder) -> Result<()> {
    let taken = shared
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .take();
    taken.map_or(Ok(()), Recorder::finish)
}
