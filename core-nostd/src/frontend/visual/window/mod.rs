//! Sliding-window bundle adjustment for a ground robot: the visual odometry of the paper's
//! section III-B.1, where the reprojection error of 3D points in the keyframes of a window is
//! minimised over the keyframe poses and the points together.
//!
//! What is solved: for a window of keyframes with robot poses `T_k` and landmarks `P_l` in the
//! world frame, minimise
//! `sum_obs rho(|pi(C^-1 T_k^-1 P_l) - z| / sigma) + sum_priors e_ij^T Omega_ij e_ij`,
//! where `pi` is the lens model ([`CameraModel`]), `C` the fixed mounting of the camera on the
//! robot ([`CameraExtrinsic`]), `rho` the Huber loss, and `e_ij` the difference between the
//! relative pose of keyframes `i` and `j` and the wheel+gyro motion measured between them.
//!
//! Why planar poses: the robot drives on a floor, so its camera never leaves the plane the
//! mounting puts it in; only `x`, `y` and the heading change. A keyframe therefore has three
//! unknowns, not six: height, roll and pitch cannot drift, which a cheap camera with few
//! features could not hold on its own, and the reduced system is half the size. The same
//! motion model is what the wheel+gyro prior speaks, so the two kinds of measurement share one
//! parametrisation (the additive `(x, y, theta)` of [`Se2`]).
//!
//! How it is solved: Levenberg-Marquardt. Each landmark touches only the keyframes that see
//! it, so its 3x3 block of the normal equations is inverted on its own and eliminated (the
//! Schur complement); what remains is a dense system over the free poses, `3 (n - fixed)`
//! unknowns, solved by Cholesky. The landmarks follow by back-substitution. The oldest
//! `fixed_poses` keyframes are held (the gauge: a window on its own cannot tell where the
//! world is); the metric scale, which one camera cannot see, comes from the motion priors.
//!
//! Before iterating, landmarks that cannot be solved are set aside and flagged: seen fewer
//! than twice, or seen along rays so close to parallel that their block is singular. Wrong
//! matches first only weigh less (Huber); once a solution stands, those beyond a chi2 gate
//! are taken out and the window is solved again, a bounded number of rounds. At the end every
//! observation carries its chi2 and an inlier flag, so the caller can drop outliers and
//! landmarks.
//!
//! Storage is fixed: `N` keyframes, `M` landmarks and `K` observations inside one
//! [`BundleWindow`] that the caller places (its constructor is `const`, so a `static` works);
//! no allocation, no recursion, and no input makes it panic.

use core::fmt;

use nalgebra::{Matrix2x3, Matrix3, Vector2, Vector3};

use super::camera::{CameraExtrinsic, CameraModel};
use crate::geom::{wrap_angle, Se2};

mod dense;
#[cfg(test)]
mod tests;

/// The end of a landmark's list of observations.
const NO_OBS: usize = usize::MAX;
/// Floor of the damping: after a long run of accepted steps, a refused one must not need
/// dozens of tenfold raises to bite again.
const MIN_LAMBDA: f64 = 1e-12;
/// Largest coordinate accepted for a pose or a landmark, metres: beyond it squares overflow
/// long before any building ends.
const MAX_COORDINATE: f64 = 1e6;
/// Largest pixel coordinate accepted: no lens images that far out.
const MAX_PIXEL: f64 = 1e6;
/// Range of pixel sigmas accepted: outside it a whitened residual overflows or vanishes.
const SIGMA_RANGE: (f64, f64) = (1e-6, 1e6);
const ZERO3: Matrix3<f64> = Matrix3::new(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
const ZERO_V: Vector3<f64> = Vector3::new(0.0, 0.0, 0.0);

/// One sighting of a landmark in a keyframe.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelObservation {
    /// Index of the keyframe (its order of [`BundleWindow::push_pose`]).
    pub keyframe: usize,
    /// Index of the landmark (its order of [`BundleWindow::push_landmark`]).
    pub landmark: usize,
    /// Measured pixel, level-0 coordinates.
    pub px: Vector2<f64>,
    /// Standard deviation of the pixel, in pixels.
    pub sigma_px: f64,
}

/// The wheel+gyro motion between two keyframes: `motion` is keyframe `to`'s pose in the frame
/// of keyframe `from`, with the information (inverse covariance) of `(x, y, theta)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MotionPrior {
    /// Earlier keyframe.
    pub from: usize,
    /// Later keyframe.
    pub to: usize,
    /// Measured relative motion.
    pub motion: Se2,
    /// Information of the motion, symmetric positive semi-definite.
    pub information: Matrix3<f64>,
}

/// Solver parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct WindowConfig {
    /// Accepted steps at most, over all rounds.
    pub max_iterations: u32,
    /// Times the observations beyond [`outlier_chi2`](Self::outlier_chi2) are taken out
    /// (and those back within it put back) and the window solved again.
    pub rejection_rounds: u32,
    /// Oldest keyframes held fixed, at least one (the gauge).
    pub fixed_poses: usize,
    /// Whitened residual norm beyond which an observation's weight falls off (Huber). At
    /// the root of the outlier gate, the observations a rejection round keeps all have full
    /// weight, and the last round converges like plain Gauss-Newton.
    pub huber: f64,
    /// An observation whose squared whitened residual exceeds this is an outlier: 5.99 is the
    /// 95 % point of a chi2 with two degrees of freedom.
    pub outlier_chi2: f64,
    /// A landmark whose block, at the start, has a Cholesky pivot below this fraction of its
    /// largest diagonal term is taken as seen without parallax and set aside.
    pub min_pivot_ratio: f64,
    /// First Levenberg-Marquardt damping, relative to each diagonal term.
    pub initial_lambda: f64,
    /// Damping beyond which the solve gives up looking for a decrease.
    pub max_lambda: f64,
    /// Converged when an accepted step lowers the cost by less than this fraction.
    pub cost_tolerance: f64,
    /// The same for a round followed by a rejection round, which needs the outliers told
    /// apart, not the last digits.
    pub rejection_cost_tolerance: f64,
    /// Converged when no unknown moves more than this (metres or radians).
    pub step_tolerance: f64,
}

