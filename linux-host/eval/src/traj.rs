//! Trajectories for evaluation: loading (TUM or KITTI), time association, Umeyama alignment,
//! and error statistics.

use std::path::Path;

use anyhow::{bail, Context, Result};
use nalgebra::{DMatrix, Matrix3, UnitQuaternion, Vector3};
use serde::Serialize;

use cloi_io::tum::{read_kitti_rows, read_tum, StampedPose};

/// A 3D pose as a rotation matrix and a translation, kept exactly as read: KITTI files
/// store rotations with 9 digits, which are not quite orthonormal, and `evo` uses them as
/// they are (its inverse is `[R^T, -R^T t]`). Keeping them the same way makes our numbers
/// agree with evo's to far better than 1e-6.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose3 {
    /// Rotation (world from body).
    pub r: Matrix3<f64>,
    /// Translation.
    pub t: Vector3<f64>,
}

impl Pose3 {
    /// The identity.
    pub fn identity() -> Self {
        Self {
            r: Matrix3::identity(),
            t: Vector3::zeros(),
        }
    }

    /// A pure translation.
    pub fn translation(x: f64, y: f64, z: f64) -> Self {
        Self {
            r: Matrix3::identity(),
            t: Vector3::new(x, y, z),
        }
    }

    /// From a rotation and a translation.
    pub fn from_parts(q: &UnitQuaternion<f64>, t: Vector3<f64>) -> Self {
        Self {
            r: q.to_rotation_matrix().into_inner(),
            t,
        }
    }

    /// `[R^T, -R^T t]`.
    pub fn inverse(&self) -> Self {
        let rt = self.r.transpose();
        Self {
            r: rt,
            t: -(rt * self.t),
        }
    }

    /// `self * other`.
    pub fn compose(&self, other: &Self) -> Self {
        Self {
            r: self.r * other.r,
            t: self.r * other.t + self.t,
        }
    }

    /// Rotation angle (rad) of the (re-orthonormalized) rotation.
    pub fn rotation_angle(&self) -> f64 {
        cloi_io::tum::rotation_from_matrix(&self.r).angle()
    }
}

/// A trajectory of timed 3D poses.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Trajectory {
    /// Times (s).
    pub stamps: Vec<f64>,
    /// Poses (world from body).
    pub poses: Vec<Pose3>,
}

/// Reads KITTI poses (12 numbers per line) without touching the matrices; times are the
/// line numbers.
fn read_kitti_raw(path: &Path) -> Result<Trajectory> {
    let mut out = Trajectory::default();
    for [r00, r01, r02, tx, r10, r11, r12, ty, r20, r21, r22, tz] in read_kitti_rows(path)? {
        out.stamps.push(out.poses.len() as f64);
        out.poses.push(Pose3 {
            r: Matrix3::new(r00, r01, r02, r10, r11, r12, r20, r21, r22),
            t: Vector3::new(tx, ty, tz),
        });
    }
    Ok(out)
}

impl Trajectory {
    /// From loaded poses.
    pub fn from_stamped(poses: &[StampedPose]) -> Self {
        Self {
            stamps: poses.iter().map(|p| p.t).collect(),
            poses: poses.iter().map(|p| Pose3::from_parts(&p.q, p.p)).collect(),
        }
    }

    /// Loads a TUM (8 columns) or KITTI (12 columns) file, told apart by the first data line.
    ///
    /// # Errors
    /// Unreadable or malformed files.
    pub fn load(path: &Path) -> Result<Self> {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let columns = text
            .lines()
            .map(str::trim)
            .find(|l| !l.is_empty() && !l.starts_with('#'))
            .map_or(0, |l| l.split_ascii_whitespace().count());
        let poses = match columns {
            8 => read_tum(path)?,
            12 => return read_kitti_raw(path),
            0 => bail!("{}: no poses", path.display()),
            n => bail!(
                "{}: {n} columns; expected TUM (8) or KITTI (12)",
                path.display()
            ),
        };
        Ok(Self::from_stamped(&poses))
    }

    /// Number of poses.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    /// `true` without poses.
    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// Keeps the poses at `ids`, in that order.
    pub fn select(&self, ids: &[usize]) -> Self {
        Self {
            stamps: ids.iter().map(|&i| self.stamps[i]).collect(),
            poses: ids.iter().map(|&i| self.poses[i]).collect(),
        }
    }

    /// Positions.
    pub fn positions(&self) -> Vec<Vector3<f64>> {
        self.poses.iter().map(|p| p.t).collect()
    }

    /// Applies `t * pose` to every pose.
    pub fn transform(&mut self, t: &Pose3) {
        for p in &mut self.poses {
            *p = t.compose(p);
        }
    }
}

