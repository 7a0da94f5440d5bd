//! Online estimate of the gyro's bias from the scan matches (the slow gyro of the paper's
//! section III-A, whose heading the front-end fuses).
//!
//! A cheap MEMS gyro reads its true rate plus a bias of up to a few tenths of a degree per
//! second that wanders while it runs. Integrated, that bias turns the odometry's heading by
//! degrees per minute, and the scan match follows it wherever the scan constrains the heading
//! weakly (a single wall of a hall beyond the LiDAR's range). Where the scan does constrain the
//! heading, the difference between the gyro's heading change and the match's over the same
//! interval measures the bias: `(dtheta_gyro - dtheta_match) / dt`, with the variance of both
//! headings over `dt^2`. A scalar Kalman filter averages these measurements, with a random walk
//! for the bias's wander; the weak matches count little by their own variance, and a
//! measurement outside the filter's chi-square gate (a wrong match, a wheel slip that fooled
//! the match) is left out.

/// Standard deviation of the bias before any measurement, rad/s: the turn-on bias of a cheap
/// MEMS gyro (about 0.3 degree/s).
const INITIAL_SIGMA: f64 = 0.005;
/// Variance growth of the bias, rad^2/s^3: a wander of about 0.01 rad/s over an hour.
const WANDER_PER_S: f64 = 0.01 * 0.01 / 3600.0;
/// Chi-square quantile of one degree of freedom at 0.999: a measurement farther from the
/// estimate than this (squared, normalized by its variance) is a wrong match or a slip, not
/// the bias, and is left out.
const GATE: f64 = 10.83;

/// The bias estimate and its variance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GyroBias {
    bias: f64,
    var: f64,
}

impl Default for GyroBias {
    fn default() -> Self {
        Self::new()
    }
}

impl GyroBias {
    /// No measurement yet: zero bias with the turn-on uncertainty.
    pub const fn new() -> Self {
        GyroBias {
            bias: 0.0,
            var: INITIAL_SIGMA * INITIAL_SIGMA,
        }
    }

    /// The estimated bias, rad/s.
    pub fn bias(&self) -> f64 {
        self.bias
    }

    /// One measurement over `seconds` whose heading came from the (bias-corrected) gyro:
    /// `innovation` is the gyro's heading change minus the match's (radians), `variance` the
    /// sum of the two headings' variances (rad^2). Non-finite or empty measurements are
    /// ignored.
    pub fn update(&mut self, innovation: f64, variance: f64, seconds: f64) {
        if !(seconds > 0.0 && variance > 0.0 && innovation.is_finite() && variance.is_finite()) {
            return;
        }
        self.var += WANDER_PER_S * seconds;
        let r = variance / (seconds * seconds);
        let z = innovation / seconds;
        if z * z > GATE * (self.var + r) {
            return;
        }
        let gain = self.var / (self.var + r);
        self.bias += gain * z;
        self.var *= 1.0 - gain;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn converges_to_a_constant_bias_and_ignores_bad_input() {
        let mut g = GyroBias::new();
        let (bias, dt) = (0.003, 0.2);
        // Noise-free measurements of the residual bias, as the odometry would deliver them
        // with the current estimate taken off.
        for _ in 0..2_000 {
            let innovation = (bias - g.bias()) * dt;
            g.update(innovation, 1e-6, dt);
        }
        assert!((g.bias() - bias).abs() < 1e-5, "{}", g.bias());
        let before = g;
        g.update(f64::NAN, 1e-6, dt);
        g.update(0.1, 1e-6, 0.0);
        g.update(0.1, f64::INFINITY, dt);
        assert_eq!(g, before);
    }

    #[test]
    fn uncertain_headings_move_the_estimate_little() {
        let (mut sure, mut unsure) = (GyroBias::new(), GyroBias::new());
        sure.update(0.001, 1e-6, 0.2);
        unsure.update(0.001, 1.0, 0.2);
        assert!(unsure.bias().abs() < 0.01 * sure.bias().abs());
    }
}
