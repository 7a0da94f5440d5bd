//! An implicit 2-d tree over a caller's slice of points, for nearest-neighbour queries
//! without a heap.
//!
//! Building reorders the slice in place: the median (along x at even depths, y at odd ones) of
//! every range sits at the range's middle, the smaller half before it and the larger after.
//! No index or node storage is needed.
//!
//! Building and querying walk the tree with an explicit stack instead of recursion (the
//! median selection is still `core`'s, see `voxel_downsample`), so the firmware's stack can
//! have a static bound. A range of `len` points has `floor(log2(len)) + 1`
//! levels below it, and a depth-first walk keeps at most one waiting range per level plus the
//! current one: `LEVELS` entries (`usize::BITS + 1`) hold any slice (12 for 1081 points).

use crate::frontend::scan::ScanPoint;

/// Entries of the walks' explicit stacks: enough for a slice of any length (see the module
/// doc).
const LEVELS: usize = usize::BITS as usize + 1;

/// A 2-d tree borrowing its points.
#[derive(Debug, Clone, Copy)]
pub struct KdTree<'a> {
    points: &'a [ScanPoint],
}

fn build(points: &mut [ScanPoint]) {
    // (start, end, axis) of the ranges still to arrange.
    let mut stack = heapless::Vec::<(usize, usize, usize), LEVELS>::new();
    let mut next = Some((0, points.len(), 0));
    while let Some((lo, hi, axis)) = next.take().or_else(|| stack.pop()) {
        // Fewer than two points are arranged already (and selecting in an empty range would
        // panic: a submap can have no cell above the occupied threshold yet).
        let Some(range) = points.get_mut(lo..hi).filter(|r| r.len() > 1) else {
            continue;
        };
        let mid = range.len() / 2;
        // Core's selection, not `crate::sort::select_nth_by` with a total-order tie-break:
        // see `voxel_downsample` for why results must not move yet.
        range.select_nth_unstable_by(mid, |a, b| a.p[axis].total_cmp(&b.p[axis]));
        for (s, e) in [(lo, lo + mid), (lo + mid + 1, hi)] {
            // Never full (see the module doc).
            if e > s + 1 && stack.push((s, e, axis ^ 1)).is_err() {
                break;
            }
        }
    }
}

impl<'a> KdTree<'a> {
    /// Arranges `points` into a tree (in place) and borrows them. Non-finite points must not be
    /// present (preprocessing never produces them).
    pub fn build(points: &'a mut [ScanPoint]) -> KdTree<'a> {
        build(points);
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
    ///
    /// Depth first, the side of `q` first; the other side of a node is entered only when its
    /// splitting line is closer than the best point found by then.
    pub fn nearest(&self, q: [f32; 2], max_d2: f32) -> Option<(&'a ScanPoint, f32)> {
        let mut best: Option<(&'a ScanPoint, f32)> = None;
        let mut best_d2 = max_d2;
        // The far sides passed on the way down: (start, end, axis, squared distance from `q`
        // to the splitting line), entered on the way back only if that line is closer than
        // the best point found by then.
        let mut far_sides = heapless::Vec::<(usize, usize, usize, f32), LEVELS>::new();
        let (mut lo, mut hi, mut axis) = (0, self.points.len(), 0);
        loop {
            let mid = lo + (hi - lo) / 2;
            if let (true, Some(node)) = (lo < hi, self.points.get(mid)) {
                let (dx, dy) = (node.p[0] - q[0], node.p[1] - q[1]);
                let d2 = dx * dx + dy * dy;
                if d2 < best_d2 {
                    best_d2 = d2;
                    best = Some((node, d2));
                }
                let diff = if axis == 0 {
                    q[0] - node.p[0]
                } else {
                    q[1] - node.p[1]
                };
                let (near, far) = if diff < 0.0 {
                    ((lo, mid), (mid + 1, hi))
                } else {
                    ((mid + 1, hi), (lo, mid))
                };
                // Never full (see the module doc).
                if far.1 > far.0
                    && far_sides
                        .push((far.0, far.1, axis ^ 1, diff * diff))
                        .is_err()
                {
                    return best;
                }
                (lo, hi, axis) = (near.0, near.1, axis ^ 1);
                continue;
            }
            // Back up to the deepest far side still worth entering.
            loop {
                let Some((l, h, a, gap)) = far_sides.pop() else {
                    return best;
                };
                if gap < best_d2 {
                    (lo, hi, axis) = (l, h, a);
                    break;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn nearest_matches_brute_force(
            pts in proptest::collection::vec((-5.0f32..5.0, -5.0f32..5.0), 0..200),
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

    #[test]
    fn a_tree_of_no_points_finds_nothing() {
        let tree = KdTree::build(&mut []);
        assert!(tree.points().is_empty());
        assert!(tree.nearest([0.0, 0.0], 1e6).is_none());
    }
}
