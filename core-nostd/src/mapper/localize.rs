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

use super::far::accept::SUPPORT;
use super::far::{AMBIGUITY, BASE_LEVEL, DISTINCT_THETA, DISTINCT_XY};
use super::loops::{submap_and_pyramid, MatchSource, Miss};
use super::{
    FrameOutput, Mapper, MapperConfig, MapperError, MapperParts, MapperState, Probe, Section,
    PYRAMID_LEVELS,
};
use crate::frontend::far_csm::{FarCsmConfig, FarMatch, FarSearch, FarStep};
use crate::frontend::grid::probability;
use crate::frontend::icp::MatchError;
use crate::frontend::lidar::{FrontendStep, Travel};
use crate::frontend::odometry::OdometryFusion;
use crate::frontend::scan::{ScanPoint, MAX_POINTS};
use crate::frontend::{align, IcpConfig, KdTree};
use crate::frontend::{PointMap, Submap};
use crate::geom::Se2;
use crate::gpe::{GpeFrame, NodeTie};

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

/// A global search of one keyframe's scan (kept as the far search's scan) over every submap,
/// spread over the keyframes that follow.
#[derive(Clone, Debug)]
struct Sweep {
    /// The keyframe's front-end pose and travel.
    frontend: Se2,
    travel: Travel,
    /// Submap slots searched so far (the next one to search).
    searched: usize,
    /// The refined matches at distinct places, each with its score in the whole map.
    places: heapless::Vec<(Se2, f32), PLACES>,
    /// Where the robot can be, from the prior: the keyframe's pose predicted from it and
    /// how far (metres, radians) it can be from there; `None`: anywhere.
    region: Option<(Se2, f64, f64)>,
}

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
    sweep: Option<Sweep>,
    /// The last fix when tracking was lost: the next global search stays within the
    /// uncertainty since.
    prior: Option<NodeTie>,
    search: FarSearch,
    counters: LocalizeCounters,
}

