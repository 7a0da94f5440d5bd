//! The GPE problem (the paper's eq. 5): the real-time pose `x_k` as the minimiser of a few
//! Gaussian "pose measurements" of it, each a target pose with a covariance; the terms that come
//! from the map are weighted by a Huber kernel.
//!
//! Residuals are taken in the world frame with the covariances rotated into it, so each term is
//! linear in `x_k` and the problem is a weighted mean solved by iteratively reweighted least
//! squares (the Huber weights). The Huber kernel bounds how far one frame can move towards a
//! target that disagrees with the prediction: a large back-end correction is absorbed over a
//! number of frames instead of in one jump, which keeps the real-time trajectory locally
//! consistent.

use nalgebra::{Matrix3, Vector3};

use crate::geom::{cov_out_of_frame, spd_inverse, symmetrize, wrap_angle, Cov3, Se2};

/// Most terms in one problem.
pub const MAX_TERMS: usize = 6;

/// One Gaussian measurement of the current pose.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseTerm {
    /// Measured pose (world frame).
    pub target: Se2,
    /// Covariance of `[x, y, theta]` in the **world** frame.
    pub cov: Cov3,
    /// Huber threshold on the Mahalanobis length; `f64::INFINITY` for a plain Gaussian.
    pub huber: f64,
}

impl PoseTerm {
    /// A term whose covariance `local` is expressed in the frame of `target` (as compounded
    /// covariances are); it is rotated into the world frame.
    pub fn from_local(target: Se2, local: &Cov3, huber: f64) -> PoseTerm {
        PoseTerm {
            target,
            cov: symmetrize(&cov_out_of_frame(local, target.theta)),
            huber,
        }
    }
}

/// Adds the variances of the standard deviations `[metres, radians]` to the diagonal of `cov`
/// (independent noise on top of a compounded covariance).
pub fn inflate(cov: &mut Cov3, sigma: [f64; 2]) {
    let [xy, th] = sigma;
    cov[(0, 0)] += xy * xy;
    cov[(1, 1)] += xy * xy;
    cov[(2, 2)] += th * th;
}

/// GPE parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct GpeConfig {
    /// Reweighting iterations allowed per frame (the work budget of one update).
    pub max_iterations: u8,
    /// Converged when the update moves the pose by less than this (metres, radians).
    pub tolerance: f64,
    /// Standard deviation added to the prediction per frame: `[metres, radians]` (process
    /// noise of the motion model).
    pub process_sigma: [f64; 2],
    /// Huber threshold of the map terms (Mahalanobis length).
    pub huber: f64,
    /// Floor of the standard deviation of an optimized node's pose: `[metres, radians]`.
    pub node_sigma: [f64; 2],
}

impl Default for GpeConfig {
    fn default() -> Self {
        GpeConfig {
            max_iterations: 8,
            tolerance: 1e-6,
            process_sigma: [0.01, 0.002],
            huber: 1.0,
            node_sigma: [0.02, 0.004],
        }
    }
}

/// What one update did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GpeSolution {
    /// The real-time pose.
    pub pose: Se2,
    /// Iterations run.
    pub iterations: u8,
    /// False when the iterations ran out: the caller falls back to the prediction.
    pub converged: bool,
}

