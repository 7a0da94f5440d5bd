//! How strongly a group of edges disagrees with the rest of the graph: the fall of the optimal
//! cost when the group is left out, the statistic of the cluster test in RRR (Latif, Cadena and
//! Neira, 2013), used by the back-end on groups of loop closures (section III-D's back-end).
//!
//! At an optimum `x` of the cost, leaving out a group of edges with stacked residual `e`,
//! Jacobian `J` and information `Lambda` lowers the optimal cost, to first order, by
//!
//! ```text
//! gain = e^T (Lambda^-1 - J H^-1 J^T)^-1 e
//! ```
//!
//! with `H` the information matrix of the whole graph at `x` (the leave-one-out formula of
//! linear least squares). A group that agrees with the rest lowers it by about its degrees of
//! freedom (chi2 distributed, 3 per edge); a group the rest had to bend to fit lowers it by far
//! more.
//!
//! `J H^-1 J^T` needs only the blocks of `H^-1` between the group's nodes: three solves with
//! the factor `L` per node. Such a solve touches only the columns on the elimination tree's
//! paths from the group's nodes to the root: the right-hand side is zero elsewhere, so the
//! forward substitution changes nothing off those paths, and the backward one reads, for a
//! column on them, only rows on them (a column's rows are its ancestors). On a pose graph
//! ordered by minimum degree those paths are a small part of the factor.
//!
//! The factor is the one the last solve left ([`factor_usable`]), or one made for the purpose
//! ([`factorize_at_estimate`]). An edge the max-mixture had switched off is out of the factor
//! and out of the test, as are nodes and edges added after the factor's analysis; every other
//! edge takes part with the weight of the component its max-mixture picks at the current
//! estimate (after a converged solve, the one the factor was assembled with).

use super::cholesky::{mul_tv, mul_v};
use super::linearize::{weigh, Stage, Warm};
use super::workspace::Vec3;
use super::{linear_step, ordering, refresh_structure, SolveError, SolveReport, SolverBuffers};
use crate::geom::spd_inverse;
use crate::graph::residual::relative_residual;
use crate::graph::{EdgeKind, PoseGraph};

/// Most edges of one group.
pub const MAX_GROUP: usize = 16;
/// Values of the dense scratch [`leave_out_gain`] needs for a group of [`MAX_GROUP`] edges.
pub const DENSE_SCRATCH: usize = (3 * MAX_GROUP) * (3 * MAX_GROUP);

const NONE: u32 = u32::MAX;

/// The outcome of [`leave_out_gain`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LeaveOut {
    /// The fall of the optimal cost if the group were left out.
    pub gain: f64,
    /// The group's edges that took part (those in the factor).
    pub edges: usize,
    /// Factor blocks the substitutions touched (the test's cost).
    pub blocks: u64,
}

/// Whether the solver's storage holds the factor of the information matrix of the graph's
/// first nodes and edges (the last solve's, undamped), usable by [`leave_out_gain`] for a
/// graph of `nodes` nodes and `edges` edges that only grew since.
pub fn factor_usable(ws: &SolverBuffers<'_>, nodes: usize, edges: usize) -> bool {
    let k = *ws.key;
    k.valid && k.factored && k.nodes <= nodes && k.edges <= edges
}

/// Assembles and factorizes the information matrix `H` at the current estimate, every edge on
/// its current component, for the calls of [`leave_out_gain`] that follow.
///
/// # Errors
/// [`SolveError::Capacity`] when the workspace is too small, [`SolveError::NotPositiveDefinite`]
/// when `H` is singular.
pub fn factorize_at_estimate(
    graph: &mut PoseGraph<'_>,
    ws: &mut SolverBuffers<'_>,
) -> Result<(), SolveError> {
    let (nodes, edges) = graph.split_mut();
    let n = nodes.len();
    if ws.node_var.len() < n || ws.edge_trig.len() < edges.len() {
        return Err(SolveError::Capacity {
            what: "nodes",
            capacity: ws.node_var.len(),
        });
    }
    let gauge_first = ordering::gauge_fixes_first(edges);
    for (t, e) in ws.edge_trig.iter_mut().zip(edges.iter()) {
        *t = [
            libm::cos(e.measurement.theta),
            libm::sin(e.measurement.theta),
        ];
    }
    ws.key.valid = false;
    let mut report = SolveReport::default();
    refresh_structure(nodes, edges, ws, gauge_first, n, Warm::Off, &mut report)?;
    linear_step(nodes, edges, ws, 0.0, false, Stage::Full, Warm::Off, 0.0)?;
    Ok(())
}

