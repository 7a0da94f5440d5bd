//! The relation metric of Kuemmerle et al. (2009): a trajectory is scored only through
//! relative poses between pairs of time stamps, so it needs no global alignment.
//!
//! For a relation `(t1, t2, d_ref)` and the estimated poses `p1`, `p2` at those times, the
//! error is `e = d_ref^-1 (p1^-1 p2)` in SE(2); we report mean and (population) standard
//! deviation of `|t(e)|` (m) and of `|theta(e)|` (deg).
//!
//! Relation files (`.relations`, whitespace separated, `#` comments): `t1 t2 x y z roll pitch
//! yaw` (the benchmark's layout; z, roll and pitch are ignored) or `t1 t2 x y theta`.
//! `cloi eval ref` builds relations from GMapping reference poses instead: every pair of
//! reference poses at most `max_distance` metres apart.

use std::path::Path;

use anyhow::{bail, Context, Result};
use cloi_core::geom::wrap_angle;
use cloi_core::Se2;
use serde::Serialize;

use cloi_io::parse_stamp_ns;

/// One relation between two times.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Relation {
    /// First time (ns).
    pub t1_ns: i64,
    /// Second time (ns).
    pub t2_ns: i64,
    /// Reference motion from the pose at `t1` to the pose at `t2`.
    pub delta: Se2,
}

/// A planar trajectory with exact (ns) time stamps, sorted by time.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PlanarTrajectory {
    /// `(time ns, pose)`, sorted by time.
    pub poses: Vec<(i64, Se2)>,
}

fn numbers<'a>(
    path: &Path,
    line_no: usize,
    fields: impl Iterator<Item = &'a str>,
) -> Result<Vec<f64>> {
    fields
        .map(|f| match f.parse::<f64>() {
            Ok(v) if v.is_finite() && v.abs() <= cloi_io::tum::MAX_COORDINATE => Ok(v),
            Ok(v) => bail!(
                "{}:{line_no}: {v} is not a usable number (finite, within +-{:e})",
                path.display(),
                cloi_io::tum::MAX_COORDINATE
            ),
            Err(_) => bail!("{}:{line_no}: {f:?} is not a number", path.display()),
        })
        .collect()
}

fn stamp(path: &Path, line_no: usize, text: &str) -> Result<i64> {
    parse_stamp_ns(text)
        .with_context(|| format!("{}:{line_no}: {text:?} is not a time stamp", path.display()))
}

fn data_lines(path: &Path) -> Result<Vec<(usize, String)>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    Ok(text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim().to_owned()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
        .collect())
}

impl PlanarTrajectory {
    /// Loads a TUM file keeping the exact decimal time stamps; the yaw comes from the
    /// quaternion.
    ///
    /// # Errors
    /// Unreadable or malformed file.
    pub fn load_tum(path: &Path) -> Result<Self> {
        let mut poses = Vec::new();
        for (line_no, line) in data_lines(path)? {
            let mut fields = line.split_ascii_whitespace();
            let t = stamp(path, line_no, fields.next().unwrap_or(""))?;
            let v = numbers(path, line_no, fields)?;
            let [x, y, _z, qx, qy, qz, qw] = v[..] else {
                bail!("{}:{line_no}: expected 8 columns (TUM)", path.display());
            };
            let yaw = (2.0 * (qw * qz + qx * qy)).atan2(1.0 - 2.0 * (qy * qy + qz * qz));
            poses.push((t, Se2::new(x, y, yaw)));
        }
        poses.sort_by_key(|p| p.0);
        Ok(Self { poses })
    }

    /// Loads GMapping reference poses: `timestamp scan_index x y theta` per line.
    ///
    /// # Errors
    /// Unreadable or malformed file.
    pub fn load_reference(path: &Path) -> Result<Self> {
        let mut poses = Vec::new();
        for (line_no, line) in data_lines(path)? {
            let mut fields = line.split_ascii_whitespace();
            let t = stamp(path, line_no, fields.next().unwrap_or(""))?;
            let v = numbers(path, line_no, fields)?;
            let [_index, x, y, theta] = v[..] else {
                bail!(
                    "{}:{line_no}: expected `timestamp index x y theta`",
                    path.display()
                );
            };
            poses.push((t, Se2::new(x, y, theta)));
        }
        poses.sort_by_key(|p| p.0);
        Ok(Self { poses })
    }