impl Default for WindowConfig {
    fn default() -> Self {
        WindowConfig {
            max_iterations: 30,
            rejection_rounds: 2,
            fixed_poses: 1,
            huber: 2.45,
            outlier_chi2: 5.991,
            min_pivot_ratio: 1e-8,
            initial_lambda: 1e-4,
            max_lambda: 1e8,
            cost_tolerance: 1e-6,
            rejection_cost_tolerance: 1e-3,
            step_tolerance: 1e-6,
        }
    }
}

/// Why the window refused an input or could not be solved.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum WindowError {
    /// The keyframe, landmark, observation or prior storage is full.
    Full,
    /// An observation or prior names a keyframe that is not in the window.
    UnknownKeyframe,
    /// An observation names a landmark that is not in the window.
    UnknownLandmark,
    /// A pose, point, pixel, sigma or information is not finite, or a sigma is not positive.
    NotFinite,
    /// A finite value out of any sensible range: a coordinate beyond a thousand kilometres, a
    /// pixel beyond a million, a sigma outside `[1e-6, 1e6]` pixels.
    OutOfRange,
    /// The window holds no keyframe.
    Empty,
    /// No observation of a solvable landmark and no motion prior: nothing constrains the
    /// window.
    NoMeasurements,
}

impl fmt::Display for WindowError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Full => write!(f, "the window's storage is full"),
            Self::UnknownKeyframe => write!(f, "no such keyframe in the window"),
            Self::UnknownLandmark => write!(f, "no such landmark in the window"),
            Self::NotFinite => write!(f, "a value is not finite or a sigma is not positive"),
            Self::OutOfRange => write!(f, "a value is out of range"),
            Self::Empty => write!(f, "the window holds no keyframe"),
            Self::NoMeasurements => write!(f, "nothing constrains the window"),
        }
    }
}

impl core::error::Error for WindowError {}

/// What the last solve made of a landmark.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum LandmarkStatus {
    /// Not solved yet.
    Pending,
    /// Solved.
    Active,
    /// Fewer than two of its observations project: its depth is not fixed.
    TooFewViews,
    /// Its rays are too close to parallel (too little motion, or too far): its depth is not
    /// fixed. Left where it was.
    NoParallax,
}

/// What the last solve made of an observation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ObservationStatus {
    /// Not solved yet.
    Pending,
    /// Its residual at the result is within [`WindowConfig::outlier_chi2`].
    Inlier,
    /// Its residual at the result is beyond [`WindowConfig::outlier_chi2`]: a wrong match, or
    /// a moving object. During the solve it weighed less (Huber), then was taken out
    /// ([`WindowConfig::rejection_rounds`]).
    Outlier,
    /// Its landmark does not project into its keyframe at the start (behind the camera or
    /// outside the lens's field); not used.
    NotProjectable,
    /// Its landmark was set aside ([`LandmarkStatus`]); not used.
    Skipped,
}

/// How a solve ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Termination {
    /// The cost or the step fell below its tolerance.
    Converged,
    /// [`WindowConfig::max_iterations`] was reached.
    IterationLimit,
    /// No damping up to [`WindowConfig::max_lambda`] lowered the cost: a minimum as far as
    /// the numbers can tell, or a problem the data does not constrain.
    NoDecrease,
}

/// The outcome of [`BundleWindow::solve`].
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct WindowSummary {
    /// Accepted steps.
    pub iterations: u32,
    /// Robust cost at the start (squared whitened units).
    pub initial_cost: f64,
    /// Robust cost at the result, over the observations still in use (rejection rounds take
    /// some out, so it can be far below the initial cost for that reason too).
    pub final_cost: f64,
    /// How it ended.
    pub termination: Termination,
    /// Landmarks solved.
    pub active_landmarks: usize,
    /// Landmarks set aside ([`LandmarkStatus::TooFewViews`], [`LandmarkStatus::NoParallax`]).
    pub skipped_landmarks: usize,
    /// Observations within the chi2 gate at the result.
    pub inliers: usize,
    /// Observations used but beyond the gate at the result.
    pub outliers: usize,
}

/// A landmark after the last solve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LandmarkReport {
    /// Position in the world frame.
    pub position: Vector3<f64>,
    /// What the solve made of it.
    pub status: LandmarkStatus,
    /// Its observations that projected at the start (those taken out as outliers included);
    /// zero when the landmark was set aside.
    pub observations: usize,
    /// Those of them flagged as outliers.
    pub outliers: usize,
    /// Sum of the squared whitened residuals of those observations at the result.
    pub chi2: f64,
}

impl LandmarkReport {
    /// Solved, and none of its observations is an outlier: a point worth keeping as it is.
    pub fn is_inlier(&self) -> bool {
        self.status == LandmarkStatus::Active && self.outliers == 0
    }
}

/// An observation after the last solve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ObservationReport {
    /// What the solve made of it.
    pub status: ObservationStatus,
    /// Its squared whitened residual at the result (0 when unused).
    pub chi2: f64,
}

#[derive(Clone, Copy, Debug)]
struct PoseSlot {
    pose: Se2,
    backup: Se2,
    cos: f64,
    sin: f64,
    /// Diagonal block of the normal equations and right-hand side.
    u: Matrix3<f64>,
    b: Vector3<f64>,
    step: Vector3<f64>,
}

const EMPTY_POSE: PoseSlot = PoseSlot {
    pose: Se2::IDENTITY,
    backup: Se2::IDENTITY,
    cos: 1.0,
    sin: 0.0,
    u: ZERO3,
    b: ZERO_V,
    step: ZERO_V,
};

