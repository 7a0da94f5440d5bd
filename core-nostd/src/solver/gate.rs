//! Odometry-chain gating of max-mixture loop closures: the warm start of a robust solve.
//!
//! From a drifted odometry guess every loop closure, true or false, has a large residual, so a
//! max-mixture would put all of them on the null hypothesis and never move. The gate instead
//! judges each loop against what odometry alone predicts for its node pair *with the
//! uncertainty of that prediction*: chaining the odometry edges gives the relative pose `T` of
//! the pair and, by first-order compounding, its covariance `S_T`; a loop with measurement `z`
//! and covariance `S_z` passes when `(T - z)^T (S_T + S_z)^-1 (T - z)` is below a chi2
//! threshold. When odometry drifts a lot that covariance is wide and many false loops pass too,
//! so a passed loop must also agree with at least [`SUPPORT_MIN`] neighbouring passed loops
//! ([`support_loops`], short cycles through two loops and two odometry stretches). The warm
//! start then runs in three phases: a few iterations with only the supported loops, each
//! weighted by dynamic covariance scaling of its gate distance (a loop that odometry predicts
//! well pulls harder); then dynamic covariance scaling of the same loops by their current
//! residual until that settles; then the free max-mixture solve, where every edge picks its most
//! likely component, except that a loop the warm start did not use is held on its null
//! component until it is consistent with the map ([`unit_variance`],
//! [`super::admission::admit_by_innovation`]).
//!
//! The chain's covariance in the world frame is kept per node: `S_b = J_a S_a J_a^T +
//! J_z S_z J_z^T`, so the relative covariance of nodes `a < b` is recovered in O(1) as
//! `R_a^T (S_b - J S_a J^T) R_a` with `J` the Jacobian of `P_a (+) T` with respect to `P_a`.

use super::cholesky::{chol_inverse, mul_v};
use super::linearize::{edge_residual, info_block, quad};
use super::resumable::work;
use super::workspace::{Block, SolverBuffers};
use crate::geom::{wrap_angle, Se2};
use crate::graph::{EdgeKind, PoseEdge, PoseNode, RobustKernel};

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

pub(super) fn transpose(a: &Block) -> Block {
    [a[0], a[3], a[6], a[1], a[4], a[7], a[2], a[5], a[8]]
}

/// `j m j^T`.
fn sandwich(j: &Block, m: &Block) -> Block {
    mul(&mul(j, m), &transpose(j))
}

pub(super) fn add(a: &Block, b: &Block) -> Block {
    let mut o = *a;
    for (x, y) in o.iter_mut().zip(b) {
        *x += y;
    }
    o
}

/// Inverse of a symmetric positive definite block, from its Cholesky factor.
pub(super) fn spd_inverse(m: &Block) -> Option<Block> {
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
    gate_index(n, edges, ws);
    let mut chain = Chain::START;
    gate_chain(&mut chain, n, edges, ws, u64::MAX);
    gate_test(n, edges, ws, chi2, 0, u64::MAX).2
}

/// The odometry chain of [`gate_chain`] between calls: the segment, pose and world-frame
/// covariance reached.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Chain {
    /// Next node.
    pub(crate) next: usize,
    seg: u32,
    pose: Se2,
    cov: Block,
}

impl Chain {
    /// Before the first node.
    pub(crate) const START: Chain = Chain {
        next: 0,
        seg: 0,
        pose: Se2::IDENTITY,
        cov: [0.0; 9],
    };
}

/// The first part of [`gate_loops`]: each node's odometry edge to its successor (`O(nodes +
/// edges)`).
pub(crate) fn gate_index(n: usize, edges: &[PoseEdge], ws: &mut SolverBuffers<'_>) {
    let [odo, ..] = &mut ws.scratch;
    for k in 0..n {
        odo[k] = NONE;
    }
    for (idx, e) in edges.iter().enumerate() {
        let (a, b) = (e.from.0 as usize, e.to.0 as usize);
        if e.kind == EdgeKind::Odometry && a.abs_diff(b) == 1 && odo[a.min(b)] == NONE {
            odo[a.min(b)] = idx as u32;
        }
    }
}

