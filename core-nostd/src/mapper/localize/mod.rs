//! Localization-only mode: the pose tracked in a saved map with the GPE, adding nothing to it.
//!
//! A map read from a `.cloimap` file (module `mapfile`) is frozen: its graph is not
//! optimized, its submaps take no scans and no frame node is added, so memory stays what
//! loading the map took. The real-time part runs as when mapping (preprocessing, LiDAR
//! front-end, GPE: sections III-B.2 and III-C); what changes is what the GPE is tied to.
//! Mapping ties it to the newest frame node; here the reference is the newest **fix**, a
//! keyframe whose scan matched the saved map, taken with the matched global pose as its
//! estimate and its own front-end pose and travel ([`NodeTie`]). Eqs. 3-5 then compose the
//! front-end motion since the fix onto the map exactly as they compose it onto a node, and a
//! new fix pulls the pose as far as its uncertainty against the motion's allows, without a
//! jump.
//!
//! **Tracking.** Every keyframe is matched with the saved map around the pose the last fix and
//! the front-end motion since predict: ICP against the occupied cells of the submaps nearest
//! to it, in the world frame. A scan sees beyond one submap (a home's is 4 m across, its
//! LiDAR reaches 10 m), so it is matched with all of the map it can see; the ICP refuses a
//! match that fixes only some directions (a corridor), that fits badly, or that lands
//! farther from the prediction than the motion model's uncertainty since the fix (clamped
//! like the loop search's window). A scan that cannot tell (too little map, or a corridor)
//! is no evidence either way; one that disagrees is a miss. [`LOST_MISSES`] misses in a row
//! (the robot was carried away, or the world changed around it), or an uncertainty since
//! the last fix beyond the largest window, and tracking is lost.
//!
//! **Global localization.** Without a fix (no initial pose, or tracking lost) a keyframe's
//! scan is kept and searched in every submap, over the keyframes that follow as far as
//! [`GLOBAL_BUDGET`] candidate evaluations a keyframe allow: the far search's branch and
//! bound (module `frontend::far_csm`) over the whole submap, once per quarter turn of heading
//! ([`SECTORS`]). Each coarse match is refined by the ICP against the map and scored against
//! the whole map (how many of the scan's points, near and far, land on walls of any
//! submap). When every submap has been searched, the best place is the **hypothesis** if no
//! distinct place (1 m or 0.3 rad away) scores within the far search's ambiguity ratio of it:
//! a room that looks like another one from where the robot stands gives no fix yet. After
//! tracking was lost, the first search keeps to the uncertainty around the dead-reckoned pose
//! (a LiDAR outage, a slip: the robot is still there), the next ones to the whole map (it
//! was carried away). A hypothesis becomes the fix only once the next [`SUPPORT`]
//! keyframes matched where it and the front-end motion put them; [`REFUTE`] misses first
//! drop it. Until then the pose is the front-end's dead reckoning from the last one, marked
//! as not localized.

mod global;
mod join;

use super::far::accept::SUPPORT;
use super::loops::MatchSource;
use super::{
    FrameOutput, Mapper, MapperConfig, MapperError, MapperParts, MapperState, Probe, Section,
    PYRAMID_LEVELS,
};
use crate::frontend::far_csm::FarSearch;
use crate::frontend::grid::probability;
use crate::frontend::icp::MatchError;
use crate::frontend::lidar::FrontendStep;
use crate::frontend::odometry::OdometryFusion;
use crate::frontend::scan::{ScanPoint, MAX_POINTS};
use crate::frontend::{align, IcpConfig, KdTree};
use crate::frontend::{PointMap, Submap};
use crate::geom::{Info3, Se2};
use crate::gpe::{GpeFrame, NodeTie};

/// Why a match with the map failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Miss {
    /// The scan holds too little of the map, or too little structure, to tell.
    Uninformative,
    /// No pose fits, or the best one fits badly.
    Mismatch,
}

