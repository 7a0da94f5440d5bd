//! Rigid motions of the plane, SE(2).
//!
//! A pose is stored as `(x, y, theta)` with `theta` wrapped to `(-pi, pi]`. The Jacobians are
//! taken with respect to that same parameterisation with additive updates (`x + dx`, ...),
//! which is what the Gauss-Newton solver linearises.

use core::f64::consts::PI;
use core::ops::Mul;

use nalgebra::{Matrix3, Vector2, Vector3};

/// The rotation about the vertical axis whose cosine and sine are `c` and `s`: on a pose
/// vector `[x, y, theta]` it turns the translation and keeps the heading, on a 3-D vector it
/// turns it about `z`. Its transpose is the rotation back.
#[inline]
pub fn yaw_rotation(c: f64, s: f64) -> Matrix3<f64> {
    Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)
}

/// Wraps an angle to `(-pi, pi]`.
///
/// Uses the IEEE remainder from `libm`, so x86-64 and ARMv7 give the same bits.
#[inline]
pub fn wrap_angle(angle: f64) -> f64 {
    let r = libm::remainder(angle, 2.0 * PI);
    if r <= -PI {
        r + 2.0 * PI
    } else {
        r
    }
}

/// A pose or a relative motion in the plane.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Se2 {
    /// Translation along x, metres.
    pub x: f64,
    /// Translation along y, metres.
    pub y: f64,
    /// Heading, radians, in `(-pi, pi]`.
    pub theta: f64,
}

/// The two 3x3 Jacobians of a binary pose operation, with respect to its first and second
/// argument.
pub type JacobianPair = (Matrix3<f64>, Matrix3<f64>);

impl Se2 {
    /// The identity motion.
    pub const IDENTITY: Se2 = Se2 {
        x: 0.0,
        y: 0.0,
        theta: 0.0,
    };

    /// A pose from its components; the angle is wrapped.
    #[inline]
    pub fn new(x: f64, y: f64, theta: f64) -> Se2 {
        Se2 {
            x,
            y,
            theta: wrap_angle(theta),
        }
    }

    /// A pose from a vector `[x, y, theta]`; the angle is wrapped.
    #[inline]
    pub fn from_vector(v: &Vector3<f64>) -> Se2 {
        Se2::new(v.x, v.y, v.z)
    }

    /// The components as a vector `[x, y, theta]`.
    #[inline]
    pub fn to_vector(&self) -> Vector3<f64> {
        Vector3::new(self.x, self.y, self.theta)
    }

    /// The translation part.
    #[inline]
    pub fn translation(&self) -> Vector2<f64> {
        Vector2::new(self.x, self.y)
    }

    /// True when every component is finite.
    #[inline]
    pub fn is_finite(&self) -> bool {
        self.x.is_finite() && self.y.is_finite() && self.theta.is_finite()
    }

    #[inline]
    fn cos_sin(&self) -> (f64, f64) {
        (libm::cos(self.theta), libm::sin(self.theta))
    }

    /// `self (+) other`: `other` expressed in the frame of `self`, brought to the world frame.
    #[inline]
    pub fn compose(&self, other: &Se2) -> Se2 {
        let (c, s) = self.cos_sin();
        Se2::new(
            self.x + c * other.x - s * other.y,
            self.y + s * other.x + c * other.y,
            self.theta + other.theta,
        )
    }

    /// The inverse motion, so that `a.compose(&a.inverse())` is the identity.
    #[inline]
    pub fn inverse(&self) -> Se2 {
        let (c, s) = self.cos_sin();
        Se2::new(
            -c * self.x - s * self.y,
            s * self.x - c * self.y,
            -self.theta,
        )
    }

    /// `self^-1 (+) other`: the pose of `other` seen from `self`.
    #[inline]
    pub fn between(&self, other: &Se2) -> Se2 {
        let (c, s) = self.cos_sin();
        let dx = other.x - self.x;
        let dy = other.y - self.y;
        Se2::new(c * dx + s * dy, -s * dx + c * dy, other.theta - self.theta)
    }

    /// Applies the motion to a point.
    #[inline]
    pub fn transform_point(&self, p: &Vector2<f64>) -> Vector2<f64> {
        let (c, s) = self.cos_sin();
        Vector2::new(self.x + c * p.x - s * p.y, self.y + s * p.x + c * p.y)
    }

    /// Jacobians of [`Se2::compose`] with respect to `self` and to `other`.
    pub fn compose_jacobians(&self, other: &Se2) -> JacobianPair {
        let (c, s) = self.cos_sin();
        let ja = Matrix3::new(
            1.0,
            0.0,
            -s * other.x - c * other.y,
            0.0,
            1.0,
            c * other.x - s * other.y,
            0.0,
            0.0,
            1.0,
        );
        let jb = yaw_rotation(c, s);
        (ja, jb)
    }

