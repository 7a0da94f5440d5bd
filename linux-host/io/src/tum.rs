//! Trajectories in the TUM format (`timestamp tx ty tz qx qy qz qw`, one pose per line, `#`
//! comments) and in the KITTI format (12 numbers of a 3x4 row-major matrix per line, no time).

use std::fmt::Write as _;
use std::io::BufRead;
use std::path::Path;

use anyhow::{bail, Context, Result};
use nalgebra::{Matrix3, Quaternion, UnitQuaternion, Vector3};

use crate::atomic;
use crate::carmen::open_maybe_compressed;

/// One pose of a 3D trajectory.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StampedPose {
    /// Time (s).
    pub t: f64,
    /// Position (m).
    pub p: Vector3<f64>,
    /// Orientation.
    pub q: UnitQuaternion<f64>,
}

impl StampedPose {
    /// A planar pose `(x, y, theta)` at time `t`.
    pub fn planar(t: f64, x: f64, y: f64, theta: f64) -> Self {
        Self {
            t,
            p: Vector3::new(x, y, 0.0),
            q: UnitQuaternion::from_axis_angle(&Vector3::z_axis(), theta),
        }
    }
}

/// Reads a TUM trajectory.
///
/// # Errors
/// Unreadable file, or a line without 8 numbers (with file and line number).
pub fn read_tum(path: &Path) -> Result<Vec<StampedPose>> {
    let reader = open_maybe_compressed(path)?;
    let mut out = Vec::new();
    for (i, line) in reader.lines().enumerate() {
        let line = line.with_context(|| format!("{}:{}", path.display(), i + 1))?;
        let text = line.trim();
        if text.is_empty() || text.starts_with('#') {
            continue;
        }
        let v: Vec<f64> = text
            .split_ascii_whitespace()
            .map(str::parse)
            .collect::<Result<_, _>>()
            .with_context(|| format!("{}:{}: not a number", path.display(), i + 1))?;
        let [t, x, y, z, qx, qy, qz, qw] = v[..] else {
            bail!(
                "{}:{}: expected 8 numbers (t x y z qx qy qz qw), found {}",
                path.display(),
                i + 1,
                v.len()
            );
        };
        check_values(&[t], MAX_STAMP_S)
            .and_then(|()| check_values(&v[1..], MAX_COORDINATE))
            .with_context(|| format!("{}:{}", path.display(), i + 1))?;
        let q = Quaternion::new(qw, qx, qy, qz);
        if q.norm() < 1e-9 {
            bail!(
                "{}:{}: the quaternion is zero, not a rotation",
                path.display(),
                i + 1
            );
        }
        out.push(StampedPose {
            t,
            p: Vector3::new(x, y, z),
            q: UnitQuaternion::from_quaternion(q),
        });
    }
    Ok(out)
}

/// Largest coordinate accepted, in the file's units: beyond it a value is corrupt (a
/// planet-sized map) and would only turn sums and decompositions into infinities.
pub const MAX_COORDINATE: f64 = 1e9;

/// Largest time stamp accepted, seconds: Unix time of the year 5138; more is corruption.
pub const MAX_STAMP_S: f64 = 1e11;

/// Checks that every value is finite and at most `max` in magnitude.
fn check_values(values: &[f64], max: f64) -> Result<()> {
    for (k, v) in values.iter().enumerate() {
        if !v.is_finite() || v.abs() > max {
            bail!(
                "value {} is {v}: numbers must be finite and within +-{max}",
                k + 1
            );
        }
    }
    Ok(())
}

/// The rotation nearest to `r`, by a bounded number of refinement steps (nalgebra's default
/// iterates until convergence, which a matrix of NaN never reaches).
pub fn rotation_from_matrix(r: &Matrix3<f64>) -> UnitQuaternion<f64> {
    UnitQuaternion::from_matrix_eps(r, f64::EPSILON, 1_000, UnitQuaternion::identity())
}

/// Reads the rows of a KITTI trajectory file: the 12 numbers of each line's 3x4 matrix, row
/// major, as written (no re-orthonormalization). Blank lines are skipped.
///
/// # Errors
/// Unreadable file, or a line without 12 numbers (with file and line number).
pub fn read_kitti_rows(path: &Path) -> Result<Vec<[f64; 12]>> {
    let reader = open_maybe_compressed(path)?;
    let mut out = Vec::new();
    for (i, line) in reader.lines().enumerate() {
        let line = line.with_context(|| format!("{}:{}", path.display(), i + 1))?;
        if line.trim().is_empty() {
            continue;
        }
        let v: Vec<f64> = line
            .split_ascii_whitespace()
            .map(str::parse)
            .collect::<Result<_, _>>()
            .with_context(|| format!("{}:{}: not a number", path.display(), i + 1))?;
        let row: [f64; 12] = v[..]
            .try_into()
            .map_err(|_| anyhow::anyhow!("{}:{}: expected 12 numbers", path.display(), i + 1))?;
        check_values(&row, MAX_COORDINATE)
            .with_context(|| format!("{}:{}", path.display(), i + 1))?;
        // Entries of a rotation matrix lie in [-1, 1]; a little more is rounding.
        let rotation = [0, 1, 2, 4, 5, 6, 8, 9, 10].map(|k| row[k]);
        check_values(&rotation, 1.5)
            .with_context(|| format!("{}:{}: not a rotation matrix", path.display(), i + 1))?;
        out.push(row);
    }
    Ok(out)
}

