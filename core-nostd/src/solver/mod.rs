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

//!
//! Modules: `options` (what a solve is asked and what it reports), `iterate` (the
//! Gauss-Newton and Levenberg-Marquardt iterations and their linear step), `resumable` (the
//! same Gauss-Newton solve in bounded chunks of work, for the back-end's steps), `ordering`,
//! `cholesky`, `linearize`, `gate`, `marginals`, `leave_out` and `workspace`.

mod admission;
mod cholesky;
mod gate;
mod iterate;
mod leave_out;
mod linearize;
mod marginals;
mod options;
mod ordering;
mod resumable;
mod workspace;

pub(crate) use cholesky::chol_inverse_above;
pub use leave_out::{
    factor_usable, factorize_at_estimate, leave_out_gain, LeaveOut, DENSE_SCRATCH, MAX_GROUP,
};
pub use marginals::marginal_information_traces;
pub use options::{Method, SolveError, SolveFailure, SolveReport, SolverOptions, AUTO_LM_TAU};
pub use resumable::{work, ChunkedSolve, Progress};
pub(crate) use workspace::rows_of;
pub use workspace::{AnalysisKey, Block, SolverBuffers, SolverWorkspace, Vec3};

use crate::graph::{PoseEdge, PoseGraph, PoseNode, RobustKernel};
use iterate::{
    apply_step, auto_fallback, gauss_newton, levenberg_marquardt, linear_step, passes_chi2_test,
};
use linearize::Warm;

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
    if let Err(e) = check_buffers(nodes, edges, ws) {
        return fail(e, report);
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
                if admission::admit_by_innovation(nodes, edges, ws, limit) == 0 {
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

/// The checks of a solve before any work: the workspace holds the graph, and every edge names
/// nodes of the graph.
pub(super) fn check_buffers(
    nodes: &[PoseNode],
    edges: &[PoseEdge],
    ws: &SolverBuffers<'_>,
) -> Result<(), SolveError> {
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
        return Err(SolveError::Capacity {
            what: "nodes",
            capacity: ws.node_capacity(),
        });
    }
    if edges.len() > ws.edge_slot.len() || edges.len() > ws.edge_trig.len() {
        return Err(SolveError::Capacity {
            what: "edges",
            capacity: ws.edge_capacity(),
        });
    }
    if ws.values.len() < ws.rows.len() {
        return Err(SolveError::Capacity {
            what: "factor blocks",
            capacity: ws.values.len(),
        });
    }
    for e in edges.iter() {
        if e.from.0 as usize >= nodes.len() || e.to.0 as usize >= nodes.len() {
            return Err(SolveError::InvalidGraph);
        }
    }

    if edges.len() > ws.edge_flags.len() {
        return Err(SolveError::Capacity {
            what: "edges",
            capacity: ws.edge_flags.len(),
        });
    }
    Ok(())
}

/// Most rounds of innovation tests (and re-solves) after a gated max-mixture solve.
const ADMISSION_ROUNDS: u32 = 8;

/// A max-mixture edge whose chosen component scales its information below this takes no part
/// in the linear system: its block would change `H` by less than this fraction, and leaving it
/// out keeps the factor as sparse as the accepted loops alone make it.
pub const INACTIVE_SCALE: f64 = 1e-3;

/// Marks which edges take part in the linear system at the current estimate (loops within
/// `limit`, max-mixture edges on a component of useful weight) and analyses the structure again
/// when that set or the graph changed. Returns whether the set changed.
pub(super) fn refresh_structure(
    nodes: &[PoseNode],
    edges: &[PoseEdge],
    ws: &mut SolverBuffers<'_>,
    gauge_first: bool,
    limit: usize,
    warm: Warm,
    report: &mut SolveReport,
) -> Result<bool, SolveError> {
    let (changed, due) = refresh_flags(nodes, edges, ws, gauge_first, limit, warm);
    if let Some(fp) = due {
        ordering::analyze(nodes, edges, gauge_first, ws)?;
        analysis_done(nodes.len(), edges.len(), fp, ws, report);
    }
    Ok(changed)
}

/// The first part of [`refresh_structure`]: sets the edges' active flags and returns whether
/// the set changed and, when the structure must be analysed again, the new analysis
/// fingerprint (the cached analysis is then marked invalid).
pub(super) fn refresh_flags(
    nodes: &[PoseNode],
    edges: &[PoseEdge],
    ws: &mut SolverBuffers<'_>,
    gauge_first: bool,
    limit: usize,
    warm: Warm,
) -> (bool, Option<u64>) {
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
    if key.valid && key.nodes == nodes.len() && key.edges == edges.len() && key.fingerprint == fp {
        return (changed, None);
    }
    ws.key.valid = false;
    (changed, Some(fp))
}

/// The end of a structural analysis of `nodes` nodes and `edges` edges with fingerprint `fp`:
/// the cached analysis is valid again.
pub(super) fn analysis_done(
    nodes: usize,
    edges: usize,
    fp: u64,
    ws: &mut SolverBuffers<'_>,
    report: &mut SolveReport,
) {
    ws.key.nodes = nodes;
    ws.key.edges = edges;
    ws.key.fingerprint = fp;
    ws.key.valid = true;
    ws.key.factored = false;
    report.analyzed = true;
    report.variables = ws.key.vars;
    report.factor_blocks = ws.key.nnz;
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

#[cfg(test)]
mod tests;