/// Keyframes in a row without a match after which tracking is lost.
pub const LOST_MISSES: u8 = 5;
/// Keyframes without a match after which a hypothesis is dropped.
pub const REFUTE: u8 = 2;
/// Candidate evaluations of the global search per keyframe (whole submaps are searched; the
/// last one started may overrun it).
pub const GLOBAL_BUDGET: u64 = 400_000;
/// Submaps whose occupied cells a scan is matched with, nearest anchor first.
const MAP_SUBMAPS: usize = 16;
/// Occupied cells for the match with the map: log-odds units at least this (probability ~0.73).
const OCCUPIED: i8 = 10;
/// Radius, in cells, of the normal fit of the map's points.
const NORMAL_RADIUS: u8 = 2;
/// Distinct places a global search keeps for one keyframe.
const PLACES: usize = 8;
/// Heading sectors each submap is searched in by the global search.
pub const SECTORS: usize = 4;

/// What localization has done so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LocalizeCounters {
    /// Keyframes (scans that moved or turned enough to be matched).
    pub keyframes: u32,
    /// Keyframes matched in the saved map while tracking or verifying a hypothesis.
    pub matches: u32,
    /// Keyframes whose scan disagreed with the map while tracking or verifying.
    pub misses: u32,
    /// Keyframes whose scan could not tell (too little of it in the map, or a corridor).
    pub uninformative: u32,
    /// Submaps searched whole by the global localization.
    pub global_searches: u32,
    /// Global matches taken as hypotheses.
    pub hypotheses: u32,
    /// Hypotheses dropped before enough keyframes supported them.
    pub refuted: u32,
    /// Times tracking started: from the initial pose or a confirmed hypothesis.
    pub fixes: u32,
    /// Times tracking was lost.
    pub lost: u32,
    /// Stamp of the frame where tracking first started, ns.
    pub first_fix_stamp: Option<i64>,
}

/// The localization's memory between frames.
#[derive(Clone, Debug)]
pub(crate) struct LocalizeState {
    /// Pose given by the caller for the first frame, not yet used.
    initial: Option<Se2>,
    /// The newest fix, or the hypothesis being verified.
    fix: Option<NodeTie>,
    /// `fix` is confirmed: the pose is tracked.
    tracking: bool,
    /// Keyframes that supported the hypothesis.
    support: u8,
    /// Keyframes in a row without a match.
    misses: u8,
    /// The global search under way.
    sweep: Option<global::Sweep>,
    /// The last fix when tracking was lost: the next global search stays within the
    /// uncertainty since.
    prior: Option<NodeTie>,
    search: FarSearch,
    /// What the reference storage holds, arranged as a k-d tree: the world points of these
    /// submaps.
    reference: Option<MapReference>,
    counters: LocalizeCounters,
    /// Multi-session mapping: the first fix joins this session to the map, and from there
    /// on the mapper maps (module `join`).
    then_map: bool,
    /// The session has joined the map: the mapper maps, this state keeps only its counters.
    joined: bool,
}

/// The map points a match was made with, kept for the next: a keyframe near the last one sees
/// the same submaps, and gathering their points (with normals) and arranging them cost more
/// than the match itself.
#[derive(Clone, Debug)]
struct MapReference {
    /// Submap slots, ascending.
    slots: heapless::Vec<usize, MAP_SUBMAPS>,
    /// Points held.
    len: usize,
}

impl LocalizeState {
    /// Lost, or starting at `initial` when the caller knows where the robot is.
    pub(crate) const fn new(initial: Option<Se2>, then_map: bool) -> Self {
        LocalizeState {
            then_map,
            joined: false,
            initial,
            fix: None,
            tracking: false,
            support: 0,
            misses: 0,
            sweep: None,
            prior: None,
            search: FarSearch::new(),
            reference: None,
            counters: LocalizeCounters {
                keyframes: 0,
                matches: 0,
                misses: 0,
                uninformative: 0,
                global_searches: 0,
                hypotheses: 0,
                refuted: 0,
                fixes: 0,
                lost: 0,
                first_fix_stamp: None,
            },
        }
    }

    fn start_tracking(&mut self, stamp: i64) {
        self.tracking = true;
        self.misses = 0;
        self.counters.fixes += 1;
        self.counters.first_fix_stamp.get_or_insert(stamp);
    }
}

