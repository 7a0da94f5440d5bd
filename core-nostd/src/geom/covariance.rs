//! Uncertainty of planar poses: 3x3 covariance and information matrices, compounding of
//! uncertain relative poses, Mahalanobis distances, and the information heuristic that the
//! paper uses for near-singular covariances (its eq. 1, zero-constraints and Chow-Liu weights).
//!
//! Compounding follows the first-order "approximate transformations" of Smith, Self and
//! Cheeseman: the covariance of `a (+) b` is `Ja Ca Ja^T + Jb Cb Jb^T` (plus cross terms when
//! the two are correlated), with `Ja`, `Jb` the Jacobians of the composition.

use nalgebra::{Cholesky, Matrix3, Vector3};

use super::se2::{yaw_rotation, Se2};

/// Covariance of a pose `[x, y, theta]` (m^2, m rad, rad^2).
pub type Cov3 = Matrix3<f64>;
/// Information (inverse covariance) of a pose.
pub type Info3 = Matrix3<f64>;

/// A pose with its covariance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UncertainPose {
    /// Mean.
    pub pose: Se2,
    /// Covariance of `[x, y, theta]`.
    pub cov: Cov3,
}

impl UncertainPose {
    /// A pose known exactly.
    pub fn exact(pose: Se2) -> UncertainPose {
        UncertainPose {
            pose,
            cov: Cov3::zeros(),
        }
    }

    /// Head-to-tail compounding `self (+) rel` of two independent uncertain poses.
    pub fn compound(&self, rel: &UncertainPose) -> UncertainPose {
        let (ja, jb) = self.pose.compose_jacobians(&rel.pose);
        UncertainPose {
            pose: self.pose.compose(&rel.pose),
            cov: symmetrize(&(ja * self.cov * ja.transpose() + jb * rel.cov * jb.transpose())),
        }
    }

    /// Head-to-tail compounding of two correlated uncertain poses, with
    /// `cross = E[(a - mean_a)(b - mean_b)^T]`.
    pub fn compound_correlated(&self, rel: &UncertainPose, cross: &Matrix3<f64>) -> UncertainPose {
        let (ja, jb) = self.pose.compose_jacobians(&rel.pose);
        let mixed = ja * cross * jb.transpose();
        UncertainPose {
            pose: self.pose.compose(&rel.pose),
            cov: symmetrize(
                &(ja * self.cov * ja.transpose()
                    + jb * rel.cov * jb.transpose()
                    + mixed
                    + mixed.transpose()),
            ),
        }
    }

    /// The inverse relation with its covariance.
    pub fn inverse(&self) -> UncertainPose {
        let j = self.pose.inverse_jacobian();
        UncertainPose {
            pose: self.pose.inverse(),
            cov: symmetrize(&(j * self.cov * j.transpose())),
        }
    }

    /// The relative pose `self^-1 (+) other` of two independent uncertain poses.
    pub fn between(&self, other: &UncertainPose) -> UncertainPose {
        let (ja, jb) = self.pose.between_jacobians(&other.pose);
        UncertainPose {
            pose: self.pose.between(&other.pose),
            cov: symmetrize(&(ja * self.cov * ja.transpose() + jb * other.cov * jb.transpose())),
        }
    }
}

/// `(m + m^T) / 2`: removes the rounding asymmetry that products leave behind.
#[inline]
pub fn symmetrize(m: &Matrix3<f64>) -> Matrix3<f64> {
    (m + m.transpose()) * 0.5
}

/// The information `info` of a pose estimated with its translation in the world frame (a
/// scan match moves `x`, `y` along the world axes), re-expressed for a relative-pose edge
/// whose residual has its translation in the frame of the measurement `z` (the g2o
/// convention of [`PoseEdge::residual`](crate::graph::PoseEdge::residual)): `J info J^T`
/// with `J = diag(R(-z.theta), 1)`. Without this, a match that pins a corridor's lateral
/// position would, seen from a keyframe turned by 90 degrees, pin its position along the
/// corridor instead.
pub fn information_in_frame_of(info: &Info3, z: &Se2) -> Info3 {
    let j = yaw_rotation(libm::cos(z.theta), libm::sin(z.theta)).transpose();
    symmetrize(&(j * info * j.transpose()))
}

/// `cov`, given in the axes of a frame whose heading is `heading`, in the axes that frame's
/// heading is measured in: `R cov R^T`.
pub fn cov_out_of_frame(cov: &Cov3, heading: f64) -> Cov3 {
    let r = yaw_rotation(libm::cos(heading), libm::sin(heading));
    r * cov * r.transpose()
}

/// The converse of [`cov_out_of_frame`]: `cov` in the axes of the frame of heading
/// `heading`, `R^T cov R`.
pub fn cov_in_frame(cov: &Cov3, heading: f64) -> Cov3 {
    let r = yaw_rotation(libm::cos(heading), libm::sin(heading));
    r.transpose() * cov * r
}