/// Pairs poses of two trajectories by time: every pose of the shorter one takes the nearest
/// pose of the longer one (which must be sorted by time) within `max_diff` seconds; ties go
/// to the earlier one. Returns index pairs `(in a, in b)`. This is the association of `evo`.
pub fn associate(a: &Trajectory, b: &Trajectory, max_diff: f64) -> Vec<(usize, usize)> {
    let swap = b.len() < a.len();
    let (short, long) = if swap { (b, a) } else { (a, b) };
    let s2 = &long.stamps;
    let mut out = Vec::new();
    if s2.is_empty() {
        return out;
    }
    for (i, &t) in short.stamps.iter().enumerate() {
        if t < s2[0] - max_diff || t > s2[s2.len() - 1] + max_diff {
            continue;
        }
        let mut up = s2.partition_point(|&x| x <= t);
        if up >= s2.len() {
            up = s2.len() - 1;
        }
        let diff_ub = s2[up] - t;
        let diff_lb = if up > 0 {
            t - s2[up - 1]
        } else {
            f64::INFINITY
        };
        let j = if diff_ub <= max_diff && diff_ub < diff_lb {
            up
        } else if diff_lb <= max_diff && diff_lb <= diff_ub {
            up - 1
        } else {
            continue;
        };
        out.push(if swap { (j, i) } else { (i, j) });
    }
    out
}

/// How to align the estimate to the reference before absolute errors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Alignment {
    /// Rigid 3D alignment (Umeyama, no scale), as `evo_ape --align`.
    Se3,
    /// Rigid planar alignment of x, y with a rotation about z (Umeyama in 2D).
    Se2,
    /// Similarity alignment (with scale), as `evo_ape --align --correct_scale`.
    Sim3,
    /// None.
    None,
}

/// The least-squares similarity `y ~ c R x + t` of Umeyama (1991) between matched points
/// (columns), with `dim` = 2 or 3 rows used; returns `(R, t, c)` embedded in 3D.
///
/// # Errors
/// Fewer than two points, or a degenerate point set.
pub fn umeyama(
    x: &[Vector3<f64>],
    y: &[Vector3<f64>],
    dim: usize,
    with_scale: bool,
) -> Result<(Matrix3<f64>, Vector3<f64>, f64)> {
    if x.len() != y.len() || x.len() < 2 || !(dim == 2 || dim == 3) {
        bail!("alignment needs at least two matched points");
    }
    let n = x.len();
    let to_mat = |pts: &[Vector3<f64>]| DMatrix::from_fn(dim, n, |r, c| pts[c][r]);
    let (xm, ym) = (to_mat(x), to_mat(y));
    let mean_x = xm.column_mean();
    let mean_y = ym.column_mean();
    let mut xc = xm.clone();
    let mut yc = ym.clone();
    for mut col in xc.column_iter_mut() {
        col -= &mean_x;
    }
    for mut col in yc.column_iter_mut() {
        col -= &mean_y;
    }
    let sigma_x = xc.norm_squared() / n as f64;
    let cov = &yc * xc.transpose() / n as f64;
    // Coordinates near f64::MAX overflow the sums, and an SVD of a non-finite matrix panics.
    if !sigma_x.is_finite() || cov.iter().any(|v| !v.is_finite()) {
        bail!("coordinates too large to align (their squares overflow)");
    }
    let svd = cov.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        bail!("SVD failed in the alignment");
    };
    let d = &svd.singular_values;
    if d.iter().filter(|&&s| s > f64::EPSILON).count() < dim - 1 {
        bail!("degenerate point set: alignment is not possible");
    }
    let mut s = DMatrix::<f64>::identity(dim, dim);
    if u.determinant() * v_t.determinant() < 0.0 {
        s[(dim - 1, dim - 1)] = -1.0;
    }
    let r = &u * &s * &v_t;
    let c = if with_scale {
        (DMatrix::from_diagonal(d) * &s).trace() / sigma_x
    } else {
        1.0
    };
    let t = &mean_y - c * &r * &mean_x;
    let mut r3 = Matrix3::identity();
    let mut t3 = Vector3::zeros();
    for i in 0..dim {
        t3[i] = t[i];
        for j in 0..dim {
            r3[(i, j)] = r[(i, j)];
        }
    }
    Ok((r3, t3, c))
}

/// Aligns `est` to `reference` (matched pose by pose) in place; returns the scale applied.
///
/// # Errors
/// As [`umeyama`].
pub fn align(est: &mut Trajectory, reference: &Trajectory, how: Alignment) -> Result<f64> {
    let (dim, scale) = match how {
        Alignment::None => return Ok(1.0),
        Alignment::Se2 => (2, false),
        Alignment::Se3 => (3, false),
        Alignment::Sim3 => (3, true),
    };
    let (r, t, c) = umeyama(&est.positions(), &reference.positions(), dim, scale)?;
    if scale {
        for p in &mut est.poses {
            p.t *= c;
        }
    }
    est.transform(&Pose3 { r, t });
    Ok(c)
}

