//! Camera models and the camera's mounting on the robot (paper section III-B.1).
//!
//! The paper relates 2D pixels and 3D points with a general projective model (Kannala and
//! Brandt): `p = pi(M, P)`. Two models are offered behind one enum, [`CameraModel`]:
//! * [`Pinhole`]: `u = fx x / z + cx`, `v = fy y / z + cy`, for narrow lenses and tests.
//! * [`Kb4`]: the equidistant fisheye model. With `r = sqrt(x^2 + y^2)` and the angle to the
//!   optical axis `theta = atan2(r, z)`, the distorted radius is
//!   `d(theta) = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)` and
//!   `u = fx d x / r + cx`, `v = fy d y / r + cy`. Cheap ceiling cameras are wide-angle; this
//!   model stays valid past 90 degrees, where a pinhole cannot.
//!
//! Why these choices:
//! * An enum rather than a trait object: the core has no heap, the set of models is closed, and
//!   a `match` keeps every call statically dispatched on the Cortex-A9.
//! * Geometry in `f64`, like the poses: the Jacobians feed bundle adjustment, where `f32`
//!   round-off would show up in the normal equations.
//! * `libm` for every transcendental function, so x86-64 and ARMv7 compute the same bits.
//! * Unprojecting a KB4 pixel inverts `d(theta)` by Newton's method with a fixed iteration cap
//!   and tolerance; the model is checked to be increasing on `[0, max_theta]` when it is built,
//!   which is what makes that inversion unique and the iteration converge.
//!
//! Frames: the camera frame has `z` along the optical axis, `x` to the right of the image and
//! `y` down it. [`CameraExtrinsic`] is the camera's pose in the robot frame (`x` forward, `y`
//! left, `z` up); the cameras of the paper look forward and up at the ceiling.

use core::fmt;

use nalgebra::{Matrix2x3, Matrix3, Vector2, Vector3};

/// Points closer to the image plane than this (in the units of the point) do not project.
const MIN_DEPTH: f64 = 1e-9;
/// Newton iterations allowed when inverting the KB4 distortion.
const NEWTON_MAX_ITERS: usize = 12;
/// Newton stops when the step is below this (radians).
const NEWTON_TOL: f64 = 1e-12;
/// Below this ratio `r / |z|` a KB4 Jacobian uses the on-axis (pinhole) form, which avoids
/// the cancellation in `d'(theta) theta_r r - d(theta)` over `r^2`.
const AXIS_EPS: f64 = 1e-7;
/// Samples of `d'(theta)` checked when a KB4 model is built.
const MONOTONE_SAMPLES: usize = 64;

/// Why a camera model cannot be built.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum CameraError {
    /// A focal length is not positive, or a parameter is not finite.
    BadIntrinsics,
    /// `max_theta` is not in `(0, pi)`.
    BadMaxAngle,
    /// The KB4 distortion is not increasing on `[0, max_theta]`, so pixels would be ambiguous.
    NotMonotone,
}

impl fmt::Display for CameraError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::BadIntrinsics => write!(f, "focal lengths must be positive and finite"),
            Self::BadMaxAngle => write!(f, "the maximum field angle must be in (0, pi)"),
            Self::NotMonotone => write!(f, "the KB4 distortion is not increasing"),
        }
    }
}

impl core::error::Error for CameraError {}

/// Focal lengths and principal point, in pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Intrinsics {
    /// Horizontal focal length.
    pub fx: f64,
    /// Vertical focal length.
    pub fy: f64,
    /// Principal point, column.
    pub cx: f64,
    /// Principal point, row.
    pub cy: f64,
}

impl Intrinsics {
    fn check(&self) -> Result<(), CameraError> {
        let finite = self.fx.is_finite()
            && self.fy.is_finite()
            && self.cx.is_finite()
            && self.cy.is_finite();
        if finite && self.fx > 0.0 && self.fy > 0.0 {
            Ok(())
        } else {
            Err(CameraError::BadIntrinsics)
        }
    }
}

/// The pinhole model, without distortion.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Pinhole {
    k: Intrinsics,
}

impl Pinhole {
    /// A pinhole camera.
    ///
    /// # Errors
    /// [`CameraError::BadIntrinsics`] for non-positive or non-finite parameters.
    pub fn new_checked(k: Intrinsics) -> Result<Self, CameraError> {
        k.check()?;
        Ok(Self { k })
    }

    /// The intrinsics.
    pub fn intrinsics(&self) -> Intrinsics {
        self.k
    }

