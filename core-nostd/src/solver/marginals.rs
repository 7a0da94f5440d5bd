//! Marginal information of single nodes, for the slow node-information weight of the paper's
//! eq. (3).
//!
//! The marginal covariance of node `i` is the `3 x 3` diagonal block of `H^-1`, with `H` the
//! Gauss-Newton information matrix at the current estimate. We factorize `H` once and solve
//! `H x = e` for the three unit vectors of every node: `3 n` sparse solves, which is why eq. (3)
//! costs so much more than eq. (4). A recursive selected inversion would be faster; this
//! version is the straightforward reference.

use super::linearize::{Stage, Warm};
use super::{cholesky, linear_step, ordering, refresh_structure, SolveError, SolverBuffers};
use crate::geom::spd_inverse;
use crate::graph::PoseGraph;
use nalgebra::Matrix3;

/// Writes into `out[i]` the trace of node `i`'s marginal information (the inverse of its
/// marginal covariance); nodes without a variable (fixed, or the gauge node) get `0`.
///
/// # Errors
/// [`SolveError::Capacity`] when the workspace or `out` is too small,
/// [`SolveError::NotPositiveDefinite`] when `H` is singular.
pub fn marginal_information_traces(
    graph: &mut PoseGraph<'_>,
    ws: &mut SolverBuffers<'_>,
    out: &mut [f64],
) -> Result<(), SolveError> {
    let (nodes, edges) = graph.split_mut();
    let n = nodes.len();
    if out.len() < n
        || ws.node_var.len() < n
        || ws.rhs.len() < n
        || ws.edge_trig.len() < edges.len()
    {
        return Err(SolveError::Capacity {
            what: "nodes",
            capacity: out.len().min(ws.rhs.len()),
        });
    }
    let gauge_first = ordering::gauge_fixes_first(edges);
    for (t, e) in ws.edge_trig.iter_mut().zip(edges.iter()) {
        *t = [
            libm::cos(e.measurement.theta),
            libm::sin(e.measurement.theta),
        ];
    }
    // Every edge in, max-mixtures on their current component; then assemble and factorize at
    // the current estimate (the step it solves is discarded).
    ws.key.valid = false;
    let mut report = super::SolveReport::default();
    refresh_structure(nodes, edges, ws, gauge_first, n, Warm::Off, &mut report)?;
    linear_step(nodes, edges, ws, 0.0, false, Stage::Full, Warm::Off, 0.0)?;
    ws.key.valid = false;
    let vars = ws.key.vars;
    for (i, o) in out.iter_mut().enumerate().take(n) {
        *o = 0.0;
        let Some(&pos) = ws.node_var.get(i) else {
            continue;
        };
        let pos = pos as usize;
        if pos >= vars {
            continue;
        }
        let mut cov = Matrix3::zeros();
        for c in 0..3 {
            for r in ws.rhs.iter_mut().take(vars) {
                *r = [0.0; 3];
            }
            if let Some(r) = ws.rhs.get_mut(pos) {
                r[c] = 1.0;
            }
            cholesky::solve_in_place(vars, ws.col_end, ws.rows, ws.values, ws.diag, ws.rhs);
            if let Some(col) = ws.rhs.get(pos) {
                for (r, v) in col.iter().enumerate() {
                    cov[(r, c)] = *v;
                }
            }
        }
        *o = spd_inverse(&cov).map(|info| info.trace()).unwrap_or(0.0);
    }
    Ok(())
}
