//! The maps a frame node's scan goes into: occupancy-grid submaps (their lifecycle) and the
//! front-end's local point map (its restart and refill).
//!
//! **Submaps.** A submap is opened at a keyframe, its anchor, and its grid lives in the
//! anchor's frame; it receives the keyframes until the robot is farther than `submap_length`
//! from the anchor, then it is finished and becomes a loop-closure candidate. A full submap
//! pool recycles the finished submap whose anchor is nearest to a newer submap's anchor: the
//! one the map loses least by.
//!
//! **Local point map.** The front-end matches against points of the recent keyframes in its
//! own frame. With `local_span` > 0 the map slides (`frontend::pointmap`): before each
//! keyframe goes in, it forgets points beyond `local_radius`, points not seen within
//! `local_span` metres of path, and points no second keyframe confirmed. With `local_span`
//! = 0 it restarts when the robot is farther than `local_reset` from where it last
//! restarted, refilled (with `local_from_submaps`) from the occupied cells of the two newest
//! submaps.

use super::loops::NORMAL_RADIUS;
use super::Mapper;
use crate::frontend::lidar::Travel;
use crate::frontend::pointmap::Slide;
use crate::frontend::Submap;
use crate::geom::Se2;

/// Submaps (the newest) that refill a restarted local point map.
const REFILL_SUBMAPS: usize = 2;

/// Keyframes after its first within which a sliding local map's point must be seen again,
/// or be forgotten: a wall in view is hit by the next keyframe's scan; a sparse return (glass
/// passes most beams) gets three chances; a person walking by has left the voxel.
const LOCAL_CONFIRM: u32 = 3;

/// A submap slot.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SubmapMeta {
    /// The slot holds a submap.
    pub in_use: bool,
    /// Still receiving scans.
    pub active: bool,
    /// Serial of the anchor keyframe (the grid is in its frame).
    pub anchor_serial: u32,
    /// Front-end pose of the anchor.
    pub anchor_frontend: Se2,
    /// Keyframes inserted.
    pub keyframes: u32,
    /// Front-end travel when the submap was opened: the drift relative to the submap grows
    /// from there.
    pub anchor_travel: Travel,
    /// The back-end's estimate of the anchor as the real-time part last saw it (module
    /// `mirror`); `None` when the anchor is not in the graph.
    pub anchor_estimate: Option<Se2>,
}

impl SubmapMeta {
    /// An empty slot.
    pub const EMPTY: SubmapMeta = SubmapMeta {
        in_use: false,
        active: false,
        anchor_serial: 0,
        anchor_frontend: Se2::IDENTITY,
        keyframes: 0,
        anchor_travel: Travel::ZERO,
        anchor_estimate: None,
    };
}

/// Which submap receives scans, which one the loop search's pyramid holds, and where the local
/// point map last restarted.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct SubmapState {
    pub(crate) active: Option<u16>,
    pub(crate) pyramid_of: Option<u16>,
    local_origin: Option<Se2>,
}

impl SubmapState {
    /// No submap, no local map.
    pub(crate) const NONE: SubmapState = SubmapState {
        active: None,
        pyramid_of: None,
        local_origin: None,
    };
}

