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

use nalgebra::{Matrix3, Vector3};

use super::workspace::{Block, SolverBuffers};
use crate::geom::{spd_inverse, squared_mahalanobis, wrap_angle, Se2, UncertainPose};
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

fn to_block(m: &Matrix3<f64>) -> Block {
    let mut b = [0.0; 9];
    for r in 0..3 {
        for c in 0..3 {
            b[3 * r + c] = m[(r, c)];
        }
    }
    b
}

fn from_block(b: &Block) -> Matrix3<f64> {
    Matrix3::from_row_slice(b)
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
    let mut cur = UncertainPose::exact(Se2::IDENTITY);
    for k in 0..n {
        ws.saved[k] = cur.pose;
        ws.work[k] = to_block(&cur.cov);
        segment[k] = seg;
        let step = edges.get(odo[k] as usize).and_then(|e| {
            let cov = spd_inverse(&e.information)?;
            let rel = UncertainPose {
                pose: e.measurement,
                cov,
            };
            Some(if e.from.0 as usize == k {
                rel
            } else {
                rel.inverse()
            })
        });
        match step {
            Some(rel) if odo[k] != NONE => cur = cur.compound(&rel),
            _ => {
                seg += 1;
                cur = UncertainPose::exact(Se2::IDENTITY);
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
        let Some(cov_z) = spd_inverse(&e.information) else {
            continue;
        };
        // Measurement from the earlier node to the later one.
        let (a, b, z) = if i < j {
            (
                i,
                j,
                UncertainPose {
                    pose: e.measurement,
                    cov: cov_z,
                },
            )
        } else {
            (
                j,
                i,
                UncertainPose {
                    pose: e.measurement,
                    cov: cov_z,
                }
                .inverse(),
            )
        };
        let (pa, pb) = (ws.saved[a], ws.saved[b]);
        let t = pa.between(&pb);
        let (ja, _) = pa.compose_jacobians(&t);
        let sa = from_block(&ws.work[a]);
        let sb = from_block(&ws.work[b]);
        let (c, s) = (libm::cos(pa.theta), libm::sin(pa.theta));
        let rot = Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0);
        let cov_t = rot.transpose() * (sb - ja * sa * ja.transpose()) * rot;
        let d = Vector3::new(
            t.x - z.pose.x,
            t.y - z.pose.y,
            wrap_angle(t.theta - z.pose.theta),
        );
        let total = (cov_t + cov_t.transpose()) * 0.5 + z.cov;
        if let Some(m) = squared_mahalanobis(&d, &total) {
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