/// Leading principal minors `(m1, m2, m3)` of the symmetric part of `m`; `m` is positive
/// definite exactly when all three are positive (Sylvester's criterion), and the pivots of its
/// Cholesky factorization are `m1`, `m2 / m1`, `m3 / m2`.
#[inline]
fn leading_minors(m: &Matrix3<f64>) -> (f64, f64, f64) {
    let (a, b, c) = (m[(0, 0)], m[(0, 1)], m[(0, 2)]);
    let (d, e, f) = (m[(1, 1)], m[(1, 2)], m[(2, 2)]);
    let m2 = a * d - b * b;
    let m3 = a * (d * f - e * e) - b * (b * f - c * e) + c * (b * e - c * d);
    (a, m2, m3)
}

/// The quantile of a chi2 with `dof` degrees of freedom at the standard normal's point `z`
/// (1.645 for 95 %, 3.090 for 99.9 %), by the Wilson-Hilferty cube approximation.
pub fn chi2_quantile(dof: f64, z: f64) -> f64 {
    let a = 2.0 / (9.0 * dof);
    let c = 1.0 - a + z * libm::sqrt(a);
    dof * c * c * c
}

/// Inverse of a symmetric positive-definite 3x3 matrix (closed form: adjugate over
/// determinant, after Sylvester's test); `None` when it is not positive definite or not finite.
/// Only the upper triangle is read.
pub fn spd_inverse(m: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    let (m1, m2, m3) = leading_minors(m);
    if !(m1 > 0.0 && m2 > 0.0 && m3 > 0.0 && m3.is_finite()) {
        return None;
    }
    let (a, b, c) = (m[(0, 0)], m[(0, 1)], m[(0, 2)]);
    let (d, e, f) = (m[(1, 1)], m[(1, 2)], m[(2, 2)]);
    let inv_det = 1.0 / m3;
    let i00 = (d * f - e * e) * inv_det;
    let i01 = (c * e - b * f) * inv_det;
    let i02 = (b * e - c * d) * inv_det;
    let i11 = (a * f - c * c) * inv_det;
    let i12 = (b * c - a * e) * inv_det;
    let i22 = m2 * inv_det;
    let inv = Matrix3::new(i00, i01, i02, i01, i11, i12, i02, i12, i22);
    inv.iter().all(|v| v.is_finite()).then_some(inv)
}

/// Squared Mahalanobis distance `d^T cov^-1 d`; `None` when `cov` is not positive definite.
pub fn squared_mahalanobis(d: &Vector3<f64>, cov: &Cov3) -> Option<f64> {
    let chol = Cholesky::new(*cov)?;
    let v = chol.solve(d);
    let r = d.dot(&v);
    r.is_finite().then_some(r)
}

/// Squared Mahalanobis distance between two global poses, using their world-frame difference
/// (angle wrapped) and the covariance `cov` of that difference.
pub fn pose_squared_mahalanobis(a: &Se2, b: &Se2, cov: &Cov3) -> Option<f64> {
    squared_mahalanobis(&a.global_difference(b), cov)
}

/// Ratio of the smallest Cholesky pivot to the largest diagonal entry below which a covariance
/// counts as near-singular.
pub const NEAR_SINGULAR_RATIO: f64 = 1e-12;

/// Scalar information of a relation with covariance `cov`, after the paper's eq. (1): the
/// Frobenius norm of the information matrix when the inverse is well defined, and otherwise
/// `|1 / det(cov)|`, which stays finite as the covariance shrinks towards zero along some
/// directions. A covariance that is exactly zero has infinite information: we return
/// `f64::MAX` so that comparisons and spanning trees keep working.
pub fn information_heuristic(cov: &Cov3) -> f64 {
    if let Some(info) = well_conditioned_inverse(cov) {
        return info.norm();
    }
    let det = libm::fabs(cov.determinant());
    if det > 0.0 && det.is_finite() {
        let v = 1.0 / det;
        if v.is_finite() {
            return v;
        }
    }
    f64::MAX
}

/// The inverse when the matrix is positive definite and its smallest Cholesky pivot is above
/// [`NEAR_SINGULAR_RATIO`] times its largest diagonal entry. (Every pivot of an SPD matrix lies
/// between its extreme eigenvalues, so this is a cheap stand-in for the eigenvalue ratio.)
fn well_conditioned_inverse(cov: &Cov3) -> Option<Info3> {
    let max_diag = cov[(0, 0)].max(cov[(1, 1)]).max(cov[(2, 2)]);
    let (m1, m2, m3) = leading_minors(cov);
    if !(max_diag > 0.0 && m1 > 0.0 && m2 > 0.0 && m3 > 0.0) {
        return None;
    }
    let min_pivot = m1.min(m2 / m1).min(m3 / m2);
    if min_pivot <= max_diag * NEAR_SINGULAR_RATIO {
        return None;
    }
    spd_inverse(cov)
}

