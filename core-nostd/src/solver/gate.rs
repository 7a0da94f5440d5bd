//! Odometry-chain gating of max-mixture loop closures: the warm start of a robust solve.
//!
//! From a drifted odometry guess every loop closure, true or false, has a large residual, so a
//! max-mixture would put all of them on the null hypothesis and never move. The gate instead
//! judges each loop against what odometry alone predicts for its node pair *with the
//! uncertainty of that prediction*: chaining the odometry edges gives the relative pose `T` of
//! the pair and, by first-order compounding, its covariance `S_T`; a loop with measurement `z`
//! and covariance `S_z` passes when `(T - z)^T (S_T + S_z)^-1 (T - z)` is below a chi2
//! threshold. The warm start then runs in three phases: a few iterations with only the passed
//! loops, each weighted by dynamic covariance scaling of its gate distance (a loop that odometry
//! predicts well pulls harder); then dynamic covariance scaling of every max-mixture loop by its
//! current residual until that settles; then the free max-mixture solve, where every edge picks
//! its most likely component.
//!
//! The chain's covariance in the world frame is kept per node: `S_b = J_a S_a J_a^T +
//! J_z S_z J_z^T`, so the relative covariance of nodes `a < b` is recovered in O(1) as
//! `R_a^T (S_b - J S_a J^T) R_a` with `J` the Jacobian of `P_a (+) T` with respect to `P_a`.

use super::cholesky::{chol_inverse, mul_v};
use super::linearize::info_block;
use super::workspace::{Block, SolverBuffers};
use crate::geom::{wrap_angle, Se2};
use crate::graph::{EdgeKind, PoseEdge, RobustKernel};

const NONE: u32 = u32::MAX;
/// Bit of `edge_flags`: the gate passed this edge.
pub(crate) const GATE_PASSED: u8 = 2;
/// The upper six bits of `edge_flags` hold the warm-start weight of a gated loop, in 63rds.
const WEIGHT_SHIFT: u8 = 2;

/// The warm-start weight stored in an edge's flags (1 for edges without one).
#[inline(always)]
pub(crate) fn stored_weight(flag: u8) -> f64 {
    let level = flag >> WEIGHT_SHIFT;
    if level == 0 {
        1.0
    } else {
        level as f64 / 63.0
    }
}

// Small block algebra (row-major 3x3), kept local so the gate adds no new users of the
// generic matrix code that the rest of the core inlines.

fn mul(a: &Block, b: &Block) -> Block {
    let mut o = [0.0; 9];
    for r in 0..3 {
        for c in 0..3 {
            o[3 * r + c] = a[3 * r] * b[c] + a[3 * r + 1] * b[3 + c] + a[3 * r + 2] * b[6 + c];
        }
    }
    o
}

fn transpose(a: &Block) -> Block {
    [a[0], a[3], a[6], a[1], a[4], a[7], a[2], a[5], a[8]]
}

/// `j m j^T`.
fn sandwich(j: &Block, m: &Block) -> Block {
    mul(&mul(j, m), &transpose(j))
}

fn add(a: &Block, b: &Block) -> Block {
    let mut o = *a;
    for (x, y) in o.iter_mut().zip(b) {
        *x += y;
    }
    o
}

/// Inverse of a symmetric positive definite block, from its Cholesky factor.
fn spd_inverse(m: &Block) -> Option<Block> {
    let li = chol_inverse(m)?;
    Some(mul(&transpose(&li), &li))
}

/// Jacobians of `p (+) q` with respect to `p` and to `q`.
fn compose_jacobians(p: &Se2, q: &Se2) -> (Block, Block) {
    let (c, s) = (libm::cos(p.theta), libm::sin(p.theta));
    (
        [
            1.0,
            0.0,
            -s * q.x - c * q.y,
            0.0,
            1.0,
            c * q.x - s * q.y,
            0.0,
            0.0,
            1.0,
        ],
        [c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0],
    )
}

/// Jacobian of `q^-1` with respect to `q`.
fn inverse_jacobian(q: &Se2) -> Block {
    let (c, s) = (libm::cos(q.theta), libm::sin(q.theta));
    [
        -c,
        -s,
        s * q.x - c * q.y,
        s,
        -c,
        c * q.x + s * q.y,
        0.0,
        0.0,
        -1.0,
    ]
}

