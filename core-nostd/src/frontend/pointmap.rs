//! The reference of LiDAR odometry: the points of the recent keyframes in the front-end's
//! frame, thinned by a voxel grid.
//!
//! Matching against the occupancy grid's cell centres is biased by up to half a cell per wall
//! (a hit is recorded in the cell on the sensor's side of a wall lying on a cell border), so
//! odometry matches against the measured points themselves; the grid serves loop closure, the
//! map and export. After every insertion the set is voxel-merged (sort-based, in place), so it
//! holds about one point per voxel of wall, independent of how long the robot stays.
//!
//! A map is filled one of two ways. [`PointMap::insert`] keeps bare points, and the caller
//! restarts the map ([`PointMap::clear`]) when the robot leaves its area. A **sliding** map
//! ([`PointMap::insert_stamped`]) never restarts: every point remembers the first and the last
//! insertion that hit its voxel and the front-end path travelled at the last one, and
//! [`PointMap::forget`] drops a point once it lies beyond the sensor's radius, once the robot
//! has travelled more than a span since it was last seen (the drift between the map's oldest
//! and newest parts stays that of the span, and an earlier pass through the same place is
//! never matched), or when a few insertions passed without a second keyframe seeing its voxel
//! (people walking by, spurious returns). What stays is what the sensor saw repeatedly over the
//! recent path: sparse but repeated returns such as glass, and walls near the end of the
//! sensor's range, which a restart from the current scan would drop.

use crate::frontend::kdtree::KdTree;
use crate::frontend::scan::{
    centroid, merge_voxels, point_order, voxel_downsample, ScanPoint, ScanPoints,
};
use crate::geom::Se2;

/// A point of a sliding map and when it was seen.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MapPoint {
    /// Position and normal in the map's frame.
    pub point: ScanPoint,
    /// Front-end path (metres) at the last insertion that hit the point's voxel.
    pub seen: f32,
    /// Serial of the first insertion that hit the voxel.
    pub first: u32,
    /// Serial of the last insertion that hit the voxel.
    pub last: u32,
}

impl MapPoint {
    /// Hit by two insertions or more.
    pub fn confirmed(&self) -> bool {
        self.last > self.first
    }
}

/// What a sliding map forgets (see the module doc).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Slide {
    /// Points farther than this from the robot, metres.
    pub radius: f32,
    /// Points not seen over this much front-end path, metres.
    pub span: f32,
    /// Points whose voxel no other insertion hit in the `confirm` insertions after the first.
    pub confirm: u32,
}

/// A voxel-thinned point set of at most `N` points in the world frame.
#[derive(Debug, Clone)]
pub struct PointMap<const N: usize> {
    /// The points of a map filled by [`PointMap::insert`] (in tree order once arranged); of a
    /// sliding map, the copy its tree is built on.
    points: ScanPoints<N>,
    /// The points of a sliding map, with when they were seen.
    stamped: heapless::Vec<MapPoint, N>,
    /// Filled by [`PointMap::insert_stamped`] since the last [`PointMap::clear`].
    sliding: bool,
    voxel: f32,
    /// The points are in tree order (arranged by the last [`PointMap::tree`], unchanged since).
    arranged: bool,
    /// Stamped insertions so far (the serial of the next one).
    inserted: u32,
    /// Points that did not fit, over the map's life.
    pub overflow: u32,
}

impl<const N: usize> PointMap<N> {
    /// An empty map with voxels of `voxel` metres (e.g. the grid resolution).
    pub const fn new(voxel: f32) -> Self {
        PointMap {
            points: heapless::Vec::new(),
            stamped: heapless::Vec::new(),
            sliding: false,
            voxel,
            arranged: false,
            inserted: 0,
            overflow: 0,
        }
    }

    /// Forgets every point (a new submap starts).
    pub fn clear(&mut self) {
        self.points.clear();
        self.stamped.clear();
        self.sliding = false;
        self.arranged = false;
    }

    /// Adds `scan` (robot frame) taken at `pose`, keeping points within `max_radius` of the
    /// robot, then merges voxels.
    pub fn insert(&mut self, pose: &Se2, scan: &[ScanPoint], max_radius: f32) {
        self.arranged = false;
        let mut merged_when_full = false;
        for w in placed(pose, scan, max_radius) {
            // When full, merge once per insertion; if that frees nothing, the rest overflows.
            if self.points.is_full() && !merged_when_full {
                voxel_downsample(&mut self.points, self.voxel);
                merged_when_full = true;
            }
            if self.points.push(w).is_err() {
                self.overflow += 1;
            }
        }
        voxel_downsample(&mut self.points, self.voxel);
    }