    /// The trajectory of a sensor mounted at `offset` on the robot (`pose * offset` for every
    /// pose). A reference that holds the sensor's poses (GMapping's corrected CARMEN logs hold
    /// the laser's) is compared with the robot's trajectory in the sensor's frame: otherwise
    /// every turn between two compared times adds about `|offset| * |rotation|` of error.
    pub fn in_sensor_frame(&self, offset: &Se2) -> Self {
        Self {
            poses: self
                .poses
                .iter()
                .map(|&(t, p)| (t, p.compose(offset)))
                .collect(),
        }
    }

    /// The pose nearest in time to `t_ns`, if within `tolerance_ns`.
    pub fn at(&self, t_ns: i64, tolerance_ns: i64) -> Option<Se2> {
        let i = self.poses.partition_point(|p| p.0 < t_ns);
        let candidates = [i.checked_sub(1), Some(i)];
        candidates
            .iter()
            .flatten()
            .filter_map(|&k| self.poses.get(k))
            .map(|&(t, p)| ((t - t_ns).abs(), p))
            .filter(|&(d, _)| d <= tolerance_ns)
            .min_by_key(|&(d, _)| d)
            .map(|(_, p)| p)
    }
}

/// Loads a relations file.
///
/// # Errors
/// Unreadable or malformed file.
pub fn load_relations(path: &Path) -> Result<Vec<Relation>> {
    let mut out = Vec::new();
    for (line_no, line) in data_lines(path)? {
        let mut fields = line.split_ascii_whitespace();
        let t1 = stamp(path, line_no, fields.next().unwrap_or(""))?;
        let t2 = stamp(path, line_no, fields.next().unwrap_or(""))?;
        let v = numbers(path, line_no, fields)?;
        let delta = match v[..] {
            [x, y, _z, _roll, _pitch, yaw] => Se2::new(x, y, yaw),
            [x, y, theta] => Se2::new(x, y, theta),
            _ => bail!(
                "{}:{line_no}: expected `t1 t2 x y z roll pitch yaw` or `t1 t2 x y theta`",
                path.display()
            ),
        };
        out.push(Relation {
            t1_ns: t1,
            t2_ns: t2,
            delta,
        });
    }
    Ok(out)
}

/// Relations between every pair of reference poses at most `max_distance` metres apart.
pub fn relations_from_reference(reference: &PlanarTrajectory, max_distance: f64) -> Vec<Relation> {
    let mut out = Vec::new();
    for (i, &(t1, p1)) in reference.poses.iter().enumerate() {
        for &(t2, p2) in &reference.poses[i + 1..] {
            let d = (p2.x - p1.x).hypot(p2.y - p1.y);
            if d <= max_distance {
                out.push(Relation {
                    t1_ns: t1,
                    t2_ns: t2,
                    delta: p1.between(&p2),
                });
            }
        }
    }
    out
}

/// Scores of the relation metric.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RelationScore {
    /// Mean translation error (m).
    pub trans_mean_m: f64,
    /// Standard deviation of the translation error (m, population).
    pub trans_std_m: f64,
    /// Mean rotation error (deg).
    pub rot_mean_deg: f64,
    /// Standard deviation of the rotation error (deg, population).
    pub rot_std_deg: f64,
    /// Relations whose two times both had a pose.
    pub pairs_used: usize,
    /// Relations without a pose at one of their times.
    pub pairs_missing: usize,
    /// Time tolerance used to match stamps (s); 0 means exact.
    pub tolerance_s: f64,
    /// Mean translation error (m) of the relations whose two times are less than
    /// [`REVISIT_SECONDS`] apart: the trajectory's local accuracy (`None` without such pairs).
    pub trans_mean_local_m: Option<f64>,
    /// Mean translation error (m) of the relations [`REVISIT_SECONDS`] or more apart: places
    /// the robot came back to, where a real-time pose carries the drift until a loop closes.
    pub trans_mean_revisit_m: Option<f64>,
    /// Relations in the local mean.
    pub pairs_local: usize,
    /// Relations in the revisit mean.
    pub pairs_revisit: usize,
}