/// One edge of the group as it enters the formula.
#[derive(Clone, Copy)]
struct Term {
    /// Variable positions of the two nodes (`NONE`: held fixed, or not in the factor).
    var: [u32; 2],
    /// Jacobians with respect to the two nodes, row major.
    jac: [[f64; 9]; 2],
    e: Vec3,
}

/// The gain of leaving out the edges `group` (indices into the graph's edges) at the current
/// estimate, with the factor in `ws` (see [`factor_usable`]); `dense` is scratch of at least
/// `(3 m)^2` values for the `m` edges of the group in the factor ([`DENSE_SCRATCH`] for any
/// group). `None` when no edge of the group is in the factor, the group is larger than
/// [`MAX_GROUP`] or `dense` too small, or the system is numerically singular.
pub fn leave_out_gain(
    graph: &PoseGraph<'_>,
    ws: &mut SolverBuffers<'_>,
    group: &[usize],
    dense: &mut [f64],
) -> Option<LeaveOut> {
    let nodes = graph.nodes();
    let edges = graph.edges();
    let (vars, known_nodes, known_edges) = (ws.key.vars, ws.key.nodes, ws.key.edges);
    let mut terms: heapless::Vec<Term, MAX_GROUP> = heapless::Vec::new();
    let mut inv_info: heapless::Vec<nalgebra::Matrix3<f64>, MAX_GROUP> = heapless::Vec::new();
    for &k in group {
        let edge = edges.get(k)?;
        if k >= known_edges
            || edge.kind == EdgeKind::Prior
            || ws.edge_flags.get(k).copied().unwrap_or(0) & 1 == 0
        {
            continue;
        }
        let (xi, xj) = (
            nodes.get(edge.from.0 as usize)?.pose,
            nodes.get(edge.to.0 as usize)?.pose,
        );
        let (cz, sz) = (
            libm::cos(edge.measurement.theta),
            libm::sin(edge.measurement.theta),
        );
        let (e, [ca, sa, gx, gy]) = relative_residual(
            &xi,
            libm::cos(xi.theta),
            libm::sin(xi.theta),
            &xj,
            &edge.measurement,
            cz,
            sz,
        );
        let w = weigh(edge, edge.chi2_of(&e), Warm::Off, 0).0;
        let var = |n: u32| {
            let v = ws.node_var.get(n as usize).copied().unwrap_or(NONE);
            if (n as usize) < known_nodes && (v as usize) < vars {
                v
            } else {
                NONE
            }
        };
        let term = Term {
            var: [var(edge.from.0), var(edge.to.0)],
            jac: [
                [-ca, -sa, gx, sa, -ca, gy, 0.0, 0.0, -1.0],
                [ca, sa, 0.0, -sa, ca, 0.0, 0.0, 0.0, 1.0],
            ],
            e,
        };
        terms.push(term).ok()?;
        inv_info.push(spd_inverse(&(edge.information * w))?).ok()?;
    }
    let m = terms.len();
    let dim = 3 * m;
    if m == 0 || dense.len() < dim * dim {
        return None;
    }
    let s = dense.get_mut(..dim * dim)?;
    s.fill(0.0);
    for (k, c) in inv_info.iter().enumerate() {
        for r in 0..3 {
            for q in 0..3 {
                s[(3 * k + r) * dim + 3 * k + q] = c[(r, q)];
            }
        }
    }
    let path = tree_paths(ws, &terms)?;
    let mut blocks = 0u64;
    // S -= J H^-1 J^T, one node's columns of H^-1 at a time: column `c` of node `v` gives
    // `w = J_k^(u) (H^-1)_(u,v)[:, c]` for every edge k and its node u, and every edge l at v adds
    // `w J_l^(v)[:, c]^T` to the block (k, l).
    for (l0, t0) in terms.iter().enumerate() {
        for side0 in 0..2 {
            let v = t0.var[side0];
            // Each node once: at its first occurrence in the group.
            if v == NONE || seen_before(&terms, l0, side0, v) {
                continue;
            }
            for c in 0..3 {
                blocks += inverse_column(ws, path, v as usize, c)?;
                for (k, tk) in terms.iter().enumerate() {
                    let mut w = [0.0; 3];
                    for side in 0..2 {
                        let u = tk.var[side];
                        if u == NONE {
                            continue;
                        }
                        let col = ws.rhs.get(u as usize)?;
                        let j = &tk.jac[side];
                        for (r, wr) in w.iter_mut().enumerate() {
                            *wr +=
                                j[3 * r] * col[0] + j[3 * r + 1] * col[1] + j[3 * r + 2] * col[2];
                        }
                    }
                    for (l, tl) in terms.iter().enumerate() {
                        for side in 0..2 {
                            if tl.var[side] != v {
                                continue;
                            }
                            let j = &tl.jac[side];
                            for (r, wr) in w.iter().enumerate() {
                                for q in 0..3 {
                                    s[(3 * k + r) * dim + 3 * l + q] -= wr * j[3 * q + c];
                                }
                            }
                        }
                    }
                }
            }
        }
    }
    let mut y = [0.0; 3 * MAX_GROUP];
    for (k, t) in terms.iter().enumerate() {
        y[3 * k..3 * k + 3].copy_from_slice(&t.e);
    }
    let e = y;
    dense_cholesky_solve(s, dim, y.get_mut(..dim)?)?;
    let gain = e.iter().zip(&y).take(dim).map(|(a, b)| a * b).sum();
    Some(LeaveOut {
        gain,
        edges: m,
        blocks,
    })
}

