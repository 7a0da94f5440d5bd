//! Wheel odometry from encoder ticks, and a low-rate gyro.
//!
//! **Wheels** (differential drive, wheel radius `r`, track `b`, `ticks_per_rev`): between two
//! odometry samples the true travel of each wheel over the ground is `ds ∓ b/2 · dθ` (exact
//! integrals of the ground-truth path; on a moving walkway the belt's motion along the heading is
//! subtracted, because the wheels only feel the floor under them). Each wheel then reports
//!
//! `d_meas = d_true · k_w · k_slip + N(0, (σ² + σ_slip²) · |d_true|)`
//!
//! where `k_w = 1 + N(0, scale_sigma²) + e_w` is a fixed per-wheel scale error drawn once (tyre
//! radius) plus an optional set error `e_w` (a cheap robot's worn tyre), `k_slip`/`σ_slip` come from slip zones and slip faults (1 and 0 elsewhere), and `σ`
//! is the noise per square-root metre. The measured travel drives a continuous encoder angle that
//! is quantised to integer ticks (quantisation does not accumulate), and the published pose is
//! integrated from tick differences with the *nominal* geometry (midpoint rule).
//!
//! **Gyro** at `rate_hz` (<= 20 Hz): each sample is the mean yaw rate over its interval plus a
//! bias (initial `N(0, bias_sigma²)` plus an optional set offset, random walk `bias_walk` rad/s/√s) plus white noise
//! `N(0, noise²)`. Linear acceleration (forward, centripetal, gravity) gets `accel_noise`.

use cloi_core::geom::Se2;
use rand::RngExt;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// Wheel and encoder parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WheelParams {
    /// Wheel radius, metres.
    pub radius: f64,
    /// Distance between the wheels, metres.
    pub track: f64,
    /// Encoder ticks per wheel revolution.
    pub ticks_per_rev: u32,
    /// 1-sigma per-wheel scale error (drawn once per run).
    pub scale_sigma: f64,
    /// Fixed scale error of the left and right wheel, added to the drawn one.
    pub scale_offset: [f64; 2],
    /// Travel noise, metres per square-root metre (1 sigma).
    pub noise: f64,
    /// Odometry messages per second.
    pub rate_hz: f64,
}

impl WheelParams {
    /// Typical small robot wheels.
    pub fn default_for(speed: f64) -> WheelParams {
        WheelParams {
            radius: if speed > 0.5 { 0.08 } else { 0.035 },
            track: if speed > 0.5 { 0.45 } else { 0.23 },
            ticks_per_rev: 2048,
            scale_sigma: 0.005,
            scale_offset: [0.0; 2],
            noise: 0.01,
            rate_hz: 50.0,
        }
    }

    /// Metres of wheel travel per tick.
    pub fn metres_per_tick(&self) -> f64 {
        2.0 * std::f64::consts::PI * self.radius / f64::from(self.ticks_per_rev)
    }
}

/// Encoder state and the integrated odometry pose.
#[derive(Clone, Debug)]
pub struct WheelOdometry {
    params: WheelParams,
    /// Fixed per-wheel scale errors (left, right).
    pub scale: [f64; 2],
    travel: [f64; 2],
    ticks: [i64; 2],
    /// Integrated pose in the odometry frame.
    pub pose: Se2,
}

/// One odometry output.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OdomReading {
    /// Integrated pose.
    pub pose: Se2,
    /// Forward speed estimate, m/s.
    pub v: f64,
    /// Yaw rate estimate, rad/s.
    pub w: f64,
    /// Cumulative encoder ticks (left, right).
    pub ticks: [i64; 2],
}

impl WheelOdometry {
    /// New odometry at the identity with scale errors drawn from `rng`.
    pub fn new(params: WheelParams, rng: &mut ChaCha8Rng) -> WheelOdometry {
        let mut draw = || 1.0 + params.scale_sigma * rng.sample::<f64, _>(StandardNormal);
        let scale = [
            draw() + params.scale_offset[0],
            draw() + params.scale_offset[1],
        ];
        WheelOdometry {
            params,
            scale,
            travel: [0.0; 2],
            ticks: [0; 2],
            pose: Se2::IDENTITY,
        }
    }