    /// Adds `scan` (robot frame) taken at `pose` after `path` metres of front-end travel to a
    /// sliding map, keeping points within `max_radius` of the robot, then merges voxels: each
    /// keeps the centroid of its points, seen when the latest of them was, first and last hit
    /// by the earliest and latest insertion among them. [`PointMap::forget`] makes room first.
    pub fn insert_stamped(&mut self, pose: &Se2, scan: &[ScanPoint], max_radius: f32, path: f32) {
        self.arranged = false;
        self.sliding = true;
        let serial = self.inserted;
        self.inserted = self.inserted.wrapping_add(1);
        for point in placed(pose, scan, max_radius) {
            let m = MapPoint {
                point,
                seen: path,
                first: serial,
                last: serial,
            };
            if self.stamped.push(m).is_err() {
                self.overflow += 1;
            }
        }
        merge_voxels(
            &mut self.stamped,
            self.voxel,
            |m| &m.point,
            |run| MapPoint {
                point: centroid(run.iter().map(|m| &m.point)),
                seen: run.iter().map(|m| m.seen).fold(f32::MIN, f32::max),
                first: run.iter().map(|m| m.first).min().unwrap_or(0),
                last: run.iter().map(|m| m.last).max().unwrap_or(0),
            },
        );
    }

    /// Before a stamped insertion at `at` (map frame) after `path` metres of front-end travel:
    /// forgets what `slide` says a sliding map no longer holds (module doc), then, if
    /// `incoming` more points would not fit, the points seen longest ago.
    pub fn forget(&mut self, at: [f32; 2], path: f32, slide: &Slide, incoming: usize) {
        let before = self.stamped.len();
        let r2 = slide.radius * slide.radius;
        let next = self.inserted;
        self.stamped.retain(|m| {
            let (dx, dy) = (m.point.p[0] - at[0], m.point.p[1] - at[1]);
            dx * dx + dy * dy <= r2
                && path - m.seen <= slide.span
                && (m.confirmed() || next.wrapping_sub(m.first) <= slide.confirm)
        });
        let room = N.saturating_sub(incoming);
        if self.stamped.len() > room {
            // The newest `room` points stay (a total order: one result whatever the algorithm).
            let order = |a: &MapPoint, b: &MapPoint| {
                b.seen
                    .total_cmp(&a.seen)
                    .then_with(|| point_order(&a.point, &b.point))
            };
            crate::sort::select_nth_by(&mut self.stamped[..], room, order);
            self.stamped.truncate(room);
        }
        if self.stamped.len() != before {
            self.arranged = false;
        }
    }

    /// Points held.
    pub fn len(&self) -> usize {
        if self.sliding {
            self.stamped.len()
        } else {
            self.points.len()
        }
    }

    /// No point held.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The points of a map filled by [`PointMap::insert`].
    pub fn points(&self) -> &[ScanPoint] {
        &self.points
    }

    /// The points of a sliding map, with when they were seen.
    pub fn stamped(&self) -> &[MapPoint] {
        &self.stamped
    }

    /// A search tree over the points (arranged the first time after a change; later calls
    /// reuse that arrangement). A map filled by [`PointMap::insert`] is reordered in place; a
    /// sliding map's points are copied first.
    pub fn tree(&mut self) -> KdTree<'_> {
        if self.arranged {
            return KdTree::arranged(&self.points);
        }
        self.arranged = true;
        if self.sliding {
            self.points.clear();
            for m in &self.stamped {
                // Never full: both hold N.
                let _ = self.points.push(m.point);
            }
        }
        KdTree::build(&mut self.points)
    }
}

