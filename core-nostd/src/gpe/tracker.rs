//! The per-frame GPE update (the paper's eqs. 3-5): the real-time global pose from the
//! prediction, the reference node and the anchor node, or the worst-case prediction.
//!
//! The terms of the problem ([`super::problem`]):
//! * the **prediction**: the previous real-time pose composed with the front-end's motion since
//!   the previous frame (the motion model), with the motion's covariance plus process noise and
//!   no robust kernel;
//! * the **reference term**: the reference node's current estimate composed with the
//!   front-end's motion since that node, with the covariance compounded since it plus a floor
//!   for the node's own uncertainty (the paper's odometry residual `zeta_k`);
//! * the **anchor term**: the same for the anchor node ([`super::anchor`]) when it is not the
//!   reference (`alpha_k`).
//!
//! Without a previous frame or a graph node the prediction is the pose; when the caller says
//! the deadline passed, or the solver does not converge, it is the worst-case prediction.

use super::predict::worst_case;
use super::problem::{inflate, solve, GpeConfig, PoseTerm, MAX_TERMS};
use crate::frontend::lidar::{MotionNoise, Travel};
use crate::geom::Se2;

/// A frame node the real-time pose is tied to.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NodeTie {
    /// The node's current global estimate.
    pub estimate: Se2,
    /// Its front-end pose.
    pub frontend: Se2,
    /// The front-end travel when it was taken.
    pub travel: Travel,
}

/// What the GPE needs of one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GpeFrame {
    /// Front-end motion since the previous frame.
    pub step: Se2,
    /// Front-end pose of the frame.
    pub frontend: Se2,
    /// Front-end travel up to the frame.
    pub travel: Travel,
    /// The reference node (the newest frame node), if the graph has one.
    pub reference: Option<NodeTie>,
    /// The anchor node, when there is one apart from the reference.
    pub anchor: Option<NodeTie>,
    /// The caller's time for this frame is up: predict instead of solving.
    pub deadline_passed: bool,
}

/// The real-time pose of a frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RealTimePose {
    /// Global pose.
    pub pose: Se2,
    /// The pose is the worst-case prediction (deadline passed or no convergence).
    pub predicted: bool,
}

/// Counters of the GPE.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GpeCounters {
    /// Updates solved.
    pub solved: u32,
    /// Frames that used the worst-case prediction.
    pub predicted: u32,
}

/// The GPE's state from frame to frame.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GpeTracker {
    previous: Option<Se2>,
    anchor: Option<u32>,
    counters: GpeCounters,
}

impl GpeTracker {
    /// The state before the first frame.
    pub const fn new() -> Self {
        GpeTracker {
            previous: None,
            anchor: None,
            counters: GpeCounters {
                solved: 0,
                predicted: 0,
            },
        }
    }

    /// Serial of the anchor node, once an optimization has finished.
    pub fn anchor(&self) -> Option<u32> {
        self.anchor
    }

    /// Sets the anchor (after an optimization).
    pub fn set_anchor(&mut self, serial: Option<u32>) {
        self.anchor = serial;
    }

    /// Continues from `pose` as if it had been the previous frame's real-time pose (the
    /// localization-only mode, where a confirmed match with the map moves the pose at once).
    pub fn restart_at(&mut self, pose: Se2) {
        self.previous = Some(pose);
    }

    /// Counters so far.
    pub fn counters(&self) -> GpeCounters {
        self.counters
    }

    /// The real-time pose of `frame`.
    pub fn update(
        &mut self,
        frame: &GpeFrame,
        config: &GpeConfig,
        noise: &impl MotionNoise,
    ) -> RealTimePose {
        let out = self.estimate(frame, config, noise);
        self.previous = Some(out.pose);
        out
    }

    fn estimate(
        &mut self,
        frame: &GpeFrame,
        config: &GpeConfig,
        noise: &impl MotionNoise,
    ) -> RealTimePose {
        let previous = self.previous.unwrap_or(Se2::IDENTITY);
        let prediction = worst_case(&previous, &frame.step);
        let (Some(reference), Some(_)) = (frame.reference, self.previous) else {
            return RealTimePose {
                pose: prediction,
                predicted: false,
            };
        };
        if frame.deadline_passed {
            return self.predicted(prediction);
        }
        let step = &frame.step;
        let distance = libm::sqrt(step.x * step.x + step.y * step.y);
        let mut cov = noise.covariance(distance, step.theta);
        inflate(&mut cov, config.process_sigma);
        let mut terms = heapless::Vec::<PoseTerm, MAX_TERMS>::new();
        // At most three terms: the pushes cannot fail.
        let _ = terms.push(PoseTerm::from_local(prediction, &cov, f64::INFINITY));
        for node in [Some(reference), frame.anchor].into_iter().flatten() {
            let relative = node.frontend.between(&frame.frontend);
            let mut c = noise.over(&frame.travel.since(&node.travel));
            inflate(&mut c, config.node_sigma);
            let target = node.estimate.compose(&relative);
            let _ = terms.push(PoseTerm::from_local(target, &c, config.huber));
        }
        match solve(&terms, config) {
            Some(s) if s.converged => {
                self.counters.solved += 1;
                RealTimePose {
                    pose: s.pose,
                    predicted: false,
                }
            }
            _ => self.predicted(prediction),
        }
    }

    fn predicted(&mut self, prediction: Se2) -> RealTimePose {
        self.counters.predicted += 1;
        RealTimePose {
            pose: prediction,
            predicted: true,
        }
    }
}