    fn project(&self, p: &Vector3<f64>) -> Option<Vector2<f64>> {
        let in_front = p.z > MIN_DEPTH;
        if !in_front {
            return None;
        }
        Some(Vector2::new(
            self.k.fx * p.x / p.z + self.k.cx,
            self.k.fy * p.y / p.z + self.k.cy,
        ))
    }

    fn unproject(&self, px: &Vector2<f64>) -> Option<Vector3<f64>> {
        let m = Vector3::new(
            (px.x - self.k.cx) / self.k.fx,
            (px.y - self.k.cy) / self.k.fy,
            1.0,
        );
        normalized(m)
    }

    fn jacobian(&self, p: &Vector3<f64>) -> Option<Matrix2x3<f64>> {
        pinhole_jacobian(&self.k, p)
    }
}

/// The derivative of `(fx x / z + cx, fy y / z + cy)`, or `None` when `z` is not positive.
fn pinhole_jacobian(k: &Intrinsics, p: &Vector3<f64>) -> Option<Matrix2x3<f64>> {
    let in_front = p.z > MIN_DEPTH;
    if !in_front {
        return None;
    }
    let iz = 1.0 / p.z;
    Some(Matrix2x3::new(
        k.fx * iz,
        0.0,
        -k.fx * p.x * iz * iz,
        0.0,
        k.fy * iz,
        -k.fy * p.y * iz * iz,
    ))
}

/// The Kannala-Brandt equidistant fisheye model with four distortion terms.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Kb4 {
    k: Intrinsics,
    dist: [f64; 4],
    max_theta: f64,
}

impl Kb4 {
    /// A KB4 camera whose field is limited to angles below `max_theta` from the optical axis.
    ///
    /// # Errors
    /// [`CameraError`] for bad intrinsics, a `max_theta` outside `(0, pi)`, or a distortion
    /// `d(theta)` that is not increasing on `[0, max_theta]`.
    pub fn new_checked(k: Intrinsics, dist: [f64; 4], max_theta: f64) -> Result<Self, CameraError> {
        k.check()?;
        if dist.iter().any(|d| !d.is_finite()) {
            return Err(CameraError::BadIntrinsics);
        }
        let in_range = max_theta > 0.0 && max_theta < core::f64::consts::PI;
        if !in_range {
            return Err(CameraError::BadMaxAngle);
        }
        let cam = Self { k, dist, max_theta };
        for i in 0..=MONOTONE_SAMPLES {
            let theta = max_theta * (i as f64) / (MONOTONE_SAMPLES as f64);
            let increasing = cam.distort(theta).1 > 0.0;
            if !increasing {
                return Err(CameraError::NotMonotone);
            }
        }
        Ok(cam)
    }

    /// The intrinsics.
    pub fn intrinsics(&self) -> Intrinsics {
        self.k
    }

    /// The distortion coefficients `k1..k4`.
    pub fn distortion(&self) -> [f64; 4] {
        self.dist
    }

    /// The largest angle from the optical axis that projects.
    pub fn max_theta(&self) -> f64 {
        self.max_theta
    }