impl Mapper<'_> {
    /// The submap slot the keyframe `serial` goes into, opening a new one when the robot left
    /// the active one.
    pub(crate) fn submap_for(&mut self, serial: u32, pose: &Se2) -> Option<u16> {
        if let Some(a) = self.st.submaps.active {
            if let Some(m) = self.submaps.get(a as usize) {
                let o = m.anchor_frontend;
                if libm::hypot(pose.x - o.x, pose.y - o.y) <= self.cfg.submap_length {
                    return Some(a);
                }
            }
            if let Some(m) = self.submaps.get_mut(a as usize) {
                m.active = false;
            }
        }
        let slot = match self.submaps.iter().position(|m| !m.in_use) {
            Some(s) => s,
            None => {
                let s = self.recycle_submap()?;
                self.st.stats.submaps_recycled += 1;
                s
            }
        };
        let per = self.cells_per_submap;
        let cells = self.cells.get_mut(slot * per..(slot + 1) * per)?;
        cells.fill(0);
        *self.submaps.get_mut(slot)? = SubmapMeta {
            in_use: true,
            active: true,
            anchor_serial: serial,
            anchor_frontend: *pose,
            keyframes: 0,
            anchor_travel: self.st.frontend.travel(),
            anchor_estimate: None,
        };
        if self.st.submaps.pyramid_of == Some(slot as u16) {
            self.st.submaps.pyramid_of = None;
        }
        self.st.submaps.active = Some(slot as u16);
        self.st.stats.submaps += 1;
        Some(slot as u16)
    }

    /// The finished submap whose anchor is nearest to a newer submap's anchor.
    fn recycle_submap(&mut self) -> Option<usize> {
        let mut best: Option<(usize, f64)> = None;
        for (i, a) in self.submaps.iter().enumerate() {
            if !a.in_use || a.active {
                continue;
            }
            let Some(pa) = a.anchor_estimate else {
                return Some(i);
            };
            for b in self.submaps.iter() {
                if !b.in_use || b.anchor_serial <= a.anchor_serial {
                    continue;
                }
                let Some(pb) = b.anchor_estimate else {
                    continue;
                };
                let d = libm::hypot(pa.x - pb.x, pa.y - pb.y);
                if best.is_none_or(|(_, bd)| d < bd) {
                    best = Some((i, d));
                }
            }
        }
        best.map(|(i, _)| i)
    }

    /// Inserts the current scan, taken at front-end pose `pose`, into the submap in `slot`.
    pub(crate) fn insert_into_submap(&mut self, slot: u16, pose: &Se2) {
        let per = self.cells_per_submap;
        let s = slot as usize;
        let Some(meta) = self.submaps.get_mut(s) else {
            return;
        };
        let local = meta.anchor_frontend.between(pose);
        meta.keyframes += 1;
        let Some(cells) = self.cells.get_mut(s * per..(s + 1) * per) else {
            return;
        };
        if let Ok(mut grid) = Submap::from_cells(Se2::IDENTITY, self.cfg.grid, cells) {
            // The only error is a non-finite pose, which the front-end does not produce.
            let _ = grid.insert_scan(&local, &Se2::IDENTITY, self.scan);
        }
        if self.st.submaps.pyramid_of == Some(slot) {
            self.st.submaps.pyramid_of = None;
        }
    }

    /// Adds the current scan, taken at front-end pose `pose` after `travel`, to the local
    /// point map: a sliding map (`local_span` > 0) first forgets what it no longer holds; a
    /// restarted one restarts (and refills) first when the robot left its area.
    pub(crate) fn update_local_map(&mut self, pose: &Se2, travel: &Travel) {
        let path = travel.path as f32;
        if self.cfg.local_span > 0.0 {
            let slide = Slide {
                radius: self.cfg.local_radius,
                span: self.cfg.local_span as f32,
                confirm: LOCAL_CONFIRM,
            };
            let at = [pose.x as f32, pose.y as f32];
            self.local.forget(at, path, &slide, self.scan.len());
            self.local
                .insert_stamped(pose, self.scan, self.cfg.local_radius, path);
            return;
        }
        let restart = match self.st.submaps.local_origin {
            Some(o) => libm::hypot(pose.x - o.x, pose.y - o.y) > self.cfg.local_reset,
            None => true,
        };
        if restart {
            self.local.clear();
            self.st.submaps.local_origin = Some(*pose);
            // A saved map's submaps lie in another session's front-end frame: localizing,
            // the local map refills from this session's scans only.
            if self.cfg.local_from_submaps && !self.localizing() {
                self.refill_local(pose);
            }
        }
        self.local.insert(pose, self.scan, self.cfg.local_radius);
    }

    /// Refills the cleared local point map with the occupied cells of the newest submaps near
    /// `pose`, oldest first.
    fn refill_local(&mut self, pose: &Se2) {
        let per = self.cells_per_submap;
        let inv = pose.inverse();
        // (anchor serial, slot) of the newest submaps, newest first.
        let mut newest: [Option<(u32, usize)>; REFILL_SUBMAPS] = [None; REFILL_SUBMAPS];
        for (i, m) in self.submaps.iter().enumerate() {
            if !m.in_use {
                continue;
            }
            let entry = Some((m.anchor_serial, i));
            if let Some(k) = newest
                .iter()
                .position(|e| e.is_none_or(|(s, _)| m.anchor_serial > s))
            {
                newest.copy_within(k..REFILL_SUBMAPS - 1, k + 1);
                if let Some(e) = newest.get_mut(k) {
                    *e = entry;
                }
            }
        }
        for (_, slot) in newest.into_iter().flatten().rev() {
            let Some(meta) = self.submaps.get(slot) else {
                continue;
            };
            let origin = inv.compose(&meta.anchor_frontend);
            let Some(cells) = self.cells.get(slot * per..(slot + 1) * per) else {
                continue;
            };
            let Ok(grid) = Submap::from_cells(origin, self.cfg.grid, cells) else {
                continue;
            };
            let n =
                grid.occupied_points(self.cfg.local_min_log_odds, NORMAL_RADIUS, self.reference);
            if let Some(points) = self.reference.get(..n) {
                self.local.insert(pose, points, self.cfg.local_radius);
            }
        }
    }
}
