//! Wheel odometry and inertial samples.

use crate::geom::Se2;

use super::Timestamp;

/// Planar velocity in the robot frame.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Twist2 {
    /// Forward speed (m/s).
    pub vx: f64,
    /// Sideways speed (m/s), zero for a differential drive.
    pub vy: f64,
    /// Turn rate (rad/s, counter-clockwise).
    pub wz: f64,
}

/// One odometry reading: the robot pose in the odometry frame, integrated by the wheels (it
/// drifts; only differences between samples are meaningful), and its velocity.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OdometrySample {
    /// When the pose was measured.
    pub stamp: Timestamp,
    /// Pose of the robot in the odometry frame.
    pub pose: Se2,
    /// Velocity in the robot frame (zero when the source has none).
    pub twist: Twist2,
    /// Covariance of (x, y, theta), row major, when the source provides one.
    pub covariance: Option<[[f64; 3]; 3]>,
}

impl OdometrySample {
    /// A sample with a pose only (no velocity, no covariance).
    pub fn new(stamp: Timestamp, pose: Se2) -> Self {
        Self {
            stamp,
            pose,
            twist: Twist2::default(),
            covariance: None,
        }
    }

    /// `true` when the pose, the twist and the covariance (if any) are finite.
    pub fn is_finite(&self) -> bool {
        let twist =
            self.twist.vx.is_finite() && self.twist.vy.is_finite() && self.twist.wz.is_finite();
        let cov = self
            .covariance
            .is_none_or(|c| c.iter().flatten().all(|v| v.is_finite()));
        self.pose.is_finite() && twist && cov
    }
}

/// One inertial reading: angular rate (gyro) and, when available, linear acceleration.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ImuSample {
    /// When it was measured.
    pub stamp: Timestamp,
    /// Angular rate about the IMU's x, y, z axes (rad/s).
    pub angular_rate: [f64; 3],
    /// Linear acceleration along x, y, z (m/s^2), if the sensor has an accelerometer.
    pub linear_acceleration: Option<[f64; 3]>,
}

impl ImuSample {
    /// A gyro-only sample with a yaw rate (rad/s), as planar robots use.
    pub fn yaw_rate_only(stamp: Timestamp, yaw_rate: f64) -> Self {
        Self {
            stamp,
            angular_rate: [0.0, 0.0, yaw_rate],
            linear_acceleration: None,
        }
    }

    /// The rate about z (rad/s).
    pub fn yaw_rate(&self) -> f64 {
        self.angular_rate[2]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finiteness_checks_every_part() {
        let mut s = OdometrySample::new(Timestamp(0), Se2::new(1.0, 2.0, 0.5));
        assert!(s.is_finite());
        s.covariance = Some([[1.0, 0.0, 0.0], [0.0, f64::NAN, 0.0], [0.0, 0.0, 1.0]]);
        assert!(!s.is_finite());
        s.covariance = None;
        s.twist.wz = f64::INFINITY;
        assert!(!s.is_finite());
    }

    #[test]
    fn yaw_rate() {
        assert_eq!(
            ImuSample::yaw_rate_only(Timestamp(5), 0.25).yaw_rate(),
            0.25
        );
    }
}