/// Reads a KITTI trajectory (3x4 matrices); times are the line numbers unless `times` is
/// given (one time per line, e.g. KITTI's `times.txt`).
///
/// # Errors
/// Unreadable file, or a line without 12 numbers.
pub fn read_kitti(path: &Path, times: Option<&Path>) -> Result<Vec<StampedPose>> {
    let stamps: Option<Vec<f64>> = match times {
        Some(tp) => {
            let text =
                std::fs::read_to_string(tp).with_context(|| format!("reading {}", tp.display()))?;
            Some(
                text.split_ascii_whitespace()
                    .map(str::parse)
                    .collect::<Result<_, _>>()
                    .with_context(|| format!("{}: not a number", tp.display()))?,
            )
        }
        None => None,
    };
    let mut out = Vec::new();
    for v in read_kitti_rows(path)? {
        let r = Matrix3::new(v[0], v[1], v[2], v[4], v[5], v[6], v[8], v[9], v[10]);
        let t = match &stamps {
            Some(s) => *s
                .get(out.len())
                .with_context(|| format!("{}: fewer times than poses", path.display()))?,
            None => out.len() as f64,
        };
        out.push(StampedPose {
            t,
            p: Vector3::new(v[3], v[7], v[11]),
            q: rotation_from_matrix(&r),
        });
    }
    Ok(out)
}

/// The TUM text of a trajectory (times with 9 decimals, positions and quaternions with 9).
pub fn tum_text(poses: &[StampedPose]) -> String {
    let mut s = String::with_capacity(poses.len() * 100);
    s.push_str("# timestamp tx ty tz qx qy qz qw\n");
    for p in poses {
        let q = p.q.quaternion();
        let _ = writeln!(
            s,
            "{:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}",
            p.t, p.p.x, p.p.y, p.p.z, q.i, q.j, q.k, q.w
        );
    }
    s
}

/// Writes a TUM trajectory atomically.
///
/// # Errors
/// Any IO error.
pub fn write_tum(path: &Path, poses: &[StampedPose]) -> Result<()> {
    atomic::write_file(path, tum_text(poses).as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tum_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.tum");
        let poses = vec![
            StampedPose::planar(976052890.244111, 1.0, 2.0, 0.5),
            StampedPose::planar(976052891.0, -1.0, 0.25, -3.0),
        ];
        write_tum(&path, &poses).unwrap();
        let back = read_tum(&path).unwrap();
        assert_eq!(back.len(), 2);
        for (a, b) in poses.iter().zip(&back) {
            assert!((a.t - b.t).abs() < 1e-6);
            assert!((a.p - b.p).norm() < 1e-9);
            assert!(a.q.angle_to(&b.q) < 1e-8);
        }
        std::fs::write(&path, "1 2 3\n").unwrap();
        let err = read_tum(&path).unwrap_err().to_string();
        assert!(err.contains(":1: expected 8 numbers"), "{err}");
    }

    #[test]
    fn kitti_lines() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("k.txt");
        std::fs::write(&path, "1 0 0 1 0 1 0 2 0 0 1 3\n0 -1 0 4 1 0 0 5 0 0 1 6\n").unwrap();
        let poses = read_kitti(&path, None).unwrap();
        assert_eq!(poses[1].t, 1.0);
        assert_eq!(poses[1].p, Vector3::new(4.0, 5.0, 6.0));
        assert!((poses[1].q.euler_angles().2 - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    }

    #[test]
    fn non_finite_huge_and_zero_rotations_are_refused_with_their_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bad.tum");
        for (row, why) in [
            ("0 0 0 0 nan 0 0 1", "finite"),
            ("0 0 0 0 0 0 0 inf", "finite"),
            ("0 1e308 0 0 0 0 0 1", "within"),
            ("0 0 0 0 0 0 0 0", "zero"),
            ("1e12 0 0 0 0 0 0 1", "within"),
        ] {
            std::fs::write(&path, format!("1700000000.5 0 0 0 0 0 0 1\n{row}\n")).unwrap();
            let err = format!("{:#}", read_tum(&path).unwrap_err());
            assert!(
                err.contains("bad.tum:2") && err.contains(why),
                "{row}: {err}"
            );
        }
        let path = dir.path().join("bad.kitti");
        for row in ["nan 0 0 1 0 1 0 2 0 0 1 3", "1e30 0 0 1 0 1 0 2 0 0 1 3"] {
            std::fs::write(&path, format!("{row}\n")).unwrap();
            let err = format!("{:#}", read_kitti(&path, None).unwrap_err());
            assert!(err.contains("bad.kitti:1"), "{row}: {err}");
        }
    }

    #[test]
    fn the_rotation_of_a_matrix_of_nan_ends() {
        let q = rotation_from_matrix(&Matrix3::from_element(f64::NAN));
        assert!(q.angle().is_nan() || q.angle().is_finite());
        let r = rotation_from_matrix(&Matrix3::identity());
        assert!(r.angle().abs() < 1e-12);
    }
}