impl LocalizeState {
    /// Lost, or starting at `initial` when the caller knows where the robot is.
    pub(crate) const fn new(initial: Option<Se2>) -> Self {
        LocalizeState {
            initial,
            fix: None,
            tracking: false,
            support: 0,
            misses: 0,
            sweep: None,
            prior: None,
            search: FarSearch::new(),
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
        mut self,
        config: MapperConfig,
        initial: Option<Se2>,
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
        self.state.localize = Some(LocalizeState::new(initial));
        self.solver.invalidate();
        Mapper::new(config, self)
    }
}

impl Mapper<'_> {
    /// Counters of the localization-only mode; `None` when mapping.
    pub fn localize_counters(&self) -> Option<LocalizeCounters> {
        self.st.localize.as_ref().map(|l| l.counters)
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
            if let Some(fix) = self.relocalize(stamp, front) {
                // Tracking (re)starts here: the pose moves to the map once, then follows it.
                self.st.gpe.restart_at(fix);
                global.pose = fix;
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
    /// fix, else a global search. The fix's pose when tracking starts at this keyframe.
    fn relocalize(&mut self, stamp: i64, front: &FrontendStep) -> Option<Se2> {
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
        if let Ok(p) = matched {
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
        let estimate = match matched {
            Ok(estimate) => estimate,
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
            return None;
        }
        l.support += 1;
        if usize::from(l.support) < SUPPORT {
            return None;
        }
        l.start_tracking(stamp);
        Some(estimate)
    }

    /// ICP of the scan of `source` (robot frame) against the saved map around the world pose
    /// `seed`: the occupied cells of the [`MAP_SUBMAPS`] submaps whose anchors are nearest to
    /// it, as world points (as many as the reference storage holds). A scan sees far beyond
    /// one submap (a home's is 4 m across, its LiDAR reaches 10 m), so it is matched with all
    /// of the map it can see. The world pose when the match is good; else why not.
    ///
    /// A good match has a small residual over enough points, and most of the points the map
    /// can judge (those on cells it observed) lie within two cells of its walls, as the loop
    /// search's fitness asks. A scan that sees more than the map holds (a part of the building
    /// not mapped, a long-range LiDAR beyond the submaps gathered) is not held against it; a
    /// wrong place, where the map saw free space, is.
    fn match_map(&mut self, source: MatchSource, seed: &Se2) -> Result<Se2, Miss> {
        let reach =
            self.cfg.max_range as f64 + self.cfg.grid.side as f64 * self.cfg.grid.resolution as f64;
        // (distance to the anchor, slot, anchor pose), nearest first.
        let mut near = heapless::Vec::<(f64, usize, Se2), MAP_SUBMAPS>::new();
        for (slot, m) in self.submaps.iter().enumerate().filter(|(_, m)| m.in_use) {
            let Some(anchor) = self.keyframe_pose(m.anchor_serial) else {
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
        let per = self.cells_per_submap;
        let mut n = 0;
        for &(_, slot, anchor) in &near {
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
        let tree = KdTree::build(self.reference.get_mut(..n).ok_or(Miss::Uninformative)?);
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
            r if fitness >= lc.min_fitness && r.rms <= lc.max_rms => Ok(r.pose),
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

    /// Continues the global search, up to the keyframe's budget: a search begins with this
    /// keyframe's scan and covers every submap; when it has, the best place, if unique in the
    /// whole map, becomes the hypothesis (tied to the keyframe the search began with).
    fn global_search(&mut self, front: &FrontendStep) {
        let lc = self.cfg.loops;
        let half = self.cfg.grid.side as f64 * self.cfg.grid.resolution as f64 * 0.5;
        let config = FarCsmConfig {
            base_level: BASE_LEVEL.min(lc.pyramid_levels.saturating_sub(2)),
            min_score: lc.min_score,
            ..FarCsmConfig::DEFAULT
        };
        let travel = self.st.frontend.travel();
        let Some(l) = self.st.localize.as_mut() else {
            return;
        };
        let prior = l.prior;
        let mut sweep = match l.sweep.take() {
            Some(s) => s,
            None => {
                self.st.far.keep_scan(self.scan.as_slice());
                let region = prior.map(|p| {
                    let (xy, theta) = self.uncertainty(&travel.since(&p.travel));
                    let centre = p.estimate.compose(&p.frontend.between(&front.pose));
                    (centre, xy, theta)
                });
                Sweep {
                    frontend: front.pose,
                    travel,
                    searched: 0,
                    places: heapless::Vec::new(),
                    region,
                }
            }
        };
        let slots = self.submaps.len();
        let mut spent = 0u64;
        while spent < GLOBAL_BUDGET && sweep.searched < slots {
            let slot = sweep.searched;
            sweep.searched += 1;
            let Some(m) = self.submaps.get(slot).filter(|m| m.in_use).copied() else {
                continue;
            };
            let Some(anchor) = self.keyframe_pose(m.anchor_serial) else {
                continue;
            };
            let reach = half * core::f64::consts::SQRT_2;
            if sweep
                .region
                .is_some_and(|(c, xy, _)| libm::hypot(anchor.x - c.x, anchor.y - c.y) > xy + reach)
            {
                continue;
            }
            let (found, evaluated) = self.search_whole(slot, &anchor, &config, half);
            spent += evaluated.max(1);
            for f in found {
                self.add_global_candidate(&mut sweep, &f);
            }
        }
        let hypothesis = if sweep.searched < slots {
            None
        } else {
            for p in &sweep.places {
                debug!(
                    "global search: place {} {} {} fits the map {}",
                    p.0.x, p.0.y, p.0.theta, p.1
                );
            }
            unique_place(&sweep.places)
        };
        let Some(l) = self.st.localize.as_mut() else {
            return;
        };
        if sweep.searched < slots {
            l.sweep = Some(sweep);
            return;
        }
        // A search within the prior's region that found nothing widens to the whole map.
        l.prior = None;
        let Some(estimate) = hypothesis else {
            return;
        };
        l.fix = Some(NodeTie {
            estimate,
            frontend: sweep.frontend,
            travel: sweep.travel,
        });
        l.support = 0;
        l.misses = 0;
        l.counters.hypotheses += 1;
    }

    /// A coarse match `f` (world frame) of the sweep's scan: refined by ICP against the map
    /// around it and, when it lies where the prior allows, kept among the sweep's places with
    /// its score in the whole map.
    fn add_global_candidate(&mut self, sweep: &mut Sweep, f: &FarMatch) {
        let Ok(world) = self.match_map(MatchSource::Far, &f.pose) else {
            return;
        };
        let outside = sweep.region.is_some_and(|(c, xy, theta)| {
            let d = c.between(&world);
            libm::hypot(d.x, d.y) > xy || libm::fabs(d.theta) > theta
        });
        if outside {
            return;
        }
        let (score, _) = self.map_fit(MatchSource::Far, &world);
        debug!(
            "global candidate {} {} {}: coarse {} fits the map {}",
            world.x, world.y, world.theta, f.score, score
        );
        add_place(&mut sweep.places, world, score);
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
            let Some(anchor) = self.keyframe_pose(m.anchor_serial) else {
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

    /// The far search of the kept scan over the whole submap in `slot`, one search per
    /// quarter turn of heading ([`SECTORS`]: a room that looks alike turned by a quarter or
    /// half turn gives each its own candidate, for the whole map to tell apart), each run to
    /// its end; the matches in the world frame, and the candidates evaluated.
    fn search_whole(
        &mut self,
        slot: usize,
        anchor: &Se2,
        config: &FarCsmConfig,
        half: f64,
    ) -> (heapless::Vec<FarMatch, SECTORS>, u64) {
        let mut found = heapless::Vec::new();
        let Some((submap, pyramid)) = submap_and_pyramid(
            self.cells,
            self.submaps,
            self.pyramid,
            &mut self.st.loops.pyramid_of,
            &self.cfg,
            slot,
        ) else {
            return (found, 0);
        };
        let Some(l) = self.st.localize.as_mut() else {
            return (found, 0);
        };
        l.counters.global_searches += 1;
        // Only the points within half a submap of the robot: with the robot near the submap's
        // middle, where it was when the submap was built, they fall inside it, while the
        // farther ones would land outside and score nothing even at the true pose.
        let r2 = (half * half) as f32;
        self.loop_scan.clear();
        for q in self.st.far.scan() {
            if q.p[0] * q.p[0] + q.p[1] * q.p[1] <= r2 {
                let _ = self.loop_scan.push(*q);
            }
        }
        let reach = self.cfg.submap_length.min(half);
        let sector = core::f64::consts::TAU / SECTORS as f64;
        let config = FarCsmConfig {
            window_theta: 0.5 * sector,
            ..*config
        };
        let mut evaluated = 0;
        for k in 0..SECTORS {
            let seed = Se2::new(0.0, 0.0, k as f64 * sector);
            if l.search
                .start(self.loop_scan.as_slice(), &seed, reach, &config)
                .is_err()
            {
                break;
            }
            let m = loop {
                match l.search.step(&submap, &pyramid, u32::MAX) {
                    Ok(FarStep::Working) => continue,
                    Ok(FarStep::Done(m)) => break m,
                    Err(_) => break None,
                }
            };
            evaluated += l.search.evaluated();
            l.search.cancel();
            if let Some(m) = m {
                let _ = found.push(FarMatch {
                    pose: anchor.compose(&m.pose),
                    ..m
                });
            }
        }
        (found, evaluated)
    }
}

/// Adds a refined match at `world` scoring `score` to the distinct `places` found for one
/// keyframe: one at the same place keeps the higher score; when all are taken, the lowest
/// scoring gives way to a higher one.
fn add_place(places: &mut heapless::Vec<(Se2, f32), PLACES>, world: Se2, score: f32) {
    if let Some(p) = places.iter_mut().find(|p| !distinct(&p.0, &world)) {
        if score > p.1 {
            *p = (world, score);
        }
        return;
    }
    if places.push((world, score)).is_ok() {
        return;
    }
    if let Some(low) = places.iter_mut().min_by(|a, b| a.1.total_cmp(&b.1)) {
        if score > low.1 {
            *low = (world, score);
        }
    }
}

/// The best scoring of `places`, unless a distinct one fits the whole map nearly as well (a
/// room like another, or one whose submap is too small to see what tells them apart).
fn unique_place(places: &[(Se2, f32)]) -> Option<Se2> {
    let &(best, score) = places.iter().max_by(|a, b| a.1.total_cmp(&b.1))?;
    let rival = places
        .iter()
        .filter(|p| distinct(&p.0, &best))
        .map(|p| p.1)
        .fold(0.0f32, f32::max);
    (rival < AMBIGUITY * score).then_some(best)
}

/// Two world poses are distinct places (the far search's thresholds).
fn distinct(a: &Se2, b: &Se2) -> bool {
    let d = a.between(b);
    libm::hypot(d.x, d.y) > DISTINCT_XY || libm::fabs(d.theta) > DISTINCT_THETA
}