/// Sets [`GATE_PASSED`] on every edge that is not a max-mixture loop and on every max-mixture
/// loop that passes the gate; returns the number of max-mixture loops that passed.
pub(crate) fn gate_loops(
    n: usize,
    edges: &[PoseEdge],
    ws: &mut SolverBuffers<'_>,
    chi2: f64,
) -> usize {
    let [odo, segment, ..] = &mut ws.scratch;
    for k in 0..n {
        odo[k] = NONE;
    }
    for (idx, e) in edges.iter().enumerate() {
        let (a, b) = (e.from.0 as usize, e.to.0 as usize);
        if e.kind == EdgeKind::Odometry && a.abs_diff(b) == 1 && odo[a.min(b)] == NONE {
            odo[a.min(b)] = idx as u32;
        }
    }
    // Chain poses (in `saved`) and world-frame covariances (in `work`), per segment.
    let mut seg = 0u32;
    let mut pose = Se2::IDENTITY;
    let mut cov: Block = [0.0; 9];
    for k in 0..n {
        ws.saved[k] = pose;
        ws.work[k] = cov;
        segment[k] = seg;
        let step = edges.get(odo[k] as usize).and_then(|e| {
            let c = spd_inverse(&info_block(e))?;
            Some(if e.from.0 as usize == k {
                (e.measurement, c)
            } else {
                let ji = inverse_jacobian(&e.measurement);
                (e.measurement.inverse(), sandwich(&ji, &c))
            })
        });
        match step {
            Some((z, cz)) if odo[k] != NONE => {
                let (ja, jb) = compose_jacobians(&pose, &z);
                cov = add(&sandwich(&ja, &cov), &sandwich(&jb, &cz));
                pose = pose.compose(&z);
            }
            _ => {
                seg += 1;
                pose = Se2::IDENTITY;
                cov = [0.0; 9];
            }
        }
    }
    let mut passed = 0;
    for (e, flag) in edges.iter().zip(ws.edge_flags.iter_mut()) {
        let mm = matches!(e.robust, RobustKernel::MaxMixture { .. }) && e.kind == EdgeKind::Loop;
        if !mm {
            *flag = (*flag & 1) | GATE_PASSED;
            continue;
        }
        *flag &= 1;
        let (i, j) = (e.from.0 as usize, e.to.0 as usize);
        if i >= n || j >= n || segment[i] != segment[j] {
            continue;
        }
        let Some(cov_z) = spd_inverse(&info_block(e)) else {
            continue;
        };
        // Measurement from the earlier node to the later one.
        let (a, b, z, cov_z) = if i < j {
            (i, j, e.measurement, cov_z)
        } else {
            let ji = inverse_jacobian(&e.measurement);
            (j, i, e.measurement.inverse(), sandwich(&ji, &cov_z))
        };
        let (pa, pb) = (ws.saved[a], ws.saved[b]);
        let t = pa.between(&pb);
        let (ja, rot) = compose_jacobians(&pa, &t);
        let mut grown = ws.work[b];
        for (g, p) in grown.iter_mut().zip(sandwich(&ja, &ws.work[a])) {
            *g -= p;
        }
        let cov_t = sandwich(&transpose(&rot), &grown);
        let mut total = add(&cov_t, &transpose(&cov_t));
        for (v, c) in total.iter_mut().zip(cov_z) {
            *v = 0.5 * *v + c;
        }
        let d = [t.x - z.x, t.y - z.y, wrap_angle(t.theta - z.theta)];
        let maha = chol_inverse(&total).map(|li| {
            let y = mul_v(&li, &d);
            y[0] * y[0] + y[1] * y[1] + y[2] * y[2]
        });
        if let Some(m) = maha {
            if m <= chi2 {
                // Dynamic covariance scaling on the gate's distance: a loop that odometry
                // predicts well pulls harder than one at the edge of the gate.
                let sc = (2.0 / (1.0 + m)).min(1.0);
                let level = (libm::round(63.0 * sc * sc) as u8).clamp(1, 63);
                *flag = (*flag & 3) | GATE_PASSED | (level << WEIGHT_SHIFT);
                passed += 1;
            }
        }
    }
    passed
}

/// Marks every edge as passed (the DCS phase of the warm start weighs all loops).
pub(crate) fn pass_all(edges: &[PoseEdge], ws: &mut SolverBuffers<'_>) {
    for f in ws.edge_flags.iter_mut().take(edges.len()) {
        *f = (*f & 1) | GATE_PASSED;
    }
}