/// The points of `scan` (robot frame) within `max_radius` of the robot, placed at `pose`.
fn placed<'a>(
    pose: &Se2,
    scan: &'a [ScanPoint],
    max_radius: f32,
) -> impl Iterator<Item = ScanPoint> + 'a {
    let (c, s) = (libm::cos(pose.theta) as f32, libm::sin(pose.theta) as f32);
    let (x, y) = (pose.x as f32, pose.y as f32);
    let r2 = max_radius * max_radius;
    scan.iter()
        .filter(move |q| q.p[0] * q.p[0] + q.p[1] * q.p[1] <= r2)
        .map(move |q| ScanPoint {
            p: [x + c * q.p[0] - s * q.p[1], y + s * q.p[0] + c * q.p[1]],
            n: [c * q.n[0] - s * q.n[1], s * q.n[0] + c * q.n[1]],
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pt(x: f32, y: f32) -> ScanPoint {
        ScanPoint {
            p: [x, y],
            n: [0.0, 1.0],
        }
    }

    #[test]
    fn merges_voxels_transforms_and_counts_overflow() {
        let mut m = PointMap::<8>::new(0.1);
        // Two points in one voxel once moved by the pose, one beyond the radius.
        let pose = Se2::new(1.0, 2.0, core::f64::consts::FRAC_PI_2);
        m.insert(&pose, &[pt(0.52, 0.0), pt(0.56, 0.0), pt(9.0, 0.0)], 5.0);
        assert_eq!(m.points().len(), 1);
        let q = m.points()[0];
        // (0.54, 0) rotated a quarter turn and shifted: (1.0, 2.54); normal (0,1) -> (-1,0).
        assert!(
            (q.p[0] - 1.0).abs() < 1e-5 && (q.p[1] - 2.54).abs() < 1e-5,
            "{q:?}"
        );
        assert!((q.n[0] + 1.0).abs() < 1e-5 && q.n[1].abs() < 1e-5);
        // Twenty distinct voxels into eight slots: eight kept, the rest counted.
        let many: heapless::Vec<ScanPoint, 20> =
            (0..20).map(|i| pt(i as f32 * 0.2, 0.05)).collect();
        m.clear();
        m.insert(&Se2::IDENTITY, &many, 100.0);
        assert_eq!(m.points().len(), 8);
        assert_eq!(m.overflow, 12);
    }

    /// The tree is arranged once per change and reused; after each insertion it answers as a
    /// brute-force search over the points.
    #[test]
    fn the_tree_is_rebuilt_after_a_change_and_reused_otherwise() {
        let mut m = PointMap::<256>::new(0.05);
        let wall: heapless::Vec<ScanPoint, 64> =
            (0..64).map(|i| pt(2.0, -3.0 + i as f32 * 0.1)).collect();
        let queries = [[1.7f32, 0.33], [0.0, 0.0], [2.5, -2.0], [1.9, 2.9]];
        for (k, pose) in [
            Se2::IDENTITY,
            Se2::new(0.3, -0.2, 0.7),
            Se2::new(-1.0, 0.5, 2.0),
        ]
        .iter()
        .enumerate()
        {
            m.insert(pose, &wall, 10.0);
            assert!(!m.arranged, "insertion {k} leaves the order stale");
            for _ in 0..2 {
                let points: heapless::Vec<ScanPoint, 256> = m.points().iter().copied().collect();
                let tree = m.tree();
                for q in queries {
                    let brute = points
                        .iter()
                        .map(|p| {
                            (p.p[0] - q[0]) * (p.p[0] - q[0]) + (p.p[1] - q[1]) * (p.p[1] - q[1])
                        })
                        .fold(f32::INFINITY, f32::min);
                    let got = tree.nearest(q, 100.0).map(|(_, d)| d);
                    assert_eq!(got, Some(brute), "insertion {k}, query {q:?}");
                }
                assert!(m.arranged);
            }
        }
    }

    /// A sliding map keeps what two keyframes saw and forgets what lies beyond the radius,
    /// what was not seen over the span, and what no second keyframe confirmed.
    #[test]
    fn a_sliding_map_forgets_far_stale_and_unconfirmed_points() {
        let slide = Slide {
            radius: 10.0,
            span: 5.0,
            confirm: 2,
        };
        let mut m = PointMap::<64>::new(0.1);
        let has =
            |m: &PointMap<64>, x: f32| m.stamped().iter().any(|q| (q.point.p[0] - x).abs() < 0.06);
        // A wall seen by every keyframe, a passer-by seen once, a far wall seen twice.
        let wall = [pt(1.0, 0.05), pt(1.0, 0.25)];
        let id = Se2::IDENTITY;
        m.insert_stamped(&id, &[wall[0], wall[1], pt(0.5, 0.55)], 20.0, 0.0);
        m.insert_stamped(&id, &[wall[0], wall[1], pt(-8.0, 0.05)], 20.0, 1.0);
        m.forget([0.0, 0.0], 1.0, &slide, 0);
        assert_eq!(m.len(), 4, "the passer-by waits for a second keyframe");
        m.insert_stamped(&id, &[pt(-8.0, 0.05)], 20.0, 1.0);
        m.forget([0.0, 0.0], 2.0, &slide, 0);
        assert!(!has(&m, 0.5), "never confirmed: forgotten");
        assert!(has(&m, -8.0) && has(&m, 1.0));
        // The robot moves 3 m on: the far wall is beyond the radius.
        m.insert_stamped(&id, &wall, 20.0, 2.0);
        m.forget([3.0, 0.0], 2.5, &slide, 0);
        assert!(!has(&m, -8.0) && has(&m, 1.0));
        // The tree holds what the map holds.
        let tree = m.tree();
        assert_eq!(tree.points().len(), 2);
        assert!(tree.nearest([1.0, 0.1], 1.0).is_some());
        // More than 5 m of path without seeing the wall again: forgotten.
        m.forget([3.0, 0.0], 7.5, &slide, 0);
        assert!(m.is_empty());
    }

    /// A full sliding map makes room for the incoming scan by forgetting the points seen
    /// longest ago.
    #[test]
    fn a_full_sliding_map_forgets_the_oldest_first() {
        let slide = Slide {
            radius: 100.0,
            span: 100.0,
            confirm: 100,
        };
        let mut m = PointMap::<8>::new(0.1);
        for i in 0..8 {
            m.insert_stamped(&Se2::IDENTITY, &[pt(i as f32, 0.05)], 100.0, i as f32);
        }
        assert_eq!(m.len(), 8);
        m.forget([0.0, 0.0], 8.0, &slide, 3);
        let mut left: heapless::Vec<f32, 8> = m.stamped().iter().map(|q| q.seen).collect();
        left.sort_unstable_by(f32::total_cmp);
        assert_eq!(&left[..], &[3.0, 4.0, 5.0, 6.0, 7.0]);
    }
}
