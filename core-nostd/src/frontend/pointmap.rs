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
    /// Points that did not fit, over the map's life.
    pub overflow: u32,
}

impl<const N: usize> PointMap<N> {
    /// An empty map with voxels of `voxel` metres (e.g. the grid resolution).
    pub const fn new(voxel: f32) -> Self {
        PointMap {
            points: heapless::Vec::new(),
            voxel,
            overflow: 0,
        }
    }

    /// Forgets every point (a new submap starts).
    pub fn clear(&mut self) {
        self.points.clear();
    }

    /// Adds `scan` (robot frame) taken at `pose`, keeping points within `max_radius` of the
    /// robot, then merges voxels.
    pub fn insert(&mut self, pose: &Se2, scan: &[ScanPoint], max_radius: f32) {
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

    /// A search tree over the points (reorders them).
    pub fn tree(&mut self) -> KdTree<'_> {
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
}