    /// Jacobian of [`Se2::inverse`] with respect to `self`.
    pub fn inverse_jacobian(&self) -> Matrix3<f64> {
        let (c, s) = self.cos_sin();
        Matrix3::new(
            -c,
            -s,
            s * self.x - c * self.y,
            s,
            -c,
            c * self.x + s * self.y,
            0.0,
            0.0,
            -1.0,
        )
    }

    /// Jacobians of [`Se2::between`] with respect to `self` and to `other`.
    pub fn between_jacobians(&self, other: &Se2) -> JacobianPair {
        let (c, s) = self.cos_sin();
        self.between_jacobians_trig(c, s, other)
    }

    /// [`Se2::between_jacobians`] with `cos(self.theta)` and `sin(self.theta)` already known
    /// (saves the trigonometry when one pose is paired with many).
    pub fn between_jacobians_trig(&self, c: f64, s: f64, other: &Se2) -> JacobianPair {
        let dx = other.x - self.x;
        let dy = other.y - self.y;
        let ja = Matrix3::new(
            -c,
            -s,
            -s * dx + c * dy,
            s,
            -c,
            -c * dx - s * dy,
            0.0,
            0.0,
            -1.0,
        );
        let jb = yaw_rotation(c, s).transpose();
        (ja, jb)
    }

    /// The exponential map: the motion reached by following the twist `[vx, vy, omega]` for
    /// unit time.
    pub fn exp(twist: &Vector3<f64>) -> Se2 {
        let (a, b) = exp_coefficients(twist.z);
        Se2::new(
            a * twist.x - b * twist.y,
            b * twist.x + a * twist.y,
            twist.z,
        )
    }

    /// The logarithm map, inverse of [`Se2::exp`] for `|theta| < pi`.
    pub fn log(&self) -> Vector3<f64> {
        let (a, b) = exp_coefficients(self.theta);
        let det = a * a + b * b;
        Vector3::new(
            (a * self.x + b * self.y) / det,
            (-b * self.x + a * self.y) / det,
            self.theta,
        )
    }

    /// The residual `[dx, dy, dtheta]` between two poses expressed in the world frame, with the
    /// angle difference wrapped. Used for Mahalanobis distances between global poses.
    #[inline]
    pub fn global_difference(&self, other: &Se2) -> Vector3<f64> {
        Vector3::new(
            other.x - self.x,
            other.y - self.y,
            wrap_angle(other.theta - self.theta),
        )
    }
}

/// `(sin w / w, (1 - cos w) / w)`, with series expansions near zero.
fn exp_coefficients(w: f64) -> (f64, f64) {
    if libm::fabs(w) < 1e-6 {
        let w2 = w * w;
        (1.0 - w2 / 6.0, w / 2.0 - w * w2 / 24.0)
    } else {
        (libm::sin(w) / w, (1.0 - libm::cos(w)) / w)
    }
}

impl Mul for Se2 {
    type Output = Se2;
    #[inline]
    fn mul(self, rhs: Se2) -> Se2 {
        self.compose(&rhs)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &Se2, b: &Se2, tol: f64) -> bool {
        libm::fabs(a.x - b.x) < tol
            && libm::fabs(a.y - b.y) < tol
            && libm::fabs(wrap_angle(a.theta - b.theta)) < tol
    }

    #[test]
    fn wrap_angle_range() {
        assert_eq!(wrap_angle(PI), PI);
        assert_eq!(wrap_angle(-PI), PI);
        assert!(libm::fabs(wrap_angle(3.0 * PI) - PI) < 1e-12);
        assert!(libm::fabs(wrap_angle(7.0) - (7.0 - 2.0 * PI)) < 1e-12);
        assert_eq!(wrap_angle(0.25), 0.25);
    }

    #[test]
    fn quarter_turn_composition() {
        let a = Se2::new(1.0, 0.0, PI / 2.0);
        let b = Se2::new(1.0, 0.0, 0.0);
        let c = a.compose(&b);
        assert!(close(&c, &Se2::new(1.0, 1.0, PI / 2.0), 1e-12));
        assert!(close(&a.between(&c), &b, 1e-12));
        assert!(close(&a.compose(&a.inverse()), &Se2::IDENTITY, 1e-12));
    }

    #[test]
    fn exp_log_small_angle() {
        let v = Vector3::new(0.3, -0.2, 1e-9);
        let back = Se2::exp(&v).log();
        assert!((back - v).norm() < 1e-12);
    }
}
