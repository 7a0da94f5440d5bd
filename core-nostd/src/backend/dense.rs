//! Small dense symmetric matrices on fixed stack storage, for the per-node work of pruning
//! (a Markov blanket of a few nodes: at most [`MAX_DIM`] scalar variables).
//!
//! Storage is a fixed `MAX_DIM x MAX_DIM` row-major array of which the top-left `n x n` block is
//! used, so nothing is allocated and the stack cost is known.

use nalgebra::Matrix3;

/// Largest dimension handled (nine poses of three variables).
pub const MAX_DIM: usize = 27;

/// A square matrix of dimension `n <= MAX_DIM` in fixed storage.
#[derive(Clone, Debug)]
pub struct DenseMatrix {
    n: usize,
    a: [f64; MAX_DIM * MAX_DIM],
}

impl DenseMatrix {
    /// The `n x n` zero matrix, or `None` when `n > MAX_DIM`.
    pub fn zeros(n: usize) -> Option<DenseMatrix> {
        (n <= MAX_DIM).then_some(DenseMatrix {
            n,
            a: [0.0; MAX_DIM * MAX_DIM],
        })
    }

    /// Dimension.
    #[inline]
    pub fn dim(&self) -> usize {
        self.n
    }

    /// Element `(r, c)`; zero outside the used block.
    #[inline]
    pub fn get(&self, r: usize, c: usize) -> f64 {
        if r < self.n && c < self.n {
            self.a.get(r * MAX_DIM + c).copied().unwrap_or(0.0)
        } else {
            0.0
        }
    }

    /// Sets element `(r, c)`; ignored outside the used block.
    #[inline]
    pub fn set(&mut self, r: usize, c: usize, v: f64) {
        if r < self.n && c < self.n {
            if let Some(x) = self.a.get_mut(r * MAX_DIM + c) {
                *x = v;
            }
        }
    }

    /// Adds `v` to element `(r, c)`.
    #[inline]
    pub fn add(&mut self, r: usize, c: usize, v: f64) {
        let old = self.get(r, c);
        self.set(r, c, old + v);
    }

    /// The 3x3 block whose top-left corner is `(3 bi, 3 bj)`.
    pub fn block3(&self, bi: usize, bj: usize) -> Matrix3<f64> {
        Matrix3::from_fn(|r, c| self.get(3 * bi + r, 3 * bj + c))
    }

    /// Adds `m` to the 3x3 block at `(3 bi, 3 bj)`.
    pub fn add_block3(&mut self, bi: usize, bj: usize, m: &Matrix3<f64>) {
        for r in 0..3 {
            for c in 0..3 {
                self.add(3 * bi + r, 3 * bj + c, m[(r, c)]);
            }
        }
    }

    /// In-place Cholesky factorisation `A = L L^T` (lower triangle kept); `false` when the
    /// matrix is not numerically positive definite.
    pub fn cholesky_in_place(&mut self) -> bool {
        let n = self.n;
        for j in 0..n {
            let mut d = self.get(j, j);
            for k in 0..j {
                let l = self.get(j, k);
                d -= l * l;
            }
            if d.is_nan() || d <= 0.0 || !d.is_finite() {
                return false;
            }
            let d = libm::sqrt(d);
            self.set(j, j, d);
            for i in (j + 1)..n {
                let mut s = self.get(i, j);
                for k in 0..j {
                    s -= self.get(i, k) * self.get(j, k);
                }
                self.set(i, j, s / d);
            }
        }
        for i in 0..n {
            for j in (i + 1)..n {
                self.set(i, j, 0.0);
            }
        }
        true
    }

    /// Inverse of a symmetric positive-definite matrix; `None` when it is not SPD.
    // The triangular solves read best with explicit indices.
    #[allow(clippy::needless_range_loop)]
    pub fn spd_inverse(&self) -> Option<DenseMatrix> {
        let n = self.n;
        let mut l = self.clone();
        if !l.cholesky_in_place() {
            return None;
        }
        // Solve L L^T X = I column by column.
        let mut inv = DenseMatrix::zeros(n)?;
        let mut col = [0.0f64; MAX_DIM];
        for c in 0..n {
            for (i, v) in col.iter_mut().enumerate().take(n) {
                *v = if i == c { 1.0 } else { 0.0 };
            }
            for i in 0..n {
                let mut s = col[i];
                for k in 0..i {
                    s -= l.get(i, k) * col[k];
                }
                col[i] = s / l.get(i, i);
            }
            for i in (0..n).rev() {
                let mut s = col[i];
                for k in (i + 1)..n {
                    s -= l.get(k, i) * col[k];
                }
                col[i] = s / l.get(i, i);
            }
            for (r, v) in col.iter().enumerate().take(n) {
                inv.set(r, c, *v);
            }
        }
        // Symmetrise away rounding differences.
        for r in 0..n {
            for c in (r + 1)..n {
                let v = 0.5 * (inv.get(r, c) + inv.get(c, r));
                inv.set(r, c, v);
                inv.set(c, r, v);
            }
        }
        Some(inv)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inverse_of_spd_matrix() {
        let mut m = DenseMatrix::zeros(4).unwrap();
        let vals = [
            [4.0, 1.0, 0.5, 0.0],
            [1.0, 3.0, 0.2, 0.1],
            [0.5, 0.2, 2.0, 0.3],
            [0.0, 0.1, 0.3, 1.5],
        ];
        for (r, row) in vals.iter().enumerate() {
            for (c, v) in row.iter().enumerate() {
                m.set(r, c, *v);
            }
        }
        let inv = m.spd_inverse().unwrap();
        for r in 0..4 {
            for c in 0..4 {
                let mut s = 0.0;
                for k in 0..4 {
                    s += m.get(r, k) * inv.get(k, c);
                }
                let expected = if r == c { 1.0 } else { 0.0 };
                assert!((s - expected).abs() < 1e-12, "({r},{c}) {s}");
            }
        }
    }

    #[test]
    fn rejects_indefinite_and_oversize() {
        let mut m = DenseMatrix::zeros(2).unwrap();
        m.set(0, 0, 1.0);
        m.set(1, 1, -1.0);
        assert!(m.spd_inverse().is_none());
        assert!(DenseMatrix::zeros(MAX_DIM + 1).is_none());
    }
}