#[derive(Clone, Copy, Debug)]
struct LandmarkSlot {
    position: Vector3<f64>,
    backup: Vector3<f64>,
    status: LandmarkStatus,
    first_obs: usize,
    /// Block of the normal equations, its damped inverse, right-hand side and step.
    v: Matrix3<f64>,
    v_inv: Matrix3<f64>,
    b: Vector3<f64>,
    step: Vector3<f64>,
}

const EMPTY_LANDMARK: LandmarkSlot = LandmarkSlot {
    position: ZERO_V,
    backup: ZERO_V,
    status: LandmarkStatus::Pending,
    first_obs: NO_OBS,
    v: ZERO3,
    v_inv: ZERO3,
    b: ZERO_V,
    step: ZERO_V,
};

#[derive(Clone, Copy, Debug)]
struct ObservationSlot {
    obs: PixelObservation,
    status: ObservationStatus,
    next: usize,
    /// Pose-landmark block of the normal equations (zero for a fixed pose).
    w: Matrix3<f64>,
    chi2: f64,
}

const EMPTY_OBSERVATION: ObservationSlot = ObservationSlot {
    obs: PixelObservation {
        keyframe: 0,
        landmark: 0,
        px: Vector2::new(0.0, 0.0),
        sigma_px: 1.0,
    },
    status: ObservationStatus::Pending,
    next: NO_OBS,
    w: ZERO3,
    chi2: 0.0,
};

#[derive(Clone, Copy, Debug)]
struct PriorSlot {
    prior: MotionPrior,
    /// Off-diagonal block `J_from^T Omega J_to`.
    cross: Matrix3<f64>,
}

const EMPTY_PRIOR: PriorSlot = PriorSlot {
    prior: MotionPrior {
        from: 0,
        to: 0,
        motion: Se2::IDENTITY,
        information: ZERO3,
    },
    cross: ZERO3,
};

/// A window of at most `N` keyframes, `M` landmarks, `K` observations and `N` motion priors,
/// with the solver's working storage.
///
/// Its size grows as `N^2` (the dense reduced system, 72 bytes per pair of keyframes) plus
/// linear terms: 184 bytes per keyframe, 24 per reduced right-hand side, and per prior,
/// landmark and observation 184, 256 and 136 bytes on x86-64 (176, 248 and 120 on ARMv7,
/// whose indices are half as wide); `tests::slot_sizes` pins them. The value is large: build
/// it where it will live (a `static`, or a resources value the caller owns), not as a local.
#[derive(Clone, Debug)]
pub struct BundleWindow<const N: usize, const M: usize, const K: usize> {
    poses: [PoseSlot; N],
    pose_count: usize,
    landmarks: [LandmarkSlot; M],
    landmark_count: usize,
    observations: [ObservationSlot; K],
    observation_count: usize,
    priors: [PriorSlot; N],
    prior_count: usize,
    /// The reduced system over the free poses, block `[row][column]`, and its right-hand
    /// side (overwritten by the pose step).
    reduced: [[Matrix3<f64>; N]; N],
    reduced_rhs: [Vector3<f64>; N],
}

impl<const N: usize, const M: usize, const K: usize> Default for BundleWindow<N, M, K> {
    fn default() -> Self {
        Self::new()
    }
}

/// A world point in the robot frame of a robot at `pose` (on the floor, z = 0) whose heading
/// has cosine `c` and sine `s`, and in the camera frame.
fn robot_and_camera(
    mount: &CameraExtrinsic,
    pose: &Se2,
    (c, s): (f64, f64),
    point: &Vector3<f64>,
) -> (Vector3<f64>, Vector3<f64>) {
    let (dx, dy) = (point.x - pose.x, point.y - pose.y);
    let q = Vector3::new(c * dx + s * dy, -s * dx + c * dy, point.z);
    (q, mount.robot_to_camera(&q))
}

/// The predicted pixel minus the measured one, or `None` where the camera model does not
/// project the point (or the result is not finite).
pub(crate) fn residual(
    model: &CameraModel,
    mount: &CameraExtrinsic,
    pose: &Se2,
    trig: (f64, f64),
    point: &Vector3<f64>,
    px: &Vector2<f64>,
) -> Option<Vector2<f64>> {
    let (_, p_cam) = robot_and_camera(mount, pose, trig, point);
    let r = model.project(&p_cam)? - px;
    // A NaN would stall every cost comparison; the sum is finite only if both terms are.
    (r.x + r.y).is_finite().then_some(r)
}

/// [`residual`] and its derivatives with respect to the robot pose `(x, y, theta)` and to the
/// landmark.
pub(crate) fn reprojection(
    model: &CameraModel,
    mount: &CameraExtrinsic,
    pose: &Se2,
    (c, s): (f64, f64),
    point: &Vector3<f64>,
    px: &Vector2<f64>,
) -> Option<(Vector2<f64>, Matrix2x3<f64>, Matrix2x3<f64>)> {
    let (q, p_cam) = robot_and_camera(mount, pose, (c, s), point);
    let r = model.project(&p_cam)? - px;
    let a = model.jacobian(&p_cam)? * mount.rotation().transpose();
    // dq/dP is the transposed heading rotation; dq/d(x, y, theta) in columns.
    let rot_t = Matrix3::new(c, s, 0.0, -s, c, 0.0, 0.0, 0.0, 1.0);
    let dq_dpose = Matrix3::new(-c, -s, q.y, s, -c, -q.x, 0.0, 0.0, 0.0);
    let (jx, jl) = (a * dq_dpose, a * rot_t);
    // One NaN would poison every block it touches; a sum is finite only if all terms are.
    (r.sum() + jx.sum() + jl.sum())
        .is_finite()
        .then_some((r, jx, jl))
}

/// The Huber weight and loss of a whitened residual of squared norm `e2`.
pub(crate) fn huber(e2: f64, k: f64) -> (f64, f64) {
    let e = libm::sqrt(e2);
    if e <= k {
        (1.0, e2)
    } else {
        (k / e, 2.0 * k * e - k * k)
    }
}

