//! Odometry fusion: wheel odometry poses with an optional slow gyro (<= 20 Hz), giving the
//! relative motion between any two recent timestamps with a covariance.
//!
//! # Fusion
//! Each wheel sample gives the wheel increment `(dx, dy, dtheta_w)` from the previous one.
//! When the gyro is live (a sample no older than `gyro_timeout_ns` at both ends of the
//! interval), the heading increment is the gyro's instead: its rate is integrated with a
//! zero-order hold (each sample's rate holds until the next sample), which is causal, so a
//! heading computed at a wheel time is never revised; the sum of heading increments still
//! telescopes to the exact integral. The wheel translation is then rotated by half the
//! heading difference, because it was travelled along the mid-interval heading.
//!
//! # Motion-noise model
//! Over an interval with path length `d` (metres) and total absolute rotation `phi`
//! (radians), with `u` the unit direction of the net translation in the start frame:
//! * along `u`: `longitudinal_per_m * d + translation_per_rad * phi`,
//! * across `u`: `lateral_per_m * d + translation_per_rad * phi`,
//! * heading: the sum over wheel steps of `heading_per_rad * |dtheta| + heading_per_m * |ds|`
//!   when the heading came from the wheels, or of `gyro_per_s * dt + gyro_per_rad * |dtheta|`
//!   (rate noise and scale error) when it came from the gyro,
//!
//! each floored by `min_variance`; no cross-covariance. Variances grow linearly with the
//! distance, the rotation and the time, as for independent errors per unit of motion.
//!
//! Timestamps are `i64` nanoseconds from the caller. A sample not strictly later than the
//! previous one of its stream, or with a non-finite value, is rejected and counted.

use core::fmt;

use heapless::Deque;
use nalgebra::Matrix3;

use crate::geom::{wrap_angle, Se2, UncertainPose};

/// Parameters of the motion-noise model (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct MotionNoise {
    /// Variance along the travel direction per metre, m^2/m.
    pub longitudinal_per_m: f64,
    /// Variance across the travel direction per metre, m^2/m.
    pub lateral_per_m: f64,
    /// Translation variance per radian turned (slip while turning), m^2/rad.
    pub translation_per_rad: f64,
    /// Wheel heading variance per radian turned, rad^2/rad.
    pub heading_per_rad: f64,
    /// Wheel heading variance per metre travelled, rad^2/m.
    pub heading_per_m: f64,
    /// Gyro heading variance per second, rad^2/s.
    pub gyro_per_s: f64,
    /// Gyro heading variance per radian turned (scale error), rad^2/rad.
    pub gyro_per_rad: f64,
    /// Floor of the variances `[x, y, theta]`.
    pub min_variance: [f64; 3],
}

impl Default for MotionNoise {
    fn default() -> Self {
        MotionNoise::DEFAULT
    }
}

impl MotionNoise {
    /// The default model, as a constant.
    pub const DEFAULT: MotionNoise = MotionNoise {
        longitudinal_per_m: 1e-3,
        lateral_per_m: 4e-4,
        translation_per_rad: 1e-4,
        heading_per_rad: 2.5e-3,
        heading_per_m: 1e-3,
        gyro_per_s: 1e-5,
        gyro_per_rad: 1e-4,
        min_variance: [1e-8, 1e-8, 1e-9],
    };
}

/// Fusion parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct OdometryConfig {
    /// Noise model.
    pub noise: MotionNoise,
    /// The gyro counts as live when its last sample is at most this old, ns.
    pub gyro_timeout_ns: i64,
    /// Queries up to this long after the last wheel sample are extrapolated at the last
    /// velocity, ns.
    pub max_extrapolation_ns: i64,
}

impl Default for OdometryConfig {
    fn default() -> Self {
        OdometryConfig::DEFAULT
    }
}

impl OdometryConfig {
    /// The default parameters, as a constant.
    pub const DEFAULT: OdometryConfig = OdometryConfig {
        noise: MotionNoise::DEFAULT,
        gyro_timeout_ns: 250_000_000,
        max_extrapolation_ns: 100_000_000,
    };
}

/// Odometry errors.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum OdomError {
    /// The sample is not later than the previous one of its stream (rejected and counted).
    OutOfOrder,
    /// The sample has a non-finite value (rejected and counted).
    NonFinite,
    /// No wheel sample yet.
    NoData,
    /// The time is before the oldest buffered sample.
    TooOld,
    /// The time is too far after the newest sample.
    TooNew,
}

