//! Nonlinear least squares on a [`PoseGraph`]: Gauss-Newton and Levenberg-Marquardt over a
//! sparse block Cholesky factorization, with robust kernels and max-mixtures (the optimization
//! step of the paper's back-end, its eq. 10).
//!
//! Per solve:
//! 1. **Analyse** (only when the graph's structure changed since the last solve with this
//!    workspace): number the free nodes, order them by minimum degree, record the factor's
//!    block pattern and where every edge's block goes (module `ordering`).
//! 2. **Iterate**: pick robust weights and max-mixture components at the current estimate,
//!    assemble `H dx = -g` directly into the factor's storage, factorize (module `cholesky`), solve,
//!    update `x += dx` (angles wrapped).
//!
//! Gauge: the first node is held fixed unless the graph has a prior edge; nodes flagged
//! `fixed` never move.
//!
//! Robust solves: max-mixture edges whose chosen component scales their information below
//! [`INACTIVE_SCALE`] are left out of the linear system (and out of the factor's pattern, which
//! is re-analysed when that set changes), so rejected loop closures cost no fill. With
//! `gate_chi2 > 0` a max-mixture solve starts with the warm start of module `gate`, which is
//! what lets it begin from a drifted odometry guess: only loops that pass the odometry gate
//! and agree with neighbouring loops act at first; every other loop must then be consistent
//! with the solved map (its chi2 below the gate, scaled by the variance of unit weight, or else
//! its normalized innovation with the map's own uncertainty) before its max-mixture may take
//! the nominal component. Random false loops thus never enter the factor, which stays as
//! sparse as the true loops make it (1,000 false loops on manhattanOlson3500 cost no fill).
//!
//! Stopping rules (`cost` is the robust cost, equal to the chi2 without robust models):
//! * **Gauss-Newton**: converged when an iteration lowers the cost by less than
//!   `relative_tolerance * cost` (an increase counts as not converged), or when the largest
//!   step component is below `step_tolerance`. Diverged when the cost becomes non-finite or
//!   exceeds `divergence_factor` times the initial cost.
//! * **Levenberg-Marquardt** (Nielsen's damping update, `H + lambda I`, `lambda` starting at
//!   `1e-5 * max diag(H)`): a step is kept only if it lowers the cost; converged when an
//!   accepted step lowers the cost by less than `relative_tolerance * cost`, when the step is
//!   below `step_tolerance`, or when ten consecutive steps are rejected (no descent left at
//!   this precision).
//! * Either way `max_iterations` linear solves are the limit; reaching it without convergence
//!   is [`SolveError::MaxIterations`]. The graph always holds the last (best, for LM) estimate.

mod cholesky;
mod gate;
mod linearize;
mod marginals;
mod ordering;
mod workspace;

pub use marginals::marginal_information_traces;
pub use workspace::{AnalysisKey, Block, SolverBuffers, SolverWorkspace, Vec3};

use core::fmt;

use crate::geom::wrap_angle;
use crate::graph::{PoseEdge, PoseGraph, PoseNode, RobustKernel};
use crate::storage::NodeId;
use linearize::Warm;

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

/// Options of [`solve`].
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