/// The motion prior's residual (measured-relative, angle wrapped) and its Jacobians with
/// respect to the `from` and `to` poses.
fn prior_residual(
    p: &MotionPrior,
    from: &Se2,
    to: &Se2,
) -> (Vector3<f64>, Matrix3<f64>, Matrix3<f64>) {
    let rel = from.between(to);
    let e = Vector3::new(
        rel.x - p.motion.x,
        rel.y - p.motion.y,
        wrap_angle(rel.theta - p.motion.theta),
    );
    let (ja, jb) = from.between_jacobians(to);
    (e, ja, jb)
}

/// The inverse of a symmetric 3x3 block by its Cholesky factor, or `None` when a pivot falls
/// below `ratio` times the largest diagonal term (or is not positive).
fn spd3_inverse(m: &Matrix3<f64>, ratio: f64) -> Option<Matrix3<f64>> {
    let scale = m[(0, 0)].max(m[(1, 1)]).max(m[(2, 2)]);
    let floor = (ratio * scale).max(0.0);
    let rows = crate::solver::rows_of(m);
    let li = Matrix3::from_row_slice(&crate::solver::chol_inverse_above(&rows, floor)?);
    // inv(m) = inv(L)^T inv(L).
    let inv = li.transpose() * li;
    inv.iter().all(|v| v.is_finite()).then_some(inv)
}

/// `m` with `lambda` times its diagonal added to the diagonal (Marquardt's scaling, which
/// keeps the damping in each unknown's own units).
fn damped(m: &Matrix3<f64>, lambda: f64) -> Matrix3<f64> {
    let mut d = *m;
    for i in 0..3 {
        d[(i, i)] += lambda * m[(i, i)].max(f64::MIN_POSITIVE);
    }
    d
}

impl<const N: usize, const M: usize, const K: usize> BundleWindow<N, M, K> {
    /// An empty window.
    pub const fn new() -> Self {
        BundleWindow {
            poses: [EMPTY_POSE; N],
            pose_count: 0,
            landmarks: [EMPTY_LANDMARK; M],
            landmark_count: 0,
            observations: [EMPTY_OBSERVATION; K],
            observation_count: 0,
            priors: [EMPTY_PRIOR; N],
            prior_count: 0,
            reduced: [[ZERO3; N]; N],
            reduced_rhs: [ZERO_V; N],
        }
    }

    /// Forgets every keyframe, landmark, observation and prior.
    pub fn clear(&mut self) {
        self.pose_count = 0;
        self.landmark_count = 0;
        self.observation_count = 0;
        self.prior_count = 0;
    }

    /// Adds a keyframe's robot pose (initial guess); returns its index. The oldest keyframes
    /// come first: they are the ones held fixed.
    ///
    /// # Errors
    /// [`WindowError::Full`], [`WindowError::NotFinite`] for a non-finite pose, or
    /// [`WindowError::OutOfRange`].
    pub fn push_pose(&mut self, pose: Se2) -> Result<usize, WindowError> {
        if !pose.is_finite() {
            return Err(WindowError::NotFinite);
        }
        if pose.x.abs() > MAX_COORDINATE || pose.y.abs() > MAX_COORDINATE {
            return Err(WindowError::OutOfRange);
        }
        let index = self.pose_count;
        let slot = self.poses.get_mut(index).ok_or(WindowError::Full)?;
        *slot = PoseSlot { pose, ..EMPTY_POSE };
        self.pose_count += 1;
        Ok(index)
    }

    /// Adds a landmark's world position (initial guess); returns its index.
    ///
    /// # Errors
    /// [`WindowError::Full`], [`WindowError::NotFinite`] for a non-finite point, or
    /// [`WindowError::OutOfRange`].
    pub fn push_landmark(&mut self, position: Vector3<f64>) -> Result<usize, WindowError> {
        if !position.iter().all(|v| v.is_finite()) {
            return Err(WindowError::NotFinite);
        }
        if position.amax() > MAX_COORDINATE {
            return Err(WindowError::OutOfRange);
        }
        let index = self.landmark_count;
        let slot = self.landmarks.get_mut(index).ok_or(WindowError::Full)?;
        *slot = LandmarkSlot {
            position,
            ..EMPTY_LANDMARK
        };
        self.landmark_count += 1;
        Ok(index)
    }

    /// Adds an observation of a landmark already in the window from a keyframe already in it.
    ///
    /// # Errors
    /// [`WindowError::Full`], [`WindowError::UnknownKeyframe`],
    /// [`WindowError::UnknownLandmark`], [`WindowError::NotFinite`] for a non-finite pixel
    /// or a sigma that is not positive and finite, or [`WindowError::OutOfRange`].
    pub fn push_observation(&mut self, obs: PixelObservation) -> Result<(), WindowError> {
        let finite = obs.px.x.is_finite()
            && obs.px.y.is_finite()
            && obs.sigma_px.is_finite()
            && obs.sigma_px > 0.0;
        if !finite {
            return Err(WindowError::NotFinite);
        }
        let in_range = obs.px.amax() <= MAX_PIXEL
            && obs.sigma_px >= SIGMA_RANGE.0
            && obs.sigma_px <= SIGMA_RANGE.1;
        if !in_range {
            return Err(WindowError::OutOfRange);
        }
        if obs.keyframe >= self.pose_count {
            return Err(WindowError::UnknownKeyframe);
        }
        if obs.landmark >= self.landmark_count {
            return Err(WindowError::UnknownLandmark);
        }
        let slot = self
            .observations
            .get_mut(self.observation_count)
            .ok_or(WindowError::Full)?;
        *slot = ObservationSlot {
            obs,
            ..EMPTY_OBSERVATION
        };
        self.observation_count += 1;
        Ok(())
    }