impl fmt::Display for OdomError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            OdomError::OutOfOrder => "odometry sample out of time order",
            OdomError::NonFinite => "non-finite odometry sample",
            OdomError::NoData => "no odometry yet",
            OdomError::TooOld => "time older than the odometry buffer",
            OdomError::TooNew => "time beyond the odometry extrapolation limit",
        })
    }
}

impl core::error::Error for OdomError {}

/// Sample counts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct OdometryStats {
    /// Wheel samples accepted.
    pub wheel: u32,
    /// Gyro samples accepted.
    pub gyro: u32,
    /// Samples rejected for their time order.
    pub out_of_order: u32,
    /// Samples rejected for non-finite values.
    pub non_finite: u32,
    /// Wheel steps whose heading came from the gyro.
    pub gyro_steps: u32,
}

/// One fused sample with the running sums of the noise model.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Sample {
    t: i64,
    pose: Se2,
    /// Path length so far, metres.
    dist: f64,
    /// Absolute rotation so far, radians.
    rot: f64,
    /// Heading variance accumulated so far, rad^2.
    heading_var: f64,
    /// Time so far whose heading came from the gyro, seconds.
    gyro_time: f64,
}

/// A relative motion between two times.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OdomIncrement {
    /// Motion and covariance, in the frame of the start pose.
    pub motion: UncertainPose,
    /// Path length, metres.
    pub distance: f64,
    /// Absolute rotation, radians.
    pub rotation: f64,
    /// Length of the interval, seconds.
    pub seconds: f64,
    /// Part of the interval whose heading came from the gyro, seconds.
    pub gyro_seconds: f64,
}

/// The fusion state with a history of `N` fused samples.
#[derive(Debug, Clone)]
pub struct OdometryFusion<const N: usize = 256> {
    config: OdometryConfig,
    history: Deque<Sample, N>,
    last_wheel: Option<(i64, Se2)>,
    /// Gyro heading integral at the last gyro sample, its time and rate.
    gyro: Option<(i64, f64, f64)>,
    /// Gyro heading at the last wheel sample, when the gyro was live then.
    gyro_at_last_wheel: Option<f64>,
    /// Estimated gyro bias, rad/s, taken off every rate from now on.
    gyro_bias: f64,
    stats: OdometryStats,
}

const NS: f64 = 1e-9;

impl<const N: usize> OdometryFusion<N> {
    /// An empty fusion.
    pub const fn new(config: OdometryConfig) -> Self {
        OdometryFusion {
            config,
            history: Deque::new(),
            last_wheel: None,
            gyro: None,
            gyro_at_last_wheel: None,
            gyro_bias: 0.0,
            stats: OdometryStats {
                wheel: 0,
                gyro: 0,
                out_of_order: 0,
                non_finite: 0,
                gyro_steps: 0,
            },
        }
    }

    /// Counts of accepted and rejected samples.
    pub fn stats(&self) -> OdometryStats {
        self.stats
    }

    /// The fused pose at the newest wheel sample (in the odometry frame).
    pub fn latest(&self) -> Option<(i64, Se2)> {
        self.history.back().map(|s| (s.t, s.pose))
    }

    fn reject(&mut self, e: OdomError) -> Result<(), OdomError> {
        match e {
            OdomError::OutOfOrder => self.stats.out_of_order += 1,
            _ => self.stats.non_finite += 1,
        }
        Err(e)
    }

    /// Sets the gyro bias (rad/s) taken off the rates pushed from now on; the headings
    /// already integrated are not revised.
    pub fn set_gyro_bias(&mut self, bias: f64) {
        if bias.is_finite() {
            self.gyro_bias = bias;
        }
    }

    /// Adds a gyro yaw rate (rad/s) measured at `t` ns.
    ///
    /// # Errors
    /// [`OdomError::OutOfOrder`] or [`OdomError::NonFinite`]; the sample is dropped.
    pub fn push_gyro(&mut self, t: i64, yaw_rate: f64) -> Result<(), OdomError> {
        if !yaw_rate.is_finite() {
            return self.reject(OdomError::NonFinite);
        }
        let heading = match self.gyro {
            Some((tg, _, _)) if t <= tg => return self.reject(OdomError::OutOfOrder),
            Some((tg, h, w)) => h + w * ((t - tg) as f64 * NS),
            None => 0.0,
        };
        self.gyro = Some((t, heading, yaw_rate - self.gyro_bias));
        self.stats.gyro += 1;
        Ok(())
    }

