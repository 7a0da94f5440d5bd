//! The innovation test of the loops the admission gate holds back (the last part of a gated
//! max-mixture solve, module `gate`), in chunks that stop inside the three solves of a test.

use super::cholesky::{backward, chol_inverse, forward, mul_v};
use super::gate::{add, spd_inverse, transpose, GATE_PASSED};
use super::linearize::{info_block, quad};
use super::resumable::work;
use super::workspace::{Block, SolverBuffers};
use crate::graph::residual::relative_residual;
use crate::graph::{EdgeKind, PoseEdge, PoseNode};

/// The innovation test of the max-mixture loops that the admission gate
/// ([`super::linearize::Warm::Admit`]) holds back: loops without [`GATE_PASSED`] whose chi2
/// at the current estimate is above `chi2` although their max-mixture would pick a component
/// of useful weight. Such a loop is left out of the system, so the factor in the workspace
/// (from the last iteration) gives the covariance of its predicted residual, `J H^-1 J^T`
/// (three solves); the loop is admitted (marked [`GATE_PASSED`], free to follow its
/// max-mixture from then on) when `e^T (J H^-1 J^T + Omega^-1)^-1 e <= chi2`. A loop that
/// closes a stretch which nothing else constrains passes; a false loop between well-known
/// places does not. Returns the number admitted.
pub(crate) fn admit_by_innovation(
    nodes: &[PoseNode],
    edges: &[PoseEdge],
    ws: &mut SolverBuffers<'_>,
    chi2: f64,
) -> usize {
    let mut admit = Admit::START;
    admit_chunk(nodes, edges, ws, chi2, &mut admit, u64::MAX).1
}

/// Where a solve of a test is.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Stage {
    /// The right-hand side (a column of `J^T`) is still to set.
    Set,
    /// The forward solve, at this column.
    Forward(usize),
    /// The backward solve, with this many columns left.
    Backward(usize),
}

/// The innovation tests between calls of [`admit_chunk`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Admit {
    /// The edge tested or next to look at.
    pub(crate) next: usize,
    /// The column of `J^T` being solved for.
    col: usize,
    stage: Stage,
    /// `J H^-1 J^T` so far, by columns.
    pred: Block,
}

impl Admit {
    /// Before the first edge.
    pub(crate) const START: Admit = Admit {
        next: 0,
        col: 0,
        stage: Stage::Set,
        pred: [0.0; 9],
    };
}

/// [`admit_by_innovation`] from where `s` stopped until at least `budget` work units were
/// spent (the forward and backward solves of a test stop between columns, the loops that need
/// no test cost one residual each); returns the units spent and the loops admitted. The tests
/// are independent of each other (a loop's admission changes only its own flag, not the
/// factor), and a split test does the same arithmetic, so split runs admit the same loops.
pub(crate) fn admit_chunk(
    nodes: &[PoseNode],
    edges: &[PoseEdge],
    ws: &mut SolverBuffers<'_>,
    chi2: f64,
    s: &mut Admit,
    budget: u64,
) -> (u64, usize) {
    let vars = ws.key.vars;
    let per = work::ADMISSION_BLOCKS_PER_UNIT;
    let mut admitted = 0;
    let mut spent = 0u64;
    while spent < budget {
        let k = s.next;
        let Some(e) = edges.get(k) else {
            break;
        };
        let f = ws.edge_flags[k];
        if f & GATE_PASSED != 0
            || e.kind != EdgeKind::Loop
            || !matches!(e.robust, crate::graph::RobustKernel::MaxMixture { .. })
        {
            s.next += 1;
            continue;
        }
        let (i, j) = (e.from.0 as usize, e.to.0 as usize);
        let (Some(ni), Some(nj)) = (nodes.get(i), nodes.get(j)) else {
            s.next += 1;
            continue;
        };
        spent += work::ADMISSION_EDGE;
        let (ci, si) = (libm::cos(ni.pose.theta), libm::sin(ni.pose.theta));
        let [cz, sz] = ws.edge_trig[k];
        let (r, [ca, sa, gx, gy]) =
            relative_residual(&ni.pose, ci, si, &nj.pose, &e.measurement, cz, sz);
        let info = info_block(e);
        let c = quad(&info, &r);
        if c <= chi2 || e.robust.weigh(c).0 < super::INACTIVE_SCALE {
            s.next += 1;
            continue;
        }
        let Some(cov_z) = spd_inverse(&info) else {
            s.next += 1;
            continue;
        };
        let jj: Block = [ca, sa, 0.0, -sa, ca, 0.0, 0.0, 0.0, 1.0];
        let ji: Block = [-ca, -sa, gx, sa, -ca, gy, 0.0, 0.0, -1.0];
        let (pi, pj) = (ws.node_var[i], ws.node_var[j]);
        let left = budget.saturating_sub(spent).saturating_mul(per);
        match s.stage {
            Stage::Set => {
                for v in ws.rhs.iter_mut().take(vars) {
                    *v = [0.0; 3];
                }
                // Column `col` of J^T, by variable position.
                for (p, jac) in [(pi, &ji), (pj, &jj)] {
                    if let Some(v) = ws.rhs.get_mut(p as usize).filter(|_| (p as usize) < vars) {
                        for (d, x) in v.iter_mut().enumerate() {
                            *x += jac[3 * s.col + d];
                        }
                    }
                }
                spent += (vars as u64).div_ceil(8 * per);
                s.stage = Stage::Forward(0);
            }
            Stage::Forward(from) => {
                let (next, touched) = forward(
                    vars, ws.col_end, ws.rows, ws.values, ws.diag, ws.rhs, from, left,
                );
                spent += touched.div_ceil(per);
                s.stage = if next >= vars {
                    Stage::Backward(vars)
                } else {
                    Stage::Forward(next)
                };
            }
            Stage::Backward(until) => {
                let (until, touched) =
                    backward(ws.col_end, ws.rows, ws.values, ws.diag, ws.rhs, until, left);
                spent += touched.div_ceil(per);
                if until > 0 {
                    s.stage = Stage::Backward(until);
                    continue;
                }
                for (p, jac) in [(pi, &ji), (pj, &jj)] {
                    if let Some(x) = ws.rhs.get(p as usize).filter(|_| (p as usize) < vars) {
                        let y = mul_v(jac, x);
                        for (row, v) in y.iter().enumerate() {
                            s.pred[3 * row + s.col] += v;
                        }
                    }
                }
                s.stage = Stage::Set;
                s.col += 1;
                if s.col < 3 {
                    continue;
                }
                let mut total = add(&s.pred, &transpose(&s.pred));
                for (v, cz) in total.iter_mut().zip(cov_z) {
                    *v = 0.5 * *v + cz;
                }
                let m = chol_inverse(&total).map(|li| {
                    let y = mul_v(&li, &r);
                    y[0] * y[0] + y[1] * y[1] + y[2] * y[2]
                });
                if m.is_some_and(|m| m <= chi2) {
                    ws.edge_flags[k] = f | GATE_PASSED;
                    admitted += 1;
                }
                *s = Admit {
                    next: k + 1,
                    ..Admit::START
                };
            }
        }
    }
    (spent, admitted)
}