    /// The noise model for one step: measured travel of both wheels for the true travel.
    pub fn measure(
        &self,
        true_travel: [f64; 2],
        slip_scale: f64,
        slip_noise: f64,
        rng: &mut ChaCha8Rng,
    ) -> [f64; 2] {
        let var = self.params.noise.powi(2) + slip_noise.powi(2);
        let mut out = [0.0; 2];
        for k in 0..2 {
            let n: f64 = rng.sample(StandardNormal);
            out[k] = true_travel[k] * self.scale[k] * slip_scale
                + n * (var * true_travel[k].abs()).sqrt();
        }
        out
    }

    /// Advances by one odometry period with the given true wheel travels, over `dt` seconds.
    pub fn step(
        &mut self,
        true_travel: [f64; 2],
        slip_scale: f64,
        slip_noise: f64,
        dt: f64,
        rng: &mut ChaCha8Rng,
    ) -> OdomReading {
        let meas = self.measure(true_travel, slip_scale, slip_noise, rng);
        let mpt = self.params.metres_per_tick();
        let mut delta = [0.0; 2];
        for k in 0..2 {
            self.travel[k] += meas[k];
            let ticks = (self.travel[k] / mpt).floor() as i64;
            delta[k] = (ticks - self.ticks[k]) as f64 * mpt;
            self.ticks[k] = ticks;
        }
        let ds = 0.5 * (delta[0] + delta[1]);
        let dth = (delta[1] - delta[0]) / self.params.track;
        let mid = self.pose.theta + 0.5 * dth;
        self.pose = Se2::new(
            self.pose.x + ds * mid.cos(),
            self.pose.y + ds * mid.sin(),
            self.pose.theta + dth,
        );
        OdomReading {
            pose: self.pose,
            v: if dt > 0.0 { ds / dt } else { 0.0 },
            w: if dt > 0.0 { dth / dt } else { 0.0 },
            ticks: self.ticks,
        }
    }
}

/// Gyro and accelerometer parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GyroParams {
    /// Samples per second (the paper's robots get at most 20 Hz).
    pub rate_hz: f64,
    /// White noise on each rate sample, rad/s (1 sigma).
    pub noise: f64,
    /// Initial bias, rad/s (1 sigma).
    pub bias_sigma: f64,
    /// Constant bias added to the drawn one, rad/s.
    pub bias_offset: f64,
    /// Bias random walk, rad/s per square-root second.
    pub bias_walk: f64,
    /// Accelerometer noise, m/s^2 (1 sigma).
    pub accel_noise: f64,
}

impl Default for GyroParams {
    fn default() -> Self {
        GyroParams {
            rate_hz: 20.0,
            noise: 0.004,
            bias_sigma: 0.003,
            bias_offset: 0.0,
            bias_walk: 0.0002,
            accel_noise: 0.03,
        }
    }
}

/// Gyro state (the drifting bias).
#[derive(Clone, Debug)]
pub struct Gyro {
    params: GyroParams,
    /// Current bias, rad/s.
    pub bias: f64,
}

/// One IMU output.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImuReading {
    /// Yaw rate, rad/s.
    pub yaw_rate: f64,
    /// Linear acceleration in the body frame, m/s^2 (z includes gravity).
    pub accel: [f64; 3],
}

impl Gyro {
    /// A gyro with its initial bias drawn from `rng`.
    pub fn new(params: GyroParams, rng: &mut ChaCha8Rng) -> Gyro {
        let bias = params.bias_sigma * rng.sample::<f64, _>(StandardNormal) + params.bias_offset;
        Gyro { params, bias }
    }