    /// `d(theta)` and its derivative.
    fn distort(&self, theta: f64) -> (f64, f64) {
        let [k1, k2, k3, k4] = self.dist;
        let t2 = theta * theta;
        // Horner in theta^2: poly = 1 + k1 t2 + k2 t2^2 + k3 t2^3 + k4 t2^4.
        let poly = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)));
        let dpoly = k1 + t2 * (2.0 * k2 + t2 * (3.0 * k3 + t2 * 4.0 * k4));
        // d = theta poly(t2); d' = poly + theta * dpoly/dt2 * 2 theta.
        (theta * poly, poly + 2.0 * t2 * dpoly)
    }

    fn project(&self, p: &Vector3<f64>) -> Option<Vector2<f64>> {
        let r = libm::sqrt(p.x * p.x + p.y * p.y);
        let theta = libm::atan2(r, p.z);
        let valid = theta <= self.max_theta && r + p.z.abs() > MIN_DEPTH;
        if !valid {
            return None;
        }
        let (d, _) = self.distort(theta);
        // Close to the axis d / r tends to 1 / z: the pinhole limit.
        let s = if r > MIN_DEPTH * p.z.abs() {
            d / r
        } else {
            1.0 / p.z
        };
        Some(Vector2::new(
            self.k.fx * s * p.x + self.k.cx,
            self.k.fy * s * p.y + self.k.cy,
        ))
    }

    fn unproject(&self, px: &Vector2<f64>) -> Option<Vector3<f64>> {
        let mx = (px.x - self.k.cx) / self.k.fx;
        let my = (px.y - self.k.cy) / self.k.fy;
        let rd = libm::sqrt(mx * mx + my * my);
        if !rd.is_finite() {
            return None;
        }
        if rd < MIN_DEPTH {
            return Some(Vector3::new(0.0, 0.0, 1.0));
        }
        if rd > self.distort(self.max_theta).0 {
            return None;
        }
        // d is increasing and d(theta) <= theta-ish, so rd is a good start.
        let mut theta = rd.min(self.max_theta);
        let mut converged = false;
        for _ in 0..NEWTON_MAX_ITERS {
            let (d, dd) = self.distort(theta);
            let step = (d - rd) / dd;
            theta = (theta - step).clamp(0.0, self.max_theta);
            if step.abs() < NEWTON_TOL {
                converged = true;
                break;
            }
        }
        if !converged {
            return None;
        }
        let s = libm::sin(theta) / rd;
        Some(Vector3::new(mx * s, my * s, libm::cos(theta)))
    }

    fn jacobian(&self, p: &Vector3<f64>) -> Option<Matrix2x3<f64>> {
        let r2 = p.x * p.x + p.y * p.y;
        let r = libm::sqrt(r2);
        let theta = libm::atan2(r, p.z);
        let valid = theta <= self.max_theta;
        if !valid {
            return None;
        }
        let off_axis = r > AXIS_EPS * p.z.abs();
        if !off_axis {
            // On the axis the model is the pinhole one to first order (d'(0) = 1).
            return pinhole_jacobian(&self.k, p);
        }
        let (fx, fy) = (self.k.fx, self.k.fy);
        let (d, dd) = self.distort(theta);
        let rho2 = r2 + p.z * p.z;
        // s = d(theta(r, z)) / r, the factor in u = fx s x + cx.
        let s = d / r;
        let ds_dr = (dd * p.z / rho2 * r - d) / r2;
        let ds_dz = -dd / rho2;
        let ds = Vector3::new(ds_dr * p.x / r, ds_dr * p.y / r, ds_dz);
        let mut j = Matrix2x3::zeros();
        j.set_row(0, &(ds.transpose() * (fx * p.x)));
        j.set_row(1, &(ds.transpose() * (fy * p.y)));
        j[(0, 0)] += fx * s;
        j[(1, 1)] += fy * s;
        Some(j)
    }
}

/// A camera model: what `pi` in the paper's reprojection is.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum CameraModel {
    /// Undistorted pinhole.
    Pinhole(Pinhole),
    /// Kannala-Brandt equidistant fisheye, four terms.
    Kb4(Kb4),
}

impl CameraModel {
    /// The pixel of a point given in the camera frame, or `None` when the point is behind the
    /// camera (pinhole) or outside the valid field angle (KB4).
    pub fn project(&self, p: &Vector3<f64>) -> Option<Vector2<f64>> {
        match self {
            Self::Pinhole(c) => c.project(p),
            Self::Kb4(c) => c.project(p),
        }
    }

    /// The unit bearing of a pixel, or `None` when no ray of the valid field maps to it.
    pub fn unproject(&self, px: &Vector2<f64>) -> Option<Vector3<f64>> {
        match self {
            Self::Pinhole(c) => c.unproject(px),
            Self::Kb4(c) => c.unproject(px),
        }
    }

    /// The 2x3 derivative of [`project`](Self::project) with respect to the point, or `None`
    /// where the projection is undefined.
    pub fn jacobian(&self, p: &Vector3<f64>) -> Option<Matrix2x3<f64>> {
        match self {
            Self::Pinhole(c) => c.jacobian(p),
            Self::Kb4(c) => c.jacobian(p),
        }
    }

    /// The intrinsics shared by both models.
    pub fn intrinsics(&self) -> Intrinsics {
        match self {
            Self::Pinhole(c) => c.intrinsics(),
            Self::Kb4(c) => c.intrinsics(),
        }
    }
}

fn normalized(v: Vector3<f64>) -> Option<Vector3<f64>> {
    let n = libm::sqrt(v.dot(&v));
    if n.is_finite() && n > 0.0 {
        Some(v / n)
    } else {
        None
    }
}

/// The camera's pose in the robot frame: `p_robot = rotation * p_camera + translation`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraExtrinsic {
    rotation: Matrix3<f64>,
    translation: Vector3<f64>,
}

