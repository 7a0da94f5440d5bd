//! Point-to-line ICP: LiDAR odometry against the current submap, and scan-to-scan refinement
//! of loop closures.
//!
//! Why point-to-line ICP rather than Gauss-Newton on the interpolated grid (Cartographer's
//! ceres matcher): the grid cost is the bilinear interpolation of 5 cm cells, whose basin of
//! attraction is about one cell, so it needs a correlative pre-search for a 20 cm / 5 degree
//! seed error, and its optimum is biased by where hits fall inside their cells (up to half a
//! cell per wall; the test `scan_to_grid_cells_is_within_half_a_cell` shows the same bias for
//! ICP against cell centres). Nearest-neighbour correspondences with line normals converge
//! from several decimetres, model walls as lines (under a centimetre from a 20 cm / 5 degree
//! seed in the tests), give a Gauss-Newton Hessian for the information matrix, and expose
//! degenerate geometry directly in that Hessian. The same routine serves scan-to-scan
//! matching, where there is no grid at all.
//!
//! References: for LiDAR odometry, the voxel-thinned points of the current submap's keyframes
//! ([`PointMap`](crate::frontend::pointmap::PointMap)); for loop refinement, a keyframe scan,
//! or an old submap's occupied cells with fitted normals
//! ([`Submap::occupied_points`](crate::frontend::grid::Submap::occupied_points), half-cell
//! accurate).
//!
//! Each iteration: transform the query points by the current pose; find the nearest
//! reference point within the gate; residual = distance to the reference point's line (or to
//! nothing when it has no normal); Huber weights; one Gauss-Newton step on `(x, y, theta)`.
//! It stops when the step is below the thresholds or after `max_iterations`.
//!
//! Degeneracy: the Hessian's rotation row/column is scaled by the query's RMS radius, so all
//! three directions are in metres; if its smallest eigenvalue is below `degeneracy_ratio`
//! times the largest, the match is refused with the weak direction (a corridor gives
//! `[1, 0, 0]`-like directions along its axis), or, with `allow_degenerate`, solved only in
//! the well-constrained directions (the seed, i.e. wheel odometry, is kept along the weak
//! one) and flagged, which is what LiDAR odometry in a corridor needs.
//!
//! The information matrix is the final Hessian divided by the weighted residual variance
//! (floored by `min_sigma` so perfect synthetic data does not give infinite confidence).
//!
//! Motion prior ([`align_with_prior`]): the pose is also measured by the odometry, with an
//! information matrix. Adding that measurement to each Gauss-Newton step makes the step a
//! maximum a posteriori one: directions the scan pins down hardly move, directions it leaves
//! weak follow the prior in proportion to the two informations. The ICP cost is in squared
//! metres without a variance, so the prior's information is multiplied by the current
//! residual variance to share its units. The returned information is the scan's alone.

use core::fmt;

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use crate::frontend::kdtree::KdTree;
use crate::frontend::scan::ScanPoint;
use crate::geom::{wrap_angle, Se2};

/// ICP parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct IcpConfig {
    /// Iteration limit.
    pub max_iterations: u16,
    /// Correspondences farther than this are ignored, metres.
    pub max_correspondence: f32,
    /// Huber threshold on the residual, metres.
    pub huber: f64,
    /// Fewest query points and fewest correspondences accepted.
    pub min_points: u32,
    /// Converged when the translation step is below this, metres...
    pub translation_eps: f64,
    /// ... and the rotation step below this, radians.
    pub rotation_eps: f64,
    /// Smallest over largest eigenvalue of the scaled Hessian below which the match is
    /// degenerate.
    pub degeneracy_ratio: f64,
    /// Floor of the residual standard deviation used for the information matrix, metres.
    pub min_sigma: f64,
    /// On degenerate geometry, keep the seed along the weak direction and solve the others
    /// (reported in [`IcpResult::degenerate`]) instead of returning
    /// [`MatchError::Degenerate`].
    pub allow_degenerate: bool,
}

