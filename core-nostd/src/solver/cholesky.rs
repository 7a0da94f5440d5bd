//! Numeric block Cholesky factorization `H = L L^T` with 3x3 blocks, left-looking, over the
//! pattern that [`super::ordering`] computed, and the two triangular solves.
//!
//! Column `j` is gathered into a dense block accumulator, updated by every earlier column `k`
//! with a block in row `j` (found through per-row linked lists of columns, advanced as the
//! factorization proceeds), then divided by the Cholesky factor of its diagonal block. The
//! inverse of each diagonal factor is stored, so both solves only multiply.

use super::workspace::{Block, Vec3};

const NONE: u32 = u32::MAX;

/// `acc -= a * b^T`.
#[inline(always)]
pub(crate) fn sub_abt(acc: &mut Block, a: &Block, b: &Block) {
    for r in 0..3 {
        let (a0, a1, a2) = (a[3 * r], a[3 * r + 1], a[3 * r + 2]);
        for c in 0..3 {
            acc[3 * r + c] -= a0 * b[3 * c] + a1 * b[3 * c + 1] + a2 * b[3 * c + 2];
        }
    }
}

/// `a * b^T`.
#[inline(always)]
fn mul_abt(a: &Block, b: &Block) -> Block {
    let mut out = [0.0; 9];
    for r in 0..3 {
        for c in 0..3 {
            out[3 * r + c] =
                a[3 * r] * b[3 * c] + a[3 * r + 1] * b[3 * c + 1] + a[3 * r + 2] * b[3 * c + 2];
        }
    }
    out
}

/// `m * v`.
#[inline(always)]
pub(crate) fn mul_v(m: &Block, v: &Vec3) -> Vec3 {
    [
        m[0] * v[0] + m[1] * v[1] + m[2] * v[2],
        m[3] * v[0] + m[4] * v[1] + m[5] * v[2],
        m[6] * v[0] + m[7] * v[1] + m[8] * v[2],
    ]
}

/// `m^T * v`.
#[inline(always)]
pub(crate) fn mul_tv(m: &Block, v: &Vec3) -> Vec3 {
    [
        m[0] * v[0] + m[3] * v[1] + m[6] * v[2],
        m[1] * v[0] + m[4] * v[1] + m[7] * v[2],
        m[2] * v[0] + m[5] * v[1] + m[8] * v[2],
    ]
}

/// The inverse of the lower Cholesky factor of the symmetric block `a` (lower triangle read),
/// or `None` when `a` is not positive definite.
#[inline]
pub(crate) fn chol_inverse(a: &Block) -> Option<Block> {
    chol_inverse_above(a, 0.0)
}

/// [`chol_inverse`], refused also when a pivot is not above `floor` (a block too close to
/// singular for its use, e.g. a landmark seen with too little parallax).
#[inline]
pub(crate) fn chol_inverse_above(a: &Block, floor: f64) -> Option<Block> {
    let d0 = a[0];
    if d0.is_nan() || d0 <= floor {
        return None;
    }
    let l00 = libm::sqrt(d0);
    let l10 = a[3] / l00;
    let l20 = a[6] / l00;
    let d1 = a[4] - l10 * l10;
    if d1.is_nan() || d1 <= floor {
        return None;
    }
    let l11 = libm::sqrt(d1);
    let l21 = (a[7] - l20 * l10) / l11;
    let d2 = a[8] - l20 * l20 - l21 * l21;
    if !d2.is_finite() || d2 <= floor {
        return None;
    }
    let l22 = libm::sqrt(d2);
    let i00 = 1.0 / l00;
    let i11 = 1.0 / l11;
    let i22 = 1.0 / l22;
    let i10 = -l10 * i00 * i11;
    let i21 = -l21 * i11 * i22;
    let i20 = -(l20 * i00 + l21 * i10) * i22;
    Some([i00, 0.0, 0.0, i10, i11, 0.0, i20, i21, i22])
}

/// Factorizes in place. On entry `diag[j]` holds `H_jj` and `values[p]` the block of `H` at
/// (`rows[p]`, column of `p`), zero where only fill exists. On exit `values` holds `L` and
/// `diag[j]` holds `L_jj^-1`.
///
/// Returns `Err(j)` with the first column whose pivot block is not positive definite.
#[allow(clippy::too_many_arguments)]
pub(crate) fn factorize(
    n: usize,
    col_end: &[u32],
    rows: &[u32],
    values: &mut [Block],
    diag: &mut [Block],
    work: &mut [Block],
    row_head: &mut [u32],
    link: &mut [u32],
    cursor: &mut [u32],
) -> Result<(), usize> {
    factorize_begin(n, row_head);
    let mut f = Factor {
        col_end,
        rows,
        values,
        diag,
        work,
        row_head,
        link,
        cursor,
    };
    factorize_columns(&mut f, 0, n, u64::MAX).map(|_| ())
}

/// The borrowed storage of a factorization that [`factorize_columns`] advances.
pub(crate) struct Factor<'a> {
    pub col_end: &'a [u32],
    pub rows: &'a [u32],
    pub values: &'a mut [Block],
    pub diag: &'a mut [Block],
    pub work: &'a mut [Block],
    pub row_head: &'a mut [u32],
    pub link: &'a mut [u32],
    pub cursor: &'a mut [u32],
}

