//! The iterations of one solve of eq. 10: the damped linear step (assemble, factorize, solve),
//! Gauss-Newton with step halving, Levenberg-Marquardt with Nielsen's damping update, and the
//! automatic fallback from the first to the second when the chi2 test fails.

use super::linearize::{self, Warm};
use super::{cholesky, refresh_structure};
use super::{SolveError, SolveReport, SolverBuffers, SolverOptions, Vec3, AUTO_LM_TAU};
use crate::geom::wrap_angle;
use crate::graph::{PoseEdge, PoseNode, RobustKernel};
use crate::storage::NodeId;

/// Most step halvings of one Gauss-Newton iteration.
pub(super) const MAX_HALVINGS: u32 = 8;
/// Iterations after which a change of the active edge set no longer blocks convergence.
pub(super) const SETTLE_ITERATIONS: u32 = 8;

/// Assembles at the current estimate, adds `lambda` to the diagonal (a negative `lambda` means
/// `1e-5` times the largest diagonal entry of `H`), factorizes and solves; the step is left in
/// `ws.rhs` (by position). Returns the robust cost and chi2 at the estimate and the damping
/// used.
#[allow(clippy::too_many_arguments)]
pub(super) fn linear_step(
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
    ws.key.factored = false;
    let (cost, chi2) = linearize::assemble(
        nodes,
        edges,
        vars,
        nnz,
        stage,
        &mut linearize::System::of(ws, warm),
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
    // Undamped and over every unknown, the factor is that of the information matrix itself.
    ws.key.factored = lambda == 0.0 && stage == linearize::Stage::Full;
    cholesky::solve_in_place(vars, ws.col_end, ws.rows, ws.values, ws.diag, ws.rhs);
    Ok((cost, chi2, lambda))
}

/// `x += dx` for every free node; returns the largest step component.
pub(super) fn apply_step(
    nodes: &mut [PoseNode],
    var_node: &[u32],
    dx: &[Vec3],
    vars: usize,
) -> f64 {
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
pub(super) fn gauss_newton(
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
pub(super) fn passes_chi2_test(
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
    chi2.is_finite() && chi2 <= crate::geom::chi2_quantile(dof, Z)
}

/// Most Levenberg-Marquardt iterations of the fallback of [`Method::Auto`], as a multiple of
/// `max_iterations`: from a raw guess its damped steps are shorter than Gauss-Newton's.
const AUTO_LM_BUDGET: u32 = 2;

/// The fallback of [`Method::Auto`]: Levenberg-Marquardt from the initial guess (kept in
/// `ws.step`); the Gauss-Newton estimate waits in `ws.saved` and comes back when Levenberg-
/// Marquardt does not reach a lower chi2.
pub(super) fn auto_fallback(
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
pub(super) fn levenberg_marquardt(
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
