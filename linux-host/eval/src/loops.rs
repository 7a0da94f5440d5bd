//! Wrong loop closures: every loop edge a mapper left in its pose graph, held against ground
//! truth. A loop edge (nodes not consecutive) claims the relative pose between two keyframes;
//! ground truth says what that relative pose really was. An edge whose claimed translation
//! differs from the true one by more than a threshold (0.3 m in the generalization benchmark)
//! is a wrong loop closure that the back-end accepted (paper, section III-D: loop closure
//! verification; this checks it from outside).
//!
//! The graph file holds every loop edge, also those the back-end's max-mixture has switched off
//! (its null hypothesis explains them better at the final poses, so they do not act on the
//! map). Given the switched-off edges (`report.json`'s `loop_edges.switched_off_edges`), the
//! check counts the wrong edges that are active apart: those are the wrong loop closures the
//! optimized map really accepted.
//!
//! The graph file holds no time stamps, so each vertex is matched to the scan of the mapper's
//! trajectory (`trajectory.tum`) at the same optimized pose: `cloi map` writes keyframe poses to
//! both files from the same solution, so the match is exact up to printing precision.

use std::collections::HashSet;
use std::path::Path;

use anyhow::{bail, Context, Result};
use cloi_core::geom::wrap_angle;
use cloi_core::Se2;
use serde::Serialize;

use crate::relations::PlanarTrajectory;
use cloi_core::graph::EdgeKind;

use cloi_io::graph_io::GraphFile;

/// How far (m, rad) a vertex may lie from a trajectory pose and still be that scan: a few
/// printing ulps, far below any motion between scans.
const SAME_POSE: f64 = 1e-5;

/// One loop edge whose claim disagrees with ground truth.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct WrongLoop {
    /// Vertex ids of the edge, as in the file.
    pub from: i64,
    /// Second vertex id.
    pub to: i64,
    /// Distance between the claimed and the true relative translation, metres.
    pub error_m: f64,
    /// Difference of the claimed and the true relative rotation, degrees.
    pub error_deg: f64,
    /// Whether the edge acts on the optimized map (not switched off by the max-mixture).
    pub active: bool,
}

/// The verdict on a graph's loop edges.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LoopCheck {
    /// Loop edges in the graph.
    pub loop_edges: usize,
    /// Loop edges whose two vertices were matched to scans with ground truth.
    pub checked: usize,
    /// Loop edges that could not be checked (a vertex without a scan, or no ground truth near
    /// its time).
    pub unchecked: usize,
    /// Checked edges that disagree with ground truth by more than the threshold.
    pub wrong: usize,
    /// Loop edges named as switched off by the back-end.
    pub switched_off: usize,
    /// Wrong edges that are not switched off: wrong loop closures acting on the map.
    pub wrong_active: usize,
    /// Largest translation disagreement among the checked edges, metres.
    pub max_error_m: f64,
    /// The threshold used, metres.
    pub threshold_m: f64,
    /// The wrong edges, worst first.
    pub wrong_edges: Vec<WrongLoop>,
}

/// The loop edges a `cloi map` report names as switched off, as `(from, to)` vertex ids.
///
/// # Errors
/// An unreadable file, or a report without the `loop_edges.switched_off_edges` list.
pub fn switched_off_edges(report: &Path) -> Result<HashSet<(i64, i64)>> {
    let text =
        std::fs::read_to_string(report).with_context(|| format!("reading {}", report.display()))?;
    let json: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{} is not JSON", report.display()))?;
    let Some(list) = json["loop_edges"]["switched_off_edges"].as_array() else {
        bail!(
            "{} has no loop_edges.switched_off_edges list (not a cloi map report, or an older one)",
            report.display()
        );
    };
    list.iter()
        .map(|pair| match (pair[0].as_i64(), pair[1].as_i64()) {
            (Some(a), Some(b)) => Ok((a, b)),
            _ => bail!(
                "{}: a switched-off edge is not a pair of vertex ids: {pair}",
                report.display()
            ),
        })
        .collect()
}

/// The time stamp of the trajectory pose equal to `pose`, if one is.
fn stamp_of(pose: &Se2, trajectory: &[(i64, Se2)]) -> Option<i64> {
    trajectory
        .iter()
        .filter(|(_, p)| {
            (p.x - pose.x).abs() < SAME_POSE
                && (p.y - pose.y).abs() < SAME_POSE
                && wrap_angle(p.theta - pose.theta).abs() < SAME_POSE * 10.0
        })
        .map(|(t, _)| *t)
        .next()
}