/// Optimizes the poses of `graph` in place.
///
/// # Errors
/// [`SolveFailure`] with the [`SolveError`] and the report so far; the graph then holds the
/// last estimate (for Levenberg-Marquardt, the best one).
pub fn solve(
    graph: &mut PoseGraph<'_>,
    ws: &mut SolverBuffers<'_>,
    options: &SolverOptions,
) -> Result<SolveReport, SolveFailure> {
    let mut report = SolveReport::default();
    let fail = |error, report| Err(SolveFailure { error, report });
    let (nodes, edges) = graph.split_mut();
    let n = nodes.len();
    let node_lens = [
        ws.node_var.len(),
        ws.var_node.len(),
        ws.col_end.len(),
        ws.diag.len(),
        ws.work.len(),
        ws.rhs.len(),
        ws.step.len(),
        ws.saved.len(),
    ];
    if node_lens
        .iter()
        .chain(
            ws.scratch
                .iter()
                .map(|s| s.len())
                .collect::<Lens>()
                .0
                .iter(),
        )
        .any(|&l| l < n)
    {
        return fail(
            SolveError::Capacity {
                what: "nodes",
                capacity: ws.node_capacity(),
            },
            report,
        );
    }
    if edges.len() > ws.edge_slot.len() || edges.len() > ws.edge_trig.len() {
        return fail(
            SolveError::Capacity {
                what: "edges",
                capacity: ws.edge_capacity(),
            },
            report,
        );
    }
    if ws.values.len() < ws.rows.len() {
        return fail(
            SolveError::Capacity {
                what: "factor blocks",
                capacity: ws.values.len(),
            },
            report,
        );
    }
    for e in edges.iter() {
        if e.from.0 as usize >= nodes.len() || e.to.0 as usize >= nodes.len() {
            return fail(SolveError::InvalidGraph, report);
        }
    }

    if edges.len() > ws.edge_flags.len() {
        return fail(
            SolveError::Capacity {
                what: "edges",
                capacity: ws.edge_flags.len(),
            },
            report,
        );
    }
    for (t, e) in ws.edge_trig.iter_mut().zip(edges.iter()) {
        *t = [
            libm::cos(e.measurement.theta),
            libm::sin(e.measurement.theta),
        ];
    }
    let n = nodes.len();
    let stages = options.stages.max(1) as usize;
    let first_limit = if stages > 1 { n / stages } else { n };

    // 1. Structure.
    let gauge_first = ordering::gauge_fixes_first(edges);
    let gated = options.gate_chi2 > 0.0
        && edges
            .iter()
            .any(|e| matches!(e.robust, RobustKernel::MaxMixture { .. }));
    if gated {
        gate::gate_loops(n, edges, ws, options.gate_chi2);
        report.gated_loops = gate::support_loops(n, edges, ws, options.gate_chi2);
    }
    let warm0 = if gated { Warm::Nominal } else { Warm::Off };
    if let Err(e) = refresh_structure(
        nodes,
        edges,
        ws,
        gauge_first,
        first_limit,
        warm0,
        &mut report,
    ) {
        return fail(e, report);
    }
    let vars = ws.key.vars;
    let auto = options.method == Method::Auto
        && !gated
        && stages == 1
        && edges.iter().all(|e| e.robust == RobustKernel::None);
    if auto {
        // The initial guess, for the fallback (Gauss-Newton leaves `step` alone).
        for (s, node) in ws.step.iter_mut().zip(nodes.iter()) {
            *s = [node.pose.x, node.pose.y, node.pose.theta];
        }
    }

    // 2. Iterations.
    let (cost0, chi0) =
        linearize::evaluate(nodes, edges, ws.edge_trig, n, Warm::Off, ws.edge_flags);
    report.initial_cost = cost0;
    report.initial_chi2 = chi0;
    report.final_cost = cost0;
    report.final_chi2 = chi0;
    if !cost0.is_finite() {
        return fail(SolveError::Diverged, report);
    }
    if vars == 0 {
        report.converged = true;
        return Ok(report);
    }
    if options.linear_init && stages == 1 {
        for stage in [linearize::Stage::Headings, linearize::Stage::Positions] {
            if let Err(e) = linear_step(nodes, edges, ws, 0.0, false, stage, warm0, 0.0) {
                return fail(e, report);
            }
            apply_step(nodes, ws.var_node, ws.rhs, vars);
        }
        let (c, x) = linearize::evaluate(nodes, edges, ws.edge_trig, n, Warm::Off, ws.edge_flags);
        report.final_cost = c;
        report.final_chi2 = x;
        if !c.is_finite() {
            return fail(SolveError::Diverged, report);
        }
    }
    if gated {
        // Warm start: a few iterations with the gated and mutually supported loops on their
        // nominal component (this closes large loops that odometry drift hides), then dynamic
        // covariance scaling over the same loops until it settles; the free max-mixture phase
        // with its admission gate and innovation tests follows.
        for (warm, cap) in [
            (Warm::Nominal, options.stage_iterations),
            (Warm::Dcs, options.max_iterations),
        ] {
            let r = gauss_newton(
                nodes,
                edges,
                ws,
                options,
                &mut report,
                n,
                cap.min(options.max_iterations),
                gauge_first,
                warm,
            );
            match r {
                Ok(()) | Err(SolveError::MaxIterations) => {}
                Err(e) => return fail(e, report),
            }
        }
    }
    // After a warm start, loops it did not use must be consistent with the map at the gate's
    // confidence before their max-mixture may pick the nominal component.
    // The gate is scaled by the variance of unit weight of the warm start's solution (never
    // above 1): when the data fit their information better than it claims, a loop has to fit
    // as well as the rest does.
    let free = if gated {
        Warm::Admit(options.gate_chi2 * gate::unit_variance(nodes, edges, ws))
    } else {
        Warm::Off
    };
    let result = match options.method {
        Method::GaussNewton | Method::Auto => {
            let mut r = Ok(());
            for stage in 1..=stages {
                let limit = n * stage / stages;
                let last = stage == stages;
                let cap = if last {
                    options.max_iterations
                } else {
                    options.stage_iterations
                };
                r = gauss_newton(
                    nodes,
                    edges,
                    ws,
                    options,
                    &mut report,
                    limit,
                    cap,
                    gauge_first,
                    free,
                );
                match r {
                    Err(SolveError::MaxIterations) if !last => r = Ok(()),
                    Err(_) => break,
                    Ok(()) => {}
                }
            }
            // Loops held back by the admission gate get the exact test: their normalized
            // innovation, with the map's own uncertainty between their ends. Each round that
            // admits a loop solves again.
            for _ in 0..ADMISSION_ROUNDS {
                if !gated || !matches!(r, Ok(()) | Err(SolveError::MaxIterations)) {
                    break;
                }
                let Warm::Admit(limit) = free else {
                    break;
                };
                if gate::admit_by_innovation(nodes, edges, ws, limit) == 0 {
                    break;
                }
                r = gauss_newton(
                    nodes,
                    edges,
                    ws,
                    options,
                    &mut report,
                    n,
                    options.max_iterations,
                    gauge_first,
                    free,
                );
            }
            r
        }
        Method::LevenbergMarquardt => levenberg_marquardt(
            nodes,
            edges,
            ws,
            options,
            &mut report,
            options.max_iterations,
        ),
    };
    let result = if auto && !passes_chi2_test(nodes, edges, ws, &result) {
        auto_fallback(nodes, edges, ws, options, &mut report, result)
    } else {
        result
    };
    let (c, x) = linearize::evaluate(nodes, edges, ws.edge_trig, n, free, ws.edge_flags);
    report.final_cost = c;
    report.final_chi2 = x;
    report.factor_blocks = ws.key.nnz;
    report.rejected_loops = edges
        .iter()
        .zip(ws.edge_trig.iter())
        .zip(ws.edge_flags.iter())
        .filter(|((e, t), &f)| {
            matches!(e.robust, RobustKernel::MaxMixture { .. })
                && linearize::edge_residual(nodes, e, t)
                    .is_none_or(|r| linearize::weigh(e, e.chi2_of(&r), free, f).0 < 1.0)
        })
        .count();
    match result {
        Ok(()) => Ok(report),
        Err(error) => fail(error, report),
    }
}