/// Relations whose times are at least this far apart count as revisits, seconds: longer than
/// a robot takes to pass one place (1 m at walking pace and a turn), shorter than any loop.
pub const REVISIT_SECONDS: f64 = 30.0;

fn mean_std(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
    (mean, var.sqrt())
}

/// Scores a trajectory against relations.
///
/// # Errors
/// No relation could be used.
pub fn score(
    traj: &PlanarTrajectory,
    relations: &[Relation],
    tolerance_s: f64,
) -> Result<RelationScore> {
    let tol = (tolerance_s * 1e9).round() as i64;
    let mut trans = Vec::with_capacity(relations.len());
    let mut rot = Vec::with_capacity(relations.len());
    let (mut local, mut revisit) = (Vec::new(), Vec::new());
    let revisit_ns = (REVISIT_SECONDS * 1e9) as i64;
    for r in relations {
        let (Some(p1), Some(p2)) = (traj.at(r.t1_ns, tol), traj.at(r.t2_ns, tol)) else {
            continue;
        };
        let e = r.delta.inverse().compose(&p1.between(&p2));
        trans.push(e.x.hypot(e.y));
        rot.push(wrap_angle(e.theta).abs().to_degrees());
        if r.t2_ns.abs_diff(r.t1_ns) >= revisit_ns.unsigned_abs() {
            revisit.push(e.x.hypot(e.y));
        } else {
            local.push(e.x.hypot(e.y));
        }
    }
    if trans.is_empty() {
        bail!(
            "none of the {} relations matched the trajectory's time stamps (tolerance {tolerance_s} s)",
            relations.len()
        );
    }
    let (trans_mean_m, trans_std_m) = mean_std(&trans);
    let (rot_mean_deg, rot_std_deg) = mean_std(&rot);
    Ok(RelationScore {
        trans_mean_m,
        trans_std_m,
        rot_mean_deg,
        rot_std_deg,
        pairs_used: trans.len(),
        pairs_missing: relations.len() - trans.len(),
        tolerance_s,
        trans_mean_local_m: (!local.is_empty()).then(|| mean_std(&local).0),
        trans_mean_revisit_m: (!revisit.is_empty()).then(|| mean_std(&revisit).0),
        pairs_local: local.len(),
        pairs_revisit: revisit.len(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(dir: &Path, name: &str, text: &str) -> std::path::PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    #[test]
    fn perfect_trajectory_scores_zero_and_errors_show() {
        let dir = tempfile::tempdir().unwrap();
        let tum = write(
            dir.path(),
            "t.tum",
            "# t x y z qx qy qz qw\n\
             10.000001 0 0 0 0 0 0 1\n\
             11.5 1 0 0 0 0 0.7071067811865476 0.7071067811865476\n\
             12 1 1 0 0 0 0.7071067811865476 0.7071067811865476\n",
        );
        let rel = write(
            dir.path(),
            "r.relations",
            "10.000001 11.5 1 0 0 0 0 1.5707963267948966\n\
             11.5 12 1 0 0 0 0 0\n\
             11.5 13 1 0 0 0 0 0\n",
        );
        let traj = PlanarTrajectory::load_tum(&tum).unwrap();
        let rels = load_relations(&rel).unwrap();
        let s = score(&traj, &rels, 0.0).unwrap();
        assert!(s.trans_mean_m < 1e-12 && s.rot_mean_deg < 1e-9, "{s:?}");
        assert_eq!((s.pairs_used, s.pairs_missing), (2, 1));

        // A relation claiming 1.1 m instead of 1 m: 0.1 m error on one of two pairs.
        let rel = write(
            dir.path(),
            "r2",
            "11.5 12 1.1 0 0\n10.000001 11.5 1 0 1.5707963267948966\n",
        );
        let s = score(&traj, &load_relations(&rel).unwrap(), 0.0).unwrap();
        assert!((s.trans_mean_m - 0.05).abs() < 1e-9);
        assert!((s.trans_std_m - 0.05).abs() < 1e-9);

        // Stamps 1 us off match only with a tolerance.
        let rel = write(dir.path(), "r3", "10.000002 11.5 1 0 1.5707963267948966\n");
        let rels = load_relations(&rel).unwrap();
        assert!(score(&traj, &rels, 0.0).is_err());
        assert_eq!(score(&traj, &rels, 1e-5).unwrap().pairs_used, 1);
    }

    #[test]
    fn nan_inf_and_huge_numbers_are_refused_with_their_line() {
        let dir = tempfile::tempdir().unwrap();
        for bad in ["nan", "inf", "1e300"] {
            let rel = write(
                dir.path(),
                "bad.relations",
                &format!("1 2 1 0 0\n1 2 {bad} 0 0\n"),
            );
            let err = format!("{:#}", load_relations(&rel).unwrap_err());
            assert!(err.contains("bad.relations:2"), "{bad}: {err}");
        }
    }

    #[test]
    fn reference_pairs_by_distance() {
        let reference = PlanarTrajectory {
            poses: vec![
                (1, Se2::new(0.0, 0.0, 0.0)),
                (2, Se2::new(0.5, 0.0, 0.0)),
                (3, Se2::new(3.0, 0.0, 0.0)),
                (4, Se2::new(0.2, 0.1, 1.0)),
            ],
        };
        let rels = relations_from_reference(&reference, 1.0);
        let pairs: Vec<(i64, i64)> = rels.iter().map(|r| (r.t1_ns, r.t2_ns)).collect();
        assert_eq!(pairs, vec![(1, 2), (1, 4), (2, 4)]);
        let s = score(&reference, &rels, 0.0).unwrap();
        assert!(s.trans_mean_m < 1e-12);
    }

    #[test]
    fn revisits_are_scored_apart_from_local_pairs() {
        let s_ns = |s: i64| s * 1_000_000_000;
        // Reference: out along x and back to the start after 60 s.
        let reference = PlanarTrajectory {
            poses: vec![
                (s_ns(0), Se2::new(0.0, 0.0, 0.0)),
                (s_ns(1), Se2::new(0.5, 0.0, 0.0)),
                (s_ns(60), Se2::new(0.1, 0.0, 0.0)),
            ],
        };
        // The estimate is locally right but has drifted 0.3 m in y by the revisit.
        let estimate = PlanarTrajectory {
            poses: vec![
                (s_ns(0), Se2::new(0.0, 0.0, 0.0)),
                (s_ns(1), Se2::new(0.5, 0.0, 0.0)),
                (s_ns(60), Se2::new(0.1, 0.3, 0.0)),
            ],
        };
        let rels = relations_from_reference(&reference, 1.0);
        let s = score(&estimate, &rels, 0.0).unwrap();
        assert_eq!((s.pairs_local, s.pairs_revisit), (1, 2));
        assert!(s.trans_mean_local_m.unwrap() < 1e-12);
        assert!(
            (s.trans_mean_revisit_m.unwrap() - 0.3).abs() < 1e-9,
            "{s:?}"
        );
    }

    #[test]
    fn sensor_frame_removes_the_mounting_error_of_turns() {
        // The robot turns on the spot; its laser sits 0.04 m behind the centre, so the
        // laser's reference poses move on a circle while the robot's stay put.
        let offset = Se2::new(-0.04, 0.0, 0.0);
        let robot = PlanarTrajectory {
            poses: (0..8)
                .map(|i| (i64::from(i), Se2::new(1.0, 2.0, 0.4 * f64::from(i))))
                .collect(),
        };
        let laser = robot.in_sensor_frame(&offset);
        let rels = relations_from_reference(&laser, 1.0);
        assert_eq!(rels.len(), 28);
        // Robot poses against laser relations: the turn shows up as translation error.
        let wrong = score(&robot, &rels, 0.0).unwrap();
        assert!(wrong.trans_mean_m > 0.03, "{wrong:?}");
        assert!(wrong.rot_mean_deg < 1e-9, "{wrong:?}");
        let right = score(&robot.in_sensor_frame(&offset), &rels, 0.0).unwrap();
        assert!(right.trans_mean_m < 1e-12, "{right:?}");
    }
}
