//! Property tests of the geometry: group laws of SE(2), analytic Jacobians against central
//! differences, and first-order covariance compounding against Monte-Carlo sampling.

use nalgebra::{Cholesky, Matrix3, Vector3};
use proptest::prelude::*;

use super::{wrap_angle, Cov3, Se2, UncertainPose};

fn pose() -> impl Strategy<Value = Se2> {
    (-50.0..50.0f64, -50.0..50.0f64, -3.2..3.2f64).prop_map(|(x, y, t)| Se2::new(x, y, t))
}

/// Difference of two poses as a vector, with the angle wrapped.
fn diff(a: &Se2, b: &Se2) -> Vector3<f64> {
    Vector3::new(a.x - b.x, a.y - b.y, wrap_angle(a.theta - b.theta))
}

fn close(a: &Se2, b: &Se2, tol: f64) -> bool {
    diff(a, b).amax() < tol
}

/// Central-difference Jacobian of `f` at `p` with respect to `p`'s `(x, y, theta)`.
fn numeric_jacobian(p: &Se2, f: impl Fn(&Se2) -> Se2) -> Matrix3<f64> {
    let h = 1e-6;
    let mut j = Matrix3::zeros();
    for k in 0..3 {
        let mut dp = Vector3::zeros();
        dp[k] = h;
        let plus = Se2 {
            x: p.x + dp.x,
            y: p.y + dp.y,
            theta: p.theta + dp.z,
        };
        let minus = Se2 {
            x: p.x - dp.x,
            y: p.y - dp.y,
            theta: p.theta - dp.z,
        };
        j.set_column(k, &(diff(&f(&plus), &f(&minus)) / (2.0 * h)));
    }
    j
}

proptest! {
    #[test]
    fn composition_is_associative(a in pose(), b in pose(), c in pose()) {
        let left = a.compose(&b).compose(&c);
        let right = a.compose(&b.compose(&c));
        prop_assert!(close(&left, &right, 1e-9), "{:?} vs {:?}", left, right);
    }

    #[test]
    fn inverse_and_identity(a in pose()) {
        prop_assert!(close(&a.compose(&a.inverse()), &Se2::IDENTITY, 1e-9));
        prop_assert!(close(&a.inverse().compose(&a), &Se2::IDENTITY, 1e-9));
        prop_assert!(close(&a.compose(&Se2::IDENTITY), &a, 1e-12));
        prop_assert!(close(&a.inverse().inverse(), &a, 1e-9));
    }

    #[test]
    fn between_undoes_compose(a in pose(), b in pose()) {
        prop_assert!(close(&a.between(&a.compose(&b)), &b, 1e-9));
        prop_assert!(close(&a.between(&b), &a.inverse().compose(&b), 1e-9));
    }

    #[test]
    fn angles_stay_wrapped(a in pose(), b in pose()) {
        for p in [a.compose(&b), a.inverse(), a.between(&b)] {
            prop_assert!(p.theta > -core::f64::consts::PI && p.theta <= core::f64::consts::PI);
        }
    }

    #[test]
    fn exp_inverts_log(x in -5.0..5.0f64, y in -5.0..5.0f64, t in -3.1..3.1f64) {
        let p = Se2::new(x, y, t);
        prop_assert!(close(&Se2::exp(&p.log()), &p, 1e-9));
    }

    #[test]
    fn compose_jacobians_match_numeric(a in pose(), b in pose()) {
        let (ja, jb) = a.compose_jacobians(&b);
        let na = numeric_jacobian(&a, |p| p.compose(&b));
        let nb = numeric_jacobian(&b, |p| a.compose(p));
        prop_assert!((ja - na).amax() < 1e-5, "ja {} na {}", ja, na);
        prop_assert!((jb - nb).amax() < 1e-5, "jb {} nb {}", jb, nb);
    }

    #[test]
    fn between_and_inverse_jacobians_match_numeric(a in pose(), b in pose()) {
        let (ja, jb) = a.between_jacobians(&b);
        let na = numeric_jacobian(&a, |p| p.between(&b));
        let nb = numeric_jacobian(&b, |p| a.between(p));
        prop_assert!((ja - na).amax() < 1e-5, "ja {} na {}", ja, na);
        prop_assert!((jb - nb).amax() < 1e-5, "jb {} nb {}", jb, nb);
        let ji = a.inverse_jacobian();
        let ni = numeric_jacobian(&a, |p| p.inverse());
        prop_assert!((ji - ni).amax() < 1e-5, "ji {} ni {}", ji, ni);
    }

    #[test]
    fn compounding_inverse_round_trip(a in pose(), s in 0.01..0.5f64) {
        let cov = Matrix3::from_diagonal(&Vector3::new(s, 2.0 * s, 0.1 * s));
        let u = UncertainPose { pose: a, cov };
        let back = u.inverse().inverse();
        prop_assert!(close(&back.pose, &a, 1e-9));
        prop_assert!((back.cov - cov).amax() < 1e-9);
    }
}

