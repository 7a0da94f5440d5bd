//! Marginalization of one pose-graph node and sparsification of the result into a Chow-Liu
//! tree (the pruning step of the paper's section III-D, after Kretzschmar and Stachniss and the
//! generic linear constraints of Carlevaris-Bianco et al.).
//!
//! Eliminating a node `m` linearizes every factor that touches it at the current estimate,
//! builds their joint information over `m` and its Markov blanket `B`, and takes the Schur
//! complement `H_BB - H_Bm H_mm^-1 H_mB`: the exact Gaussian marginal over `B`. That factor is
//! dense (every blanket pair is linked), so it is replaced by `|B| - 1` relative-pose edges
//! chosen by a maximum spanning tree of pairwise information. Each new edge measures the
//! current relative pose of its two nodes, with the information of that relative pose under
//! the dense marginal. The marginal is invariant to moving the whole blanket, so its relative
//! covariances are computed with the first blanket node held fixed.
//!
//! Factor errors follow the g2o convention, `e = z^-1 (+) (x_i^-1 (+) x_j)`, whose Jacobians are
//! the `between` Jacobians rotated by `-theta_z`.

use heapless::Vec;
use nalgebra::Matrix3;

use super::chow_liu::{maximum_spanning_tree, MAX_TREE_NODES};
use super::dense::DenseMatrix;
use crate::geom::{information_heuristic, spd_inverse, symmetrize, yaw_rotation, Info3, Se2};

/// Largest Markov blanket handled (with the eliminated node, `3 (k + 1)` fits
/// [`super::dense::MAX_DIM`]).
pub const MAX_BLANKET: usize = MAX_TREE_NODES - 1;

/// Cap on the information of a new edge along any axis, so that near-rigid relations
/// (zero-constraints) keep the normal equations well conditioned.
pub const MAX_EDGE_INFORMATION: f64 = 1e12;

/// A relative-pose factor in local indices: `0` is the node being eliminated, `1..=k` its
/// blanket nodes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalFactor {
    /// Local index of the first pose.
    pub from: u8,
    /// Local index of the second pose.
    pub to: u8,
    /// Measured relative pose `x_from^-1 (+) x_to`.
    pub measurement: Se2,
    /// Its information.
    pub information: Info3,
}

/// A new edge produced by sparsification, in blanket indices (`0..k`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TreeEdge {
    /// Blanket index of the first pose.
    pub from: u8,
    /// Blanket index of the second pose.
    pub to: u8,
    /// Measurement: the current relative pose.
    pub measurement: Se2,
    /// Information of that relative pose under the dense marginal.
    pub information: Info3,
    /// The pair's weight in the spanning tree (eq. 1 information).
    pub weight: f64,
}

/// Why a node could not be eliminated. The node is then simply kept.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum MarginalizeError {
    /// The blanket has more than [`MAX_BLANKET`] nodes.
    BlanketTooLarge,
    /// A factor names a local index outside the poses given.
    BadIndex,
    /// The eliminated node's information block is not positive definite.
    SingularNode,
    /// The marginal could not be inverted even after regularization.
    SingularMarginal,
}

impl core::fmt::Display for MarginalizeError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            MarginalizeError::BlanketTooLarge => "Markov blanket too large",
            MarginalizeError::BadIndex => "factor refers to a pose outside the blanket",
            MarginalizeError::SingularNode => "node information is singular",
            MarginalizeError::SingularMarginal => "marginal information is singular",
        })
    }
}

impl core::error::Error for MarginalizeError {}

/// Linearization of one factor: `(J_from, J_to)` of its g2o-convention error.
#[cfg(test)]
fn factor_jacobians(
    poses: &[Se2],
    f: &LocalFactor,
) -> Result<(Matrix3<f64>, Matrix3<f64>), MarginalizeError> {
    let xi = poses
        .get(usize::from(f.from))
        .ok_or(MarginalizeError::BadIndex)?;
    factor_jacobians_trig(poses, (libm::cos(xi.theta), libm::sin(xi.theta)), f)
}

/// [`factor_jacobians`] with `(cos, sin)` of the first pose's heading already known.
fn factor_jacobians_trig(
    poses: &[Se2],
    (ci, si): (f64, f64),
    f: &LocalFactor,
) -> Result<(Matrix3<f64>, Matrix3<f64>), MarginalizeError> {
    let xi = poses
        .get(usize::from(f.from))
        .ok_or(MarginalizeError::BadIndex)?;
    let xj = poses
        .get(usize::from(f.to))
        .ok_or(MarginalizeError::BadIndex)?;
    let (ja, jb) = xi.between_jacobians_trig(ci, si, xj);
    // Rotation by -theta_z on the translational rows.
    let rz_t = rotation_transpose(f.measurement.theta);
    Ok((rz_t * ja, rz_t * jb))
}