/// Most rounds of innovation tests (and re-solves) after a gated max-mixture solve.
const ADMISSION_ROUNDS: u32 = 8;

/// Most step halvings of one Gauss-Newton iteration.
const MAX_HALVINGS: u32 = 8;
/// Iterations after which a change of the active edge set no longer blocks convergence.
const SETTLE_ITERATIONS: u32 = 8;

/// A max-mixture edge whose chosen component scales its information below this takes no part
/// in the linear system: its block would change `H` by less than this fraction, and leaving it
/// out keeps the factor as sparse as the accepted loops alone make it.
pub const INACTIVE_SCALE: f64 = 1e-3;

/// Marks which edges take part in the linear system at the current estimate (loops within
/// `limit`, max-mixture edges on a component of useful weight) and analyses the structure again
/// when that set or the graph changed. Returns whether the set changed.
fn refresh_structure(
    nodes: &[PoseNode],
    edges: &[PoseEdge],
    ws: &mut SolverBuffers<'_>,
    gauge_first: bool,
    limit: usize,
    warm: Warm,
    report: &mut SolveReport,
) -> Result<bool, SolveError> {
    let mut changed = false;
    for ((flag, e), t) in ws.edge_flags.iter_mut().zip(edges).zip(ws.edge_trig.iter()) {
        let mut active = linearize::within(e, limit);
        if matches!(warm, Warm::Nominal | Warm::Dcs) {
            active &= *flag & gate::GATE_PASSED != 0;
        } else if active && matches!(e.robust, RobustKernel::MaxMixture { .. }) {
            let chi2 = linearize::edge_residual(nodes, e, t)
                .map(|r| e.chi2_of(&r))
                .unwrap_or(f64::INFINITY);
            active = linearize::weigh(e, chi2, warm, *flag).0 >= INACTIVE_SCALE;
        }
        let f = active as u8;
        changed |= *flag & 1 != f;
        *flag = (*flag & !1) | f;
    }
    let fp = ordering::fingerprint(nodes, edges, ws.edge_flags, gauge_first);
    let key = *ws.key;
    if !(key.valid && key.nodes == nodes.len() && key.edges == edges.len() && key.fingerprint == fp)
    {
        ws.key.valid = false;
        ordering::analyze(nodes, edges, gauge_first, ws)?;
        ws.key.nodes = nodes.len();
        ws.key.edges = edges.len();
        ws.key.fingerprint = fp;
        ws.key.valid = true;
        report.analyzed = true;
        report.variables = ws.key.vars;
        report.factor_blocks = ws.key.nnz;
    }
    Ok(changed)
}