/// A small deterministic Gaussian generator (xorshift64* and Box-Muller), so the Monte-Carlo
/// check needs no RNG crate and repeats exactly.
struct Gauss(u64);

impl Gauss {
    fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        let bits = self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11;
        (bits as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn normal(&mut self) -> f64 {
        let (u, v) = (self.uniform(), self.uniform());
        libm::sqrt(-2.0 * libm::log(u)) * libm::cos(2.0 * core::f64::consts::PI * v)
    }
    fn sample(&mut self, mean: &Se2, chol_l: &Matrix3<f64>) -> Se2 {
        let z = Vector3::new(self.normal(), self.normal(), self.normal());
        let d = chol_l * z;
        Se2::new(mean.x + d.x, mean.y + d.y, mean.theta + d.z)
    }
}

fn sample_covariance(samples: &[Se2], mean: &Se2) -> Cov3 {
    let mut c = Cov3::zeros();
    for s in samples {
        let d = diff(s, mean);
        c += d * d.transpose();
    }
    c / (samples.len() as f64 - 1.0)
}

#[test]
fn compounding_agrees_with_monte_carlo() {
    extern crate std;
    use std::vec::Vec;

    let a = UncertainPose {
        pose: Se2::new(2.0, -1.0, 0.7),
        cov: Matrix3::new(0.010, 0.002, 0.0, 0.002, 0.020, 0.001, 0.0, 0.001, 0.0025),
    };
    let b = UncertainPose {
        pose: Se2::new(1.5, 0.5, -0.4),
        cov: Matrix3::from_diagonal(&Vector3::new(0.004, 0.001, 0.0016)),
    };
    let la = Cholesky::new(a.cov).unwrap().l();
    let lb = Cholesky::new(b.cov).unwrap().l();
    let mut g = Gauss(0x9E37_79B9_7F4A_7C15);
    let n = 40_000;

    let predicted = a.compound(&b);
    let samples: Vec<Se2> = (0..n)
        .map(|_| g.sample(&a.pose, &la).compose(&g.sample(&b.pose, &lb)))
        .collect();
    let mc = sample_covariance(&samples, &predicted.pose);
    let rel = (mc - predicted.cov).norm() / predicted.cov.norm();
    assert!(
        rel < 0.05,
        "compound: relative error {rel}\nmc {mc}\npredicted {}",
        predicted.cov
    );

    let inv = a.inverse();
    let samples: Vec<Se2> = (0..n).map(|_| g.sample(&a.pose, &la).inverse()).collect();
    let mc = sample_covariance(&samples, &inv.pose);
    let rel = (mc - inv.cov).norm() / inv.cov.norm();
    assert!(
        rel < 0.05,
        "inverse: relative error {rel}\nmc {mc}\npredicted {}",
        inv.cov
    );

    let rel_pose = a.between(&b);
    let samples: Vec<Se2> = (0..n)
        .map(|_| g.sample(&a.pose, &la).between(&g.sample(&b.pose, &lb)))
        .collect();
    let mc = sample_covariance(&samples, &rel_pose.pose);
    let rel = (mc - rel_pose.cov).norm() / rel_pose.cov.norm();
    assert!(
        rel < 0.05,
        "between: relative error {rel}\nmc {mc}\npredicted {}",
        rel_pose.cov
    );
}