impl CameraExtrinsic {
    /// A camera at `position` (metres, robot frame) whose optical axis points along the
    /// robot heading `yaw` (radians, counter-clockwise from the robot's `x`) raised by `tilt`
    /// radians above the floor plane; `tilt = pi/2` looks straight up. The image's `x` axis
    /// stays parallel to the floor, so a level robot sees a level ceiling.
    pub fn mounted(position: [f64; 3], yaw: f64, tilt: f64) -> Self {
        let (sy, cy) = (libm::sin(yaw), libm::cos(yaw));
        let (st, ct) = (libm::sin(tilt), libm::cos(tilt));
        // Camera axes in the robot frame before the yaw: optical axis forward and up, image
        // rows going down the view, image columns to the robot's right.
        let z = Vector3::new(ct, 0.0, st);
        let y = Vector3::new(st, 0.0, -ct);
        let x = Vector3::new(0.0, -1.0, 0.0);
        let yaw_rot = crate::geom::yaw_rotation(cy, sy);
        let rotation = yaw_rot * Matrix3::from_columns(&[x, y, z]);
        Self {
            rotation,
            translation: Vector3::new(position[0], position[1], position[2]),
        }
    }

    /// The camera-to-robot rotation.
    pub fn rotation(&self) -> &Matrix3<f64> {
        &self.rotation
    }

    /// The camera's optical centre in the robot frame.
    pub fn translation(&self) -> &Vector3<f64> {
        &self.translation
    }

    /// A robot-frame point in the camera frame.
    pub fn robot_to_camera(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation.transpose() * (p - self.translation)
    }

