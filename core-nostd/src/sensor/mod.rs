//! Sensor frames as the mapper consumes them: small `Copy` values and views over borrowed
//! buffers, so the core never owns heap data. The host decodes files (ROS 2 bags, CARMEN logs)
//! or drivers into these types and lends them to the core for one call.
//!
//! * [`Timestamp`]: signed nanoseconds since an epoch the caller chooses (Unix time for logs).
//! * [`OdometrySample`], [`ImuSample`]: wheel odometry (pose and twist) and angular rate.
//! * [`ScanGeometry`]: beam angles and range limits of a planar laser scanner, and
//!   [`MAX_BEAMS`], the most beams one scan may carry.
//! * [`ImageView`]: a camera picture over `&[u8]` (mono8, rgb8, bgr8).
//! * [`ld06`]: the LDRobot LD06 / LD19 serial LiDAR protocol: packets decoded byte by byte,
//!   points gathered into whole revolutions.
//! * [`rplidar`]: the Slamtec RPLIDAR (A1, A2, C1) standard scan: requests, descriptor and
//!   nodes decoded byte by byte, gathered into the same revolutions as the LD06's points.
//! * [`urg`]: Hokuyo's SCIP 2.0 (URG-04LX, UTM-30LX): requests, parameters and the scans of
//!   `MD` / `GD` decoded line by line.
//! * [`create2`]: the iRobot Create 2's Open Interface as a wheel-odometry source: the
//!   encoder stream's requests and frames, the counts integrated into a pose.
//! * [`gyro`]: what the gyro drivers share (full scales, errors, the yaw rate as a trait) and
//!   the bias measured at standstill; [`mpu6050`] (the InvenSense MPU-6050 family) and
//!   [`lsm6ds`] (the STMicroelectronics LSM6DS family) read the yaw rate on an `embedded-hal`
//!   I2C bus.
//! * [`log`]: the compact binary sensor log (`.cloilog`) streamed to the firmware, with its
//!   encoder and a streaming, allocation-free decoder.

pub mod create2;
pub mod gyro;
mod image;
pub mod ld06;
pub mod log;
pub mod lsm6ds;
pub mod mpu6050;
mod odometry;
pub mod rplidar;
mod scan;
mod time;
pub mod urg;

pub use image::{ImageError, ImageView, PixelFormat};
pub use odometry::{ImuSample, OdometrySample, Twist2};
pub use scan::{ScanGeometry, MAX_BEAMS};
pub use time::Timestamp;