/// The exact Gaussian marginal over the Markov blanket of an eliminated node, in factored form.
///
/// Every factor of the eliminated node `m` touches `m`, so the joint information over
/// `(m, b_0 .. b_{k-1})` has a block-diagonal blanket part: `H_BB = diag(A_i)`, `H_mB =
/// [C_0 .. C_{k-1}]`. The marginal information is `Lambda_ij = delta_ij A_i - C_i^T H_mm^-1
/// C_j`. Holding `b_0` fixed (the marginal is invariant to moving the whole blanket), the
/// Woodbury identity gives the blanket's covariance with nothing larger than 3x3:
///
/// `Sigma_ij = delta_ij A_i^-1 + W_i S^-1 W_j^T`, `W_i = A_i^-1 C_i^T`,
/// `S = H_mm - sum_{i >= 1} C_i A_i^-1 C_i^T`.
#[derive(Clone, Debug)]
pub struct Marginal {
    k: usize,
    a: [Matrix3<f64>; MAX_BLANKET],
    c: [Matrix3<f64>; MAX_BLANKET],
    hmm_inv: Matrix3<f64>,
    a_inv: [Matrix3<f64>; MAX_BLANKET],
    w: [Matrix3<f64>; MAX_BLANKET],
    s_inv: Matrix3<f64>,
    /// `W_i S^-1`, so that an off-diagonal covariance block costs one product.
    ws: [Matrix3<f64>; MAX_BLANKET],
    /// The diagonal covariance blocks `Sigma_ii`.
    sigma_diag: [Matrix3<f64>; MAX_BLANKET],
    /// Heading of each blanket node at the linearization point and its `(cos, sin)`.
    trig: [(f64, (f64, f64)); MAX_BLANKET],
}

impl Marginal {
    /// Blanket size.
    pub fn blanket_len(&self) -> usize {
        self.k
    }

    /// Block `(i, j)` of the marginal information `Lambda`.
    pub fn information_block(&self, i: usize, j: usize) -> Matrix3<f64> {
        let (Some(ai), Some(ci), Some(cj)) = (self.a.get(i), self.c.get(i), self.c.get(j)) else {
            return Matrix3::zeros();
        };
        let diag = if i == j { *ai } else { Matrix3::zeros() };
        diag - ci.transpose() * self.hmm_inv * cj
    }

    /// The whole marginal information as a dense `3 k` matrix (for checks and small tools).
    pub fn information(&self) -> Option<DenseMatrix> {
        let mut out = DenseMatrix::zeros(3 * self.k)?;
        for i in 0..self.k {
            for j in 0..self.k {
                out.add_block3(i, j, &self.information_block(i, j));
            }
        }
        Some(out)
    }

    /// Block `(i, j)` of the blanket covariance with blanket node 0 held fixed.
    pub fn anchored_covariance(&self, i: usize, j: usize) -> Matrix3<f64> {
        if i == 0 || j == 0 || i >= self.k || j >= self.k {
            return Matrix3::zeros();
        }
        let (Some(wi), Some(wj)) = (self.w.get(i), self.w.get(j)) else {
            return Matrix3::zeros();
        };
        if i == j {
            return self.sigma_diag.get(i).copied().unwrap_or_else(|| {
                let shared = wi * self.s_inv * wj.transpose();
                self.a_inv.get(i).map_or(shared, |a| a + shared)
            });
        }
        // `ws[i] = W_i S^-1`: the same product order as `W_i S^-1 W_j^T`.
        self.ws
            .get(i)
            .map_or_else(|| wi * self.s_inv * wj.transpose(), |v| v * wj.transpose())
    }
}