/// The pose of `truth` at `t_ns` interpolated between the poses before and after it, if they
/// are at most `max_gap_ns` apart.
fn interpolate(truth: &PlanarTrajectory, t_ns: i64, max_gap_ns: i64) -> Option<Se2> {
    let i = truth.poses.partition_point(|p| p.0 < t_ns);
    let (ta, a) = *truth.poses.get(i.checked_sub(1)?)?;
    let (tb, b) = *truth.poses.get(i)?;
    if tb - ta > max_gap_ns || tb <= ta {
        return None;
    }
    let f = (t_ns - ta) as f64 / (tb - ta) as f64;
    Some(Se2::new(
        a.x + f * (b.x - a.x),
        a.y + f * (b.y - a.y),
        a.theta + f * wrap_angle(b.theta - a.theta),
    ))
}

/// Checks every loop edge of `graph` (its vertex poses as `cloi map` wrote them) against
/// `truth`, locating vertices in time through `estimate` (the mapper's trajectory). Ground
/// truth is taken at the nearest stamp within `tolerance_ns`, else interpolated between the
/// two poses around the time if they are at most `max_gap_ns` apart (a sparse reference such
/// as GMapping's, which holds only the scans it processed).
///
/// `switched_off` names the edges (`(from, to)` vertex ids) the back-end switched off.
///
/// # Errors
/// A threshold that is not a positive number, or a graph whose vertices match no scan at all
/// (the wrong trajectory file).
pub fn check_loops(
    graph: &GraphFile,
    switched_off: &HashSet<(i64, i64)>,
    estimate: &PlanarTrajectory,
    truth: &PlanarTrajectory,
    tolerance_ns: i64,
    max_gap_ns: i64,
    threshold_m: f64,
) -> Result<LoopCheck> {
    if !(threshold_m > 0.0 && threshold_m.is_finite()) {
        bail!("the wrong-loop threshold must be a positive number of metres");
    }
    let stamps: Vec<Option<i64>> = graph
        .poses
        .iter()
        .map(|p| stamp_of(p, &estimate.poses))
        .collect();
    if !graph.poses.is_empty() && stamps.iter().all(Option::is_none) {
        bail!("no vertex of the graph lies on the trajectory: are they from the same run?");
    }
    let mut check = LoopCheck {
        loop_edges: 0,
        checked: 0,
        unchecked: 0,
        wrong: 0,
        switched_off: 0,
        wrong_active: 0,
        max_error_m: 0.0,
        threshold_m,
        wrong_edges: Vec::new(),
    };
    let id = |node: usize| graph.ids.get(node).copied().unwrap_or(-1);
    for e in graph.edges.iter().filter(|e| e.kind() == EdgeKind::Loop) {
        check.loop_edges += 1;
        let active = !switched_off.contains(&(id(e.from), id(e.to)));
        if !active {
            check.switched_off += 1;
        }
        let truth_at = |node: usize| {
            stamps.get(node).copied().flatten().and_then(|t| {
                truth
                    .at(t, tolerance_ns)
                    .or_else(|| interpolate(truth, t, max_gap_ns))
            })
        };
        let (Some(a), Some(b)) = (truth_at(e.from), truth_at(e.to)) else {
            check.unchecked += 1;
            continue;
        };
        let real = a.inverse().compose(&b);
        let claim = e.measurement;
        let error_m = (claim.x - real.x).hypot(claim.y - real.y);
        let error_deg = wrap_angle(claim.theta - real.theta).abs().to_degrees();
        check.checked += 1;
        check.max_error_m = check.max_error_m.max(error_m);
        if error_m > threshold_m {
            check.wrong += 1;
            if active {
                check.wrong_active += 1;
            }
            check.wrong_edges.push(WrongLoop {
                from: id(e.from),
                to: id(e.to),
                error_m,
                error_deg,
                active,
            });
        }
    }
    check
        .wrong_edges
        .sort_by(|x, y| y.error_m.total_cmp(&x.error_m));
    Ok(check)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A square drive of four keyframes with ground truth; the estimate is the truth moved by a
    /// rigid transform (the checker must not care), and two loop edges: one true, one 0.5 m off.
    #[test]
    fn flags_only_the_loop_edge_that_disagrees_with_ground_truth() {
        let truth_poses = [
            Se2::new(0.0, 0.0, 0.0),
            Se2::new(2.0, 0.0, 1.5),
            Se2::new(2.0, 2.0, 3.0),
            Se2::new(0.0, 2.0, -1.5),
        ];
        let shift = Se2::new(5.0, -1.0, 0.3);
        let est: Vec<Se2> = truth_poses.iter().map(|p| shift.compose(p)).collect();
        let stamp = |i: usize| 1_000_000_000 * (i as i64 + 1);
        let truth = PlanarTrajectory {
            poses: truth_poses
                .iter()
                .enumerate()
                .map(|(i, p)| (stamp(i) + 3_000_000, *p))
                .collect(),
        };
        // The estimate has scans between the keyframes too.
        let mut estimate = PlanarTrajectory::default();
        for (i, p) in est.iter().enumerate() {
            estimate.poses.push((stamp(i), *p));
            estimate
                .poses
                .push((stamp(i) + 500_000_000, p.compose(&Se2::new(0.3, 0.0, 0.0))));
        }
        let good = truth_poses[0].inverse().compose(&truth_poses[3]);
        let real_02 = truth_poses[0].inverse().compose(&truth_poses[2]);
        let bad = Se2::new(real_02.x + 0.3, real_02.y - 0.4, real_02.theta);
        let mut text = String::new();
        for (i, p) in est.iter().enumerate() {
            text += &format!("VERTEX_SE2 {} {} {} {}\n", 10 + i, p.x, p.y, p.theta);
        }
        for i in 0..3 {
            let m = truth_poses[i].inverse().compose(&truth_poses[i + 1]);
            text += &format!(
                "EDGE_SE2 {} {} {} {} {} 1 0 0 1 0 1\n",
                10 + i,
                11 + i,
                m.x,
                m.y,
                m.theta
            );
        }
        text += &format!(
            "EDGE_SE2 10 13 {} {} {} 1 0 0 1 0 1\n",
            good.x, good.y, good.theta
        );
        text += &format!(
            "EDGE_SE2 10 12 {} {} {} 1 0 0 1 0 1\n",
            bad.x, bad.y, bad.theta
        );
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("test.g2o");
        std::fs::write(&path, text).expect("write");
        let graph = cloi_io::graph_io::read_graph(&path, None).expect("graph");
        let c = check_loops(
            &graph,
            &HashSet::new(),
            &estimate,
            &truth,
            10_000_000,
            0,
            0.3,
        )
        .expect("checks");
        assert_eq!(c.loop_edges, 2);
        assert_eq!(c.checked, 2);
        assert_eq!(c.unchecked, 0);
        assert_eq!(c.wrong, 1);
        assert_eq!((c.wrong_edges[0].from, c.wrong_edges[0].to), (10, 12));
        assert!((c.max_error_m - 0.5).abs() < 1e-6, "{}", c.max_error_m);
        assert_eq!((c.switched_off, c.wrong_active), (0, 1));
        // The wrong edge switched off by the back-end still counts as wrong, not as active.
        let off = HashSet::from([(10, 12)]);
        let c = check_loops(&graph, &off, &estimate, &truth, 10_000_000, 0, 0.3).expect("checks");
        assert_eq!((c.wrong, c.switched_off, c.wrong_active), (1, 1, 0));
        assert!(!c.wrong_edges[0].active);
        // Ground truth too far in time: nothing can be checked.
        let c = check_loops(
            &graph,
            &HashSet::new(),
            &estimate,
            &truth,
            1_000_000,
            0,
            0.3,
        )
        .expect("checks");
        assert_eq!((c.checked, c.unchecked, c.wrong), (0, 2, 0));
        // ... unless interpolation may bridge the 1 s between ground-truth poses: the stamps
        // are 3 ms off, so the interpolated truth moves by under 3 cm and the verdict stands.
        let mut padded = truth.clone();
        padded
            .poses
            .insert(0, (stamp(0) - 1_000_000_000, truth_poses[0]));
        padded.poses.push((stamp(4), truth_poses[3]));
        let c = check_loops(
            &graph,
            &HashSet::new(),
            &estimate,
            &padded,
            1_000_000,
            1_100_000_000,
            0.3,
        )
        .expect("checks");
        assert_eq!((c.checked, c.unchecked, c.wrong), (2, 0, 1));
        // A threshold above the error accepts both; a trajectory of another run is an error.
        assert_eq!(
            check_loops(
                &graph,
                &HashSet::new(),
                &estimate,
                &truth,
                10_000_000,
                0,
                0.6
            )
            .expect("checks")
            .wrong,
            0
        );
        assert!(check_loops(&graph, &HashSet::new(), &truth, &truth, 10_000_000, 0, 0.3).is_err());
        assert!(check_loops(
            &graph,
            &HashSet::new(),
            &estimate,
            &truth,
            10_000_000,
            0,
            f64::NAN
        )
        .is_err());
    }
}
