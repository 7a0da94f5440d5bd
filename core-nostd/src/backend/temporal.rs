//! The temporal node of the paper's eqs. (8)-(9).
//!
//! When a window of new frame nodes reaches the back-end, its first node gets a pose and a
//! covariance propagated from the last optimized node through the relative motion between them,
//! so it can join the optimized set for pruning before the window itself is optimized. The
//! paper adds the two covariances; we compound them to first order (Smith, Self and Cheeseman),
//! which equals that sum when the last optimized node has no rotation uncertainty and is
//! correct otherwise.

use crate::geom::UncertainPose;

/// The temporal node: `last_optimized (+) relative`, with the compounded covariance.
pub fn temporal_node(last_optimized: &UncertainPose, relative: &UncertainPose) -> UncertainPose {
    last_optimized.compound(relative)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::Se2;
    use nalgebra::{Matrix3, Vector3};

    #[test]
    fn reduces_to_the_papers_sum_without_heading_uncertainty() {
        // With no heading uncertainty on the optimized node and the relative motion expressed
        // along the world axes (heading 0), eq. (9) is a plain sum.
        let last = UncertainPose {
            pose: Se2::new(3.0, 1.0, 0.0),
            cov: Matrix3::from_diagonal(&Vector3::new(0.02, 0.03, 0.0)),
        };
        let rel = UncertainPose {
            pose: Se2::new(0.5, 0.0, 0.1),
            cov: Matrix3::from_diagonal(&Vector3::new(0.001, 0.002, 0.0005)),
        };
        let t = temporal_node(&last, &rel);
        assert_eq!(t.pose, last.pose.compose(&rel.pose));
        assert!((t.cov - (last.cov + rel.cov)).amax() < 1e-15);
    }

    #[test]
    fn heading_uncertainty_spreads_into_position() {
        let last = UncertainPose {
            pose: Se2::new(0.0, 0.0, 0.0),
            cov: Matrix3::from_diagonal(&Vector3::new(0.0, 0.0, 0.01)),
        };
        let rel = UncertainPose::exact(Se2::new(2.0, 0.0, 0.0));
        // A heading error of sigma 0.1 rad over 2 m: lateral variance 0.04 m^2.
        assert!((temporal_node(&last, &rel).cov[(1, 1)] - 0.04).abs() < 1e-15);
    }
}
