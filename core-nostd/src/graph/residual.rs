//! The residuals of the pose graph's edges (the error terms of eq. 9): a relative edge
//! `i -> j` with measurement `z` and a prior on one node. They belong to the graph, not to the
//! solver: the graph reports an edge's error with them and the solver linearizes them.
//!
//! With `R(a)` the rotation by `a` and `t = R(a_i)^T (t_j - t_i)`, a relative edge's residual
//! is `e = [R(a_z)^T (t - t_z), wrap(a_j - a_i - a_z)]`.

use crate::geom::{wrap_angle, Se2};

/// Residual of a relative edge and the pieces of its Jacobians: `(e, ca, sa, gx, gy)` with
/// `J_j = [[ca, sa, 0], [-sa, ca, 0], [0, 0, 1]]` and
/// `J_i = [[-ca, -sa, gx], [sa, -ca, gy], [0, 0, -1]]`.
#[inline(always)]
pub(crate) fn relative_residual(
    xi: &Se2,
    ci: f64,
    si: f64,
    xj: &Se2,
    z: &Se2,
    cz: f64,
    sz: f64,
) -> ([f64; 3], [f64; 4]) {
    let dx = xj.x - xi.x;
    let dy = xj.y - xi.y;
    let tx = ci * dx + si * dy;
    let ty = -si * dx + ci * dy;
    let ux = tx - z.x;
    let uy = ty - z.y;
    let e = [
        cz * ux + sz * uy,
        -sz * ux + cz * uy,
        wrap_angle(xj.theta - xi.theta - z.theta),
    ];
    let ca = ci * cz - si * sz;
    let sa = si * cz + ci * sz;
    let gx = cz * ty - sz * tx;
    let gy = -sz * ty - cz * tx;
    (e, [ca, sa, gx, gy])
}

/// Residual of a prior `z` on `x`: `e = [R(a_z)^T (t - t_z), wrap(a - a_z)]`, Jacobian
/// `diag(R(a_z)^T, 1)`.
#[inline(always)]
pub(crate) fn prior_residual(x: &Se2, z: &Se2, cz: f64, sz: f64) -> [f64; 3] {
    let ux = x.x - z.x;
    let uy = x.y - z.y;
    [
        cz * ux + sz * uy,
        -sz * ux + cz * uy,
        wrap_angle(x.theta - z.theta),
    ]
}
