//! Matching a scan with the saved map (see the parent module): ICP against the occupied cells
//! of the submaps around a world pose, and the scan's fit to the whole map.

use super::Miss;
use crate::frontend::grid::probability;
use crate::frontend::icp::MatchError;
use crate::frontend::scan::{ScanPoint, MAX_POINTS};
use crate::frontend::{align, IcpConfig, KdTree, Submap};
use crate::geom::{Info3, Se2};
use crate::mapper::loops::{MatchSource, NORMAL_RADIUS, OCCUPIED};
use crate::mapper::Mapper;

/// Submaps whose occupied cells a scan is matched with, nearest anchor first.
const MAP_SUBMAPS: usize = 16;

/// The map points a match was made with, kept for the next: a keyframe near the last one sees
/// the same submaps, and gathering their points (with normals) and arranging them cost more
/// than the match itself.
#[derive(Clone, Debug)]
pub(super) struct MapReference {
    /// Submap slots, ascending.
    slots: heapless::Vec<usize, MAP_SUBMAPS>,
    /// Points held.
    len: usize,
}

impl Mapper<'_> {
    /// ICP of the scan of `source` (robot frame) against the saved map around the world pose
    /// `seed`: the occupied cells of the [`MAP_SUBMAPS`] submaps whose anchors are nearest to
    /// it, as world points (as many as the reference storage holds). A scan sees far beyond
    /// one submap (a home's is 4 m across, its LiDAR reaches 10 m), so it is matched with all
    /// of the map it can see. The world pose and its information (over steps along the world
    /// axes) when the match is good; else why not.
    ///
    /// A good match has a small residual over enough points, and most of the points the map
    /// can judge (those on cells it observed) lie within two cells of its walls, as the loop
    /// search's fitness asks. A scan that sees more than the map holds (a part of the building
    /// not mapped, a long-range LiDAR beyond the submaps gathered) is not held against it; a
    /// wrong place, where the map saw free space, is.
    pub(super) fn match_map(
        &mut self,
        source: MatchSource,
        seed: &Se2,
    ) -> Result<(Se2, Info3), Miss> {
        let reach =
            self.cfg.max_range as f64 + self.cfg.grid.side as f64 * self.cfg.grid.resolution as f64;
        // (distance to the anchor, slot, anchor pose), nearest first.
        let mut near = heapless::Vec::<(f64, usize, Se2), MAP_SUBMAPS>::new();
        for (slot, m) in self.submaps.iter().enumerate().filter(|(_, m)| m.in_use) {
            let Some(anchor) = m.anchor_estimate else {
                continue;
            };
            let d = libm::hypot(anchor.x - seed.x, anchor.y - seed.y);
            if d > reach {
                continue;
            }
            let at = near.iter().position(|c| c.0 > d).unwrap_or(near.len());
            if at < MAP_SUBMAPS {
                if near.is_full() {
                    near.pop();
                }
                let _ = near.insert(at, (d, slot, anchor));
            }
        }
        let mut slots = heapless::Vec::<usize, MAP_SUBMAPS>::new();
        for c in &near {
            // As many as `near` holds.
            let _ = slots.push(c.1);
        }
        crate::sort::sort(&mut slots);
        let held = (self.st.localize.as_ref())
            .and_then(|l| l.reference.as_ref())
            .filter(|r| r.slots == slots)
            .map(|r| r.len);
        let n = match held {
            Some(n) => n,
            None => self.gather_reference(&near, slots),
        };
        let points: &[ScanPoint] = match source {
            MatchSource::Scan => self.scan.as_slice(),
            MatchSource::Far => self.st.far.scan(),
        };
        let icp = IcpConfig {
            allow_degenerate: false,
            degeneracy_ratio: self.cfg.loops.degeneracy_ratio,
            ..self.cfg.icp
        };
        if n < icp.min_points as usize || points.len() < icp.min_points as usize {
            return Err(Miss::Uninformative);
        }
        let tree = KdTree::arranged(self.reference.get(..n).ok_or(Miss::Uninformative)?);
        let lc = self.cfg.loops;
        let r = match align(points, &tree, seed, &icp) {
            Ok(r) => r,
            Err(MatchError::Degenerate { .. }) => return Err(Miss::Uninformative),
            Err(e) => {
                debug!("map match failed: {}", e);
                return Err(Miss::Mismatch);
            }
        };
        // The fitness counts the points within two cells of the map's walls (the ICP's own
        // correspondences reach farther, to converge from the seed) among those the map can
        // judge.
        let tight = IcpConfig {
            max_correspondence: 2.0 * self.cfg.grid.resolution,
            max_iterations: 1,
            ..icp
        };
        let close = align(points, &tree, &r.pose, &tight).map_or(0, |t| t.inliers);
        let judged = self.map_fit(source, &r.pose).1;
        let fitness = close as f32 / judged.max(1) as f32;
        match r {
            r if r.inliers < icp.min_points || judged < icp.min_points => Err(Miss::Uninformative),
            r if fitness >= lc.min_fitness && r.rms <= lc.max_rms => Ok((r.pose, r.information)),
            r => {
                debug!(
                    "map match refused: fitness {} rms {} ({} points, {} judged, {} reference)",
                    fitness,
                    r.rms,
                    points.len(),
                    judged,
                    n
                );
                Err(Miss::Mismatch)
            }
        }
    }

    /// Gathers the occupied cells of the `near` submaps (nearest first) into the reference
    /// storage as world points, as many as it holds, and arranges them as a k-d tree; how
    /// many. Remembered for the next match unless the storage filled (the points kept then
    /// depend on the order of `near`, not only on `slots`).
    fn gather_reference(
        &mut self,
        near: &[(f64, usize, Se2)],
        slots: heapless::Vec<usize, MAP_SUBMAPS>,
    ) -> usize {
        let per = self.cells_per_submap;
        let mut n = 0;
        for &(_, slot, anchor) in near {
            let (Some(cells), Some(out)) = (
                self.cells.get(slot * per..(slot + 1) * per),
                self.reference.get_mut(n..),
            ) else {
                break;
            };
            if let Ok(grid) = Submap::from_cells(anchor, self.cfg.grid, cells) {
                n += grid.occupied_points(OCCUPIED, NORMAL_RADIUS, out);
            }
        }
        if let Some(points) = self.reference.get_mut(..n) {
            KdTree::build(points);
        }
        let whole = n < self.reference.len();
        if let Some(l) = self.st.localize.as_mut() {
            l.reference = whole.then_some(MapReference { slots, len: n });
        }
        n
    }

    /// How well the scan of `source` at the world pose `world` fits the whole saved map: the
    /// mean over its points of the highest occupancy probability near the point (its cell and
    /// the eight around it) in any submap, 0 where no submap reaches; and how many of its
    /// points land where the map observed anything (hit or seen through) near them.
    pub(super) fn map_fit(&self, source: MatchSource, world: &Se2) -> (f32, u32) {
        let per = self.cells_per_submap;
        let half = self.cfg.grid.side as f64 * self.cfg.grid.resolution as f64 * 0.5;
        let reach = self.cfg.max_range as f64 + half * core::f64::consts::SQRT_2;
        let mut best = [0.0f32; MAX_POINTS];
        let mut seen = [false; MAX_POINTS];
        let scan: &[ScanPoint] = match source {
            MatchSource::Scan => self.scan.as_slice(),
            MatchSource::Far => self.st.far.scan(),
        };
        let n = scan.len().min(MAX_POINTS);
        for (slot, m) in self.submaps.iter().enumerate().filter(|(_, m)| m.in_use) {
            let Some(anchor) = m.anchor_estimate else {
                continue;
            };
            if libm::hypot(anchor.x - world.x, anchor.y - world.y) > reach {
                continue;
            }
            let Some(cells) = self.cells.get(slot * per..(slot + 1) * per) else {
                continue;
            };
            let Ok(grid) = Submap::from_cells(Se2::IDENTITY, self.cfg.grid, cells) else {
                continue;
            };
            let pose = anchor.between(world);
            let (c, s) = (libm::cos(pose.theta) as f32, libm::sin(pose.theta) as f32);
            let (tx, ty) = (pose.x as f32, pose.y as f32);
            for ((q, b), o) in scan.iter().zip(best.iter_mut()).zip(seen.iter_mut()) {
                let p = [tx + c * q.p[0] - s * q.p[1], ty + s * q.p[0] + c * q.p[1]];
                let g = grid.local_to_cell(p);
                let (ix, iy) = (libm::floorf(g[0]) as i32, libm::floorf(g[1]) as i32);
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        if let Some(v) = grid.cell(ix + dx, iy + dy) {
                            *b = b.max(probability(v));
                            *o |= v != 0;
                        }
                    }
                }
            }
        }
        if n == 0 {
            return (0.0, 0);
        }
        let observed = seen.iter().take(n).filter(|&&o| o).count() as u32;
        (best.iter().take(n).sum::<f32>() / n as f32, observed)
    }
}