/// The exact marginal over the blanket (`poses[1..]`) after eliminating `poses[0]`, from the
/// factors that touch it (each factor must join `poses[0]` to a blanket pose).
///
/// # Errors
/// See [`MarginalizeError`].
pub fn marginalize(poses: &[Se2], factors: &[LocalFactor]) -> Result<Marginal, MarginalizeError> {
    let k = poses.len().saturating_sub(1);
    if k > MAX_BLANKET {
        return Err(MarginalizeError::BlanketTooLarge);
    }
    let z = Matrix3::zeros();
    let mut hmm = z;
    let mut trig = [(1.0, 0.0); MAX_BLANKET + 1];
    for (t, x) in trig.iter_mut().zip(poses) {
        *t = (libm::cos(x.theta), libm::sin(x.theta));
    }
    let mut out = Marginal {
        k,
        a: [z; MAX_BLANKET],
        c: [z; MAX_BLANKET],
        hmm_inv: z,
        a_inv: [z; MAX_BLANKET],
        w: [z; MAX_BLANKET],
        s_inv: z,
        ws: [z; MAX_BLANKET],
        sigma_diag: [z; MAX_BLANKET],
        trig: [(0.0, (1.0, 0.0)); MAX_BLANKET],
    };
    for ((t, x), p) in out
        .trig
        .iter_mut()
        .zip(trig.iter().skip(1))
        .zip(poses.iter().skip(1))
    {
        *t = (p.theta, *x);
    }
    for f in factors {
        let first = usize::from(f.from);
        let (ja, jb) = factor_jacobians_trig(
            poses,
            *trig.get(first).ok_or(MarginalizeError::BadIndex)?,
            f,
        )?;
        // Orient the factor as (m, blanket node).
        let (jm, jo, other) = match (f.from, f.to) {
            (0, o) if o > 0 => (ja, jb, usize::from(o)),
            (o, 0) if o > 0 => (jb, ja, usize::from(o)),
            _ => return Err(MarginalizeError::BadIndex),
        };
        let i = other - 1;
        let oo = f.information * jo;
        hmm += jm.transpose() * f.information * jm;
        let (Some(a), Some(c)) = (out.a.get_mut(i), out.c.get_mut(i)) else {
            return Err(MarginalizeError::BadIndex);
        };
        *a += jo.transpose() * oo;
        *c += jm.transpose() * oo;
    }
    out.hmm_inv = spd_inverse(&hmm).ok_or(MarginalizeError::SingularNode)?;
    let mut s = hmm;
    for i in 1..k {
        let (Some(a), Some(c)) = (out.a.get(i), out.c.get(i)) else {
            break;
        };
        let a_inv = spd_inverse(a).ok_or(MarginalizeError::SingularMarginal)?;
        let w = a_inv * c.transpose();
        s -= c * w;
        if let (Some(ai), Some(wi)) = (out.a_inv.get_mut(i), out.w.get_mut(i)) {
            *ai = a_inv;
            *wi = w;
        }
    }
    if k >= 2 {
        out.s_inv = spd_inverse(&symmetrize(&s)).ok_or(MarginalizeError::SingularMarginal)?;
        for i in 1..k {
            let (Some(w), Some(a_inv)) = (out.w.get(i).copied(), out.a_inv.get(i).copied()) else {
                break;
            };
            let v = w * out.s_inv;
            if let (Some(vs), Some(d)) = (out.ws.get_mut(i), out.sigma_diag.get_mut(i)) {
                *vs = v;
                *d = a_inv + v * w.transpose();
            }
        }
    }
    Ok(out)
}

/// Covariance of the relative pose `x_i^-1 (+) x_j` of two blanket nodes under the marginal;
/// `trig[i]` holds `(cos, sin)` of `x_i`'s heading.
fn relative_covariance(
    blanket: &[Se2],
    trig: &[(f64, f64)],
    m: &Marginal,
    i: usize,
    j: usize,
) -> Option<Matrix3<f64>> {
    let (xi, xj, &(c, s)) = (blanket.get(i)?, blanket.get(j)?, trig.get(i)?);
    let (ja, jb) = xi.between_jacobians_trig(c, s, xj);
    let cross = ja * m.anchored_covariance(i, j) * jb.transpose();
    Some(symmetrize(
        &(ja * m.anchored_covariance(i, i) * ja.transpose()
            + jb * m.anchored_covariance(j, j) * jb.transpose()
            + cross
            + cross.transpose()),
    ))
}

/// `R(-theta)` acting on the translational part.
fn rotation_transpose(theta: f64) -> Matrix3<f64> {
    yaw_rotation(libm::cos(theta), libm::sin(theta)).transpose()
}

