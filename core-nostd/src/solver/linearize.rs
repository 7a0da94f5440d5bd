//! Residuals, Jacobians and the assembly of the normal equations `H dx = -g` straight into the
//! factor's storage.
//!
//! For an edge `i -> j` with measurement `z` (angle `a_z`), write `R(a)` for the rotation by
//! `a`, `t = R(a_i)^T (t_j - t_i)` for the translation of `x_j` seen from `x_i`. The residual is
//! `e = [R(a_z)^T (t - t_z), wrap(a_j - a_i - a_z)]`; its Jacobians are
//! `J_j = diag(R(a_i + a_z)^T, 1)` and `J_i = -J_j` plus, in the angle column, the derivative
//! `R(a_z)^T [t_y, -t_x]` of the translation part.

use super::ordering::{NO_SLOT, TRANSPOSED};
use super::workspace::{rows_of, Block, Vec3};
use super::SolverBuffers;
use crate::graph::residual::{prior_residual, relative_residual};
use crate::graph::{EdgeKind, PoseEdge, PoseNode};

const NONE: u32 = u32::MAX;

/// The residual of `edge` at the current poses.
#[inline(always)]
pub(crate) fn edge_residual(nodes: &[PoseNode], edge: &PoseEdge, trig: &[f64; 2]) -> Option<Vec3> {
    let xi = &nodes.get(edge.from.0 as usize)?.pose;
    if edge.kind == EdgeKind::Prior {
        return Some(prior_residual(xi, &edge.measurement, trig[0], trig[1]));
    }
    let xj = &nodes.get(edge.to.0 as usize)?.pose;
    let (ci, si) = (libm::cos(xi.theta), libm::sin(xi.theta));
    Some(relative_residual(xi, ci, si, xj, &edge.measurement, trig[0], trig[1]).0)
}

/// `e^T M e` for a symmetric block.
#[inline(always)]
pub(crate) fn quad(m: &Block, e: &Vec3) -> f64 {
    m[0] * e[0] * e[0]
        + m[4] * e[1] * e[1]
        + m[8] * e[2] * e[2]
        + 2.0 * (m[1] * e[0] * e[1] + m[2] * e[0] * e[2] + m[5] * e[1] * e[2])
}

/// The information of an edge as a block.
#[inline(always)]
pub(crate) fn info_block(edge: &PoseEdge) -> Block {
    rows_of(&edge.information)
}

/// Whether `edge` takes part while only nodes below `limit` may close loops.
#[inline(always)]
pub(crate) fn within(edge: &PoseEdge, limit: usize) -> bool {
    edge.kind != EdgeKind::Loop || (edge.from.0 as usize) < limit && (edge.to.0 as usize) < limit
}

/// Robust cost and plain chi2 of the edges within `limit` (see [`within`]).
pub(crate) fn evaluate(
    nodes: &[PoseNode],
    edges: &[PoseEdge],
    trig: &[[f64; 2]],
    limit: usize,
    warm: Warm,
    flags: &[u8],
) -> (f64, f64) {
    let mut acc = (0.0, 0.0);
    evaluate_range(
        nodes,
        edges,
        trig,
        limit,
        warm,
        flags,
        0..edges.len(),
        &mut acc,
    );
    acc
}

/// [`evaluate`] over the edges in `range`, added to `acc` (robust cost, chi2) in edge order,
/// so that a sum split over several ranges is the same to the bit as one pass.
#[allow(clippy::too_many_arguments)]
pub(crate) fn evaluate_range(
    nodes: &[PoseNode],
    edges: &[PoseEdge],
    trig: &[[f64; 2]],
    limit: usize,
    warm: Warm,
    flags: &[u8],
    range: core::ops::Range<usize>,
    acc: &mut (f64, f64),
) {
    let (mut cost, mut chi2) = *acc;
    let start = range.start;
    let picked = edges.get(range.clone()).unwrap_or_default();
    let picked_trig = trig.get(range).unwrap_or_default();
    for (off, (edge, t)) in picked.iter().zip(picked_trig).enumerate() {
        let k = start + off;
        if !within(edge, limit) {
            continue;
        }
        if matches!(warm, Warm::Nominal | Warm::Dcs)
            && flags
                .get(k)
                .is_some_and(|f| f & super::gate::GATE_PASSED == 0)
        {
            continue;
        }
        if let Some(e) = edge_residual(nodes, edge, t) {
            let c = quad(&info_block(edge), &e);
            chi2 += c;
            cost += weigh(edge, c, warm, flags.get(k).copied().unwrap_or(0)).1;
        }
    }
    *acc = (cost, chi2);
}

/// The system being assembled: slices of the solver's workspace.
pub(crate) struct System<'s> {
    pub node_var: &'s [u32],
    pub flags: &'s [u8],
    /// How max-mixture edges are weighted.
    pub warm: Warm,
    pub edge_slot: &'s [u32],
    pub trig: &'s [[f64; 2]],
    pub diag: &'s mut [Block],
    pub values: &'s mut [Block],
    pub rhs: &'s mut [Vec3],
}