/// The lengths of the scratch arrays.
struct Lens([usize; 6]);

impl FromIterator<usize> for Lens {
    fn from_iter<T: IntoIterator<Item = usize>>(iter: T) -> Self {
        let mut out = [0; 6];
        for (o, v) in out.iter_mut().zip(iter) {
            *o = v;
        }
        Lens(out)
    }
}

/// Assembles at the current estimate, adds `lambda` to the diagonal (a negative `lambda` means
/// `1e-5` times the largest diagonal entry of `H`), factorizes and solves; the step is left in
/// `ws.rhs` (by position). Returns the robust cost and chi2 at the estimate and the damping
/// used.
#[allow(clippy::too_many_arguments)]
fn linear_step(
    nodes: &[PoseNode],
    edges: &[PoseEdge],
    ws: &mut SolverBuffers<'_>,
    lambda: f64,
    saved_rhs: bool,
    stage: linearize::Stage,
    warm: Warm,
    tau: f64,
) -> Result<(f64, f64, f64), SolveError> {
    let vars = ws.key.vars;
    let nnz = ws.key.nnz;
    let (cost, chi2) = linearize::assemble(
        nodes,
        edges,
        vars,
        nnz,
        stage,
        &mut linearize::System {
            node_var: ws.node_var,
            flags: ws.edge_flags,
            warm,
            edge_slot: ws.edge_slot,
            trig: ws.edge_trig,
            diag: ws.diag,
            values: ws.values,
            rhs: ws.rhs,
        },
    );
    let mut lambda = lambda;
    if lambda < 0.0 {
        let mut max_diag: f64 = 0.0;
        for d in ws.diag.iter().take(vars) {
            max_diag = max_diag.max(d[0]).max(d[4]).max(d[8]);
        }
        lambda = tau * max_diag.max(1e-12);
    }
    for d in ws.diag.iter_mut().take(vars) {
        if lambda > 0.0 {
            d[0] += lambda;
            d[4] += lambda;
            d[8] += lambda;
        }
    }
    if saved_rhs {
        // Keep -g for the gain ratio of Levenberg-Marquardt.
        ws.step[..vars].copy_from_slice(&ws.rhs[..vars]);
    }
    let [row_head, link, cursor, ..] = &mut ws.scratch;
    if let Err(col) = cholesky::factorize(
        vars, ws.col_end, ws.rows, ws.values, ws.diag, ws.work, row_head, link, cursor,
    ) {
        let node = ws.var_node.get(col).copied().unwrap_or(0);
        return Err(SolveError::NotPositiveDefinite(NodeId(node)));
    }
    cholesky::solve_in_place(vars, ws.col_end, ws.rows, ws.values, ws.diag, ws.rhs);
    Ok((cost, chi2, lambda))
}