/// Starts a factorization of `n` columns: no column has updates pending yet.
pub(crate) fn factorize_begin(n: usize, row_head: &mut [u32]) {
    for h in row_head.iter_mut().take(n) {
        *h = NONE;
    }
}

/// Factorizes columns `from..n` in order (see [`factorize`]; the linked lists of pending
/// updates live in `f`, so a factorization may stop after any column and resume later with
/// the same result to the bit) until at least `budget` blocks were touched. Returns the next
/// column and the blocks touched (one per `3x3` multiply-subtract, one per block scaled by the
/// pivot), or `Err(j)` as [`factorize`].
pub(crate) fn factorize_columns(
    f: &mut Factor<'_>,
    from: usize,
    n: usize,
    budget: u64,
) -> Result<(usize, u64), usize> {
    let Factor {
        col_end,
        rows,
        values,
        diag,
        work,
        row_head,
        link,
        cursor,
    } = f;
    let mut touched = 0u64;
    let mut start = if from == 0 {
        0
    } else {
        col_end[from - 1] as usize
    };
    for j in from..n {
        if touched >= budget {
            return Ok((j, touched));
        }
        let end = col_end[j] as usize;
        work[j] = diag[j];
        for p in start..end {
            work[rows[p] as usize] = values[p];
        }
        let mut k = row_head[j];
        while k != NONE {
            let next_k = link[k as usize];
            let p = cursor[k as usize] as usize;
            let kend = col_end[k as usize] as usize;
            let ljk = values[p];
            sub_abt(&mut work[j], &ljk, &ljk);
            for q in p + 1..kend {
                let r = rows[q] as usize;
                sub_abt(&mut work[r], &values[q], &ljk);
            }
            touched += (kend - p) as u64;
            if p + 1 < kend {
                cursor[k as usize] = (p + 1) as u32;
                let r = rows[p + 1] as usize;
                link[k as usize] = row_head[r];
                row_head[r] = k;
            }
            k = next_k;
        }
        let inv = chol_inverse(&work[j]).ok_or(j)?;
        diag[j] = inv;
        for p in start..end {
            values[p] = mul_abt(&work[rows[p] as usize], &inv);
        }
        touched += (end - start) as u64 + 1;
        if start < end {
            cursor[j] = start as u32;
            let r = rows[start] as usize;
            link[j] = row_head[r];
            row_head[r] = j as u32;
        }
        start = end;
    }
    Ok((n, touched))
}

/// Solves `L L^T x = b` in place (`x` overwrites `b`).
pub(crate) fn solve_in_place(
    n: usize,
    col_end: &[u32],
    rows: &[u32],
    values: &[Block],
    diag: &[Block],
    b: &mut [Vec3],
) {
    forward(n, col_end, rows, values, diag, b, 0, u64::MAX);
    backward(col_end, rows, values, diag, b, n, u64::MAX);
}

/// The forward solve `L y = b` over columns `from..n`, until at least `budget` blocks were
/// touched; returns the next column and the blocks touched.
#[allow(clippy::too_many_arguments)]
pub(crate) fn forward(
    n: usize,
    col_end: &[u32],
    rows: &[u32],
    values: &[Block],
    diag: &[Block],
    b: &mut [Vec3],
    from: usize,
    budget: u64,
) -> (usize, u64) {
    let mut touched = 0u64;
    let mut start = if from == 0 {
        0
    } else {
        col_end[from - 1] as usize
    };
    for j in from..n {
        if touched >= budget {
            return (j, touched);
        }
        let end = col_end[j] as usize;
        let y = mul_v(&diag[j], &b[j]);
        b[j] = y;
        for p in start..end {
            let r = rows[p] as usize;
            let d = mul_v(&values[p], &y);
            b[r][0] -= d[0];
            b[r][1] -= d[1];
            b[r][2] -= d[2];
        }
        touched += (end - start) as u64 + 1;
        start = end;
    }
    (n, touched)
}

/// The backward solve `L^T x = y` over columns `until-1` down to 0, until at least `budget`
/// blocks were touched; returns the number of columns still to solve (0 when done) and the
/// blocks touched.
pub(crate) fn backward(
    col_end: &[u32],
    rows: &[u32],
    values: &[Block],
    diag: &[Block],
    b: &mut [Vec3],
    until: usize,
    budget: u64,
) -> (usize, u64) {
    let mut touched = 0u64;
    for j in (0..until).rev() {
        if touched >= budget {
            return (j + 1, touched);
        }
        let start = if j == 0 { 0 } else { col_end[j - 1] as usize };
        let end = col_end[j] as usize;
        let mut acc = b[j];
        for p in start..end {
            let d = mul_tv(&values[p], &b[rows[p] as usize]);
            acc[0] -= d[0];
            acc[1] -= d[1];
            acc[2] -= d[2];
        }
        b[j] = mul_tv(&diag[j], &acc);
        touched += (end - start) as u64 + 1;
    }
    (0, touched)
}