/// Lists in `ws.scratch[1]`, ascending, the columns on the elimination tree's paths from the
/// group's variables to the root (marked in `ws.scratch[0]`); their count.
fn tree_paths(ws: &mut SolverBuffers<'_>, terms: &[Term]) -> Option<usize> {
    let vars = ws.key.vars;
    let [mark, list, ..] = &mut ws.scratch;
    let mark = mark.get_mut(..vars)?;
    mark.fill(0);
    let mut lowest = vars;
    for v in terms.iter().flat_map(|t| t.var) {
        let mut j = v as usize;
        while j < vars && mark[j] == 0 {
            mark[j] = 1;
            lowest = lowest.min(j);
            let start = if j == 0 {
                0
            } else {
                *ws.col_end.get(j - 1)? as usize
            };
            let end = *ws.col_end.get(j)? as usize;
            // A column's first row is its parent in the elimination tree.
            j = if start < end {
                *ws.rows.get(start)? as usize
            } else {
                vars
            };
        }
    }
    let mut count = 0;
    for (j, &m) in mark.iter().enumerate().skip(lowest) {
        if m != 0 {
            *list.get_mut(count)? = j as u32;
            count += 1;
        }
    }
    Some(count)
}

/// Column `c` of variable `v` of `H^-1` into `ws.rhs`, valid on the `path` columns listed by
/// [`tree_paths`] (which must contain `v`'s path); the factor blocks touched.
fn inverse_column(ws: &mut SolverBuffers<'_>, path: usize, v: usize, c: usize) -> Option<u64> {
    let list = ws.scratch[1].get(..path)?;
    let (col_end, rows, values, diag) = (&*ws.col_end, &*ws.rows, &*ws.values, &*ws.diag);
    let rhs = &mut *ws.rhs;
    for &j in list {
        *rhs.get_mut(j as usize)? = [0.0; 3];
    }
    rhs.get_mut(v)?[c] = 1.0;
    let range = |j: usize| -> Option<(usize, usize)> {
        let start = if j == 0 {
            0
        } else {
            *col_end.get(j - 1)? as usize
        };
        Some((start, *col_end.get(j)? as usize))
    };
    let mut touched = 0u64;
    // Forward, L y = e: nothing changes before v.
    for &j in list.iter().filter(|&&j| j as usize >= v) {
        let j = j as usize;
        let (start, end) = range(j)?;
        let y = mul_v(diag.get(j)?, rhs.get(j)?);
        *rhs.get_mut(j)? = y;
        for p in start..end {
            let d = mul_v(values.get(p)?, &y);
            let b = rhs.get_mut(*rows.get(p)? as usize)?;
            b[0] -= d[0];
            b[1] -= d[1];
            b[2] -= d[2];
        }
        touched += (end - start) as u64 + 1;
    }
    // Backward, L^T x = y.
    for &j in list.iter().rev() {
        let j = j as usize;
        let (start, end) = range(j)?;
        let mut acc = *rhs.get(j)?;
        for p in start..end {
            let d = mul_tv(values.get(p)?, rhs.get(*rows.get(p)? as usize)?);
            acc[0] -= d[0];
            acc[1] -= d[1];
            acc[2] -= d[2];
        }
        *rhs.get_mut(j)? = mul_tv(diag.get(j)?, &acc);
        touched += (end - start) as u64 + 1;
    }
    Some(touched)
}

