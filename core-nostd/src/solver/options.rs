//! What a solve is asked (method, tolerances, robust gating) and what it reports, including
//! the ways it can fail.

use core::fmt;

use crate::storage::NodeId;

/// The iteration scheme.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Method {
    /// Undamped Gauss-Newton.
    GaussNewton,
    /// Levenberg-Marquardt with Nielsen's damping update.
    LevenbergMarquardt,
    /// Gauss-Newton, checked by a chi2 test: when it fails (diverges, meets a singular system,
    /// or converges to a chi2 above the 99.9 % quantile of its degrees of freedom, the sign of a
    /// wrong basin), Levenberg-Marquardt runs again from the initial guess (no linear
    /// initialisation, damping [`AUTO_LM_TAU`]) and the lower chi2 is kept. Graphs with robust
    /// kernels, stages or a warm start are solved by Gauss-Newton alone.
    Auto,
}

/// Levenberg-Marquardt's initial damping in the fallback of [`Method::Auto`].
pub const AUTO_LM_TAU: f64 = 1e-3;

/// Options of [`solve`](super::solve).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SolverOptions {
    /// Iteration scheme.
    pub method: Method,
    /// Most linear solves.
    pub max_iterations: u32,
    /// Converged when one iteration lowers the cost by less than this fraction.
    pub relative_tolerance: f64,
    /// Converged when no step component exceeds this (metres / radians).
    pub step_tolerance: f64,
    /// Gauss-Newton diverged when the cost exceeds this multiple of the initial cost.
    pub divergence_factor: f64,
    /// Before iterating, re-estimate every heading, then every position, from one linear
    /// solve each (a LAGO-style initialisation from the given guess). It removes the bad
    /// basins that odometry guesses lead Gauss-Newton into, at the price of two extra
    /// factorizations; the robust weights of the initial guess apply. Only without stages.
    pub linear_init: bool,
    /// Gauss-Newton in this many stages over the node order: stage `s` of `S` lets only loop
    /// closures among the first `s/S` of the nodes act (later nodes follow their odometry), so
    /// every new loop is judged against a map that is already consistent, as an online mapper
    /// would. This is what lets max-mixtures start from a drifted odometry guess. 1: batch.
    pub stages: u32,
    /// Most Gauss-Newton iterations of each stage but the last, and of the gated warm start.
    pub stage_iterations: u32,
    /// Warm start of max-mixture loops: when positive, each max-mixture loop closure is first
    /// tested against the odometry chain's prediction and its covariance (module `gate`,
    /// chi2 threshold with 3 degrees of freedom, e.g. 16.27 for 99.9 %), and the solve starts
    /// with the phases described there. 0 disables it (Gauss-Newton only).
    pub gate_chi2: f64,
    /// Levenberg-Marquardt's initial damping, as a fraction of the largest diagonal entry of
    /// `H`.
    pub lm_tau: f64,
}

impl Default for SolverOptions {
    fn default() -> Self {
        SolverOptions {
            method: Method::GaussNewton,
            max_iterations: 100,
            relative_tolerance: 1e-8,
            step_tolerance: 1e-10,
            divergence_factor: 1e6,
            linear_init: true,
            stages: 1,
            stage_iterations: 10,
            gate_chi2: 0.0,
            lm_tau: 1e-5,
        }
    }
}

/// What a solve did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SolveReport {
    /// Linear solves performed.
    pub iterations: u32,
    /// Robust cost at the start.
    pub initial_cost: f64,
    /// Robust cost at the end.
    pub final_cost: f64,
    /// Sum of `e^T Omega e` over all edges at the start (robust models ignored).
    pub initial_chi2: f64,
    /// The same at the end.
    pub final_chi2: f64,
    /// Whether a stopping rule other than the iteration limit ended the solve.
    pub converged: bool,
    /// Free nodes (variables).
    pub variables: usize,
    /// Off-diagonal 3x3 blocks of the factor.
    pub factor_blocks: usize,
    /// Whether this solve had to compute the ordering.
    pub analyzed: bool,
    /// Max-mixture loop closures that the warm start used: they passed the odometry gate and
    /// have consistent neighbours.
    pub gated_loops: usize,
    /// Max-mixture edges on a component other than the nominal one at the end (rejected).
    pub rejected_loops: usize,
}

/// Why a solve failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SolveError {
    /// The graph, or its factor, does not fit the workspace.
    Capacity {
        /// `"nodes"`, `"edges"` or `"factor blocks"`.
        what: &'static str,
        /// The workspace's capacity.
        capacity: usize,
    },
    /// An edge names a node outside the graph.
    InvalidGraph,
    /// The system is not positive definite at this node (a node without constraints, or a
    /// degenerate information matrix) even with damping.
    NotPositiveDefinite(NodeId),
    /// The cost became non-finite or grew beyond the divergence limit.
    Diverged,
    /// The iteration limit was reached before a stopping rule held.
    MaxIterations,
}

impl fmt::Display for SolveError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SolveError::Capacity { what, capacity } => {
                write!(f, "the solver workspace holds at most {capacity} {what}")
            }
            SolveError::InvalidGraph => write!(f, "an edge refers to a node outside the graph"),
            SolveError::NotPositiveDefinite(n) => {
                write!(f, "the system is not positive definite at node {}", n.0)
            }
            SolveError::Diverged => write!(f, "the optimization diverged"),
            SolveError::MaxIterations => write!(f, "the iteration limit was reached"),
        }
    }
}

impl core::error::Error for SolveError {}

/// A failed solve: the error and what was done up to it (the graph holds the last estimate).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SolveFailure {
    /// Why it failed.
    pub error: SolveError,
    /// The report up to the failure.
    pub report: SolveReport,
}

impl fmt::Display for SolveFailure {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} after {} iterations (chi2 {:.6})",
            self.error, self.report.iterations, self.report.final_chi2
        )
    }
}

impl core::error::Error for SolveFailure {}