/// `x += dx` for every free node; returns the largest step component.
fn apply_step(nodes: &mut [PoseNode], var_node: &[u32], dx: &[Vec3], vars: usize) -> f64 {
    let mut largest: f64 = 0.0;
    for (pos, d) in dx.iter().enumerate().take(vars) {
        if let Some(n) = var_node.get(pos).and_then(|&i| nodes.get_mut(i as usize)) {
            n.pose.x += d[0];
            n.pose.y += d[1];
            n.pose.theta = wrap_angle(n.pose.theta + d[2]);
            largest = largest
                .max(libm::fabs(d[0]))
                .max(libm::fabs(d[1]))
                .max(libm::fabs(d[2]));
        }
    }
    if largest.is_finite() {
        largest
    } else {
        f64::INFINITY
    }
}

#[allow(clippy::too_many_arguments)]
fn gauss_newton(
    nodes: &mut [PoseNode],
    edges: &[PoseEdge],
    ws: &mut SolverBuffers<'_>,
    options: &SolverOptions,
    report: &mut SolveReport,
    limit: usize,
    max_iterations: u32,
    gauge_first: bool,
    warm: Warm,
) -> Result<(), SolveError> {
    let vars = ws.key.vars;
    let bound = options.divergence_factor * report.initial_cost.max(1.0);
    // Max-mixture costs are not smooth: switching components makes a full step raise the cost
    // on the way to a better basin, so steps are not halved there.
    let mixtures = edges
        .iter()
        .any(|e| matches!(e.robust, RobustKernel::MaxMixture { .. }));
    let (mut cost, _) = linearize::evaluate(nodes, edges, ws.edge_trig, limit, warm, ws.edge_flags);
    let mut done = 0;
    while done < max_iterations {
        let changed = refresh_structure(nodes, edges, ws, gauge_first, limit, warm, report)?;
        linear_step(
            nodes,
            edges,
            ws,
            0.0,
            false,
            linearize::Stage::Full,
            warm,
            0.0,
        )?;
        report.iterations += 1;
        done += 1;
        let n = nodes.len();
        ws.saved[..n]
            .iter_mut()
            .zip(nodes.iter())
            .for_each(|(s, node)| *s = node.pose);
        let mut largest = apply_step(nodes, ws.var_node, ws.rhs, vars);
        let (mut new_cost, mut new_chi2) =
            linearize::evaluate(nodes, edges, ws.edge_trig, limit, warm, ws.edge_flags);
        // Backtracking: an increase (a bad linearization far from the solution, or a
        // max-mixture switching components) halves the step, at most `MAX_HALVINGS` times.
        let mut halvings = 0;
        while (new_cost.is_nan() || new_cost > cost)
            && halvings < MAX_HALVINGS
            && cost.is_finite()
            && (!mixtures || warm == Warm::Dcs)
        {
            halvings += 1;
            for d in ws.rhs.iter_mut().take(vars) {
                d[0] *= 0.5;
                d[1] *= 0.5;
                d[2] *= 0.5;
            }
            for (node, s) in nodes.iter_mut().zip(ws.saved.iter()) {
                node.pose = *s;
            }
            largest = apply_step(nodes, ws.var_node, ws.rhs, vars);
            (new_cost, new_chi2) =
                linearize::evaluate(nodes, edges, ws.edge_trig, limit, warm, ws.edge_flags);
        }
        report.final_cost = new_cost;
        report.final_chi2 = new_chi2;
        if !new_cost.is_finite() || new_cost > bound {
            return Err(SolveError::Diverged);
        }
        let decrease = cost - new_cost;
        cost = new_cost;
        let settled = !changed || done > SETTLE_ITERATIONS;
        if settled
            && (largest < options.step_tolerance
                || (decrease >= 0.0 && decrease <= options.relative_tolerance * new_cost)
                || halvings == MAX_HALVINGS)
        {
            report.converged = true;
            return Ok(());
        }
    }
    Err(SolveError::MaxIterations)
}

