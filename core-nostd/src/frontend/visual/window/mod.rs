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
//!
//! Files: `types` (inputs, configuration, errors, reports), `residual` (the residuals and the
//! small blocks the solve inverts), `solve` (the iterations), `dense` (the reduced system's
//! Cholesky).

use core::fmt;

use nalgebra::{Matrix2x3, Matrix3, Vector2, Vector3};

use super::camera::{CameraExtrinsic, CameraModel};
use crate::geom::{wrap_angle, Se2};

mod dense;
mod residual;
mod solve;
mod types;

use residual::*;
pub use types::*;
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
}
