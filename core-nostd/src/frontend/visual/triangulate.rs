//! Two-view triangulation, the first step of the visual odometry of section III-B.1: a feature
//! matched between two frames becomes a 3D point `P` in the world (the `p_w` that later frames
//! reproject as `p_p = pi(M_k, P)`).
//!
//! The robot moves on the floor, so each frame's camera pose is its planar robot pose (from
//! the wheel odometry and gyro, or the GPE) composed with the fixed mounting
//! ([`CameraExtrinsic`]). Each pixel is unprojected to a bearing; the point is the midpoint of
//! the shortest segment between the two rays. Each pixel's noise (in pixels, over the focal
//! length) is an angular noise of its ray, and the depth error it causes is about that noise
//! over the parallax, the angle between the rays. A pair is refused when that expected error
//! is too large a share of the depth (the camera moved little, or along the ray), when the
//! point lies behind either camera, or when the rays pass farther apart than their noise
//! allows at that depth (a wrong match or a wrong pose).

use nalgebra::{Matrix3, Vector2, Vector3};

use super::camera::{CameraExtrinsic, CameraModel};
use crate::geom::{yaw_rotation, Se2};

/// Acceptance limits of a triangulated point.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct TriangulateConfig {
    /// Largest expected depth error, as a fraction of the depth: the two observations'
    /// angular noise over the parallax. A narrower angle between the rays fixes no depth.
    pub max_relative_depth_error: f64,
    /// The rays may pass at most this many standard deviations of their angular noise (at
    /// the point's depth) apart; farther, the match or a pose is wrong.
    pub gap_sigmas: f64,
}

impl Default for TriangulateConfig {
    fn default() -> Self {
        TriangulateConfig {
            max_relative_depth_error: 0.1,
            gap_sigmas: 3.0,
        }
    }
}

/// One sighting of a feature: its pixel and the standard deviation of that position (the
/// detector's jitter, larger on coarser pyramid levels).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Observation {
    /// Pixel, level-0 coordinates.
    pub px: Vector2<f64>,
    /// Standard deviation of the position, level-0 pixels.
    pub sigma_px: f64,
}

/// Why a match gave no point.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum TriangulateError {
    /// A pixel has no bearing in the camera model.
    NoRay,
    /// The rays are too close to parallel.
    LowParallax,
    /// The closest points lie behind a camera.
    Behind,
    /// The rays pass too far apart for one point.
    Inconsistent,
}

/// A triangulated point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WorldPoint {
    /// Position in the world frame, metres.
    pub position: Vector3<f64>,
    /// Angle between the two rays at the point, radians.
    pub parallax: f64,
    /// Distance between the rays at their closest points, metres.
    pub gap: f64,
    /// Expected standard deviation of the depth from the first camera, metres.
    pub depth_sigma: f64,
}

/// Where a camera is: its optical centre and its camera-to-world rotation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraPose {
    /// Optical centre in the world frame.
    pub centre: Vector3<f64>,
    /// Rotation from the camera frame to the world frame.
    pub rotation: Matrix3<f64>,
}

impl CameraPose {
    /// The camera mounted by `extrinsic` on a robot at planar pose `robot` (on the floor).
    pub fn of_robot(robot: &Se2, extrinsic: &CameraExtrinsic) -> Self {
        let (s, c) = (libm::sin(robot.theta), libm::cos(robot.theta));
        let yaw = yaw_rotation(c, s);
        let base = Vector3::new(robot.x, robot.y, 0.0);
        CameraPose {
            centre: base + yaw * extrinsic.translation(),
            rotation: yaw * extrinsic.rotation(),
        }
    }

    /// A world point in this camera's frame.
    pub fn world_to_camera(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation.transpose() * (p - self.centre)
    }
}