    /// Gyro heading integral at `t`, when the gyro is live.
    fn gyro_heading(&self, t: i64) -> Option<f64> {
        let (tg, h, w) = self.gyro?;
        let age = t - tg;
        if age > self.config.gyro_timeout_ns || age < -self.config.gyro_timeout_ns {
            return None;
        }
        Some(h + w * (age as f64 * NS))
    }

    /// Adds a wheel odometry pose (in the wheel odometry's own frame) measured at `t` ns.
    ///
    /// # Errors
    /// [`OdomError::OutOfOrder`] or [`OdomError::NonFinite`]; the sample is dropped.
    pub fn push_wheel(&mut self, t: i64, pose: Se2) -> Result<(), OdomError> {
        if !pose.is_finite() {
            return self.reject(OdomError::NonFinite);
        }
        let gyro_now = self.gyro_heading(t);
        let Some((t_prev, prev_wheel)) = self.last_wheel else {
            self.last_wheel = Some((t, pose));
            self.gyro_at_last_wheel = gyro_now;
            self.push_sample(Sample {
                t,
                pose: Se2::IDENTITY,
                dist: 0.0,
                rot: 0.0,
                heading_var: 0.0,
                gyro_time: 0.0,
            });
            self.stats.wheel += 1;
            return Ok(());
        };
        if t <= t_prev {
            return self.reject(OdomError::OutOfOrder);
        }
        let wheel = prev_wheel.between(&pose);
        let noise = &self.config.noise;
        let ds = libm::sqrt(wheel.x * wheel.x + wheel.y * wheel.y);
        let (step, heading_var) = match (self.gyro_at_last_wheel, gyro_now) {
            (Some(g0), Some(g1)) => {
                let dth = g1 - g0;
                let half = 0.5 * (dth - wheel.theta);
                let (c, s) = (libm::cos(half), libm::sin(half));
                self.stats.gyro_steps += 1;
                let var = noise.gyro_per_s * ((t - t_prev) as f64 * NS)
                    + noise.gyro_per_rad * libm::fabs(dth);
                (
                    Se2::new(c * wheel.x - s * wheel.y, s * wheel.x + c * wheel.y, dth),
                    var,
                )
            }
            _ => (
                wheel,
                noise.heading_per_rad * libm::fabs(wheel.theta) + noise.heading_per_m * ds,
            ),
        };
        let Some(last) = self.history.back().copied() else {
            return Err(OdomError::NoData);
        };
        // The heading step may exceed pi with a fast gyro; take it unwrapped for the sums.
        let (dtheta, gyro_dt) = match (self.gyro_at_last_wheel, gyro_now) {
            (Some(g0), Some(g1)) => (g1 - g0, (t - t_prev) as f64 * NS),
            _ => (wheel.theta, 0.0),
        };
        self.push_sample(Sample {
            t,
            pose: last.pose.compose(&step),
            dist: last.dist + ds,
            rot: last.rot + libm::fabs(dtheta),
            heading_var: last.heading_var + heading_var,
            gyro_time: last.gyro_time + gyro_dt,
        });
        self.last_wheel = Some((t, pose));
        self.gyro_at_last_wheel = gyro_now;
        self.stats.wheel += 1;
        Ok(())
    }

    fn push_sample(&mut self, s: Sample) {
        if self.history.is_full() {
            self.history.pop_front();
        }
        // Cannot fail after the pop above.
        let _ = self.history.push_back(s);
    }

    /// The fused sample at `t`: interpolated between samples, or extrapolated at the last
    /// velocity for at most `max_extrapolation_ns`.
    fn sample_at(&self, t: i64) -> Result<Sample, OdomError> {
        let (Some(first), Some(last)) = (self.history.front(), self.history.back()) else {
            return Err(OdomError::NoData);
        };
        if t < first.t {
            return Err(OdomError::TooOld);
        }
        if t > last.t + self.config.max_extrapolation_ns {
            return Err(OdomError::TooNew);
        }
        if self.history.len() == 1 || t == last.t {
            return Ok(*last);
        }
        // Segment [a, b] containing t (the last one when extrapolating).
        let (mut a, mut b) = (first, first);
        for s in self.history.iter() {
            a = b;
            b = s;
            if s.t >= t && !core::ptr::eq(a, b) {
                break;
            }
        }
        let alpha = (t - a.t) as f64 / (b.t - a.t) as f64;
        let lerp = |x: f64, y: f64| x + alpha * (y - x);
        Ok(Sample {
            t,
            pose: Se2::new(
                lerp(a.pose.x, b.pose.x),
                lerp(a.pose.y, b.pose.y),
                a.pose.theta + alpha * wrap_angle(b.pose.theta - a.pose.theta),
            ),
            dist: lerp(a.dist, b.dist),
            rot: lerp(a.rot, b.rot),
            heading_var: lerp(a.heading_var, b.heading_var),
            gyro_time: lerp(a.gyro_time, b.gyro_time),
        })
    }