impl Default for IcpConfig {
    fn default() -> Self {
        IcpConfig {
            max_iterations: 30,
            max_correspondence: 0.5,
            huber: 0.05,
            min_points: 20,
            translation_eps: 1e-5,
            rotation_eps: 1e-5,
            degeneracy_ratio: 2e-3,
            min_sigma: 0.01,
            allow_degenerate: false,
        }
    }
}

/// An independent measurement of the pose being matched: the odometry's prediction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Prior {
    /// The predicted pose of the query frame in the reference frame.
    pub pose: Se2,
    /// Its information matrix (`[x, y, theta]`, in the reference frame's axes).
    pub information: Matrix3<f64>,
}

/// A converged (or iteration-limited) match.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IcpResult {
    /// Pose of the query frame in the reference frame.
    pub pose: Se2,
    /// Iterations run.
    pub iterations: u16,
    /// The step fell below the thresholds.
    pub converged: bool,
    /// Query points with a correspondence at the final pose.
    pub inliers: u32,
    /// `inliers` over the query size, in `[0, 1]`.
    pub fitness: f32,
    /// Root mean square residual of the inliers, metres.
    pub rms: f64,
    /// Information matrix of `pose` (`[x, y, theta]`).
    pub information: Matrix3<f64>,
    /// With [`IcpConfig::allow_degenerate`]: the weakly constrained direction (as in
    /// [`MatchError::Degenerate`]), along which the pose stayed at the seed.
    pub degenerate: Option<[f64; 3]>,
}

/// Matching failures.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum MatchError {
    /// Too few query or reference points.
    TooFewPoints {
        /// Points available.
        have: u32,
        /// Points needed.
        need: u32,
    },
    /// Too few correspondences within the gate.
    TooFewCorrespondences {
        /// Correspondences found.
        have: u32,
        /// Correspondences needed.
        need: u32,
    },
    /// The geometry does not constrain one direction (unit vector `[x, y, theta * r]`, `r`
    /// the RMS radius of the scan): e.g. the axis of a featureless corridor.
    Degenerate {
        /// The weakly constrained direction.
        direction: [f64; 3],
        /// Smallest over largest eigenvalue.
        ratio: f64,
    },
    /// The normal equations could not be solved.
    IllConditioned,
    /// The seed pose is not finite.
    InvalidSeed,
}

impl fmt::Display for MatchError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            MatchError::TooFewPoints { have, need } => {
                write!(f, "too few points to match ({have}, need {need})")
            }
            MatchError::TooFewCorrespondences { have, need } => {
                write!(f, "too few correspondences ({have}, need {need})")
            }
            MatchError::Degenerate { direction, ratio } => write!(
                f,
                "degenerate geometry along [{:.3}, {:.3}, {:.3}] (eigenvalue ratio {ratio:.2e})",
                direction[0], direction[1], direction[2]
            ),
            MatchError::IllConditioned => f.write_str("ill-conditioned normal equations"),
            MatchError::InvalidSeed => f.write_str("non-finite seed pose"),
        }
    }
}

impl core::error::Error for MatchError {}

struct Linearized {
    h: Matrix3<f64>,
    g: Vector3<f64>,
    inliers: u32,
    sum_w_e2: f64,
    rows: u32,
}

