//! The anchor node of the GPE (the paper's section III-C.1): the previously optimized node
//! nearest, in squared Mahalanobis distance, to the last pose the back-end optimized.
//!
//! The distance of a candidate is taken under the front-end's motion uncertainty accumulated
//! between it and the newest optimized node, so a node the robot reached by a long or turning
//! path counts as farther than one just behind it. Only the newest optimized nodes are
//! candidates: the anchor ties the real-time pose to the part of the map the robot is in.

use crate::frontend::lidar::{MotionNoise, Travel};
use crate::geom::{pose_squared_mahalanobis, Se2};

/// Most nodes (newest first) considered as the anchor.
pub const ANCHOR_CANDIDATES: usize = 32;

/// An optimized frame node offered as the anchor.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AnchorCandidate {
    /// Stable identity of the node (its keyframe serial).
    pub serial: u32,
    /// Optimized global pose.
    pub estimate: Se2,
    /// Front-end travel when the node was taken.
    pub travel: Travel,
}

/// Chooses the anchor among `newest_first` (the newest optimized node first, which is `x_f`);
/// `None` when there is no node.
pub fn choose_anchor(
    newest_first: impl IntoIterator<Item = AnchorCandidate>,
    noise: &impl MotionNoise,
) -> Option<u32> {
    let mut nodes = newest_first.into_iter().take(ANCHOR_CANDIDATES).peekable();
    let last = *nodes.peek()?;
    let mut best: Option<(u32, f64)> = None;
    for node in nodes {
        let cov = noise.over(&last.travel.since(&node.travel));
        let d =
            pose_squared_mahalanobis(&node.estimate, &last.estimate, &cov).unwrap_or(f64::INFINITY);
        if best.is_none_or(|(_, b)| d < b) {
            best = Some((node.serial, d));
        }
    }
    best.map(|(s, _)| s)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::Cov3;
    use nalgebra::Matrix3;

    /// Variance growing with the path, with no floor: a zero travel has no usable covariance,
    /// which takes the newest node out of the running and lets the others compete.
    #[derive(Debug)]
    struct NoFloor;

    impl MotionNoise for NoFloor {
        fn covariance(&self, distance: f64, rotation: f64) -> Cov3 {
            Matrix3::from_diagonal_element(1e-3 * (libm::fabs(distance) + libm::fabs(rotation)))
        }
    }

    /// The same with a floor.
    #[derive(Debug)]
    struct Floored;

    impl MotionNoise for Floored {
        fn covariance(&self, distance: f64, rotation: f64) -> Cov3 {
            NoFloor.covariance(distance, rotation) + Matrix3::from_diagonal_element(1e-6)
        }
    }

    fn node(serial: u32, x: f64, path: f64) -> AnchorCandidate {
        AnchorCandidate {
            serial,
            estimate: Se2::new(x, 0.0, 0.0),
            travel: Travel {
                path,
                rotation: 0.0,
            },
        }
    }

    #[test]
    fn the_newest_node_is_its_own_anchor() {
        let nodes = [node(5, 2.0, 2.0), node(4, 2.0, 1.5), node(3, 1.0, 1.0)];
        assert_eq!(choose_anchor(nodes, &Floored), Some(5));
        assert_eq!(choose_anchor([], &Floored), None);
    }

    #[test]
    fn distance_is_weighed_by_the_travel_between() {
        // 8 is 1 m off after 1 m of path (d = 1 / 1e-3); 2 is 0.5 m off after 30 m of path
        // (d = 0.25 / 0.03): the long way round makes the larger offset more plausible.
        let nodes = [node(9, 10.0, 30.0), node(8, 9.0, 29.0), node(2, 10.5, 0.0)];
        assert_eq!(choose_anchor(nodes, &NoFloor), Some(2));
    }

    #[test]
    fn only_the_newest_candidates_are_considered() {
        // Every candidate is 1 m off after 1 m of path except the oldest, which sits on the
        // newest node: it would win, but it is one past the limit.
        let mut nodes = [node(0, 0.0, 0.0); ANCHOR_CANDIDATES + 1];
        for (i, n) in nodes.iter_mut().enumerate() {
            let serial = (ANCHOR_CANDIDATES - i) as u32;
            *n = node(serial, 9.0, 29.0);
        }
        nodes[0] = node(100, 10.0, 30.0);
        nodes[ANCHOR_CANDIDATES] = node(0, 10.0, 0.0);
        let chosen = choose_anchor(nodes, &NoFloor);
        assert!(chosen.is_some_and(|s| s != 0 && s != 100), "{chosen:?}");
        let mut within = nodes;
        within[ANCHOR_CANDIDATES - 1] = node(1, 10.0, 0.0);
        assert_eq!(choose_anchor(within, &NoFloor), Some(1));
    }
}
