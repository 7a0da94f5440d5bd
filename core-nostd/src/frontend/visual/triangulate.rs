//! Two-view triangulation, the first step of the visual odometry of section III-B.1: a feature
//! matched between two frames becomes a 3D point `P` in the world (the `p_w` that later frames
//! reproject as `p_p = pi(M_k, P)`).
//!
//! The robot moves on the floor, so each frame's camera pose is its planar robot pose (from
//! the wheel odometry and gyro, or the GPE) composed with the fixed mounting
//! ([`CameraExtrinsic`]). Each pixel is unprojected to a bearing; the point is the midpoint of
//! the shortest segment between the two rays. It is refused when the rays are too close to
//! parallel to fix a depth (the camera moved along the ray: little parallax), when it lies
//! behind either camera, or when the rays pass farther apart than the pixel noise allows at
//! that depth (a wrong match or a wrong pose).

use nalgebra::{Matrix3, Vector2, Vector3};

use super::camera::{CameraExtrinsic, CameraModel};
use crate::geom::Se2;

/// Acceptance limits of a triangulated point.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct TriangulateConfig {
    /// Smallest angle between the two rays at the point, radians. Below it the depth is
    /// mostly noise (ORB-SLAM's choice is about one degree).
    pub min_parallax: f64,
    /// Largest distance between the two rays at their closest points, as a fraction of the
    /// point's depth: the angle the pixel noise and the pose error may explain.
    pub max_gap_per_depth: f64,
}

impl Default for TriangulateConfig {
    fn default() -> Self {
        TriangulateConfig {
            min_parallax: 1.0_f64.to_radians(),
            // About 4 px at the 250 px focal length of a quarter-VGA camera.
            max_gap_per_depth: 0.016,
        }
    }
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
        let yaw = Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0);
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

/// The world point seen at pixel `a` by the camera at `pose_a` and at pixel `b` by the camera
/// at `pose_b` (the same camera model for both).
///
/// # Errors
/// [`TriangulateError`] when the pair does not fix a point (see the module docs).
pub fn triangulate(
    model: &CameraModel,
    pose_a: &CameraPose,
    a: &Vector2<f64>,
    pose_b: &CameraPose,
    b: &Vector2<f64>,
    cfg: &TriangulateConfig,
) -> Result<WorldPoint, TriangulateError> {
    let ray = |pose: &CameraPose, px| {
        model
            .unproject(px)
            .map(|d| pose.rotation * d)
            .ok_or(TriangulateError::NoRay)
    };
    let (da, db) = (ray(pose_a, a)?, ray(pose_b, b)?);
    // Unit bearings: the cosine of the angle between the rays is their dot product.
    let cos = da.dot(&db).clamp(-1.0, 1.0);
    let parallax = libm::acos(cos);
    if parallax < cfg.min_parallax {
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
    if gap > cfg.max_gap_per_depth * s.min(t) {
        return Err(TriangulateError::Inconsistent);
    }
    Ok(WorldPoint {
        position: (pa + pb) * 0.5,
        parallax,
        gap,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frontend::visual::camera::{Intrinsics, Kb4};

    fn cleaner_camera() -> (CameraModel, CameraExtrinsic) {
        let k = Intrinsics {
            fx: 120.0,
            fy: 120.0,
            cx: 160.0,
            cy: 120.0,
        };
        let model = CameraModel::Kb4(
            Kb4::new_checked(k, [0.02, -0.01, 0.003, -0.0005], 1.6).expect("valid lens"),
        );
        // The cleaner's camera: 10 cm forward, 9 cm up, tilted 60 degrees toward the ceiling.
        let mount = CameraExtrinsic::mounted([0.1, 0.0, 0.09], 0.0, 60f64.to_radians());
        (model, mount)
    }

    fn pixel(model: &CameraModel, pose: &CameraPose, p: &Vector3<f64>) -> Vector2<f64> {
        model.project(&pose.world_to_camera(p)).expect("in view")
    }

    #[test]
    fn a_ceiling_point_seen_from_two_odometry_poses_is_recovered() {
        let (model, mount) = cleaner_camera();
        let pa = CameraPose::of_robot(&Se2::new(1.0, 2.0, 0.3), &mount);
        let pb = CameraPose::of_robot(&Se2::new(1.25, 2.08, 0.35), &mount);
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
            let noisy = b + Vector2::new(0.5, -0.3);
            let near = triangulate(&model, &pa, &a, &pb, &noisy, &cfg).expect("a point");
            let depth = (point - pa.centre).norm();
            let expected = depth * (0.6 / 120.0) / got.parallax;
            let moved = (near.position - point).norm();
            assert!(moved < 1.5 * expected, "{moved} m against {expected} m");
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
        let b = pixel(&model, &pb, &point) + Vector2::new(0.0, 40.0);
        assert!(matches!(
            triangulate(&model, &pa, &a, &pb, &b, &cfg),
            Err(TriangulateError::Inconsistent | TriangulateError::Behind)
        ));
        // Rays that meet behind the cameras: camera b looks along the line from a point X
        // behind camera a, through its own centre.
        let da = (pa.rotation * model.unproject(&a).expect("a ray")).normalize();
        let x = pa.centre - da;
        let q = pb.centre + (pb.centre - x) * 2.0;
        let b = pixel(&model, &pb, &q);
        assert_eq!(
            triangulate(&model, &pa, &a, &pb, &b, &cfg),
            Err(TriangulateError::Behind)
        );
    }
}