fn linearize(query: &[ScanPoint], tree: &KdTree<'_>, pose: &Se2, cfg: &IcpConfig) -> Linearized {
    let (c, s) = (libm::cos(pose.theta), libm::sin(pose.theta));
    let gate2 = cfg.max_correspondence * cfg.max_correspondence;
    let mut out = Linearized {
        h: Matrix3::zeros(),
        g: Vector3::zeros(),
        inliers: 0,
        sum_w_e2: 0.0,
        rows: 0,
    };
    let add = |j: Vector3<f64>, e: f64, out: &mut Linearized| {
        let a = libm::fabs(e);
        let w = if a <= cfg.huber { 1.0 } else { cfg.huber / a };
        out.h += j * j.transpose() * w;
        out.g += j * (w * e);
        out.sum_w_e2 += w * e * e;
        out.rows += 1;
    };
    for q in query {
        if !(q.p[0].is_finite() && q.p[1].is_finite()) {
            continue;
        }
        let (px, py) = (q.p[0] as f64, q.p[1] as f64);
        let t = [pose.x + c * px - s * py, pose.y + s * px + c * py];
        let Some((r, _)) = tree.nearest([t[0] as f32, t[1] as f32], gate2) else {
            continue;
        };
        out.inliers += 1;
        // d t / d theta
        let dth = [-s * px - c * py, c * px - s * py];
        let d = [t[0] - r.p[0] as f64, t[1] - r.p[1] as f64];
        // Reference points without a normal (corners, clutter) give no residual: a
        // point-to-point term would lock onto the sampling pattern along a wall.
        if !r.has_normal() {
            continue;
        }
        let n = [r.n[0] as f64, r.n[1] as f64];
        let e = n[0] * d[0] + n[1] * d[1];
        add(
            Vector3::new(n[0], n[1], n[0] * dth[0] + n[1] * dth[1]),
            e,
            &mut out,
        );
    }
    out
}

/// Degeneracy-aware Gauss-Newton step.
///
/// The Hessian is scaled so its three directions are in metres (rotation times `radius`) and
/// decomposed; with all eigenvalues above `degeneracy_ratio` times the largest, this is the
/// ordinary step `-H^-1 g`. Otherwise the weak direction is reported: as an error, or, when
/// `allow_degenerate` is set, the step is taken only along the well-constrained eigenvectors
/// (the seed is kept along the weak one) and the direction is returned with it.
fn solve_step(
    h: &Matrix3<f64>,
    g: &Vector3<f64>,
    radius: f64,
    cfg: &IcpConfig,
) -> Result<(Vector3<f64>, Option<[f64; 3]>), MatchError> {
    let scale = Vector3::new(1.0, 1.0, 1.0 / radius);
    let sm = Matrix3::from_diagonal(&scale);
    let hs = sm * h * sm;
    if !hs.iter().all(|v| v.is_finite()) {
        return Err(MatchError::IllConditioned);
    }
    let eig = SymmetricEigen::try_new(hs, f64::EPSILON, 200).ok_or(MatchError::IllConditioned)?;
    let (mut imin, mut imax) = (0, 0);
    for i in 1..3 {
        if eig.eigenvalues[i] < eig.eigenvalues[imin] {
            imin = i;
        }
        if eig.eigenvalues[i] > eig.eigenvalues[imax] {
            imax = i;
        }
    }
    let (lmin, lmax) = (eig.eigenvalues[imin], eig.eigenvalues[imax]);
    if lmax.is_nan() || lmax <= 0.0 {
        return Err(MatchError::IllConditioned);
    }
    let ratio = lmin / lmax;
    let mut degenerate = None;
    if ratio < cfg.degeneracy_ratio {
        let v = eig.eigenvectors.column(imin);
        let mut dir = [v[0], v[1], v[2]];
        // Sign convention: largest component positive.
        let big =
            dir.iter().copied().fold(
                0.0f64,
                |m, x| if libm::fabs(x) > libm::fabs(m) { x } else { m },
            );
        if big < 0.0 {
            dir = [-dir[0], -dir[1], -dir[2]];
        }
        if !cfg.allow_degenerate {
            return Err(MatchError::Degenerate {
                direction: dir,
                ratio,
            });
        }
        degenerate = Some(dir);
    }
    let gs = g.component_mul(&scale);
    let mut step_s = Vector3::zeros();
    for i in 0..3 {
        let l = eig.eigenvalues[i];
        if l >= cfg.degeneracy_ratio * lmax {
            let v = eig.eigenvectors.column(i);
            step_s -= v * (v.dot(&gs) / l);
        }
    }
    let step = step_s.component_mul(&scale);
    if !(step[0].is_finite() && step[1].is_finite() && step[2].is_finite()) {
        return Err(MatchError::IllConditioned);
    }
    Ok((step, degenerate))
}

