//! Geometry of planar poses and their uncertainty.

mod covariance;
mod se2;

pub use covariance::{
    chi2_quantile, cov_in_frame, cov_out_of_frame, information_heuristic, information_in_frame_of,
    pose_squared_mahalanobis, spd_inverse, squared_mahalanobis, symmetrize,
    zero_constraint_information, Cov3, Info3, UncertainPose, NEAR_SINGULAR_RATIO,
};
pub use se2::{wrap_angle, yaw_rotation, JacobianPair, Se2};

/// `libm::floorf(x) as i32`, without the float floor: truncate, then step down when the
/// truncation went up. Equal to it for every `f32` (NaN gives 0, out-of-range values
/// saturate), and a few instructions instead of libm's bit manipulation, which dominated the
/// voxel and grid-cell lookups of the front-end.
#[inline]
pub fn floor_to_i32(x: f32) -> i32 {
    let t = x as i32;
    if (t as f32) > x {
        t.saturating_sub(1)
    } else {
        t
    }
}

#[cfg(test)]
mod proptests;

#[cfg(test)]
mod floor_tests {
    use super::floor_to_i32;
    use proptest::prelude::*;

    #[test]
    fn floor_agrees_with_libm_on_special_values() {
        for x in [
            0.0f32,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            -1.5,
            2.5e9,
            -2.5e9,
            2_147_483_520.0,
            -2_147_483_648.0,
            f32::MAX,
            f32::MIN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
            8_388_607.5,
            -8_388_607.5,
        ] {
            assert_eq!(floor_to_i32(x), libm::floorf(x) as i32, "{x}");
        }
    }

    proptest! {
        #[test]
        fn floor_agrees_with_libm_on_every_bit_pattern(bits in any::<u32>()) {
            let x = f32::from_bits(bits);
            prop_assert_eq!(floor_to_i32(x), libm::floorf(x) as i32);
        }

        #[test]
        fn floor_agrees_with_libm_on_grid_coordinates(x in -5000.0f32..5000.0) {
            prop_assert_eq!(floor_to_i32(x), libm::floorf(x) as i32);
        }
    }
}