    /// The fused pose at `t` in the odometry frame (starts at the identity).
    ///
    /// # Errors
    /// [`OdomError::NoData`], [`OdomError::TooOld`], [`OdomError::TooNew`].
    pub fn pose_at(&self, t: i64) -> Result<Se2, OdomError> {
        self.sample_at(t).map(|s| s.pose)
    }

    /// The motion from `t_from` to `t_to` (in the frame of the pose at `t_from`) with its
    /// covariance from the noise model.
    ///
    /// # Errors
    /// [`OdomError::NoData`], [`OdomError::TooOld`], [`OdomError::TooNew`].
    pub fn increment(&self, t_from: i64, t_to: i64) -> Result<OdomIncrement, OdomError> {
        let a = self.sample_at(t_from)?;
        let b = self.sample_at(t_to)?;
        let motion = a.pose.between(&b.pose);
        let d = libm::fabs(b.dist - a.dist);
        let phi = libm::fabs(b.rot - a.rot);
        let n = &self.config.noise;
        let var_long = n.longitudinal_per_m * d + n.translation_per_rad * phi;
        let var_lat = n.lateral_per_m * d + n.translation_per_rad * phi;
        let norm = libm::sqrt(motion.x * motion.x + motion.y * motion.y);
        let (ux, uy) = if norm > 1e-12 {
            (motion.x / norm, motion.y / norm)
        } else {
            (1.0, 0.0)
        };
        // R diag(long, lat) R^T with R's first column u.
        let cxx = var_long * ux * ux + var_lat * uy * uy;
        let cyy = var_long * uy * uy + var_lat * ux * ux;
        let cxy = (var_long - var_lat) * ux * uy;
        let m = &n.min_variance;
        let cov = Matrix3::new(
            cxx + m[0],
            cxy,
            0.0,
            cxy,
            cyy + m[1],
            0.0,
            0.0,
            0.0,
            libm::fabs(b.heading_var - a.heading_var) + m[2],
        );
        Ok(OdomIncrement {
            motion: UncertainPose { pose: motion, cov },
            distance: d,
            rotation: phi,
            seconds: (t_to - t_from) as f64 * NS,
            gyro_seconds: libm::fabs(b.gyro_time - a.gyro_time),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: i64 = 1_000_000;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        libm::fabs(a - b) < tol
    }

    #[test]
    fn wheel_only_increments_and_noise_model() {
        let mut f = OdometryFusion::<16>::new(OdometryConfig::default());
        assert_eq!(f.increment(0, 0), Err(OdomError::NoData));
        // Wheel frame starts somewhere arbitrary.
        let start = Se2::new(5.0, -1.0, 1.0);
        f.push_wheel(0, start).unwrap();
        f.push_wheel(100 * MS, start.compose(&Se2::new(0.1, 0.0, 0.0)))
            .unwrap();
        f.push_wheel(200 * MS, start.compose(&Se2::new(0.2, 0.0, 0.1)))
            .unwrap();
        let inc = f.increment(0, 200 * MS).unwrap();
        let m = inc.motion.pose;
        assert!(close(m.x, 0.2, 1e-12) && close(m.y, 0.0, 1e-12) && close(m.theta, 0.1, 1e-12));
        assert!(close(inc.distance, 0.2, 1e-12) && close(inc.rotation, 0.1, 1e-12));
        let n = MotionNoise::default();
        // Translation along x: longitudinal variance on x.
        let c = inc.motion.cov;
        assert!(close(
            c[(0, 0)],
            n.longitudinal_per_m * 0.2 + n.translation_per_rad * 0.1 + 1e-8,
            1e-15
        ));
        assert!(close(
            c[(1, 1)],
            n.lateral_per_m * 0.2 + n.translation_per_rad * 0.1 + 1e-8,
            1e-15
        ));
        assert!(close(
            c[(2, 2)],
            n.heading_per_rad * 0.1 + n.heading_per_m * 0.2 + 1e-9,
            1e-15
        ));
        // Halfway through the first step: interpolation.
        let half = f.increment(0, 50 * MS).unwrap();
        assert!(close(half.motion.pose.x, 0.05, 1e-12));
        // Extrapolation at the last velocity up to the limit, then an error.
        let ex = f.increment(200 * MS, 250 * MS).unwrap();
        assert!(close(ex.motion.pose.x, 0.05, 1e-3), "{ex:?}");
        assert_eq!(f.increment(0, 400 * MS), Err(OdomError::TooNew));
        assert_eq!(f.increment(-1, 0), Err(OdomError::TooOld));
    }

    #[test]
    fn out_of_order_and_non_finite_are_rejected_and_counted() {
        let mut f = OdometryFusion::<8>::new(OdometryConfig::default());
        f.push_wheel(100, Se2::IDENTITY).unwrap();
        assert_eq!(f.push_wheel(100, Se2::IDENTITY), Err(OdomError::OutOfOrder));
        assert_eq!(f.push_wheel(50, Se2::IDENTITY), Err(OdomError::OutOfOrder));
        assert_eq!(
            f.push_wheel(200, Se2::new(f64::NAN, 0.0, 0.0)),
            Err(OdomError::NonFinite)
        );
        f.push_gyro(100, 0.1).unwrap();
        assert_eq!(f.push_gyro(90, 0.1), Err(OdomError::OutOfOrder));
        assert_eq!(f.push_gyro(120, f64::INFINITY), Err(OdomError::NonFinite));
        let s = f.stats();
        assert_eq!(
            (s.wheel, s.gyro, s.out_of_order, s.non_finite),
            (1, 1, 3, 2)
        );
        // The history is a ring: old samples go, times before them are refused.
        for i in 1..20 {
            f.push_wheel(100 + i * MS, Se2::new(i as f64 * 0.01, 0.0, 0.0))
                .unwrap();
        }
        assert_eq!(f.increment(100, 100 + 19 * MS), Err(OdomError::TooOld));
        assert!(f.increment(100 + 12 * MS, 100 + 19 * MS).is_ok());
    }

    #[test]
    fn gyro_heading_replaces_wheel_heading() {
        let mut f = OdometryFusion::<16>::new(OdometryConfig::default());
        // Gyro at 20 Hz: 0.5 rad/s then 1.0 rad/s from t = 50 ms.
        f.push_gyro(0, 0.5).unwrap();
        f.push_wheel(0, Se2::IDENTITY).unwrap();
        f.push_gyro(50 * MS, 1.0).unwrap();
        // The wheels claim 0.2 rad over 100 ms and 0.1 m straight ahead.
        f.push_wheel(100 * MS, Se2::new(0.1, 0.0, 0.2)).unwrap();
        // Gyro: 0.5 * 0.05 + 1.0 * 0.05 = 0.075 rad. Translation rotated by
        // (0.075 - 0.2) / 2 relative to the wheel step.
        let inc = f.increment(0, 100 * MS).unwrap();
        let m = inc.motion.pose;
        let half: f64 = 0.5 * (0.075 - 0.2);
        assert!(close(m.theta, 0.075, 1e-12), "{m:?}");
        assert!(close(m.x, 0.1 * half.cos(), 1e-12) && close(m.y, 0.1 * half.sin(), 1e-12));
        let n = MotionNoise::default();
        assert!(close(
            inc.motion.cov[(2, 2)],
            n.gyro_per_s * 0.1 + n.gyro_per_rad * 0.075 + 1e-9,
            1e-15
        ));
        assert_eq!(f.stats().gyro_steps, 1);
        // The gyro goes silent: after the timeout the wheel heading is used again.
        f.push_wheel(200 * MS, Se2::new(0.2, 0.0, 0.3)).unwrap();
        f.push_wheel(400 * MS, Se2::new(0.3, 0.0, 0.4)).unwrap();
        let inc = f.increment(200 * MS, 400 * MS).unwrap();
        assert!(close(inc.motion.pose.theta, 0.1, 1e-12), "{inc:?}");
        assert_eq!(f.stats().gyro_steps, 2);
    }
}