/// Whether a Gauss-Newton outcome is statistically plausible: it did not diverge or meet a
/// singular system, and when it converged, its chi2 is below the 99.9 % quantile of the chi2 distribution with the
/// problem's degrees of freedom (3 per edge minus 3 per free node; Wilson-Hilferty
/// approximation). A chi2 far above that quantile, on data whose information matrices are
/// otherwise consistent, is the mark of a wrong local minimum.
fn passes_chi2_test(
    nodes: &[PoseNode],
    edges: &[PoseEdge],
    ws: &SolverBuffers<'_>,
    result: &Result<(), SolveError>,
) -> bool {
    match result {
        Ok(()) => {}
        // Still moving at the iteration limit: not a stall, and a restart would cost as much
        // again.
        Err(SolveError::Capacity { .. } | SolveError::InvalidGraph | SolveError::MaxIterations) => {
            return true
        }
        Err(SolveError::Diverged | SolveError::NotPositiveDefinite(_)) => return false,
    }
    let dof = 3.0 * (edges.len() as f64 - ws.key.vars as f64);
    if dof < 1.0 {
        return true;
    }
    let (_, chi2) = linearize::evaluate(
        nodes,
        edges,
        ws.edge_trig,
        nodes.len(),
        Warm::Off,
        ws.edge_flags,
    );
    // 99.9 % point of the standard normal.
    const Z: f64 = 3.090_232;
    let h = 2.0 / (9.0 * dof);
    let q = 1.0 - h + Z * libm::sqrt(h);
    chi2.is_finite() && chi2 <= dof * q * q * q
}

/// Most Levenberg-Marquardt iterations of the fallback of [`Method::Auto`], as a multiple of
/// `max_iterations`: from a raw guess its damped steps are shorter than Gauss-Newton's.
const AUTO_LM_BUDGET: u32 = 2;

/// The fallback of [`Method::Auto`]: Levenberg-Marquardt from the initial guess (kept in
/// `ws.step`); the Gauss-Newton estimate waits in `ws.saved` and comes back when Levenberg-
/// Marquardt does not reach a lower chi2.
fn auto_fallback(
    nodes: &mut [PoseNode],
    edges: &[PoseEdge],
    ws: &mut SolverBuffers<'_>,
    options: &SolverOptions,
    report: &mut SolveReport,
    gn_result: Result<(), SolveError>,
) -> Result<(), SolveError> {
    let n = nodes.len();
    let (_, gn_chi2) = linearize::evaluate(nodes, edges, ws.edge_trig, n, Warm::Off, ws.edge_flags);
    let gn_report = *report;
    for ((s, node), start) in ws
        .saved
        .iter_mut()
        .zip(nodes.iter_mut())
        .zip(ws.step.iter())
    {
        *s = node.pose;
        node.pose.x = start[0];
        node.pose.y = start[1];
        node.pose.theta = start[2];
    }
    let (c, x) = linearize::evaluate(nodes, edges, ws.edge_trig, n, Warm::Off, ws.edge_flags);
    report.final_cost = c;
    report.final_chi2 = x;
    report.converged = false;
    let lm_options = SolverOptions {
        lm_tau: AUTO_LM_TAU,
        ..*options
    };
    let limit = report
        .iterations
        .saturating_add(AUTO_LM_BUDGET.saturating_mul(options.max_iterations));
    let lm_result = levenberg_marquardt(nodes, edges, ws, &lm_options, report, limit);
    let (_, lm_chi2) = linearize::evaluate(nodes, edges, ws.edge_trig, n, Warm::Off, ws.edge_flags);
    if lm_chi2 < gn_chi2 || !gn_chi2.is_finite() {
        return lm_result;
    }
    for (node, s) in nodes.iter_mut().zip(ws.saved.iter()) {
        node.pose = *s;
    }
    *report = SolveReport {
        iterations: report.iterations,
        ..gn_report
    };
    gn_result
}