    /// A camera-frame point in the robot frame.
    pub fn camera_to_robot(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * p + self.translation
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn intr() -> Intrinsics {
        Intrinsics {
            fx: 190.0,
            fy: 188.0,
            cx: 161.0,
            cy: 118.5,
        }
    }

    fn kb4() -> CameraModel {
        let k = [0.02, -0.01, 0.003, -0.0005];
        CameraModel::Kb4(Kb4::new_checked(intr(), k, 1.6).unwrap())
    }

    fn pinhole() -> CameraModel {
        CameraModel::Pinhole(Pinhole::new_checked(intr()).unwrap())
    }

    /// Central differences of `project`, column by column.
    fn numeric_jacobian(cam: &CameraModel, p: &Vector3<f64>) -> Matrix2x3<f64> {
        let mut j = Matrix2x3::zeros();
        let h = 1e-6;
        for c in 0..3 {
            let mut a = *p;
            let mut b = *p;
            a[c] += h;
            b[c] -= h;
            let d = (cam.project(&a).unwrap() - cam.project(&b).unwrap()) / (2.0 * h);
            j.set_column(c, &d);
        }
        j
    }

    proptest! {
        #[test]
        fn kb4_pixel_round_trips(u in 0.0f64..320.0, v in 0.0f64..240.0) {
            let cam = kb4();
            let px = Vector2::new(u, v);
            let ray = cam.unproject(&px).unwrap();
            prop_assert!((ray.norm() - 1.0).abs() < 1e-12);
            let back = cam.project(&ray).unwrap();
            prop_assert!((back - px).norm() < 1e-7, "{px:?} -> {back:?}");
        }

        #[test]
        fn pinhole_pixel_round_trips(u in -100.0f64..400.0, v in -100.0f64..300.0) {
            let cam = pinhole();
            let px = Vector2::new(u, v);
            let back = cam.project(&cam.unproject(&px).unwrap()).unwrap();
            prop_assert!((back - px).norm() < 1e-9);
        }

        #[test]
        fn kb4_point_round_trips_to_its_bearing(
            x in -3.0f64..3.0, y in -3.0f64..3.0, z in 0.05f64..3.0,
        ) {
            let cam = kb4();
            let p = Vector3::new(x, y, z);
            let ray = cam.unproject(&cam.project(&p).unwrap()).unwrap();
            prop_assert!((ray - p.normalize()).norm() < 1e-9);
        }

        #[test]
        fn jacobians_match_central_differences(
            x in -2.0f64..2.0, y in -2.0f64..2.0, z in 0.3f64..3.0,
        ) {
            let p = Vector3::new(x, y, z);
            for cam in [kb4(), pinhole()] {
                let j = cam.jacobian(&p).unwrap();
                let n = numeric_jacobian(&cam, &p);
                let scale = 1.0 + n.abs().max();
                prop_assert!((j - n).abs().max() < 1e-5 * scale, "{cam:?}\n{j}\n{n}");
            }
        }

        #[test]
        fn extrinsic_round_trips(
            x in -1.0f64..1.0, y in -1.0f64..1.0, z in -1.0f64..1.0,
            yaw in -3.2f64..3.2, tilt in 0.0f64..1.6,
        ) {
            let e = CameraExtrinsic::mounted([0.1, -0.05, 0.3], yaw, tilt);
            let p = Vector3::new(x, y, z);
            prop_assert!((e.camera_to_robot(&e.robot_to_camera(&p)) - p).norm() < 1e-12);
            let r = e.rotation();
            prop_assert!((r.transpose() * r - Matrix3::identity()).abs().max() < 1e-12);
            prop_assert!((r.determinant() - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn behind_or_outside_the_field_does_not_project() {
        assert!(pinhole().project(&Vector3::new(0.1, 0.1, -1.0)).is_none());
        assert!(pinhole().project(&Vector3::new(0.1, 0.1, 0.0)).is_none());
        // 1.6 rad is past 90 degrees: a point slightly behind the image plane still projects.
        assert!(kb4().project(&Vector3::new(1.0, 0.0, -0.01)).is_some());
        assert!(kb4().project(&Vector3::new(1.0, 0.0, -1.0)).is_none());
        assert!(kb4().project(&Vector3::new(0.0, 0.0, -1.0)).is_none());
        assert!(kb4().unproject(&Vector2::new(1e6, 0.0)).is_none());
        assert!(kb4().unproject(&Vector2::new(f64::NAN, 0.0)).is_none());
        assert_eq!(
            kb4().project(&Vector3::new(0.0, 0.0, 2.0)),
            Some(Vector2::new(161.0, 118.5))
        );
    }

    #[test]
    fn bad_models_are_refused() {
        let bad = Intrinsics { fx: 0.0, ..intr() };
        assert_eq!(Pinhole::new_checked(bad), Err(CameraError::BadIntrinsics));
        assert_eq!(
            Kb4::new_checked(intr(), [0.0; 4], 3.5),
            Err(CameraError::BadMaxAngle)
        );
        // A strongly negative k1 folds d(theta) back before 1.5 rad.
        assert_eq!(
            Kb4::new_checked(intr(), [-0.5, 0.0, 0.0, 0.0], 1.5),
            Err(CameraError::NotMonotone)
        );
    }

    #[test]
    fn a_190_degree_fisheye_works_to_its_edge() {
        // A 320 x 240 fisheye of focal 320 / 3.4 px covering 95 degrees off the axis.
        let k = Intrinsics {
            fx: 320.0 / 3.4,
            fy: 320.0 / 3.4,
            cx: 159.5,
            cy: 119.5,
        };
        let theta_max = 95f64.to_radians();
        let cam =
            CameraModel::Kb4(Kb4::new_checked(k, [0.02, -0.004, 0.0006, 0.0], theta_max).unwrap());
        // A point 94 degrees off the axis (slightly behind the image plane) round-trips.
        let a = 94f64.to_radians();
        let p = Vector3::new(a.sin(), 0.0, a.cos());
        let px = cam.project(&p).unwrap();
        assert!(px.x > 300.0);
        let ray = cam.unproject(&px).unwrap();
        assert!((ray - p).norm() < 1e-9);
        let num = numeric_jacobian(&cam, &p);
        assert!((cam.jacobian(&p).unwrap() - num).abs().max() < 1e-4);
    }

    #[test]
    fn an_upward_camera_sees_the_point_above_it_on_its_axis() {
        let e = CameraExtrinsic::mounted([0.2, 0.0, 0.3], 0.0, core::f64::consts::FRAC_PI_2);
        let above = e.robot_to_camera(&Vector3::new(0.2, 0.0, 2.3));
        assert!((above - Vector3::new(0.0, 0.0, 2.0)).norm() < 1e-12);
        // Tilting a forward camera back by 90 degrees turns the image's top backwards: a
        // ceiling point ahead of the robot appears below the image centre (+y).
        let ahead = e.robot_to_camera(&Vector3::new(1.2, 0.0, 2.3));
        assert!(ahead.y > 0.0 && ahead.x.abs() < 1e-12);
        // A point to the robot's left appears on the image's left (-x).
        let left = e.robot_to_camera(&Vector3::new(0.2, 1.0, 2.3));
        assert!(left.x < 0.0);
    }
}