    /// Adds a wheel+gyro motion between two keyframes already in the window.
    ///
    /// # Errors
    /// [`WindowError::Full`], [`WindowError::UnknownKeyframe`] (also for `from == to`), or
    /// [`WindowError::NotFinite`] for a non-finite motion or information, or an information
    /// with a negative diagonal.
    pub fn push_motion_prior(&mut self, prior: MotionPrior) -> Result<(), WindowError> {
        let info = &prior.information;
        let finite = prior.motion.is_finite()
            && info.iter().all(|v| v.is_finite())
            && (0..3).all(|i| info[(i, i)] >= 0.0);
        if !finite {
            return Err(WindowError::NotFinite);
        }
        let known =
            prior.from < self.pose_count && prior.to < self.pose_count && prior.from != prior.to;
        if !known {
            return Err(WindowError::UnknownKeyframe);
        }
        let slot = self
            .priors
            .get_mut(self.prior_count)
            .ok_or(WindowError::Full)?;
        // The solver reads the lower triangle as the upper one: keep it symmetric.
        let information = (info + info.transpose()) * 0.5;
        *slot = PriorSlot {
            prior: MotionPrior {
                information,
                ..prior
            },
            cross: ZERO3,
        };
        self.prior_count += 1;
        Ok(())
    }

    /// Keyframes in the window.
    pub fn pose_count(&self) -> usize {
        self.pose_count
    }

    /// Landmarks in the window.
    pub fn landmark_count(&self) -> usize {
        self.landmark_count
    }

    /// Observations in the window.
    pub fn observation_count(&self) -> usize {
        self.observation_count
    }

    /// A keyframe's robot pose (the estimate after a solve).
    pub fn pose(&self, index: usize) -> Option<Se2> {
        self.live_poses().get(index).map(|p| p.pose)
    }

    /// A landmark's position (the estimate after a solve).
    pub fn landmark(&self, index: usize) -> Option<Vector3<f64>> {
        self.live_landmarks().get(index).map(|l| l.position)
    }

    /// What the last solve made of a landmark.
    pub fn landmark_report(&self, index: usize) -> Option<LandmarkReport> {
        let slot = self.live_landmarks().get(index)?;
        let mut report = LandmarkReport {
            position: slot.position,
            status: slot.status,
            observations: 0,
            outliers: 0,
            chi2: 0.0,
        };
        let mut o = slot.first_obs;
        while let Some(obs) = self.live_observations().get(o) {
            match obs.status {
                ObservationStatus::Inlier => report.observations += 1,
                ObservationStatus::Outlier => {
                    report.observations += 1;
                    report.outliers += 1;
                }
                _ => {}
            }
            report.chi2 += obs.chi2;
            o = obs.next;
        }
        Some(report)
    }

    /// What the last solve made of an observation (in the order of
    /// [`push_observation`](Self::push_observation)).
    pub fn observation_report(&self, index: usize) -> Option<ObservationReport> {
        self.live_observations()
            .get(index)
            .map(|o| ObservationReport {
                status: o.status,
                chi2: o.chi2,
            })
    }

    fn live_poses(&self) -> &[PoseSlot] {
        self.poses.get(..self.pose_count).unwrap_or(&[])
    }

    fn live_landmarks(&self) -> &[LandmarkSlot] {
        self.landmarks.get(..self.landmark_count).unwrap_or(&[])
    }

    fn live_observations(&self) -> &[ObservationSlot] {
        self.observations
            .get(..self.observation_count)
            .unwrap_or(&[])
    }

    /// Refines the keyframe poses (except the oldest `cfg.fixed_poses`) and the landmarks.
    ///
    /// The estimates are updated in place; the reports then tell which landmarks were set
    /// aside and which observations are outliers.
    ///
    /// # Errors
    /// [`WindowError::Empty`] without keyframes, [`WindowError::NoMeasurements`] when no
    /// usable observation nor prior remains. The estimates are left unchanged then.
    pub fn solve(
        &mut self,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        cfg: &WindowConfig,
    ) -> Result<WindowSummary, WindowError> {
        if self.pose_count == 0 {
            return Err(WindowError::Empty);
        }
        let fixed = cfg.fixed_poses.max(1);
        let used = self.prepare(model, mount, cfg);
        if used == 0 && self.prior_count == 0 {
            return Err(WindowError::NoMeasurements);
        }
        let initial_cost = self.cost(model, mount, cfg.huber).unwrap_or(f64::INFINITY);
        let (mut iterations, mut cost) = (0, initial_cost);
        let mut termination;
        // The Huber weights keep gross errors from dragging the first solution far; taking
        // them out entirely and solving again removes the pull they still have. A round
        // followed by another only has to tell the outliers apart, so it stops early; under
        // Huber weights the last digits come slowly.
        let mut round = 0;
        loop {
            let last = round == cfg.rejection_rounds;
            let round_cfg = WindowConfig {
                cost_tolerance: if last {
                    cfg.cost_tolerance
                } else {
                    cfg.rejection_cost_tolerance.max(cfg.cost_tolerance)
                },
                ..*cfg
            };
            let budget = cfg.max_iterations.saturating_sub(iterations);
            let (more, end, c) = self.iterate(model, mount, &round_cfg, fixed, cost, budget);
            iterations += more;
            termination = end;
            cost = c;
            // Without steps left, another round could only flip flags back and forth.
            if last || iterations >= cfg.max_iterations {
                break;
            }
            round += 1;
            if self.reclassify(model, mount, cfg.outlier_chi2) == 0 {
                // Nothing to take out: finish this round's solution instead.
                round = cfg.rejection_rounds;
                continue;
            }
            self.classify_landmarks(model, mount, cfg.min_pivot_ratio);
            cost = self.cost(model, mount, cfg.huber).unwrap_or(f64::INFINITY);
        }
        let (inliers, outliers) = self.flag(model, mount, cfg.outlier_chi2);
        let mut active = 0;
        let mut skipped = 0;
        for l in self.live_landmarks() {
            match l.status {
                LandmarkStatus::Active => active += 1,
                LandmarkStatus::TooFewViews | LandmarkStatus::NoParallax => skipped += 1,
                LandmarkStatus::Pending => {}
            }
        }
        Ok(WindowSummary {
            iterations,
            initial_cost,
            final_cost: cost,
            termination,
            active_landmarks: active,
            skipped_landmarks: skipped,
            inliers,
            outliers,
        })
    }