/// Solves for the pose that best agrees with `terms` (at least one), starting at the first
/// term's target. Angles are taken relative to the start so wrapping never splits the mean.
/// `None` when no term has a usable covariance.
pub fn solve(terms: &[PoseTerm], config: &GpeConfig) -> Option<GpeSolution> {
    let first = terms.first()?;
    let mut x = first.target;
    let mut info: [Option<Matrix3<f64>>; MAX_TERMS] = [None; MAX_TERMS];
    for (slot, t) in info.iter_mut().zip(terms) {
        *slot = spd_inverse(&t.cov);
    }
    if info.iter().all(Option::is_none) {
        return None;
    }
    let mut iterations = 0u8;
    while iterations < config.max_iterations {
        iterations += 1;
        let mut h = Matrix3::zeros();
        let mut b = Vector3::zeros();
        for (t, omega) in terms.iter().zip(info.iter()) {
            let Some(omega) = omega else { continue };
            // Residual of the current estimate against the target, world frame.
            let r = Vector3::new(
                x.x - t.target.x,
                x.y - t.target.y,
                wrap_angle(x.theta - t.target.theta),
            );
            let m2 = (r.transpose() * omega * r)[0];
            let w = if m2.is_finite() && t.huber.is_finite() && m2 > t.huber * t.huber {
                t.huber / libm::sqrt(m2)
            } else {
                1.0
            };
            let wo = omega * w;
            h += wo;
            b += wo * r;
        }
        let step = -(spd_inverse(&h)? * b);
        if !(step[0].is_finite() && step[1].is_finite() && step[2].is_finite()) {
            return None;
        }
        x = Se2::new(x.x + step[0], x.y + step[1], x.theta + step[2]);
        if libm::fabs(step[0]) < config.tolerance
            && libm::fabs(step[1]) < config.tolerance
            && libm::fabs(step[2]) < config.tolerance
        {
            return Some(GpeSolution {
                pose: x,
                iterations,
                converged: true,
            });
        }
    }
    Some(GpeSolution {
        pose: x,
        iterations,
        converged: false,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn iso(s: f64) -> Cov3 {
        Matrix3::from_diagonal(&Vector3::new(s * s, s * s, s * s))
    }

    #[test]
    fn equal_gaussians_meet_in_the_middle() {
        let a = PoseTerm {
            target: Se2::new(0.0, 0.0, 0.1),
            cov: iso(0.1),
            huber: f64::INFINITY,
        };
        let b = PoseTerm {
            target: Se2::new(1.0, 2.0, 0.3),
            ..a
        };
        let s = solve(&[a, b], &GpeConfig::default()).unwrap();
        assert!(s.converged);
        assert!((s.pose.x - 0.5).abs() < 1e-9 && (s.pose.y - 1.0).abs() < 1e-9);
        assert!((s.pose.theta - 0.2).abs() < 1e-9);
    }

    #[test]
    fn angles_across_pi_average_correctly() {
        let a = PoseTerm {
            target: Se2::new(0.0, 0.0, 3.1),
            cov: iso(0.1),
            huber: f64::INFINITY,
        };
        let b = PoseTerm {
            target: Se2::new(0.0, 0.0, -3.1),
            ..a
        };
        let s = solve(&[a, b], &GpeConfig::default()).unwrap();
        assert!(wrap_angle(s.pose.theta - core::f64::consts::PI).abs() < 1e-9);
    }

    #[test]
    fn huber_bounds_the_pull_of_a_distant_target() {
        // A tight prediction and a map term one metre away: the Gaussian would move the pose by
        // the information-weighted share, the Huber term by much less.
        let pred = PoseTerm {
            target: Se2::IDENTITY,
            cov: iso(0.01),
            huber: f64::INFINITY,
        };
        let map = PoseTerm {
            target: Se2::new(1.0, 0.0, 0.0),
            cov: iso(0.05),
            huber: 1.0,
        };
        let gauss = solve(
            &[
                pred,
                PoseTerm {
                    huber: f64::INFINITY,
                    ..map
                },
            ],
            &GpeConfig {
                max_iterations: 50,
                ..GpeConfig::default()
            },
        )
        .unwrap();
        let robust = solve(
            &[pred, map],
            &GpeConfig {
                max_iterations: 50,
                ..GpeConfig::default()
            },
        )
        .unwrap();
        assert!((gauss.pose.x - 1.0 / 26.0).abs() < 1e-6, "{}", gauss.pose.x);
        assert!(robust.converged);
        assert!(
            robust.pose.x > 0.0 && robust.pose.x < 0.005,
            "{}",
            robust.pose.x
        );
    }

    #[test]
    fn unusable_covariances_give_none() {
        let t = PoseTerm {
            target: Se2::IDENTITY,
            cov: Matrix3::zeros(),
            huber: 1.0,
        };
        assert_eq!(solve(&[t], &GpeConfig::default()), None);
        assert_eq!(solve(&[], &GpeConfig::default()), None);
    }
}