    /// One sample: `mean_rate` is the true mean yaw rate over the last `dt` seconds,
    /// `forward_accel`, `v` and `w` the true motion at the sample time.
    pub fn sample(
        &mut self,
        mean_rate: f64,
        forward_accel: f64,
        v: f64,
        w: f64,
        dt: f64,
        rng: &mut ChaCha8Rng,
    ) -> ImuReading {
        let walk: f64 = rng.sample(StandardNormal);
        self.bias += self.params.bias_walk * dt.max(0.0).sqrt() * walk;
        let n: f64 = rng.sample(StandardNormal);
        let mut acc = [forward_accel, v * w, 9.80665];
        for a in &mut acc {
            *a += self.params.accel_noise * rng.sample::<f64, _>(StandardNormal);
        }
        ImuReading {
            yaw_rate: mean_rate + self.bias + self.params.noise * n,
            accel: acc,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn mean_sd(xs: &[f64]) -> (f64, f64) {
        let n = xs.len() as f64;
        let m = xs.iter().sum::<f64>() / n;
        let v = xs.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0);
        (m, v.sqrt())
    }

    #[test]
    fn wheel_noise_statistics_match_the_model() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let params = WheelParams {
            scale_sigma: 0.0,
            noise: 0.02,
            ..WheelParams::default_for(0.3)
        };
        let mut odo = WheelOdometry::new(params, &mut rng);
        odo.scale = [1.01, 0.98];
        let d = 0.004; // 0.2 m/s at 50 Hz
        let (slip_scale, slip_noise) = (1.05, 0.015);
        let n = 40_000;
        let mut left = Vec::with_capacity(n);
        let mut right = Vec::with_capacity(n);
        for _ in 0..n {
            let m = odo.measure([d, -d], slip_scale, slip_noise, &mut rng);
            left.push(m[0]);
            right.push(m[1]);
        }
        let expected_sd = ((0.02f64.powi(2) + 0.015f64.powi(2)) * d).sqrt();
        for (xs, k, sign) in [(&left, 1.01, 1.0), (&right, 0.98, -1.0)] {
            let (m, sd) = mean_sd(xs);
            let expected = sign * d * k * slip_scale;
            // Standard error of the mean is sd / 200.
            assert!(
                (m - expected).abs() < 4.0 * expected_sd / 200.0,
                "{m} vs {expected}"
            );
            assert!(
                (sd / expected_sd - 1.0).abs() < 0.03,
                "{sd} vs {expected_sd}"
            );
        }
    }

    #[test]
    fn ticks_do_not_accumulate_quantisation_and_straight_drive_integrates() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let params = WheelParams {
            scale_sigma: 0.0,
            noise: 0.0,
            ..WheelParams::default_for(0.3)
        };
        let mut odo = WheelOdometry::new(params, &mut rng);
        let mut r = None;
        for _ in 0..1000 {
            r = Some(odo.step([0.0031, 0.0031], 1.0, 0.0, 0.02, &mut rng));
        }
        let r = r.expect("stepped");
        let mpt = params.metres_per_tick();
        assert!((r.ticks[0] as f64 * mpt - 3.1).abs() <= mpt);
        assert!((r.pose.x - 3.1).abs() <= mpt && r.pose.y.abs() < 1e-9);
    }

    #[test]
    fn gyro_bias_and_noise_statistics() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let params = GyroParams {
            bias_walk: 0.0,
            ..GyroParams::default()
        };
        let mut g = Gyro::new(params, &mut rng);
        let bias = g.bias;
        let errs: Vec<f64> = (0..20_000)
            .map(|_| g.sample(0.3, 0.0, 0.0, 0.3, 0.05, &mut rng).yaw_rate - 0.3)
            .collect();
        let (m, sd) = mean_sd(&errs);
        assert!((m - bias).abs() < 4.0 * params.noise / 141.0);
        assert!((sd / params.noise - 1.0).abs() < 0.03);
    }
}