/// Levenberg-Marquardt until `report.iterations` reaches `limit`. The poses before a trial
/// step wait in `ws.work` (free between factorizations).
fn levenberg_marquardt(
    nodes: &mut [PoseNode],
    edges: &[PoseEdge],
    ws: &mut SolverBuffers<'_>,
    options: &SolverOptions,
    report: &mut SolveReport,
    limit: u32,
) -> Result<(), SolveError> {
    let vars = ws.key.vars;
    let mut cost = report.final_cost;
    let mut lambda: f64 = -1.0;
    let mut nu = 2.0;
    let mut rejections = 0u32;
    while report.iterations < limit {
        let step = linear_step(
            nodes,
            edges,
            ws,
            lambda,
            true,
            linearize::Stage::Full,
            Warm::Off,
            options.lm_tau,
        );
        report.iterations += 1;
        match step {
            Ok((_, _, used)) => lambda = used,
            Err(SolveError::NotPositiveDefinite(_)) if lambda > 0.0 => {
                lambda *= nu;
                nu *= 2.0;
                rejections += 1;
                if rejections >= 10 {
                    report.converged = true;
                    return Ok(());
                }
                continue;
            }
            Err(e) => return Err(e),
        }
        // Predicted decrease: dx^T (lambda dx - g), with -g saved in ws.step.
        let mut predicted = 0.0;
        for (d, mg) in ws.rhs.iter().zip(ws.step.iter()).take(vars) {
            for c in 0..3 {
                predicted += d[c] * (lambda * d[c] + mg[c]);
            }
        }
        for (w, node) in ws.work.iter_mut().zip(nodes.iter()) {
            w[0] = node.pose.x;
            w[1] = node.pose.y;
            w[2] = node.pose.theta;
        }
        let largest = apply_step(nodes, ws.var_node, ws.rhs, vars);
        let (new_cost, new_chi2) = linearize::evaluate(
            nodes,
            edges,
            ws.edge_trig,
            nodes.len(),
            Warm::Off,
            ws.edge_flags,
        );
        let rho = if predicted > 0.0 {
            (cost - new_cost) / predicted
        } else {
            -1.0
        };
        if new_cost.is_finite() && new_cost < cost && rho > 0.0 {
            let decrease = cost - new_cost;
            cost = new_cost;
            report.final_cost = new_cost;
            report.final_chi2 = new_chi2;
            rejections = 0;
            let t = 2.0 * rho - 1.0;
            lambda *= (1.0 - t * t * t).max(1.0 / 3.0);
            nu = 2.0;
            if largest < options.step_tolerance || decrease <= options.relative_tolerance * cost {
                report.converged = true;
                return Ok(());
            }
        } else {
            for (node, w) in nodes.iter_mut().zip(ws.work.iter()) {
                node.pose.x = w[0];
                node.pose.y = w[1];
                node.pose.theta = w[2];
            }
            lambda *= nu;
            nu *= 2.0;
            rejections += 1;
            if rejections >= 10 || largest < options.step_tolerance {
                report.converged = true;
                return Ok(());
            }
        }
    }
    Err(SolveError::MaxIterations)
}

#[cfg(test)]
mod tests;
