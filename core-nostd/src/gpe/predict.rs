//! The worst-case prediction (the paper's eqs. 6-7).
//!
//! When the estimate cannot be computed in time, the correction that the last estimate applied
//! to the odometry is assumed to hold one frame longer. Composing that correction with the new
//! odometry pose cancels the odometry pose of the last frame, so the prediction is the last
//! corrected pose composed with the odometry increment since it. In this mapper the increment
//! is the front-end's motion since the previous frame, which is also the prediction term of the
//! GPE problem.

use crate::geom::Se2;

/// The previous corrected pose composed with the increment since it.
pub fn worst_case(previous: &Se2, increment: &Se2) -> Se2 {
    previous.compose(increment)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn worst_case_is_previous_pose_plus_increment() {
        let p = worst_case(&Se2::new(1.0, 2.0, 0.5), &Se2::new(0.1, 0.0, 0.1));
        let q = Se2::new(1.0, 2.0, 0.5).compose(&Se2::new(0.1, 0.0, 0.1));
        assert_eq!(p, q);
        // Zero motion keeps the pose.
        assert_eq!(worst_case(&p, &Se2::IDENTITY), p);
    }
}
