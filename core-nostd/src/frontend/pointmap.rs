//! The reference of LiDAR odometry: the points of the keyframes of the current submap, in the
//! world frame, thinned by a voxel grid.
//!
//! Matching against the occupancy grid's cell centres is biased by up to half a cell per wall
//! (a hit is recorded in the cell on the sensor's side of a wall lying on a cell border), so
//! odometry matches against the measured points themselves; the grid serves loop closure, the
//! map and export. After every insertion the set is voxel-merged (sort-based, in place), so it
//! holds about one point per voxel of wall, independent of how long the robot stays.

use crate::frontend::kdtree::KdTree;
use crate::frontend::scan::{voxel_downsample, ScanPoint, ScanPoints};
use crate::geom::Se2;

/// A voxel-thinned point set of at most `N` points in the world frame.
#[derive(Debug, Clone)]
pub struct PointMap<const N: usize> {
    points: ScanPoints<N>,
    voxel: f32,
    /// The points are in tree order (arranged by the last [`PointMap::tree`], unchanged since).
    arranged: bool,
    /// Points that did not fit, over the map's life.
    pub overflow: u32,
}

impl<const N: usize> PointMap<N> {
    /// An empty map with voxels of `voxel` metres (e.g. the grid resolution).
    pub const fn new(voxel: f32) -> Self {
        PointMap {
            points: heapless::Vec::new(),
            voxel,
            arranged: false,
            overflow: 0,
        }
    }

    /// Forgets every point (a new submap starts).
    pub fn clear(&mut self) {
        self.points.clear();
        self.arranged = false;
    }

    /// Adds `scan` (robot frame) taken at `pose`, keeping points within `max_radius` of the
    /// robot, then merges voxels.
    pub fn insert(&mut self, pose: &Se2, scan: &[ScanPoint], max_radius: f32) {
        self.arranged = false;
        let (c, s) = (libm::cos(pose.theta) as f32, libm::sin(pose.theta) as f32);
        let (x, y) = (pose.x as f32, pose.y as f32);
        let r2 = max_radius * max_radius;
        let mut merged_when_full = false;
        for q in scan {
            if q.p[0] * q.p[0] + q.p[1] * q.p[1] > r2 {
                continue;
            }
            // When full, merge once per insertion; if that frees nothing, the rest overflows.
            if self.points.is_full() && !merged_when_full {
                voxel_downsample(&mut self.points, self.voxel);
                merged_when_full = true;
            }
            let w = ScanPoint {
                p: [x + c * q.p[0] - s * q.p[1], y + s * q.p[0] + c * q.p[1]],
                n: [c * q.n[0] - s * q.n[1], s * q.n[0] + c * q.n[1]],
            };
            if self.points.push(w).is_err() {
                self.overflow += 1;
            }
        }
        voxel_downsample(&mut self.points, self.voxel);
    }

    /// The points.
    pub fn points(&self) -> &[ScanPoint] {
        &self.points
    }

    /// A search tree over the points (reorders them the first time after a change; later
    /// calls reuse that order).
    pub fn tree(&mut self) -> KdTree<'_> {
        if self.arranged {
            return KdTree::arranged(&self.points);
        }
        self.arranged = true;
        KdTree::build(&mut self.points)
    }
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
}
