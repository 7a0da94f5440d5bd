//! An implicit 2-d tree over a caller's slice of points, for nearest-neighbour queries
//! without a heap.
//!
//! Building reorders the slice in place: the median (along x at even depths, y at odd ones) of
//! every range sits at the range's middle, the smaller half before it and the larger after.
//! No index or node storage is needed; a query descends with recursion of depth
//! `log2(len)` (11 for 1081 points).

use crate::frontend::scan::ScanPoint;

/// A 2-d tree borrowing its points.
#[derive(Debug, Clone, Copy)]
pub struct KdTree<'a> {
    points: &'a [ScanPoint],
}

fn build(points: &mut [ScanPoint], axis: usize) {
    if points.len() <= 1 {
        return;
    }
    let mid = points.len() / 2;
    points.select_nth_unstable_by(mid, |a, b| a.p[axis].total_cmp(&b.p[axis]));
    let (left, right) = points.split_at_mut(mid);
    build(left, axis ^ 1);
    if let Some((_, rest)) = right.split_first_mut() {
        build(rest, axis ^ 1);
    }
}

impl<'a> KdTree<'a> {
    /// Arranges `points` into a tree (in place) and borrows them. Non-finite points must not be
    /// present (preprocessing never produces them).
    pub fn build(points: &'a mut [ScanPoint]) -> KdTree<'a> {
        build(points, 0);
        KdTree { points }
    }

    /// A tree over points that [`KdTree::build`] arranged and nothing changed since (the
    /// caller keeps track; a wrong arrangement gives wrong answers, never a panic).
    pub(crate) fn arranged(points: &'a [ScanPoint]) -> KdTree<'a> {
        KdTree { points }
    }

    /// The points, in tree order.
    pub fn points(&self) -> &'a [ScanPoint] {
        self.points
    }

    /// The nearest point to `q` closer than `sqrt(max_d2)`, with its squared distance.
    pub fn nearest(&self, q: [f32; 2], max_d2: f32) -> Option<(&'a ScanPoint, f32)> {
        let mut best: Option<(&'a ScanPoint, f32)> = None;
        let mut best_d2 = max_d2;
        nearest(self.points, 0, q, &mut best, &mut best_d2);
        best
    }
}

fn nearest<'a>(
    pts: &'a [ScanPoint],
    axis: usize,
    q: [f32; 2],
    best: &mut Option<(&'a ScanPoint, f32)>,
    best_d2: &mut f32,
) {
    let Some((left, rest)) = pts.split_at_checked(pts.len() / 2) else {
        return;
    };
    let Some((node, right)) = rest.split_first() else {
        return;
    };
    let (dx, dy) = (node.p[0] - q[0], node.p[1] - q[1]);
    let d2 = dx * dx + dy * dy;
    if d2 < *best_d2 {
        *best_d2 = d2;
        *best = Some((node, d2));
    }
    let diff = if axis == 0 {
        q[0] - node.p[0]
    } else {
        q[1] - node.p[1]
    };
    let (near, far) = if diff < 0.0 {
        (left, right)
    } else {
        (right, left)
    };
    if !near.is_empty() {
        nearest(near, axis ^ 1, q, best, best_d2);
    }
    if !far.is_empty() && diff * diff < *best_d2 {
        nearest(far, axis ^ 1, q, best, best_d2);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn nearest_matches_brute_force(
            pts in proptest::collection::vec((-5.0f32..5.0, -5.0f32..5.0), 1..200),
            q in (-6.0f32..6.0, -6.0f32..6.0),
            r in 0.1f32..3.0,
        ) {
            let mut arr = [ScanPoint::default(); 200];
            for (a, p) in arr.iter_mut().zip(&pts) {
                a.p = [p.0, p.1];
            }
            let slice = &mut arr[..pts.len()];
            let tree = KdTree::build(slice);
            let q = [q.0, q.1];
            let brute = tree
                .points()
                .iter()
                .map(|p| (p.p[0] - q[0]) * (p.p[0] - q[0]) + (p.p[1] - q[1]) * (p.p[1] - q[1]))
                .filter(|&d| d < r * r)
                .fold(None, |m: Option<f32>, d| Some(m.map_or(d, |m| m.min(d))));
            let got = tree.nearest(q, r * r).map(|(_, d)| d);
            prop_assert_eq!(got, brute);
        }
    }
}
