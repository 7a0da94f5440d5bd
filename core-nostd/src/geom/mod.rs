//! Geometry of planar poses and their uncertainty.

mod covariance;
mod se2;

pub use covariance::{
    information_heuristic, pose_squared_mahalanobis, spd_inverse, squared_mahalanobis, symmetrize,
    zero_constraint_information, Cov3, Info3, UncertainPose, NEAR_SINGULAR_RATIO,
};
pub use se2::{wrap_angle, JacobianPair, Se2};

#[cfg(test)]
mod proptests;