/// Chains the odometry over the next nodes of `chain` (poses in `saved`, world-frame
/// covariances in `work`, per segment) until at least `budget` work units were spent (at
/// least one node); returns the units.
pub(crate) fn gate_chain(
    chain: &mut Chain,
    n: usize,
    edges: &[PoseEdge],
    ws: &mut SolverBuffers<'_>,
    budget: u64,
) -> u64 {
    let [odo, segment, ..] = &mut ws.scratch;
    let Chain {
        next,
        mut seg,
        mut pose,
        mut cov,
    } = *chain;
    let mut spent = 0u64;
    let mut k = next;
    while k < n && spent < budget {
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
        spent += work::GATE_NODE;
        k += 1;
    }
    *chain = Chain {
        next: k,
        seg,
        pose,
        cov,
    };
    spent
}

/// The gate's test of edges `from..` until at least `budget` work units were spent (at least
/// one edge): returns the next edge, the units and the max-mixture loops that passed.
pub(crate) fn gate_test(
    n: usize,
    edges: &[PoseEdge],
    ws: &mut SolverBuffers<'_>,
    chi2: f64,
    from: usize,
    budget: u64,
) -> (usize, u64, usize) {
    let mut passed = 0;
    let mut spent = 0u64;
    let [_, segment, ..] = &ws.scratch;
    let mut k = from;
    while k < edges.len() && spent < budget {
        let (Some(e), Some(flag)) = (edges.get(k), ws.edge_flags.get_mut(k)) else {
            break;
        };
        k += 1;
        let mm = matches!(e.robust, RobustKernel::MaxMixture { .. }) && e.kind == EdgeKind::Loop;
        if !mm {
            *flag = (*flag & 1) | GATE_PASSED;
            spent += work::GATE_EDGE;
            continue;
        }
        spent += work::GATE_LOOP;
        *flag &= 1;
        let (i, j) = (e.from.0 as usize, e.to.0 as usize);
        if i >= n || j >= n || segment[i] != segment[j] {
            continue;
        }
        let Some((a, b, z, cov_z)) = oriented(e) else {
            continue;
        };
        let (t, cov_t) = chain_between(ws.saved, ws.work, a, b);
        if let Some(m) = mismatch(&t, &add(&cov_t, &cov_z), &z) {
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
    (k, spent, passed)
}

/// Measurement of a relative edge from its earlier node to its later one: `(a, b, z, cov_z)`
/// with `a < b`; `None` for a degenerate information matrix.
fn oriented(e: &PoseEdge) -> Option<(usize, usize, Se2, Block)> {
    let cov_z = spd_inverse(&info_block(e))?;
    let (i, j) = (e.from.0 as usize, e.to.0 as usize);
    Some(if i < j {
        (i, j, e.measurement, cov_z)
    } else {
        let ji = inverse_jacobian(&e.measurement);
        (j, i, e.measurement.inverse(), sandwich(&ji, &cov_z))
    })
}

/// The odometry chain's relative pose from node `a` to node `b` (same segment, either order)
/// and its covariance in `a`'s frame, from the chained poses and world covariances.
fn chain_between(poses: &[Se2], covs: &[Block], a: usize, b: usize) -> (Se2, Block) {
    if a == b {
        return (Se2::IDENTITY, [0.0; 9]);
    }
    let (lo, hi) = (a.min(b), a.max(b));
    let (pa, pb) = (poses[lo], poses[hi]);
    let t = pa.between(&pb);
    let (ja, rot) = compose_jacobians(&pa, &t);
    let mut grown = covs[hi];
    for (g, p) in grown.iter_mut().zip(sandwich(&ja, &covs[lo])) {
        *g -= p;
    }
    let c = sandwich(&transpose(&rot), &grown);
    let mut cov = add(&c, &transpose(&c));
    for v in cov.iter_mut() {
        *v *= 0.5;
    }
    if a < b {
        (t, cov)
    } else {
        let ji = inverse_jacobian(&t);
        (t.inverse(), sandwich(&ji, &cov))
    }
}

/// Squared Mahalanobis distance between a predicted relative pose `t` (with the summed
/// covariance `total` of prediction and measurement) and a measurement `z`.
fn mismatch(t: &Se2, total: &Block, z: &Se2) -> Option<f64> {
    let d = [t.x - z.x, t.y - z.y, wrap_angle(t.theta - z.theta)];
    chol_inverse(total).map(|li| {
        let y = mul_v(&li, &d);
        y[0] * y[0] + y[1] * y[1] + y[2] * y[2]
    })
}

/// Two loop closures support each other when both ends of one lie within this many nodes of
/// the other's ends: the cycle they close with the two short odometry stretches between their
/// ends is then tight enough to test (a long cycle inherits the odometry's drift and tests
/// nothing).
pub(crate) const SUPPORT_WINDOW: usize = 5;
/// A gated loop keeps its place in the warm start only with at least this many consistent
/// neighbours (see [`support_loops`]).
pub(crate) const SUPPORT_MIN: u32 = 2;

const LINK_BITS: u32 = 24;
const LINK_NONE: u32 = (1 << LINK_BITS) - 1;

/// Pairwise consistency of the gated loops (a local form of pairwise consistency
/// maximization): for two gated loops `(a1, b1, z1)` and `(a2, b2, z2)` with `|a1 - a2|` and
/// `|b1 - b2|` at most [`SUPPORT_WINDOW`], the path `a2 -> a1` (odometry), `a1 -> b1` (`z1`),
/// `b1 -> b2` (odometry) predicts `z2`; with the compounded covariance of that path plus
/// `z2`'s own, a squared Mahalanobis distance within `chi2` makes the two consistent. True
/// loops come in runs along a revisited stretch and agree with each other; a false loop
/// rarely has a neighbour at all, let alone one that agrees. Gated loops with fewer than
/// [`SUPPORT_MIN`] consistent neighbours lose [`GATE_PASSED`]; the max-mixture phase decides on
/// them later, at a consistent estimate.
///
/// Uses `scratch[2]` (bucket heads per lower end) and `edge_slot` (bucket links and counts), so
/// it invalidates the cached analysis. Expects the chain poses in `saved`, world covariances
/// in `work` and segments in `scratch[1]` (as [`gate_loops`] leaves them). Returns the gated
/// loops that keep their place.
pub(crate) fn support_loops(
    n: usize,
    edges: &[PoseEdge],
    ws: &mut SolverBuffers<'_>,
    chi2: f64,
) -> usize {
    if let Some(kept) = support_begin(n, edges, ws) {
        return kept;
    }
    support_pairs(n, edges, ws, chi2, 0, u64::MAX);
    support_end(edges, ws)
}

/// A gated max-mixture loop.
fn gated(e: &PoseEdge, f: u8) -> bool {
    f & GATE_PASSED != 0
        && e.kind == EdgeKind::Loop
        && matches!(e.robust, RobustKernel::MaxMixture { .. })
}

/// The first part of [`support_loops`]: the gated loops in buckets by their lower end
/// (`O(nodes + edges)`). `Some` (the gated loops) when there are too many edges to link, and
/// the test is skipped.
pub(crate) fn support_begin(
    n: usize,
    edges: &[PoseEdge],
    ws: &mut SolverBuffers<'_>,
) -> Option<usize> {
    ws.key.valid = false;
    if edges.len() >= LINK_NONE as usize {
        return Some(
            edges
                .iter()
                .zip(ws.edge_flags.iter())
                .filter(|(e, &f)| gated(e, f))
                .count(),
        );
    }
    let [_, _, head, ..] = &mut ws.scratch;
    for h in head.iter_mut().take(n) {
        *h = LINK_NONE;
    }
    for (k, (e, &f)) in edges.iter().zip(ws.edge_flags.iter()).enumerate().rev() {
        ws.edge_slot[k] = LINK_NONE;
        if gated(e, f) {
            let a = (e.from.0 as usize).min(e.to.0 as usize);
            ws.edge_slot[k] = head[a];
            head[a] = k as u32;
        }
    }
    None
}

/// The pair tests of [`support_loops`] for the loops whose lower end is `from..` until at
/// least `budget` work units were spent (at least one node): returns the next node and the
/// units.
pub(crate) fn support_pairs(
    n: usize,
    edges: &[PoseEdge],
    ws: &mut SolverBuffers<'_>,
    chi2: f64,
    from: usize,
    budget: u64,
) -> (usize, u64) {
    let [_, segment, head, ..] = &mut ws.scratch;
    let count_of = |slot: u32| slot >> LINK_BITS;
    let link_of = |slot: u32| slot & LINK_NONE;
    let mut spent = 0u64;
    let mut a1 = from;
    while a1 < n && spent < budget {
        spent += work::GATE_EDGE;
        let mut x = head[a1];
        while x != LINK_NONE {
            spent += work::GATE_LOOP;
            let ex = &edges[x as usize];
            let Some((_, b1, z1, c1)) = oriented(ex) else {
                x = link_of(ws.edge_slot[x as usize]);
                continue;
            };
            for a2 in a1..(a1 + SUPPORT_WINDOW + 1).min(n) {
                if segment[a2] != segment[a1] {
                    break;
                }
                let mut y = if a2 == a1 {
                    link_of(ws.edge_slot[x as usize])
                } else {
                    head[a2]
                };
                while y != LINK_NONE {
                    let next = link_of(ws.edge_slot[y as usize]);
                    let ey = &edges[y as usize];
                    spent += work::GATE_LOOP;
                    if let Some((_, b2, z2, c2)) = oriented(ey) {
                        if b1.abs_diff(b2) <= SUPPORT_WINDOW && segment[b1] == segment[b2] {
                            spent += work::GATE_PAIR;
                            let (ta, ca) = chain_between(ws.saved, ws.work, a2, a1);
                            let (tb, cb) = chain_between(ws.saved, ws.work, b1, b2);
                            let mut p = Se2::IDENTITY;
                            let mut cov: Block = [0.0; 9];
                            for (q, cq) in [(ta, ca), (z1, c1), (tb, cb)] {
                                let (jp, jq) = compose_jacobians(&p, &q);
                                cov = add(&sandwich(&jp, &cov), &sandwich(&jq, &cq));
                                p = p.compose(&q);
                            }
                            if mismatch(&p, &add(&cov, &c2), &z2).is_some_and(|m| m <= chi2) {
                                for k in [x, y] {
                                    let s = ws.edge_slot[k as usize];
                                    let c = (count_of(s) + 1).min(255);
                                    ws.edge_slot[k as usize] = link_of(s) | (c << LINK_BITS);
                                }
                            }
                        }
                    }
                    y = next;
                }
            }
            x = link_of(ws.edge_slot[x as usize]);
        }
        a1 += 1;
    }
    (a1, spent)
}

/// The end of [`support_loops`]: gated loops with too little support lose [`GATE_PASSED`];
/// returns the gated loops that keep their place.
pub(crate) fn support_end(edges: &[PoseEdge], ws: &mut SolverBuffers<'_>) -> usize {
    let count_of = |slot: u32| slot >> LINK_BITS;
    let mut kept = 0;
    for (k, e) in edges.iter().enumerate() {
        let f = ws.edge_flags[k];
        if !gated(e, f) {
            continue;
        }
        if count_of(ws.edge_slot[k]) >= SUPPORT_MIN {
            kept += 1;
        } else {
            ws.edge_flags[k] = f & 1;
        }
    }
    kept
}

/// The a posteriori variance of unit weight of the edges that the warm start uses (every
/// edge but the max-mixture loops without [`GATE_PASSED`]): their chi2 at the current estimate
/// over their redundancy (3 per edge minus 3 per free node), at most 1 (the test never gets
/// looser than the stated information) and 1 without redundancy.
pub(crate) fn unit_variance(nodes: &[PoseNode], edges: &[PoseEdge], ws: &SolverBuffers<'_>) -> f64 {
    let mut chi2 = 0.0;
    let mut count = 0usize;
    for ((e, t), &f) in edges
        .iter()
        .zip(ws.edge_trig.iter())
        .zip(ws.edge_flags.iter())
    {
        let mm = e.kind == EdgeKind::Loop && matches!(e.robust, RobustKernel::MaxMixture { .. });
        if mm && f & GATE_PASSED == 0 {
            continue;
        }
        if let Some(r) = edge_residual(nodes, e, t) {
            chi2 += quad(&info_block(e), &r);
            count += 1;
        }
    }
    let dof = 3.0 * (count as f64 - ws.key.vars as f64);
    let v = chi2 / dof;
    if dof >= 1.0 && v.is_finite() {
        v.clamp(1e-9, 1.0)
    } else {
        1.0
    }
}
