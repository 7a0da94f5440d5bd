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
use crate::geom::{information_heuristic, spd_inverse, symmetrize, Info3, Se2};

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
fn factor_jacobians(
    poses: &[Se2],
    f: &LocalFactor,
) -> Result<(Matrix3<f64>, Matrix3<f64>), MarginalizeError> {
    let xi = poses
        .get(usize::from(f.from))
        .ok_or(MarginalizeError::BadIndex)?;
    let xj = poses
        .get(usize::from(f.to))
        .ok_or(MarginalizeError::BadIndex)?;
    let (ja, jb) = xi.between_jacobians(xj);
    let (c, s) = (
        libm::cos(f.measurement.theta),
        libm::sin(f.measurement.theta),
    );
    // Rotation by -theta_z on the translational rows.
    let rz_t = Matrix3::new(c, s, 0.0, -s, c, 0.0, 0.0, 0.0, 1.0);
    Ok((rz_t * ja, rz_t * jb))
}

/// The exact marginal information over the blanket (`poses[1..]`) after eliminating
/// `poses[0]`, from the factors that touch it (and any among the blanket that should be folded
/// in). The result has dimension `3 k` in blanket order.
///
/// # Errors
/// See [`MarginalizeError`].
pub fn marginalize(
    poses: &[Se2],
    factors: &[LocalFactor],
) -> Result<DenseMatrix, MarginalizeError> {
    let k = poses.len().saturating_sub(1);
    if k > MAX_BLANKET {
        return Err(MarginalizeError::BlanketTooLarge);
    }
    let mut h = DenseMatrix::zeros(3 * (k + 1)).ok_or(MarginalizeError::BlanketTooLarge)?;
    for f in factors {
        let (ja, jb) = factor_jacobians(poses, f)?;
        let (a, b) = (usize::from(f.from), usize::from(f.to));
        let oa = f.information * ja;
        let ob = f.information * jb;
        h.add_block3(a, a, &(ja.transpose() * oa));
        h.add_block3(b, b, &(jb.transpose() * ob));
        let ab = ja.transpose() * ob;
        h.add_block3(a, b, &ab);
        h.add_block3(b, a, &ab.transpose());
    }
    let hmm_inv = spd_inverse(&h.block3(0, 0)).ok_or(MarginalizeError::SingularNode)?;
    let mut out = DenseMatrix::zeros(3 * k).ok_or(MarginalizeError::BlanketTooLarge)?;
    for i in 0..k {
        let him = h.block3(i + 1, 0);
        let left = him * hmm_inv;
        for j in 0..k {
            let block = h.block3(i + 1, j + 1) - left * h.block3(0, j + 1);
            out.add_block3(i, j, &block);
        }
    }
    Ok(out)
}

/// Covariance of the blanket with blanket node 0 held fixed: a `3 (k - 1)` matrix over nodes
/// `1..k`. A singular marginal (a direction nothing constrains) is regularized once with a tiny
/// multiple of its largest diagonal entry.
fn anchored_covariance(marginal: &DenseMatrix) -> Result<DenseMatrix, MarginalizeError> {
    let n = marginal.dim().saturating_sub(3);
    let mut reduced = DenseMatrix::zeros(n).ok_or(MarginalizeError::BlanketTooLarge)?;
    let mut max_diag: f64 = 0.0;
    for r in 0..n {
        for c in 0..n {
            reduced.set(r, c, marginal.get(r + 3, c + 3));
        }
        max_diag = max_diag.max(marginal.get(r + 3, r + 3));
    }
    if let Some(cov) = reduced.spd_inverse() {
        return Ok(cov);
    }
    let eps = if max_diag > 0.0 {
        max_diag * 1e-9
    } else {
        1e-9
    };
    for r in 0..n {
        reduced.add(r, r, eps);
    }
    reduced
        .spd_inverse()
        .ok_or(MarginalizeError::SingularMarginal)
}

/// Covariance block `(i, j)` of blanket nodes under the anchored covariance (node 0 fixed).
fn cov_block(cov: &DenseMatrix, i: usize, j: usize) -> Matrix3<f64> {
    if i == 0 || j == 0 {
        Matrix3::zeros()
    } else {
        cov.block3(i - 1, j - 1)
    }
}

/// Covariance of the relative pose `x_i^-1 (+) x_j` of two blanket nodes.
fn relative_covariance(
    blanket: &[Se2],
    cov: &DenseMatrix,
    i: usize,
    j: usize,
) -> Option<Matrix3<f64>> {
    let (xi, xj) = (blanket.get(i)?, blanket.get(j)?);
    let (ja, jb) = xi.between_jacobians(xj);
    let cross = ja * cov_block(cov, i, j) * jb.transpose();
    Some(symmetrize(
        &(ja * cov_block(cov, i, i) * ja.transpose()
            + jb * cov_block(cov, j, j) * jb.transpose()
            + cross
            + cross.transpose()),
    ))
}

/// `R(-theta)` acting on the translational part.
fn rotation_transpose(theta: f64) -> Matrix3<f64> {
    let (c, s) = (libm::cos(theta), libm::sin(theta));
    Matrix3::new(c, s, 0.0, -s, c, 0.0, 0.0, 0.0, 1.0)
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

/// Sparsifies a dense marginal over `blanket` (from [`marginalize`]) into the edges of a
/// Chow-Liu tree: at most `k - 1` relative-pose edges.
///
/// # Errors
/// The marginal cannot be inverted, or the blanket is too large.
pub fn chow_liu_edges(
    blanket: &[Se2],
    marginal: &DenseMatrix,
) -> Result<Vec<TreeEdge, { MAX_TREE_NODES - 1 }>, MarginalizeError> {
    let k = blanket.len();
    let mut edges = Vec::new();
    if k < 2 {
        return Ok(edges);
    }
    if k > MAX_BLANKET || marginal.dim() != 3 * k {
        return Err(MarginalizeError::BlanketTooLarge);
    }
    let cov = anchored_covariance(marginal)?;
    let tree = maximum_spanning_tree(k, |i, j| {
        relative_covariance(blanket, &cov, i, j).map(|c| information_heuristic(&c))
    })
    .ok_or(MarginalizeError::BlanketTooLarge)?;
    for p in tree {
        let (i, j) = (usize::from(p.a), usize::from(p.b));
        let (Some(xi), Some(xj), Some(c)) = (
            blanket.get(i),
            blanket.get(j),
            relative_covariance(blanket, &cov, i, j),
        ) else {
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
                let got = marginal.get(r, c);
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