    /// Levenberg-Marquardt from the current estimates, whose cost is `cost`, for at most
    /// `budget` accepted steps. Returns the steps taken, how it ended and the final cost.
    fn iterate(
        &mut self,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        cfg: &WindowConfig,
        fixed: usize,
        mut cost: f64,
        budget: u32,
    ) -> (u32, Termination, f64) {
        let mut lambda = cfg.initial_lambda;
        let mut iterations = 0;
        while iterations < budget {
            self.linearize(model, mount, fixed, cfg.huber);
            // Raise the damping until a step lowers the cost.
            loop {
                let Some(step) = self.compute_step(fixed, lambda) else {
                    lambda *= 10.0;
                    if lambda > cfg.max_lambda {
                        return (iterations, Termination::NoDecrease, cost);
                    }
                    continue;
                };
                // A step at the tolerance is still taken if it lowers the cost: with exact
                // data the last step carries the solution from micrometres to round-off.
                let small = step <= cfg.step_tolerance;
                self.apply_step(fixed);
                match self.cost(model, mount, cfg.huber) {
                    Some(new_cost) if new_cost < cost => {
                        iterations += 1;
                        let decrease = cost - new_cost;
                        cost = new_cost;
                        lambda = (lambda * 0.1).max(MIN_LAMBDA);
                        if small || decrease <= cfg.cost_tolerance * cost {
                            return (iterations, Termination::Converged, cost);
                        }
                        break;
                    }
                    _ => {
                        self.restore(fixed);
                        if small {
                            return (iterations, Termination::Converged, cost);
                        }
                        lambda *= 10.0;
                        if lambda > cfg.max_lambda {
                            return (iterations, Termination::NoDecrease, cost);
                        }
                    }
                }
            }
        }
        (iterations, Termination::IterationLimit, cost)
    }

    fn refresh_trig(&mut self) {
        let n = self.pose_count;
        for p in self.poses.iter_mut().take(n) {
            p.cos = libm::cos(p.pose.theta);
            p.sin = libm::sin(p.pose.theta);
        }
    }

    /// Links each landmark's observations and drops those that do not project, then sets
    /// aside the landmarks whose depth the rest do not fix. Returns the observations used.
    fn prepare(
        &mut self,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        cfg: &WindowConfig,
    ) -> usize {
        self.refresh_trig();
        let (nl, no) = (self.landmark_count, self.observation_count);
        for l in self.landmarks.iter_mut().take(nl) {
            l.first_obs = NO_OBS;
            l.status = LandmarkStatus::Pending;
        }
        // Prepending in reverse keeps each list in the order of insertion.
        for i in (0..no).rev() {
            let Some(slot) = self.observations.get_mut(i) else {
                continue;
            };
            slot.chi2 = 0.0;
            slot.next = NO_OBS;
            let (k, l) = (slot.obs.keyframe, slot.obs.landmark);
            let (Some(pose), Some(lm)) = (self.poses.get(k), self.landmarks.get_mut(l)) else {
                slot.status = ObservationStatus::NotProjectable;
                continue;
            };
            let (p, c, s) = (&pose.pose, pose.cos, pose.sin);
            if residual(model, mount, p, (c, s), &lm.position, &slot.obs.px).is_none() {
                slot.status = ObservationStatus::NotProjectable;
                continue;
            }
            slot.status = ObservationStatus::Pending;
            slot.next = lm.first_obs;
            lm.first_obs = i;
        }
        self.classify_landmarks(model, mount, cfg.min_pivot_ratio)
    }

    /// Sets aside the landmarks not yet set aside whose observations in use (pending) do not
    /// fix their depth: fewer than two, or a block with a pivot below `ratio` of its scale.
    /// Their observations become [`ObservationStatus::Skipped`]. Returns the observations
    /// still in use.
    fn classify_landmarks(
        &mut self,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        ratio: f64,
    ) -> usize {
        self.refresh_trig();
        let mut used = 0;
        for l in 0..self.landmark_count {
            let Some(lm) = self.landmarks.get(l) else {
                continue;
            };
            let open = matches!(lm.status, LandmarkStatus::Pending | LandmarkStatus::Active);
            if !open {
                continue;
            }
            let (position, first) = (lm.position, lm.first_obs);
            let mut count = 0usize;
            let mut v = ZERO3;
            let mut o = first;
            while let Some(slot) = self.observations.get(o) {
                o = slot.next;
                if slot.status != ObservationStatus::Pending {
                    continue;
                }
                let Some(pose) = self.poses.get(slot.obs.keyframe) else {
                    continue;
                };
                let (p, c, s) = (&pose.pose, pose.cos, pose.sin);
                if let Some((_, _, jl)) =
                    reprojection(model, mount, p, (c, s), &position, &slot.obs.px)
                {
                    count += 1;
                    v += jl.transpose() * jl / (slot.obs.sigma_px * slot.obs.sigma_px);
                }
            }
            let status = if count < 2 {
                LandmarkStatus::TooFewViews
            } else if spd3_inverse(&v, ratio).is_none() {
                LandmarkStatus::NoParallax
            } else {
                used += count;
                LandmarkStatus::Active
            };
            if status != LandmarkStatus::Active {
                let mut o = first;
                while let Some(slot) = self.observations.get_mut(o) {
                    if slot.status == ObservationStatus::Pending {
                        slot.status = ObservationStatus::Skipped;
                    }
                    o = slot.next;
                }
            }
            if let Some(lm) = self.landmarks.get_mut(l) {
                lm.status = status;
            }
        }
        used
    }