/// Information matrix of a zero-constraint: the identity relative pose between two frames of
/// synchronized sensors, with a tiny standard deviation `sigma_xy` (m) and `sigma_theta` (rad).
/// The diagonal information is clamped to `max_information` so that the normal equations keep
/// a usable condition number.
pub fn zero_constraint_information(sigma_xy: f64, sigma_theta: f64, max_information: f64) -> Info3 {
    let clamp = |s: f64| {
        let v = 1.0 / (s * s);
        if v.is_finite() && v < max_information {
            v
        } else {
            max_information
        }
    };
    Matrix3::from_diagonal(&Vector3::new(
        clamp(sigma_xy),
        clamp(sigma_xy),
        clamp(sigma_theta),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn information_follows_the_edge_residual_frame() {
        use crate::graph::{EdgeKind, PoseEdge};
        use crate::storage::NodeId;
        // A match in a corridor along the world's y axis: the lateral position (x) is pinned,
        // the position along the corridor (y) is weak. The keyframe is turned a quarter turn
        // in that frame, so the edge's residual has x along the corridor.
        let world_info = Info3::new(1e4, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1e3);
        let z = Se2::new(2.0, 5.0, core::f64::consts::FRAC_PI_2 + 0.1);
        let mut edge = PoseEdge::new(NodeId(0), NodeId(1), z, Info3::identity(), EdgeKind::Loop);
        edge.information = information_in_frame_of(&world_info, &z);
        for (dx, dy) in [(0.0, 1.0), (0.1, 0.0), (0.3, -0.4)] {
            let moved = Se2::new(z.x + dx, z.y + dy, z.theta);
            let e = edge.residual(&Se2::IDENTITY, &moved);
            let e = Vector3::new(e[0], e[1], e[2]);
            let d = Vector3::new(dx, dy, 0.0);
            let (got, want) = (
                (e.transpose() * edge.information * e)[0],
                (d.transpose() * world_info * d)[0],
            );
            assert!(
                (got - want).abs() < 1e-9 * want.max(1.0),
                "{dx} {dy}: {got} vs {want}"
            );
        }
    }

    #[test]
    fn compounding_exact_poses_has_zero_covariance() {
        let a = UncertainPose::exact(Se2::new(1.0, 2.0, 0.3));
        let b = UncertainPose::exact(Se2::new(-0.5, 0.1, 1.0));
        assert_eq!(a.compound(&b).cov, Cov3::zeros());
    }

    #[test]
    fn compounding_translation_rotates_covariance() {
        // A quarter turn then an uncertain step along x: the uncertainty ends up along y.
        let a = UncertainPose::exact(Se2::new(0.0, 0.0, core::f64::consts::FRAC_PI_2));
        let b = UncertainPose {
            pose: Se2::new(1.0, 0.0, 0.0),
            cov: Matrix3::from_diagonal(&Vector3::new(0.04, 0.0, 0.0)),
        };
        let c = a.compound(&b).cov;
        assert!((c[(1, 1)] - 0.04).abs() < 1e-15);
        assert!(c[(0, 0)].abs() < 1e-15);
    }

    #[test]
    fn mahalanobis_of_unit_covariance_is_squared_norm() {
        let d = Vector3::new(1.0, 2.0, 0.5);
        let m = squared_mahalanobis(&d, &Cov3::identity()).unwrap();
        assert!((m - d.norm_squared()).abs() < 1e-12);
        assert!(squared_mahalanobis(&d, &Cov3::zeros()).is_none());
    }

    #[test]
    fn heuristic_switches_to_determinant_when_singular() {
        let good = Matrix3::from_diagonal(&Vector3::new(1.0, 4.0, 0.25));
        let expected: f64 = Matrix3::from_diagonal(&Vector3::new(1.0, 0.25, 4.0)).norm();
        assert!((information_heuristic(&good) - expected).abs() < 1e-12);
        let tiny = Matrix3::from_diagonal(&Vector3::new(1.0, 1e-20, 1.0));
        assert!((information_heuristic(&tiny) - 1e20).abs() / 1e20 < 1e-9);
        assert_eq!(information_heuristic(&Cov3::zeros()), f64::MAX);
    }

    #[test]
    fn zero_constraint_information_is_clamped() {
        let i = zero_constraint_information(1e-9, 1e-9, 1e8);
        assert_eq!(i[(0, 0)], 1e8);
        let j = zero_constraint_information(0.01, 0.1, 1e8);
        assert!((j[(0, 0)] - 1e4).abs() < 1e-6);
        assert!((j[(2, 2)] - 100.0).abs() < 1e-9);
    }
}