impl<'s> System<'s> {
    /// The assembly's view of the solver's workspace.
    pub(crate) fn of(ws: &'s mut SolverBuffers<'_>, warm: Warm) -> Self {
        System {
            node_var: ws.node_var,
            flags: ws.edge_flags,
            warm,
            edge_slot: ws.edge_slot,
            trig: ws.edge_trig,
            diag: ws.diag,
            values: ws.values,
            rhs: ws.rhs,
        }
    }
}

#[inline(always)]
fn add(acc: &mut Block, m: &Block) {
    for (a, v) in acc.iter_mut().zip(m) {
        *a += v;
    }
}

#[inline(always)]
fn add_t(acc: &mut Block, m: &Block) {
    for r in 0..3 {
        for c in 0..3 {
            acc[3 * r + c] += m[3 * c + r];
        }
    }
}

#[inline(always)]
fn sub_v(acc: &mut Vec3, v: &Vec3) {
    acc[0] -= v[0];
    acc[1] -= v[1];
    acc[2] -= v[2];
}

/// Which unknowns an assembly linearizes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Stage {
    /// Positions and headings (the Gauss-Newton system).
    Full,
    /// Headings only, from the angle residuals alone: with the angle differences taken at the
    /// current estimate, this is linear, and one solve gives every heading consistent with
    /// all loops at once (the first step of a LAGO-style initialisation).
    Headings,
    /// Positions only, headings held: again linear, one solve places every position.
    Positions,
}

/// Assembles `H` and `-g` at the current poses (with the robust weights of this estimate) and
/// returns the robust cost and the plain chi2 there.
pub(crate) fn assemble(
    nodes: &[PoseNode],
    edges: &[PoseEdge],
    vars: usize,
    nnz: usize,
    stage: Stage,
    s: &mut System<'_>,
) -> (f64, f64) {
    assemble_begin(vars, nnz, s);
    let mut acc = (0.0, 0.0);
    assemble_edges(nodes, edges, 0..edges.len(), stage, s, &mut acc);
    assemble_end(vars, stage, s);
    acc
}

/// The first part of [`assemble`]: clears `H` and `-g`.
pub(crate) fn assemble_begin(vars: usize, nnz: usize, s: &mut System<'_>) {
    for d in s.diag.iter_mut().take(vars) {
        *d = [0.0; 9];
    }
    for v in s.values.iter_mut().take(nnz) {
        *v = [0.0; 9];
    }
    for r in s.rhs.iter_mut().take(vars) {
        *r = [0.0; 3];
    }
}

/// The middle part of [`assemble`]: adds the edges in `range` (in order, so a split assembly
/// sums exactly as one pass) and their robust cost and chi2 to `acc`.
pub(crate) fn assemble_edges(
    nodes: &[PoseNode],
    edges: &[PoseEdge],
    range: core::ops::Range<usize>,
    stage: Stage,
    s: &mut System<'_>,
    acc: &mut (f64, f64),
) {
    let (mut cost, mut chi2) = *acc;
    let start = range.start;
    for (off, edge) in edges.get(range).unwrap_or_default().iter().enumerate() {
        let k = start + off;
        let (Some(ni), Some(nj)) = (
            nodes.get(edge.from.0 as usize),
            nodes.get(edge.to.0 as usize),
        ) else {
            continue;
        };
        if s.flags[k] & 1 == 0 {
            continue;
        }
        let [cz, sz] = s.trig[k];
        let omega = info_block(edge);
        let pi = s.node_var[edge.from.0 as usize];
        if edge.kind == EdgeKind::Prior {
            let mut e = prior_residual(&ni.pose, &edge.measurement, cz, sz);
            let c = quad(&omega, &e);
            let (w, rc) = weigh(edge, c, s.warm, s.flags[k]);
            chi2 += c;
            cost += rc;
            if pi == NONE {
                continue;
            }
            let mut j: Block = [cz, sz, 0.0, -sz, cz, 0.0, 0.0, 0.0, 1.0];
            restrict(stage, &mut e, &mut j, None);
            let wo = scale(&omega, w);
            let a = mul(&wo, &j);
            add(&mut s.diag[pi as usize], &mul_atb(&j, &a));
            sub_v(&mut s.rhs[pi as usize], &mul_atv(&a, &e));
            continue;
        }
        let xi = &ni.pose;
        let (ci, si) = (libm::cos(xi.theta), libm::sin(xi.theta));
        let (mut e, [ca, sa, gx, gy]) =
            relative_residual(xi, ci, si, &nj.pose, &edge.measurement, cz, sz);
        let c = quad(&omega, &e);
        let (w, rc) = weigh(edge, c, s.warm, s.flags[k]);
        chi2 += c;
        cost += rc;
        let pj = s.node_var[edge.to.0 as usize];
        if pi == NONE && pj == NONE {
            continue;
        }
        let wo = scale(&omega, w);
        let mut jj: Block = [ca, sa, 0.0, -sa, ca, 0.0, 0.0, 0.0, 1.0];
        let mut ji: Block = [-ca, -sa, gx, sa, -ca, gy, 0.0, 0.0, -1.0];
        restrict(stage, &mut e, &mut jj, Some(&mut ji));
        let a = mul(&wo, &jj);
        if pj != NONE {
            add(&mut s.diag[pj as usize], &mul_atb(&jj, &a));
            sub_v(&mut s.rhs[pj as usize], &mul_atv(&a, &e));
        }
        if pi != NONE {
            let bi = mul(&wo, &ji);
            add(&mut s.diag[pi as usize], &mul_atb(&ji, &bi));
            sub_v(&mut s.rhs[pi as usize], &mul_atv(&bi, &e));
            let slot = s.edge_slot[k];
            if pj != NONE && slot != NO_SLOT {
                let hij = mul_atb(&ji, &a);
                let idx = (slot & !TRANSPOSED) as usize;
                if slot & TRANSPOSED == 0 {
                    add(&mut s.values[idx], &hij);
                } else {
                    add_t(&mut s.values[idx], &hij);
                }
            }
        }
    }
    *acc = (cost, chi2);
}