    /// Takes out of use the observations whose chi2 at the current estimates is beyond
    /// `gate`, and puts back those taken out earlier that are now within it. Returns how many
    /// changed.
    fn reclassify(&mut self, model: &CameraModel, mount: &CameraExtrinsic, gate: f64) -> usize {
        self.refresh_trig();
        let mut changed = 0;
        let no = self.observation_count;
        for slot in self.observations.iter_mut().take(no) {
            let open = matches!(
                slot.status,
                ObservationStatus::Pending | ObservationStatus::Outlier
            );
            let (Some(pose), Some(lm)) = (
                self.poses.get(slot.obs.keyframe),
                self.landmarks.get(slot.obs.landmark),
            ) else {
                continue;
            };
            if !open || lm.status != LandmarkStatus::Active {
                continue;
            }
            let (p, c, s) = (&pose.pose, pose.cos, pose.sin);
            let lin = residual(model, mount, p, (c, s), &lm.position, &slot.obs.px);
            let chi2 = lin.map_or(f64::INFINITY, |r| {
                r.norm_squared() / (slot.obs.sigma_px * slot.obs.sigma_px)
            });
            let status = if chi2 <= gate {
                ObservationStatus::Pending
            } else {
                ObservationStatus::Outlier
            };
            if status != slot.status {
                changed += 1;
                slot.status = status;
            }
        }
        changed
    }

    /// The robust cost at the current estimates, or `None` when an observation in use no
    /// longer projects (a step that put a landmark behind a camera is refused).
    fn cost(&mut self, model: &CameraModel, mount: &CameraExtrinsic, k: f64) -> Option<f64> {
        self.refresh_trig();
        let mut total = 0.0;
        for slot in self.live_observations() {
            if slot.status != ObservationStatus::Pending {
                continue;
            }
            let pose = self.poses.get(slot.obs.keyframe)?;
            let lm = self.landmarks.get(slot.obs.landmark)?;
            let (p, c, s) = (&pose.pose, pose.cos, pose.sin);
            let r = residual(model, mount, p, (c, s), &lm.position, &slot.obs.px)?;
            let e2 = r.norm_squared() / (slot.obs.sigma_px * slot.obs.sigma_px);
            total += huber(e2, k).1;
        }
        for slot in self.priors.iter().take(self.prior_count) {
            let p = &slot.prior;
            let (from, to) = (self.poses.get(p.from)?, self.poses.get(p.to)?);
            let (e, _, _) = prior_residual(p, &from.pose, &to.pose);
            total += e.dot(&(p.information * e));
        }
        total.is_finite().then_some(total)
    }

    /// The normal equations at the current estimates: the pose blocks, the landmark blocks,
    /// the pose-landmark blocks per observation, and the priors' off-diagonal blocks.
    fn linearize(&mut self, model: &CameraModel, mount: &CameraExtrinsic, fixed: usize, k: f64) {
        self.refresh_trig();
        let (np, nl, no) = (self.pose_count, self.landmark_count, self.observation_count);
        for p in self.poses.iter_mut().take(np) {
            p.u = ZERO3;
            p.b = ZERO_V;
        }
        for l in self.landmarks.iter_mut().take(nl) {
            l.v = ZERO3;
            l.b = ZERO_V;
        }
        for slot in self.observations.iter_mut().take(no) {
            slot.w = ZERO3;
            if slot.status != ObservationStatus::Pending {
                continue;
            }
            let (kf, l) = (slot.obs.keyframe, slot.obs.landmark);
            let (Some(pose), Some(lm)) = (self.poses.get_mut(kf), self.landmarks.get_mut(l)) else {
                continue;
            };
            let (p, c, s) = (&pose.pose, pose.cos, pose.sin);
            let Some((r, jx, jl)) =
                reprojection(model, mount, p, (c, s), &lm.position, &slot.obs.px)
            else {
                // The cost was evaluated at this same point, so this does not happen; the
                // observation would simply contribute nothing.
                continue;
            };
            let inv_sigma = 1.0 / slot.obs.sigma_px;
            let (r, jx, jl) = (r * inv_sigma, jx * inv_sigma, jl * inv_sigma);
            let (w, _) = huber(r.norm_squared(), k);
            let jl_tw = jl.transpose() * w;
            lm.v += jl_tw * jl;
            lm.b -= jl_tw * r;
            if kf >= fixed {
                let jx_tw = jx.transpose() * w;
                pose.u += jx_tw * jx;
                pose.b -= jx_tw * r;
                slot.w = jx_tw * jl;
            }
        }
        for i in 0..self.prior_count {
            let Some(slot) = self.priors.get(i) else {
                continue;
            };
            let p = slot.prior;
            let (Some(from), Some(to)) = (self.poses.get(p.from), self.poses.get(p.to)) else {
                continue;
            };
            let (e, ja, jb) = prior_residual(&p, &from.pose, &to.pose);
            let (ja_to, jb_to) = (
                ja.transpose() * p.information,
                jb.transpose() * p.information,
            );
            if let Some(from) = self.poses.get_mut(p.from).filter(|_| p.from >= fixed) {
                from.u += ja_to * ja;
                from.b -= ja_to * e;
            }
            if let Some(to) = self.poses.get_mut(p.to).filter(|_| p.to >= fixed) {
                to.u += jb_to * jb;
                to.b -= jb_to * e;
            }
            if let Some(slot) = self.priors.get_mut(i) {
                slot.cross = ja_to * jb;
            }
        }
    }