/// The weighted residual variance of `lin`, floored by `min_sigma`.
fn residual_variance(lin: &Linearized, cfg: &IcpConfig) -> f64 {
    let dof = (lin.rows as f64 - 3.0).max(1.0);
    (lin.sum_w_e2 / dof).max(cfg.min_sigma * cfg.min_sigma)
}

/// Aligns `query` (points in its own frame) to the reference points in `tree`, starting from
/// `seed` (pose of the query frame in the reference frame).
///
/// # Errors
/// [`MatchError`] for too few points or correspondences, degenerate or ill-conditioned
/// geometry, or a non-finite seed.
pub fn align(
    query: &[ScanPoint],
    tree: &KdTree<'_>,
    seed: &Se2,
    cfg: &IcpConfig,
) -> Result<IcpResult, MatchError> {
    align_with_prior(query, tree, seed, None, cfg)
}

/// [`align`] with the odometry's `prior` on the pose as one more measurement (see the module
/// docs). The returned information is the scan's alone, so a caller can still weigh the match
/// against other measurements.
///
/// # Errors
/// As [`align`].
pub fn align_with_prior(
    query: &[ScanPoint],
    tree: &KdTree<'_>,
    seed: &Se2,
    prior: Option<&Prior>,
    cfg: &IcpConfig,
) -> Result<IcpResult, MatchError> {
    if !seed.is_finite() {
        return Err(MatchError::InvalidSeed);
    }
    let need = cfg.min_points.max(3);
    for have in [query.len(), tree.points().len()] {
        if (have as u32) < need {
            return Err(MatchError::TooFewPoints {
                have: have as u32,
                need,
            });
        }
    }
    let radius = {
        let s: f64 = query
            .iter()
            .filter(|q| q.p[0].is_finite() && q.p[1].is_finite())
            .map(|q| (q.p[0] as f64) * (q.p[0] as f64) + (q.p[1] as f64) * (q.p[1] as f64))
            .sum();
        libm::sqrt(s / query.len() as f64).max(0.1)
    };
    let mut pose = *seed;
    let mut converged = false;
    let mut iterations = 0;
    let mut lin;
    loop {
        lin = linearize(query, tree, &pose, cfg);
        if lin.inliers < need {
            return Err(MatchError::TooFewCorrespondences {
                have: lin.inliers,
                need,
            });
        }
        if converged || iterations >= cfg.max_iterations {
            break;
        }
        let (step, _) = match prior {
            Some(p) => {
                let var = residual_variance(&lin, cfg);
                let info = p.information * var;
                let r = Vector3::new(
                    pose.x - p.pose.x,
                    pose.y - p.pose.y,
                    wrap_angle(pose.theta - p.pose.theta),
                );
                solve_step(&(lin.h + info), &(lin.g + info * r), radius, cfg)?
            }
            None => solve_step(&lin.h, &lin.g, radius, cfg)?,
        };
        pose = Se2::new(pose.x + step[0], pose.y + step[1], pose.theta + step[2]);
        iterations += 1;
        converged = libm::sqrt(step[0] * step[0] + step[1] * step[1]) < cfg.translation_eps
            && libm::fabs(step[2]) < cfg.rotation_eps;
    }
    let (_, degenerate) = solve_step(&lin.h, &lin.g, radius, cfg)?;
    let var = residual_variance(&lin, cfg);
    let rms = libm::sqrt(lin.sum_w_e2 / (lin.rows.max(1) as f64));
    Ok(IcpResult {
        pose,
        iterations,
        converged,
        inliers: lin.inliers,
        fitness: lin.inliers as f32 / query.len() as f32,
        rms,
        information: lin.h / var,
        degenerate,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frontend::grid::{GridParams, Submap};
    use crate::frontend::pointmap::PointMap;
    use crate::frontend::scan::tests::{polygon, room, scan_at};
    use crate::frontend::scan::{preprocess, PreprocessConfig, ScanPoints};

    fn scan(pose: Se2, walls: &[[f64; 4]], out: &mut ScanPoints) {
        let mut ranges = [0.0f32; 720];
        let g = scan_at(pose, 720, walls, &mut ranges);
        preprocess(&ranges, &g, &PreprocessConfig::default(), out).unwrap();
    }

    fn assert_close(got: &Se2, want: &Se2, trans: f64, rot_deg: f64) {
        let d = got.between(want);
        let t = libm::sqrt(d.x * d.x + d.y * d.y);
        assert!(
            t < trans && libm::fabs(d.theta).to_degrees() < rot_deg,
            "got {got:?}, want {want:?}"
        );
    }

    #[test]
    fn scan_to_scan_recovers_displacement() {
        let walls = room();
        let mut reference: ScanPoints = heapless::Vec::new();
        let mut query: ScanPoints = heapless::Vec::new();
        scan(Se2::IDENTITY, &walls, &mut reference);
        let truth = Se2::new(0.35, -0.2, 0.12);
        scan(truth, &walls, &mut query);
        let tree = KdTree::build(&mut reference);
        let seed = truth.compose(&Se2::new(0.2, 0.0, 5f64.to_radians()));
        let r = align(&query, &tree, &seed, &IcpConfig::default()).unwrap();
        assert!(r.converged, "{r:?}");
        assert_close(&r.pose, &truth, 0.01, 0.2);
        assert!(r.fitness > 0.9);
        // Information is symmetric positive definite.
        assert!(r.information.cholesky().is_some());
        assert!((r.information - r.information.transpose()).norm() < 1e-6);
    }

    /// The point map of the test submap: two scans.
    fn build_point_map(walls: &[[f64; 4]], pm: &mut PointMap<2048>) {
        let mut s: ScanPoints = heapless::Vec::new();
        for pose in [Se2::IDENTITY, Se2::new(-0.5, 0.8, -0.3)] {
            scan(pose, walls, &mut s);
            pm.insert(&pose, &s, 30.0);
        }
    }

    #[test]
    fn scan_to_submap_recovers_displacement() {
        let walls = room();
        let mut pm = PointMap::<2048>::new(0.05);
        build_point_map(&walls, &mut pm);
        assert!(pm.points().len() > 300, "{}", pm.points().len());
        let truth = Se2::new(0.3, 0.25, 0.2);
        let mut query: ScanPoints = heapless::Vec::new();
        scan(truth, &walls, &mut query);
        let tree = pm.tree();
        for seed in [
            Se2::new(-0.14, 0.14, -5f64.to_radians()),
            Se2::new(0.2, 0.0, 5f64.to_radians()),
            Se2::new(0.0, -0.2, -5f64.to_radians()),
        ] {
            let r = align(&query, &tree, &truth.compose(&seed), &IcpConfig::default()).unwrap();
            assert_close(&r.pose, &truth, 0.01, 0.2);
        }
    }

    #[test]
    fn scan_to_grid_cells_is_within_half_a_cell() {
        let walls = room();
        let mut cells = [0i8; 120 * 120];
        let params = GridParams {
            side: 120,
            ..GridParams::HOME
        };
        let mut map = Submap::new(Se2::new(0.5, 0.5, 0.0), params, &mut cells).unwrap();
        let mut s: ScanPoints = heapless::Vec::new();
        for pose in [Se2::IDENTITY, Se2::new(-0.5, 0.8, -0.3)] {
            scan(pose, &walls, &mut s);
            map.insert_scan(&pose, &Se2::IDENTITY, &s).unwrap();
        }
        let mut refs = [ScanPoint::default(); 1500];
        let n = map.occupied_points(5, 2, &mut refs);
        assert!(n > 300 && n < 1500, "{n}");
        let tree = KdTree::build(&mut refs[..n]);
        let truth = Se2::new(0.3, 0.25, 0.2);
        let mut query: ScanPoints = heapless::Vec::new();
        scan(truth, &walls, &mut query);
        let seed = truth.compose(&Se2::new(-0.14, 0.14, -5f64.to_radians()));
        let r = align(&query, &tree, &seed, &IcpConfig::default()).unwrap();
        // Cell centres are biased by up to half a cell (2.5 cm) per wall.
        assert_close(&r.pose, &truth, 0.035, 0.5);
    }

    #[test]
    fn corridor_is_reported_degenerate() {
        let mut walls = heapless::Vec::<[f64; 4], 32>::new();
        walls.push([-50.0, -1.0, 50.0, -1.0]).unwrap();
        walls.push([-50.0, 1.0, 50.0, 1.0]).unwrap();
        let mut reference: ScanPoints = heapless::Vec::new();
        let mut ranges = [0.0f32; 720];
        let mut g = scan_at(Se2::IDENTITY, 720, &walls, &mut ranges);
        g.range_max = 8.0;
        preprocess(&ranges, &g, &PreprocessConfig::default(), &mut reference).unwrap();
        let mut query: ScanPoints = heapless::Vec::new();
        scan_at(Se2::new(0.3, 0.1, 0.02), 720, &walls, &mut ranges);
        preprocess(&ranges, &g, &PreprocessConfig::default(), &mut query).unwrap();
        let tree = KdTree::build(&mut reference);
        match align(
            &query,
            &tree,
            &Se2::new(0.2, 0.0, 0.0),
            &IcpConfig::default(),
        ) {
            Err(MatchError::Degenerate { direction, .. }) => {
                assert!(direction[0] > 0.99, "{direction:?}");
            }
            other => panic!("expected a degenerate match, got {other:?}"),
        }
        // Allowed: y and theta are solved, x stays at the seed.
        let cfg = IcpConfig {
            allow_degenerate: true,
            ..IcpConfig::default()
        };
        let r = align(&query, &tree, &Se2::new(0.2, 0.0, 0.0), &cfg).unwrap();
        assert!(r.degenerate.is_some_and(|d| d[0] > 0.99), "{r:?}");
        assert!((r.pose.x - 0.2).abs() < 0.01, "{r:?}");
        assert!(
            (r.pose.y - 0.1).abs() < 0.005 && (r.pose.theta - 0.02).abs() < 0.002,
            "{r:?}"
        );
        // The same corridor with an end wall in range is fine.
        polygon(&[[6.0, -1.0], [6.0, 1.0]], &mut walls);
        let mut g = scan_at(Se2::IDENTITY, 720, &walls, &mut ranges);
        g.range_max = 8.0;
        preprocess(&ranges, &g, &PreprocessConfig::default(), &mut reference).unwrap();
        scan_at(Se2::new(0.3, 0.1, 0.02), 720, &walls, &mut ranges);
        preprocess(&ranges, &g, &PreprocessConfig::default(), &mut query).unwrap();
        let tree = KdTree::build(&mut reference);
        let r = align(
            &query,
            &tree,
            &Se2::new(0.2, 0.0, 0.0),
            &IcpConfig::default(),
        )
        .unwrap();
        assert_close(&r.pose, &Se2::new(0.3, 0.1, 0.02), 0.01, 0.2);
    }

    #[test]
    fn too_few_points_and_bad_seed() {
        let mut reference: ScanPoints = heapless::Vec::new();
        scan(Se2::IDENTITY, &room(), &mut reference);
        let tree = KdTree::build(&mut reference);
        let few = [ScanPoint::default(); 5];
        assert_eq!(
            align(&few, &tree, &Se2::IDENTITY, &IcpConfig::default()),
            Err(MatchError::TooFewPoints { have: 5, need: 20 })
        );
        let q = tree.points();
        assert_eq!(
            align(
                q,
                &tree,
                &Se2::new(f64::NAN, 0.0, 0.0),
                &IcpConfig::default()
            ),
            Err(MatchError::InvalidSeed)
        );
        // Far away: no correspondences.
        assert!(matches!(
            align(q, &tree, &Se2::new(100.0, 0.0, 0.0), &IcpConfig::default()),
            Err(MatchError::TooFewCorrespondences { .. })
        ));
    }
}