/// Information of an edge with measurement `z` whose parameters `(x, y, theta)` have covariance
/// `cov`, in the g2o error convention (a perturbation on the right of `z`, so the translation
/// is rotated into `z`'s frame); capped at [`MAX_EDGE_INFORMATION`] along each axis when the
/// covariance is (near) singular.
fn edge_information(z: &Se2, cov: &Matrix3<f64>) -> Info3 {
    let r = rotation_transpose(z.theta);
    let cov_e = symmetrize(&(r * cov * r.transpose()));
    let regularized = cov_e + Matrix3::identity() * (1.0 / MAX_EDGE_INFORMATION);
    spd_inverse(&regularized).unwrap_or_else(|| Matrix3::identity() * MAX_EDGE_INFORMATION)
}

/// Sparsifies the marginal over `blanket` (from [`marginalize`]) into the edges of a Chow-Liu
/// tree: at most `k - 1` relative-pose edges, each measuring the current relative pose of its
/// two nodes with the information of that relative pose under the marginal.
///
/// # Errors
/// The blanket does not match the marginal.
pub fn chow_liu_edges(
    blanket: &[Se2],
    marginal: &Marginal,
) -> Result<Vec<TreeEdge, { MAX_TREE_NODES - 1 }>, MarginalizeError> {
    let k = blanket.len();
    let mut edges = Vec::new();
    if k < 2 {
        return Ok(edges);
    }
    if k > MAX_BLANKET || marginal.blanket_len() != k {
        return Err(MarginalizeError::BlanketTooLarge);
    }
    // The blanket's headings were the marginal's linearization point: reuse their (cos, sin)
    // when the poses are the same ones.
    let mut trig = [(1.0, 0.0); MAX_BLANKET];
    for ((t, x), known) in trig.iter_mut().zip(blanket).zip(marginal.trig.iter()) {
        *t = if known.0.to_bits() == x.theta.to_bits() {
            known.1
        } else {
            (libm::cos(x.theta), libm::sin(x.theta))
        };
    }
    // Pair weights are computed on the fly; the k - 1 tree pairs are recomputed below rather
    // than storing all k (k - 1) / 2 covariances.
    let pair = |i: usize, j: usize| relative_covariance(blanket, &trig, marginal, i, j);
    let tree = maximum_spanning_tree(k, |i, j| pair(i, j).map(|c| information_heuristic(&c)))
        .ok_or(MarginalizeError::BlanketTooLarge)?;
    for p in tree {
        let (i, j) = (usize::from(p.a), usize::from(p.b));
        let (Some(xi), Some(xj), Some(c)) = (blanket.get(i), blanket.get(j), pair(i, j)) else {
            return Err(MarginalizeError::BadIndex);
        };
        let measurement = xi.between(xj);
        let _ = edges.push(TreeEdge {
            from: p.a,
            to: p.b,
            measurement,
            information: edge_information(&measurement, &c),
            weight: p.weight,
        });
    }
    Ok(edges)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::UncertainPose;
    use nalgebra::Vector3;

    fn diag(a: f64, b: f64, c: f64) -> Matrix3<f64> {
        Matrix3::from_diagonal(&Vector3::new(a, b, c))
    }

    #[test]
    fn eliminating_a_chain_link_compounds_the_two_edges() {
        // a -- m -- b with exact measurements: the single tree edge a -> b must carry the
        // composed measurement and the compounded covariance (Smith-Self-Cheeseman).
        let a = Se2::new(0.0, 0.0, 0.3);
        let z1 = Se2::new(1.0, 0.2, 0.4);
        let z2 = Se2::new(0.8, -0.1, -0.2);
        let m = a.compose(&z1);
        let b = m.compose(&z2);
        // Edge covariances in the g2o convention (perturbations on the right of z) ...
        let c1 = diag(0.01, 0.02, 0.001);
        let c2 = diag(0.03, 0.01, 0.002);
        // ... and the same as covariances of the parameters (x, y, theta) of z.
        let additive = |z: &Se2, c: &Matrix3<f64>| {
            let r = rotation_transpose(z.theta).transpose();
            r * c * r.transpose()
        };
        let factors = [
            LocalFactor {
                from: 1,
                to: 0,
                measurement: z1,
                information: spd_inverse(&c1).unwrap(),
            },
            LocalFactor {
                from: 0,
                to: 2,
                measurement: z2,
                information: spd_inverse(&c2).unwrap(),
            },
        ];
        let marginal = marginalize(&[m, a, b], &factors).unwrap();
        let edges = chow_liu_edges(&[a, b], &marginal).unwrap();
        assert_eq!(edges.len(), 1);
        let e = edges[0];
        let expected = UncertainPose {
            pose: z1,
            cov: additive(&z1, &c1),
        }
        .compound(&UncertainPose {
            pose: z2,
            cov: additive(&z2, &c2),
        });
        assert!((e.measurement.to_vector() - expected.pose.to_vector()).amax() < 1e-12);
        let got_cov = additive(&e.measurement, &spd_inverse(&e.information).unwrap());
        assert!(
            (got_cov - expected.cov).amax() < 1e-9,
            "got {got_cov} expected {}",
            expected.cov
        );
    }

    #[test]
    fn schur_complement_equals_dense_reference() {
        // A star around m with four blanket nodes plus one blanket-blanket factor. Reference:
        // add a strong prior on blanket node 0, invert the whole Hessian densely, take the
        // blanket's covariance block and invert it; remove the prior again. This must equal
        // the Schur complement from `marginalize`.
        let m = Se2::new(1.0, 1.0, 0.2);
        let blanket = [
            Se2::new(0.0, 0.0, 0.0),
            Se2::new(2.0, 0.5, 0.7),
            Se2::new(1.5, 2.5, -1.0),
            Se2::new(0.2, 2.0, 2.5),
        ];
        let mut poses = [Se2::IDENTITY; 5];
        poses[0] = m;
        poses[1..].copy_from_slice(&blanket);
        let info = Matrix3::new(50.0, 5.0, 1.0, 5.0, 80.0, -2.0, 1.0, -2.0, 200.0);
        let mut factors: Vec<LocalFactor, 8> = Vec::new();
        for b in 1..5u8 {
            // Measurements slightly off the estimate so the linearization point is generic.
            let z = poses[usize::from(b)].between(&m).compose(&Se2::new(
                0.01 * f64::from(b),
                -0.02,
                0.01,
            ));
            factors
                .push(LocalFactor {
                    from: b,
                    to: 0,
                    measurement: z,
                    information: info * f64::from(b),
                })
                .unwrap();
        }
        let marginal = marginalize(&poses, &factors).unwrap();

        let prior = 1e6;
        let mut h = DenseMatrix::zeros(15).unwrap();
        for f in &factors {
            let (ja, jb) = factor_jacobians(&poses, f).unwrap();
            let (a, b) = (usize::from(f.from), usize::from(f.to));
            h.add_block3(a, a, &(ja.transpose() * f.information * ja));
            h.add_block3(b, b, &(jb.transpose() * f.information * jb));
            h.add_block3(a, b, &(ja.transpose() * f.information * jb));
            h.add_block3(b, a, &(jb.transpose() * f.information * ja));
        }
        h.add_block3(1, 1, &(Matrix3::identity() * prior));
        let full_cov = h.spd_inverse().unwrap();
        let mut blanket_cov = DenseMatrix::zeros(12).unwrap();
        for r in 0..12 {
            for c in 0..12 {
                blanket_cov.set(r, c, full_cov.get(r + 3, c + 3));
            }
        }
        let reference = blanket_cov.spd_inverse().unwrap();
        for r in 0..12 {
            for c in 0..12 {
                let expected = reference.get(r, c) - if r == c && r < 3 { prior } else { 0.0 };
                let got = marginal.information().unwrap().get(r, c);
                assert!(
                    (got - expected).abs() < 1e-6 * (1.0 + expected.abs()),
                    "({r},{c}) {got} vs {expected}"
                );
            }
        }
        // And the tree has k - 1 edges.
        assert_eq!(chow_liu_edges(&blanket, &marginal).unwrap().len(), 3);
    }

    #[test]
    fn errors_are_typed() {
        let f = LocalFactor {
            from: 0,
            to: 5,
            measurement: Se2::IDENTITY,
            information: Matrix3::identity(),
        };
        assert_eq!(
            marginalize(&[Se2::IDENTITY, Se2::IDENTITY], &[f]).unwrap_err(),
            MarginalizeError::BadIndex
        );
        let poses = [Se2::IDENTITY; MAX_BLANKET + 2];
        assert_eq!(
            marginalize(&poses, &[]).unwrap_err(),
            MarginalizeError::BlanketTooLarge
        );
        // A node with no factor has no information.
        assert_eq!(
            marginalize(&[Se2::IDENTITY, Se2::IDENTITY], &[]).unwrap_err(),
            MarginalizeError::SingularNode
        );
    }
}
