//! The reduced pose system of the window, solved in place by a dense Cholesky factorisation.
//!
//! The matrix is kept as 3x3 blocks so its capacity follows the window's keyframe count
//! (`[[Matrix3; N]; N]` needs no const arithmetic); the factorisation works on scalars through
//! two accessors. After the landmarks are eliminated every pair of keyframes that share a
//! landmark is coupled, so a window is dense and a sparse ordering would buy nothing.

use nalgebra::{Matrix3, Vector3};

fn get<const N: usize>(a: &[[Matrix3<f64>; N]; N], i: usize, j: usize) -> f64 {
    a.get(i / 3)
        .and_then(|row| row.get(j / 3))
        .map_or(0.0, |b| b[(i % 3, j % 3)])
}

fn set<const N: usize>(a: &mut [[Matrix3<f64>; N]; N], i: usize, j: usize, value: f64) {
    if let Some(b) = a.get_mut(i / 3).and_then(|row| row.get_mut(j / 3)) {
        b[(i % 3, j % 3)] = value;
    }
}

fn get_v<const N: usize>(v: &[Vector3<f64>; N], i: usize) -> f64 {
    v.get(i / 3).map_or(0.0, |b| b[i % 3])
}

fn set_v<const N: usize>(v: &mut [Vector3<f64>; N], i: usize, value: f64) {
    if let Some(b) = v.get_mut(i / 3) {
        b[i % 3] = value;
    }
}

/// Solves `A x = b` for the leading `blocks` x `blocks` blocks of the symmetric `a` (only its
/// lower triangle is read, then overwritten by the factor; the blocks above the diagonal are
/// neither read nor written), `b` overwritten by `x`. `None` when `a`
/// is not positive definite (a pivot not above zero, or not finite).
pub(super) fn cholesky_solve<const N: usize>(
    a: &mut [[Matrix3<f64>; N]; N],
    b: &mut [Vector3<f64>; N],
    blocks: usize,
) -> Option<()> {
    let n = 3 * blocks.min(N);
    // Column by column: A = L L^T with L in the lower triangle.
    for j in 0..n {
        let mut d = get(a, j, j);
        for k in 0..j {
            let l = get(a, j, k);
            d -= l * l;
        }
        if !(d.is_finite() && d > 0.0) {
            return None;
        }
        let ljj = libm::sqrt(d);
        set(a, j, j, ljj);
        for i in (j + 1)..n {
            let mut s = get(a, i, j);
            for k in 0..j {
                s -= get(a, i, k) * get(a, j, k);
            }
            set(a, i, j, s / ljj);
        }
    }
    // L y = b, then L^T x = y.
    for i in 0..n {
        let mut s = get_v(b, i);
        for k in 0..i {
            s -= get(a, i, k) * get_v(b, k);
        }
        set_v(b, i, s / get(a, i, i));
    }
    for i in (0..n).rev() {
        let mut s = get_v(b, i);
        for k in (i + 1)..n {
            s -= get(a, k, i) * get_v(b, k);
        }
        set_v(b, i, s / get(a, i, i));
    }
    Some(())
}