impl<'r> MapperParts<'r> {
    /// Starts localizing in the map these parts hold (read with
    /// [`MapReader::read_into_parts`](super::mapfile::MapReader::read_into_parts)), from
    /// `initial` when the caller knows the robot's pose in the map, else by global
    /// localization. The map stays as it is; the local map, scan, odometry history and small
    /// state start empty.
    ///
    /// # Errors
    /// As [`MapperParts::start`].
    pub fn localize(
        self,
        config: MapperConfig,
        initial: Option<Se2>,
    ) -> Result<Mapper<'r>, MapperError> {
        self.start_in_map(config, initial, false)
    }

    /// Starts a mapper on the map these parts hold, localizing until the first fix, mapping
    /// from there (see [`MapperParts::extend`] and [`MapperParts::localize`]).
    fn start_in_map(
        mut self,
        config: MapperConfig,
        initial: Option<Se2>,
        then_map: bool,
    ) -> Result<Mapper<'r>, MapperError> {
        if self.pyramid.len() != PYRAMID_LEVELS * config.grid.cells() {
            return Err(MapperError::Storage(
                "submap grid size differs from the storage's",
            ));
        }
        if initial.is_some_and(|p| !p.is_finite()) {
            return Err(MapperError::Config("the initial pose is not finite"));
        }
        // A map saved while a submap was open: it is one of the map's submaps now.
        self.submaps.iter_mut().for_each(|m| m.active = false);
        *self.local = PointMap::new(config.local_voxel);
        self.scan.clear();
        *self.odometry = OdometryFusion::new(config.odometry);
        *self.state = MapperState::new(config.keyframe);
        self.state.rt.localize = Some(LocalizeState::new(initial, then_map));
        if then_map {
            // The session's frame nodes continue the map's serials (the graph keeps its
            // nodes in serial order).
            let newest = self.graph.node_count().checked_sub(1);
            let next = newest
                .and_then(|i| self.meta.get(i))
                .map_or(0, |m| m.serial + 1);
            self.state.rt.frames.start_session(next);
        }
        self.solver.invalidate();
        Mapper::new(config, self)
    }
}