    /// Solves the damped normal equations by eliminating the landmarks; leaves the steps in
    /// the slots and returns the largest of them, or `None` when a block or the reduced
    /// system is not positive definite at this damping.
    fn compute_step(&mut self, fixed: usize, lambda: f64) -> Option<f64> {
        let np = self.pose_count;
        let free = np.saturating_sub(fixed);
        for row in self.reduced.iter_mut().take(free) {
            for block in row.iter_mut().take(free) {
                *block = ZERO3;
            }
        }
        for f in 0..free {
            let pose = self.poses.get(f + fixed)?;
            *self.reduced.get_mut(f)?.get_mut(f)? = damped(&pose.u, lambda);
            *self.reduced_rhs.get_mut(f)? = pose.b;
        }
        // The factorisation reads only the blocks on and below the diagonal: only those are
        // formed, which halves the landmark pairs below.
        for slot in self.priors.iter().take(self.prior_count) {
            let (a, b) = (slot.prior.from, slot.prior.to);
            if a >= fixed && b >= fixed {
                let (a, b) = (a - fixed, b - fixed);
                if a > b {
                    *self.reduced.get_mut(a)?.get_mut(b)? += slot.cross;
                } else {
                    *self.reduced.get_mut(b)?.get_mut(a)? += slot.cross.transpose();
                }
            }
        }
        for l in 0..self.landmark_count {
            let lm = self.landmarks.get_mut(l)?;
            if lm.status != LandmarkStatus::Active {
                continue;
            }
            // The damping itself keeps the block invertible; only a breakdown is refused.
            lm.v_inv = spd3_inverse(&damped(&lm.v, lambda), 0.0)?;
            let (v_inv, b_l, first) = (lm.v_inv, lm.b, lm.first_obs);
            let mut a = first;
            while let Some(oa) = self.observations.get(a) {
                if oa.status == ObservationStatus::Pending && oa.obs.keyframe >= fixed {
                    let ka = oa.obs.keyframe - fixed;
                    let t = oa.w * v_inv;
                    *self.reduced_rhs.get_mut(ka)? -= t * b_l;
                    let mut b = first;
                    while let Some(ob) = self.observations.get(b) {
                        let lower = ob.obs.keyframe >= fixed && ob.obs.keyframe - fixed <= ka;
                        if ob.status == ObservationStatus::Pending && lower {
                            let kb = ob.obs.keyframe - fixed;
                            *self.reduced.get_mut(ka)?.get_mut(kb)? -= t * ob.w.transpose();
                        }
                        b = ob.next;
                    }
                }
                a = oa.next;
            }
        }
        dense::cholesky_solve(&mut self.reduced, &mut self.reduced_rhs, free)?;
        let mut largest = 0.0f64;
        for p in self.poses.iter_mut().take(fixed.min(np)) {
            p.step = ZERO_V;
        }
        for f in 0..free {
            let step = *self.reduced_rhs.get(f)?;
            largest = largest.max(step.amax());
            self.poses.get_mut(f + fixed)?.step = step;
        }
        // Back-substitution: each landmark's step given the poses'.
        for l in 0..self.landmark_count {
            let lm = self.landmarks.get(l)?;
            if lm.status != LandmarkStatus::Active {
                continue;
            }
            let mut rhs = lm.b;
            let mut o = lm.first_obs;
            while let Some(slot) = self.observations.get(o) {
                if slot.status == ObservationStatus::Pending {
                    if let Some(pose) = self.poses.get(slot.obs.keyframe) {
                        rhs -= slot.w.transpose() * pose.step;
                    }
                }
                o = slot.next;
            }
            let lm = self.landmarks.get_mut(l)?;
            lm.step = lm.v_inv * rhs;
            largest = largest.max(lm.step.amax());
        }
        largest.is_finite().then_some(largest)
    }

    fn apply_step(&mut self, fixed: usize) {
        let np = self.pose_count;
        for p in self.poses.iter_mut().take(np).skip(fixed) {
            p.backup = p.pose;
            p.pose = Se2::new(
                p.pose.x + p.step.x,
                p.pose.y + p.step.y,
                p.pose.theta + p.step.z,
            );
        }
        let nl = self.landmark_count;
        for l in self.landmarks.iter_mut().take(nl) {
            l.backup = l.position;
            if l.status == LandmarkStatus::Active {
                l.position += l.step;
            }
        }
    }

    fn restore(&mut self, fixed: usize) {
        let (np, nl) = (self.pose_count, self.landmark_count);
        for p in self.poses.iter_mut().take(np).skip(fixed) {
            p.pose = p.backup;
        }
        for l in self.landmarks.iter_mut().take(nl) {
            l.position = l.backup;
        }
    }

    /// Each used observation's chi2 at the result and its inlier flag; returns the counts.
    fn flag(&mut self, model: &CameraModel, mount: &CameraExtrinsic, gate: f64) -> (usize, usize) {
        self.refresh_trig();
        let (mut inliers, mut outliers) = (0, 0);
        let no = self.observation_count;
        for slot in self.observations.iter_mut().take(no) {
            let in_use = matches!(
                slot.status,
                ObservationStatus::Pending | ObservationStatus::Inlier | ObservationStatus::Outlier
            );
            if !in_use {
                continue;
            }
            let (Some(pose), Some(lm)) = (
                self.poses.get(slot.obs.keyframe),
                self.landmarks.get(slot.obs.landmark),
            ) else {
                continue;
            };
            // A landmark set aside in a later round takes its rejected observations along.
            if lm.status != LandmarkStatus::Active {
                slot.status = ObservationStatus::Skipped;
                continue;
            }
            let (p, c, s) = (&pose.pose, pose.cos, pose.sin);
            let lin = residual(model, mount, p, (c, s), &lm.position, &slot.obs.px);
            let chi2 = lin.map_or(f64::INFINITY, |r| {
                r.norm_squared() / (slot.obs.sigma_px * slot.obs.sigma_px)
            });
            slot.chi2 = chi2;
            if chi2 <= gate {
                slot.status = ObservationStatus::Inlier;
                inliers += 1;
            } else {
                slot.status = ObservationStatus::Outlier;
                outliers += 1;
            }
        }
        (inliers, outliers)
    }
}
