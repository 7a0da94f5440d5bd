//! The residuals the window minimises and the small blocks its solve inverts: a landmark seen
//! from a planar robot pose through the mounting, the motion prior's error, and the damped
//! 3x3 landmark block.

use super::*;

/// A world point in the robot frame of a robot at `pose` (on the floor, z = 0) whose heading
/// has cosine `c` and sine `s`, and in the camera frame.
pub(super) fn robot_and_camera(
    mount: &CameraExtrinsic,
    pose: &Se2,
    (c, s): (f64, f64),
    point: &Vector3<f64>,
) -> (Vector3<f64>, Vector3<f64>) {
    let (dx, dy) = (point.x - pose.x, point.y - pose.y);
    let q = Vector3::new(c * dx + s * dy, -s * dx + c * dy, point.z);
    (q, mount.robot_to_camera(&q))
}

/// The predicted pixel minus the measured one, or `None` where the camera model does not
/// project the point (or the result is not finite).
pub(crate) fn residual(
    model: &CameraModel,
    mount: &CameraExtrinsic,
    pose: &Se2,
    trig: (f64, f64),
    point: &Vector3<f64>,
    px: &Vector2<f64>,
) -> Option<Vector2<f64>> {
    let (_, p_cam) = robot_and_camera(mount, pose, trig, point);
    let r = model.project(&p_cam)? - px;
    // A NaN would stall every cost comparison; the sum is finite only if both terms are.
    (r.x + r.y).is_finite().then_some(r)
}

/// [`residual`] and its derivatives with respect to the robot pose `(x, y, theta)` and to the
/// landmark.
pub(crate) fn reprojection(
    model: &CameraModel,
    mount: &CameraExtrinsic,
    pose: &Se2,
    (c, s): (f64, f64),
    point: &Vector3<f64>,
    px: &Vector2<f64>,
) -> Option<(Vector2<f64>, Matrix2x3<f64>, Matrix2x3<f64>)> {
    let (q, p_cam) = robot_and_camera(mount, pose, (c, s), point);
    let r = model.project(&p_cam)? - px;
    let a = model.jacobian(&p_cam)? * mount.rotation().transpose();
    // dq/dP is the transposed heading rotation; dq/d(x, y, theta) in columns.
    let rot_t = crate::geom::yaw_rotation(c, s).transpose();
    let dq_dpose = Matrix3::new(-c, -s, q.y, s, -c, -q.x, 0.0, 0.0, 0.0);
    let (jx, jl) = (a * dq_dpose, a * rot_t);
    // One NaN would poison every block it touches; a sum is finite only if all terms are.
    (r.sum() + jx.sum() + jl.sum())
        .is_finite()
        .then_some((r, jx, jl))
}

/// The Huber weight and loss of a whitened residual of squared norm `e2`.
pub(crate) fn huber(e2: f64, k: f64) -> (f64, f64) {
    let e = libm::sqrt(e2);
    if e <= k {
        (1.0, e2)
    } else {
        (k / e, 2.0 * k * e - k * k)
    }
}

/// The motion prior's residual (measured-relative, angle wrapped) and its Jacobians with
/// respect to the `from` and `to` poses.
pub(super) fn prior_residual(
    p: &MotionPrior,
    from: &Se2,
    to: &Se2,
) -> (Vector3<f64>, Matrix3<f64>, Matrix3<f64>) {
    let rel = from.between(to);
    let e = Vector3::new(
        rel.x - p.motion.x,
        rel.y - p.motion.y,
        wrap_angle(rel.theta - p.motion.theta),
    );
    let (ja, jb) = from.between_jacobians(to);
    (e, ja, jb)
}

/// The inverse of a symmetric 3x3 block by its Cholesky factor, or `None` when a pivot falls
/// below `ratio` times the largest diagonal term (or is not positive).
pub(super) fn spd3_inverse(m: &Matrix3<f64>, ratio: f64) -> Option<Matrix3<f64>> {
    let scale = m[(0, 0)].max(m[(1, 1)]).max(m[(2, 2)]);
    let floor = (ratio * scale).max(0.0);
    let rows = crate::solver::rows_of(m);
    let li = Matrix3::from_row_slice(&crate::solver::chol_inverse_above(&rows, floor)?);
    // inv(m) = inv(L)^T inv(L).
    let inv = li.transpose() * li;
    inv.iter().all(|v| v.is_finite()).then_some(inv)
}

/// `m` with `lambda` times its diagonal added to the diagonal (Marquardt's scaling, which
/// keeps the damping in each unknown's own units).
pub(super) fn damped(m: &Matrix3<f64>, lambda: f64) -> Matrix3<f64> {
    let mut d = *m;
    for i in 0..3 {
        d[(i, i)] += lambda * m[(i, i)].max(f64::MIN_POSITIVE);
    }
    d
}