impl Mapper<'_> {
    /// Counters of the localization-only mode, or of the localization a session extending a
    /// saved map started with; `None` for a new map.
    pub fn localize_counters(&self) -> Option<LocalizeCounters> {
        self.st.localize.as_ref().map(|l| l.counters)
    }

    /// Whether the mapper is localizing in a saved map (adding nothing to it): in
    /// localization-only mode, or in a session extending a map before its first fix.
    pub(crate) fn localizing(&self) -> bool {
        self.st.localize.as_ref().is_some_and(|l| !l.joined)
    }

    /// The per-frame step in localization-only mode, after the front-end: the GPE tied to the
    /// newest fix, then for a keyframe the local map and the match in the saved map.
    pub(crate) fn localize_frame(
        &mut self,
        stamp: i64,
        front: &FrontendStep,
        deadline_passed: bool,
        probe: &mut impl Probe,
    ) -> FrameOutput {
        probe.enter(Section::Gpe);
        let travel = self.st.frontend.travel();
        let mut reference = None;
        if let Some(l) = self.st.localize.as_mut() {
            if let Some(initial) = l.initial.take() {
                l.fix = Some(NodeTie {
                    estimate: initial,
                    frontend: front.pose,
                    travel,
                });
                l.start_tracking(stamp);
                self.st.gpe.restart_at(initial);
            }
            reference = l.fix.filter(|_| l.tracking);
        }
        let frame = GpeFrame {
            step: front.step,
            frontend: front.pose,
            travel,
            reference,
            anchor: None,
            deadline_passed,
        };
        let mut global = self.st.gpe.update(&frame, &self.cfg.gpe, &self.cfg.noise);

        probe.enter(Section::Keyframe);
        let keyframe = self.st.frames.offer(&front.pose);
        if keyframe {
            self.update_local_map(&front.pose);
            probe.enter(Section::LoopSearch);
            if let Some((fix, information)) = self.relocalize(stamp, front) {
                // Tracking (re)starts here: the pose moves to the map once, then follows it.
                self.st.gpe.restart_at(fix);
                global.pose = fix;
                if self.st.localize.as_ref().is_some_and(|l| l.then_map) {
                    self.join_map(stamp, &front.pose, &fix, &information);
                }
            }
        }
        let localized = self.st.localize.as_ref().is_some_and(|l| l.tracking);
        FrameOutput {
            stamp,
            pose: global.pose,
            frontend: front.pose,
            reference_serial: self.st.frames.newest_serial(),
            keyframe,
            predicted: global.predicted,
            loops: 0,
            localized,
        }
    }

    /// Matches the keyframe just taken in the saved map: tracking or verifying against the
    /// fix, else a global search. The fix's pose, and the information of its match (world
    /// axes), when tracking starts at this keyframe (or, for a session extending the map,
    /// when a keyframe tracked from the initial pose matched).
    fn relocalize(&mut self, stamp: i64, front: &FrontendStep) -> Option<(Se2, Info3)> {
        let travel = self.st.frontend.travel();
        let l = self.st.localize.as_mut()?;
        l.counters.keyframes += 1;
        let Some(fix) = l.fix else {
            self.global_search(front);
            return None;
        };
        let tracking = l.tracking;
        let lc = self.cfg.loops;
        let (xy, theta) = self.uncertainty(&travel.since(&fix.travel));
        let predicted = fix.estimate.compose(&fix.frontend.between(&front.pose));
        let beyond = xy > lc.window_max || theta > lc.angle_max;
        // A match farther from the prediction than its uncertainty (at least the loop search's
        // smallest window) allows is not believed. Unlike the loop search's window this is
        // not clamped above: after a LiDAR outage the dead reckoning may be a metre off, and
        // the ICP, seeded there, only finds the map nearby.
        let window = (xy.max(lc.window_min), theta.max(lc.angle_min));
        let matched = self.match_map(MatchSource::Scan, &predicted);
        let l = self.st.localize.as_mut()?;
        // Tracking, a good match outside the window says the prediction is off more than the
        // motion model allows (a wheel slip, a gyro drifting through a LiDAR outage): it is
        // not believed at once, but proposed like a global match, for the next keyframes to
        // confirm.
        if let Ok((p, _)) = matched {
            let d = predicted.between(&p);
            if libm::hypot(d.x, d.y) > window.0 || libm::fabs(d.theta) > window.1 {
                debug!(
                    "map match {} m, {} rad from the prediction",
                    libm::hypot(d.x, d.y),
                    d.theta
                );
                l.counters.misses += 1;
                if tracking {
                    l.tracking = false;
                    l.counters.lost += 1;
                }
                l.fix = Some(NodeTie {
                    estimate: p,
                    frontend: front.pose,
                    travel,
                });
                l.support = 0;
                l.misses = 0;
                l.counters.hypotheses += 1;
                return None;
            }
        }
        let (estimate, information) = match matched {
            Ok(m) => m,
            Err(miss) => {
                // A scan that cannot tell is no evidence against the fix: only the growing
                // uncertainty then ends tracking.
                if miss == Miss::Uninformative && !beyond {
                    l.counters.uninformative += 1;
                    return None;
                }
                l.counters.misses += 1;
                l.misses = l.misses.saturating_add(1);
                if !tracking && (l.misses >= REFUTE || beyond) {
                    l.fix = None;
                    l.counters.refuted += 1;
                } else if tracking && (l.misses >= LOST_MISSES || beyond) {
                    debug!("localization lost after {} misses", l.misses);
                    // The robot is most likely still within the uncertainty around the
                    // dead-reckoned pose (a LiDAR outage, a slip): the search looks there
                    // first, and widens to the whole map when that finds nothing (a robot
                    // carried away).
                    l.prior = Some(fix);
                    l.fix = None;
                    l.tracking = false;
                    l.counters.lost += 1;
                }
                return None;
            }
        };
        l.counters.matches += 1;
        l.misses = 0;
        l.fix = Some(NodeTie {
            estimate,
            frontend: front.pose,
            travel,
        });
        if tracking {
            // Tracking from a given pose: a session extending the map joins it at the first
            // keyframe that matched.
            return l.then_map.then_some((estimate, information));
        }
        l.support += 1;
        if usize::from(l.support) < SUPPORT {
            return None;
        }
        l.start_tracking(stamp);
        Some((estimate, information))
    }

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
    fn match_map(&mut self, source: MatchSource, seed: &Se2) -> Result<(Se2, Info3), Miss> {
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
    fn map_fit(&self, source: MatchSource, world: &Se2) -> (f32, u32) {
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