/// The world point seen in observation `a` by the camera at `pose_a` and in `b` by the
/// camera at `pose_b` (the same camera model for both).
///
/// # Errors
/// [`TriangulateError`] when the pair does not fix a point (see the module docs).
pub fn triangulate(
    model: &CameraModel,
    pose_a: &CameraPose,
    a: &Observation,
    pose_b: &CameraPose,
    b: &Observation,
    cfg: &TriangulateConfig,
) -> Result<WorldPoint, TriangulateError> {
    let ray = |pose: &CameraPose, o: &Observation| {
        model
            .unproject(&o.px)
            .map(|d| pose.rotation * d)
            .ok_or(TriangulateError::NoRay)
    };
    let (da, db) = (ray(pose_a, a)?, ray(pose_b, b)?);
    // Angular noise of each ray: pixel noise over the focal length (the centre's, which a
    // fisheye's edge exceeds a little).
    let k = model.intrinsics();
    let focal = k.fx.min(k.fy);
    let (noise_a, noise_b) = (a.sigma_px / focal, b.sigma_px / focal);
    // Unit bearings: the cosine of the angle between the rays is their dot product.
    let cos = da.dot(&db).clamp(-1.0, 1.0);
    let parallax = libm::acos(cos);
    let relative = (noise_a + noise_b) / parallax;
    // NaN (no parallax at all) is refused too.
    let depth_fixed = relative.is_finite() && relative <= cfg.max_relative_depth_error;
    if !depth_fixed {
        return Err(TriangulateError::LowParallax);
    }
    // Closest points o_a + s d_a and o_b + t d_b (both directions of unit length).
    let w = pose_a.centre - pose_b.centre;
    let (d, e) = (da.dot(&w), db.dot(&w));
    let denom = 1.0 - cos * cos;
    let s = (cos * e - d) / denom;
    let t = (e - cos * d) / denom;
    if !(s > 0.0 && t > 0.0) {
        return Err(TriangulateError::Behind);
    }
    let (pa, pb) = (pose_a.centre + da * s, pose_b.centre + db * t);
    let gap = (pa - pb).norm();
    if gap > cfg.gap_sigmas * libm::hypot(noise_a * s, noise_b * t) {
        return Err(TriangulateError::Inconsistent);
    }
    Ok(WorldPoint {
        position: (pa + pb) * 0.5,
        parallax,
        gap,
        depth_sigma: relative * s,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frontend::visual::synth::cleaner_camera;

    fn pixel(model: &CameraModel, pose: &CameraPose, p: &Vector3<f64>) -> Observation {
        Observation {
            px: model.project(&pose.world_to_camera(p)).expect("in view"),
            sigma_px: 0.5,
        }
    }

    #[test]
    fn a_ceiling_point_seen_from_two_odometry_poses_is_recovered() {
        let (model, mount) = cleaner_camera();
        let pa = CameraPose::of_robot(&Se2::new(1.0, 2.0, 0.3), &mount);
        // Half a metre on: enough parallax for a tenth of the depth at half a pixel of noise.
        let pb = CameraPose::of_robot(&Se2::new(1.45, 2.2, 0.4), &mount);
        let cfg = TriangulateConfig::default();
        for point in [
            Vector3::new(2.5, 2.6, 2.4),
            Vector3::new(3.0, 1.5, 2.4),
            Vector3::new(2.0, 3.2, 1.8),
        ] {
            let (a, b) = (pixel(&model, &pa, &point), pixel(&model, &pb, &point));
            let got = triangulate(&model, &pa, &a, &pb, &b, &cfg).expect("a point");
            assert!(
                (got.position - point).norm() < 1e-6,
                "{got:?} for {point:?}"
            );
            assert!(got.gap < 1e-6);
            // Half a pixel of noise on one side moves the point along the ray by about depth
            // x (noise / focal length) / parallax, to first order.
            let noisy = Observation {
                px: b.px + Vector2::new(0.5, -0.3),
                ..b
            };
            let near = triangulate(&model, &pa, &a, &pb, &noisy, &cfg).expect("a point");
            let depth = (point - pa.centre).norm();
            let expected = depth * (0.6 / 120.0) / got.parallax;
            let moved = (near.position - point).norm();
            assert!(moved < 1.5 * expected, "{moved} m against {expected} m");
            // Half a pixel on each side is about the error the point expects.
            assert!(moved < 2.0 * got.depth_sigma, "{moved} m against {:?}", got);
        }
    }

    #[test]
    fn pairs_that_fix_no_point_are_refused_with_the_reason() {
        let (model, mount) = cleaner_camera();
        let cfg = TriangulateConfig::default();
        let pa = CameraPose::of_robot(&Se2::new(0.0, 0.0, 0.0), &mount);
        let point = Vector3::new(2.0, 0.3, 2.4);
        let a = pixel(&model, &pa, &point);
        // No motion: the same ray twice.
        assert_eq!(
            triangulate(&model, &pa, &a, &pa, &a, &cfg),
            Err(TriangulateError::LowParallax)
        );
        // A wrong match: the second pixel 40 px away from where the point appears.
        let pb = CameraPose::of_robot(&Se2::new(0.3, 0.0, 0.0), &mount);
        let mut b = pixel(&model, &pb, &point);
        b.px.y += 40.0;
        assert!(matches!(
            triangulate(&model, &pa, &a, &pb, &b, &cfg),
            Err(TriangulateError::Inconsistent | TriangulateError::Behind)
        ));
        // Rays that meet behind the cameras: camera b looks along the line from a point X
        // behind camera a, through its own centre.
        let da = (pa.rotation * model.unproject(&a.px).expect("a ray")).normalize();
        let x = pa.centre - da;
        let q = pb.centre + (pb.centre - x) * 2.0;
        let b = pixel(&model, &pb, &q);
        assert_eq!(
            triangulate(&model, &pa, &a, &pb, &b, &cfg),
            Err(TriangulateError::Behind)
        );
    }
}