/// Statistics of an error array, as `evo` reports them (population standard deviation).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ErrorStats {
    /// Root mean square.
    pub rmse: f64,
    /// Mean.
    pub mean: f64,
    /// Median (mean of the two middle values for an even count).
    pub median: f64,
    /// Population standard deviation.
    pub std: f64,
    /// Smallest.
    pub min: f64,
    /// Largest.
    pub max: f64,
    /// Sum of squares.
    pub sse: f64,
    /// Number of values.
    pub count: usize,
}

impl ErrorStats {
    /// Statistics of `errors`.
    ///
    /// # Errors
    /// No errors to summarize.
    pub fn of(errors: &[f64]) -> Result<Self> {
        if errors.is_empty() {
            bail!("no error values (no matched poses or pairs)");
        }
        let n = errors.len() as f64;
        let mean = errors.iter().sum::<f64>() / n;
        let sse: f64 = errors.iter().map(|e| e * e).sum();
        let var = errors.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / n;
        let mut sorted = errors.to_vec();
        sorted.sort_by(f64::total_cmp);
        let mid = sorted.len() / 2;
        let median = if sorted.len().is_multiple_of(2) {
            0.5 * (sorted[mid - 1] + sorted[mid])
        } else {
            sorted[mid]
        };
        Ok(Self {
            rmse: (sse / n).sqrt(),
            mean,
            median,
            std: var.sqrt(),
            min: sorted[0],
            max: sorted[sorted.len() - 1],
            sse,
            count: errors.len(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stats_like_numpy() {
        let s = ErrorStats::of(&[1.0, 2.0, 3.0, 4.0]).unwrap();
        assert_eq!(s.mean, 2.5);
        assert_eq!(s.median, 2.5);
        assert!((s.std - 1.25f64.sqrt()).abs() < 1e-15);
        assert!((s.rmse - 7.5f64.sqrt()).abs() < 1e-15);
        assert_eq!((s.min, s.max, s.sse, s.count), (1.0, 4.0, 30.0, 4));
        assert!(ErrorStats::of(&[]).is_err());
    }

    #[test]
    fn association_takes_nearest_within_tolerance() {
        let a = Trajectory {
            stamps: vec![0.0, 1.0, 2.0],
            poses: vec![Pose3::identity(); 3],
        };
        let b = Trajectory {
            stamps: vec![0.004, 0.5, 1.02, 1.995, 3.0],
            poses: vec![Pose3::identity(); 5],
        };
        assert_eq!(associate(&a, &b, 0.01), vec![(0, 0), (2, 3)]);
        assert_eq!(associate(&b, &a, 0.01), vec![(0, 0), (3, 2)]);
    }

    #[test]
    fn umeyama_refuses_coordinates_whose_squares_overflow() {
        let x = [
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(1e308, 0.0, 0.0),
            Vector3::new(0.0, 1.0, 0.0),
        ];
        let err = umeyama(&x, &x, 3, true).expect_err("overflowing input");
        assert!(err.to_string().contains("too large"), "{err}");
    }

    #[test]
    fn umeyama_recovers_a_rigid_motion() {
        let pts: Vec<Vector3<f64>> = (0..20)
            .map(|i| {
                let f = f64::from(i);
                Vector3::new(f.sin() * 3.0, f.cos() * 2.0 + f * 0.1, (f * 0.3).sin())
            })
            .collect();
        let rot = UnitQuaternion::from_euler_angles(0.1, -0.2, 0.7);
        let t = Vector3::new(1.0, -2.0, 0.5);
        let moved: Vec<_> = pts.iter().map(|p| rot * p * 2.0 + t).collect();
        let (r, tt, c) = umeyama(&pts, &moved, 3, true).unwrap();
        assert!((r - rot.to_rotation_matrix().into_inner()).norm() < 1e-9);
        assert!((tt - t).norm() < 1e-9);
        assert!((c - 2.0).abs() < 1e-9);
        // Planar: only the yaw part.
        let yaw = UnitQuaternion::from_euler_angles(0.0, 0.0, 0.7);
        let flat: Vec<_> = pts.iter().map(|p| Vector3::new(p.x, p.y, 0.0)).collect();
        let moved: Vec<_> = flat.iter().map(|p| yaw * p + t).collect();
        let (r, tt, _) = umeyama(&flat, &moved, 2, false).unwrap();
        assert!((r - yaw.to_rotation_matrix().into_inner()).norm() < 1e-9);
        assert!((tt.xy() - t.xy()).norm() < 1e-9);
        assert!(umeyama(&pts[..1], &pts[..1], 3, false).is_err());
    }
}