/// Whether node variable `v` (side `side` of term `l`) already occurs earlier in `terms`.
fn seen_before(terms: &[Term], l: usize, side: usize, v: u32) -> bool {
    terms
        .iter()
        .take(l + 1)
        .enumerate()
        .any(|(k, t)| (0..2).any(|s| (k < l || s < side) && t.var[s] == v))
}

/// Solves `S y = b` in place (`S` symmetric positive definite, `dim x dim`, row major,
/// overwritten by its Cholesky factor); `None` when `S` is not positive definite.
fn dense_cholesky_solve(s: &mut [f64], dim: usize, b: &mut [f64]) -> Option<()> {
    for j in 0..dim {
        let mut d = s[j * dim + j];
        for k in 0..j {
            d -= s[j * dim + k] * s[j * dim + k];
        }
        if !(d > 0.0 && d.is_finite()) {
            return None;
        }
        let d = libm::sqrt(d);
        s[j * dim + j] = d;
        for i in j + 1..dim {
            let mut v = s[i * dim + j];
            for k in 0..j {
                v -= s[i * dim + k] * s[j * dim + k];
            }
            s[i * dim + j] = v / d;
        }
    }
    for i in 0..dim {
        let mut v = b[i];
        for k in 0..i {
            v -= s[i * dim + k] * b[k];
        }
        b[i] = v / s[i * dim + i];
    }
    for i in (0..dim).rev() {
        let mut v = b[i];
        for k in i + 1..dim {
            v -= s[k * dim + i] * b[k];
        }
        b[i] = v / s[i * dim + i];
    }
    Some(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::{Info3, Se2};
    use crate::graph::{GraphStorage, PoseEdge};
    use crate::solver::{solve, SolverOptions, SolverWorkspace};
    use crate::storage::NodeId;

    /// A square loop of odometry with one loop closure, optionally lying by `lie` metres.
    fn square(storage: &mut GraphStorage<16, 32>, lie: f64) -> PoseGraph<'_> {
        let mut g = storage.graph();
        let info = Info3::identity() * 100.0;
        let mut pose = Se2::IDENTITY;
        g.add_node(pose).unwrap();
        for k in 1..8u32 {
            let step = Se2::new(
                1.0,
                0.0,
                if k % 2 == 0 {
                    core::f64::consts::FRAC_PI_2
                } else {
                    0.0
                },
            );
            pose = pose.compose(&step);
            g.add_node(pose).unwrap();
            g.add_edge(PoseEdge::new(
                NodeId(k - 1),
                NodeId(k),
                step,
                info,
                EdgeKind::Odometry,
            ))
            .unwrap();
        }
        // Node 7 back to node 0: the truth is one more unit step and a quarter turn.
        let truth = pose.inverse().compose(&Se2::IDENTITY);
        let z = Se2::new(truth.x + lie, truth.y, truth.theta);
        g.add_edge(PoseEdge::new(NodeId(7), NodeId(0), z, info, EdgeKind::Loop))
            .unwrap();
        g
    }

    fn gain_of(lie: f64) -> LeaveOut {
        let mut storage = GraphStorage::<16, 32>::new();
        let mut g = square(&mut storage, lie);
        let mut ws = SolverWorkspace::<16, 32, 256>::new();
        let mut b = ws.buffers();
        solve(&mut g, &mut b, &SolverOptions::default()).unwrap();
        factorize_at_estimate(&mut g, &mut b).unwrap();
        let k = g.edges().len() - 1;
        let mut dense = [0.0; 9];
        leave_out_gain(&g, &mut b, &[k], &mut dense).unwrap()
    }

    #[test]
    fn the_gain_is_the_fall_of_the_optimal_cost() {
        // With one loop on a chain the graph is linear in the lie's direction to first order;
        // leaving the loop out leaves a cost of zero, so the gain is the optimal cost itself.
        for lie in [0.0, 0.05, 0.3] {
            let mut storage = GraphStorage::<16, 32>::new();
            let mut g = square(&mut storage, lie);
            let mut ws = SolverWorkspace::<16, 32, 256>::new();
            let mut b = ws.buffers();
            solve(&mut g, &mut b, &SolverOptions::default()).unwrap();
            let cost = g.chi2();
            let got = gain_of(lie);
            assert_eq!(got.edges, 1);
            assert!(
                (got.gain - cost).abs() <= 1e-3 * cost.max(1e-6) + 1e-9,
                "lie {lie}: gain {} cost {cost}",
                got.gain
            );
        }
        assert!(gain_of(0.3).gain > 100.0 * gain_of(0.01).gain);
    }

    #[test]
    fn a_group_out_of_the_factor_has_no_gain() {
        let mut storage = GraphStorage::<16, 32>::new();
        let mut g = square(&mut storage, 0.1);
        let mut ws = SolverWorkspace::<16, 32, 256>::new();
        let mut b = ws.buffers();
        factorize_at_estimate(&mut g, &mut b).unwrap();
        b.edge_flags[g.edges().len() - 1] = 0;
        let mut dense = [0.0; 9];
        assert_eq!(
            leave_out_gain(&g, &mut b, &[g.edges().len() - 1], &mut dense),
            None
        );
        // Too little scratch.
        b.edge_flags[g.edges().len() - 1] = 1;
        assert_eq!(
            leave_out_gain(&g, &mut b, &[g.edges().len() - 1], &mut dense[..4]),
            None
        );
    }

    #[test]
    fn dense_cholesky_solves() {
        let mut s = [4.0, 2.0, 2.0, 3.0];
        let mut b = [2.0, 1.0];
        dense_cholesky_solve(&mut s, 2, &mut b).unwrap();
        // [[4, 2], [2, 3]] y = [2, 1]: y = [0.5, 0].
        assert!((b[0] - 0.5).abs() < 1e-12 && b[1].abs() < 1e-12);
        let mut bad = [1.0, 2.0, 2.0, 1.0];
        assert_eq!(dense_cholesky_solve(&mut bad, 2, &mut [1.0, 1.0]), None);
    }
}