/// The last part of [`assemble`]: the unknowns a stage leaves out stay at zero with a unit
/// diagonal.
pub(crate) fn assemble_end(vars: usize, stage: Stage, s: &mut System<'_>) {
    let pad = match stage {
        Stage::Full => None,
        Stage::Headings => Some([0, 4]),
        Stage::Positions => Some([8, 8]),
    };
    if let Some(idx) = pad {
        for d in s.diag.iter_mut().take(vars) {
            d[idx[0]] = 1.0;
            d[idx[1]] = 1.0;
        }
    }
}

/// How max-mixture edges are weighted during the warm start of a robust solve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Warm {
    /// By their own model (no warm start).
    Off,
    /// By their own model, except that a max-mixture loop the warm start did not use (no
    /// [`super::gate::GATE_PASSED`]) stays on its widest component while its chi2 exceeds this
    /// quantile: a loop first has to be consistent with the map at this confidence.
    Admit(f64),
    /// Nominal component (the loops that passed the odometry gate).
    Nominal,
    /// Dynamic covariance scaling (Agarwal et al.): information scaled by `s^2` with
    /// `s = min(1, 2 / (1 + chi2))`.
    Dcs,
}

/// The robust weight and cost of an edge under `warm`.
#[inline(always)]
pub(crate) fn weigh(edge: &PoseEdge, chi2: f64, warm: Warm, flag: u8) -> (f64, f64) {
    if warm == Warm::Off || !matches!(edge.robust, crate::graph::RobustKernel::MaxMixture { .. }) {
        return edge.robust.weigh(chi2);
    }
    match warm {
        Warm::Admit(limit) => {
            if flag & super::gate::GATE_PASSED == 0 && chi2 > limit {
                edge.robust.weigh_widest(chi2)
            } else {
                edge.robust.weigh(chi2)
            }
        }
        Warm::Dcs => {
            let s = (2.0 / (1.0 + chi2)).min(1.0);
            (s * s, s * s * chi2)
        }
        _ => {
            let w = super::gate::stored_weight(flag);
            (w, w * chi2)
        }
    }
}

/// Restricts a residual and its Jacobians to the unknowns of `stage`.
#[inline(always)]
fn restrict(stage: Stage, e: &mut Vec3, jj: &mut Block, ji: Option<&mut Block>) {
    match stage {
        Stage::Full => {}
        Stage::Headings => {
            e[0] = 0.0;
            e[1] = 0.0;
            *jj = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, jj[8]];
            if let Some(ji) = ji {
                *ji = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, ji[8]];
            }
        }
        Stage::Positions => {
            jj[2] = 0.0;
            jj[5] = 0.0;
            jj[8] = 0.0;
            if let Some(ji) = ji {
                ji[2] = 0.0;
                ji[5] = 0.0;
                ji[8] = 0.0;
            }
        }
    }
}

#[inline(always)]
fn scale(m: &Block, w: f64) -> Block {
    let mut out = *m;
    if w != 1.0 {
        for v in out.iter_mut() {
            *v *= w;
        }
    }
    out
}

/// `a * b`.
#[inline(always)]
fn mul(a: &Block, b: &Block) -> Block {
    let mut out = [0.0; 9];
    for r in 0..3 {
        for c in 0..3 {
            out[3 * r + c] = a[3 * r] * b[c] + a[3 * r + 1] * b[3 + c] + a[3 * r + 2] * b[6 + c];
        }
    }
    out
}

/// `a^T * b`.
#[inline(always)]
fn mul_atb(a: &Block, b: &Block) -> Block {
    let mut out = [0.0; 9];
    for r in 0..3 {
        for c in 0..3 {
            out[3 * r + c] = a[r] * b[c] + a[3 + r] * b[3 + c] + a[6 + r] * b[6 + c];
        }
    }
    out
}

/// `a^T * v`.
#[inline(always)]
fn mul_atv(a: &Block, v: &Vec3) -> Vec3 {
    [
        a[0] * v[0] + a[3] * v[1] + a[6] * v[2],
        a[1] * v[0] + a[4] * v[1] + a[7] * v[2],
        a[2] * v[0] + a[5] * v[1] + a[8] * v[2],
    ]
}
