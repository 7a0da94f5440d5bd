//! What goes into a window and what comes out: observations, priors, the configuration, the
//! errors, the summary of a solve and the reports per landmark and observation.

use super::*;

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
