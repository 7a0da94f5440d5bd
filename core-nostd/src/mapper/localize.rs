//! Localization-only mode: the pose tracked in a saved map with the GPE, adding nothing to it.
//!
//! A map read from a `.cloimap` file (module `mapfile`) is frozen: its graph is not
//! optimized, its submaps take no scans and no frame node is added, so memory stays what
//! loading the map took. The real-time part runs as when mapping (preprocessing, LiDAR
//! front-end, GPE: sections III-B.2 and III-C); what changes is what the GPE is tied to.
//! Mapping ties it to the newest frame node; here the reference is the newest **fix**, a
//! keyframe whose scan matched a saved submap, taken with the matched global pose as its
//! estimate and its own front-end pose and travel ([`NodeTie`]). Eqs. 3-5 then compose the
//! front-end motion since the fix onto the map exactly as they compose it onto a node, and a
//! new fix pulls the pose as far as its uncertainty against the motion's allows, without a
//! jump.
//!
//! **Tracking.** Every keyframe is matched in the saved submaps that contain the pose the last
//! fix and the front-end motion since predict, nearest anchor first, by the windowed search
//! and refinement of the loop closure (module `loops`, with all of its tests). The window is
//! the motion model's uncertainty since the fix, clamped like the loop search's. A keyframe
//! without a match is a miss; [`LOST_MISSES`] misses in a row (the robot was carried away, or
//! the world changed around it), or an uncertainty since the last fix beyond the largest
//! window, and tracking is lost.
//!
//! **Global localization.** Without a fix (no initial pose, or tracking lost) a keyframe's
//! scan is searched in whole submaps over every heading (the far search's branch and bound,
//! module `frontend::far_csm`), submaps in turn, as many as [`GLOBAL_BUDGET`] candidate
//! evaluations allow per keyframe. The best match is a **hypothesis** when no distinct pose
//! scores within the far search's ambiguity ratio of it, in its submap or in another one
//! searched for the same keyframe, when it refines like a windowed match and when it agrees
//! with the submap's free space (the far loop search's tests, module `far`). It becomes the
//! fix only after the next [`SUPPORT`] keyframes matched where it and the front-end motion put
//! them; [`REFUTE`] misses first drop it. Until then the pose is the front-end's dead
//! reckoning from the last one, marked as not localized.

use super::far::accept::{consistent_with_free_space, SUPPORT};
use super::far::{AMBIGUITY, BASE_LEVEL, DISTINCT_THETA, DISTINCT_XY};
use super::loops::{submap_and_pyramid, MatchSource, Miss};
use super::{
    FrameOutput, Mapper, MapperConfig, MapperError, MapperParts, MapperState, Probe, Section,
    PYRAMID_LEVELS,
};
use crate::frontend::far_csm::{FarCsmConfig, FarMatch, FarSearch, FarStep};
use crate::frontend::grid::probability;
use crate::frontend::lidar::FrontendStep;
use crate::frontend::odometry::OdometryFusion;
use crate::frontend::scan::MAX_POINTS;
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
/// Submaps a tracking match is tried in, nearest anchor first.
const TRACK_CANDIDATES: usize = 3;
/// Distinct places a global search keeps for one keyframe.
const PLACES: usize = 4;

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
    /// Submap slot the global search continues with.
    next_slot: usize,
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
            next_slot: 0,
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
        let window = (
            xy.clamp(lc.window_min, lc.window_max),
            theta.clamp(lc.angle_min, lc.angle_max),
        );
        let matched = self.match_saved(&predicted, window);
        let miss = self.st.loops.last_miss;
        let l = self.st.localize.as_mut()?;
        let Some(estimate) = matched else {
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
                l.fix = None;
                l.tracking = false;
                l.counters.lost += 1;
            }
            return None;
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

    /// The global pose of the current scan matched in the saved submaps that contain
    /// `predicted`, nearest anchor first, within `window` (metres, radians). Without a match,
    /// `loops.last_miss` says why: a mismatch when any submap disagreed.
    fn match_saved(&mut self, predicted: &Se2, window: (f64, f64)) -> Option<Se2> {
        let half = self.cfg.grid.side as f64 * self.cfg.grid.resolution as f64 * 0.5;
        // (distance to the anchor, slot, anchor pose), nearest first.
        let mut near = heapless::Vec::<(f64, usize, Se2), TRACK_CANDIDATES>::new();
        for (slot, m) in self.submaps.iter().enumerate().filter(|(_, m)| m.in_use) {
            let Some(anchor) = self.keyframe_pose(m.anchor_serial) else {
                continue;
            };
            let local = anchor.between(predicted);
            if libm::fabs(local.x) > half || libm::fabs(local.y) > half {
                continue;
            }
            let d = libm::hypot(local.x, local.y);
            let at = near.iter().position(|c| c.0 > d).unwrap_or(near.len());
            if at < TRACK_CANDIDATES {
                if near.is_full() {
                    near.pop();
                }
                let _ = near.insert(at, (d, slot, anchor));
            }
        }
        let mut miss = Miss::Uninformative;
        for &(_, slot, anchor) in &near {
            let seed = anchor.between(predicted);
            if let Some((z, _)) =
                self.match_in_submap(slot, MatchSource::Scan, &seed, window.0, window.1)
            {
                return Some(anchor.compose(&z));
            }
            if self.st.loops.last_miss == Miss::Mismatch {
                miss = Miss::Mismatch;
            }
        }
        self.st.loops.last_miss = miss;
        None
    }

    /// Searches the current scan in whole submaps, in turn, up to the keyframe's budget; a
    /// unique, refined match consistent with free space becomes the hypothesis.
    fn global_search(&mut self, front: &FrontendStep) {
        let lc = self.cfg.loops;
        let half = self.cfg.grid.side as f64 * self.cfg.grid.resolution as f64 * 0.5;
        let config = FarCsmConfig {
            base_level: BASE_LEVEL.min(lc.pyramid_levels.saturating_sub(2)),
            min_score: lc.min_score,
            ..FarCsmConfig::DEFAULT
        };
        let slots = self.submaps.len();
        // The refined matches at distinct places, each with its score in the whole map.
        let mut places = heapless::Vec::<(Se2, f32), PLACES>::new();
        let mut spent = 0u64;
        for _ in 0..slots {
            if spent >= GLOBAL_BUDGET {
                break;
            }
            let Some(l) = self.st.localize.as_mut() else {
                return;
            };
            let slot = l.next_slot % slots;
            l.next_slot = (slot + 1) % slots;
            let Some(m) = self.submaps.get(slot).filter(|m| m.in_use).copied() else {
                continue;
            };
            let Some(anchor) = self.keyframe_pose(m.anchor_serial) else {
                continue;
            };
            let (found, evaluated) = self.search_whole(slot, &config, half);
            spent += evaluated.max(1);
            // A place that scores as well elsewhere in its submap is no evidence.
            let Some(f) = found.filter(|f| f.runner_up < AMBIGUITY * f.score) else {
                continue;
            };
            let Some(z) = self.refine_global(slot, &f) else {
                continue;
            };
            let world = anchor.compose(&z);
            let score = self.map_score(&world);
            add_place(&mut places, world, score);
        }
        // The best place, unless a distinct one fits the whole map nearly as well (a room
        // like another, or one whose submap is too small to see what tells them apart).
        let Some(&(estimate, best)) = places.iter().max_by(|a, b| a.1.total_cmp(&b.1)) else {
            return;
        };
        let rival = places
            .iter()
            .filter(|p| distinct(&p.0, &estimate))
            .map(|p| p.1)
            .fold(0.0f32, f32::max);
        if rival >= AMBIGUITY * best {
            return;
        }
        let travel = self.st.frontend.travel();
        if let Some(l) = self.st.localize.as_mut() {
            l.fix = Some(NodeTie {
                estimate,
                frontend: front.pose,
                travel,
            });
            l.support = 0;
            l.misses = 0;
            l.counters.hypotheses += 1;
        }
    }

    /// How well the current scan at the world pose `world` fits the whole saved map: the mean
    /// over its points of the highest occupancy probability near the point (its cell and the
    /// eight around it) in any submap, 0 where no submap reaches.
    fn map_score(&self, world: &Se2) -> f32 {
        let per = self.cells_per_submap;
        let half = self.cfg.grid.side as f64 * self.cfg.grid.resolution as f64 * 0.5;
        let reach = self.cfg.max_range as f64 + half * core::f64::consts::SQRT_2;
        let mut best = [0.0f32; MAX_POINTS];
        let n = self.scan.len().min(MAX_POINTS);
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
            for (q, b) in self.scan.iter().zip(best.iter_mut()) {
                let p = [tx + c * q.p[0] - s * q.p[1], ty + s * q.p[0] + c * q.p[1]];
                let g = grid.local_to_cell(p);
                let (ix, iy) = (libm::floorf(g[0]) as i32, libm::floorf(g[1]) as i32);
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        if let Some(v) = grid.cell(ix + dx, iy + dy) {
                            *b = b.max(probability(v));
                        }
                    }
                }
            }
        }
        if n == 0 {
            return 0.0;
        }
        best.iter().take(n).sum::<f32>() / n as f32
    }

    /// A coarse whole-submap match refined like a windowed one and checked against the
    /// submap's free space; the scan's pose in the submap's frame.
    fn refine_global(&mut self, slot: usize, f: &FarMatch) -> Option<Se2> {
        let (z, _) =
            self.match_in_submap(slot, MatchSource::Scan, &f.pose, f.cell, f.angular_step)?;
        let (inside, conflicting) = self.free_space_conflicts(slot, MatchSource::Scan, &z);
        consistent_with_free_space(inside, conflicting).then_some(z)
    }

    /// The far search of the current scan over the whole submap in `slot` (every heading),
    /// run to its end; the match in the submap's frame, and the candidates evaluated.
    fn search_whole(
        &mut self,
        slot: usize,
        config: &FarCsmConfig,
        half: f64,
    ) -> (Option<FarMatch>, u64) {
        let Some((submap, pyramid)) = submap_and_pyramid(
            self.cells,
            self.submaps,
            self.pyramid,
            &mut self.st.loops.pyramid_of,
            &self.cfg,
            slot,
        ) else {
            return (None, 0);
        };
        let Some(l) = self.st.localize.as_mut() else {
            return (None, 0);
        };
        l.counters.global_searches += 1;
        // Only the points within half a submap of the robot: with the robot near the submap's
        // middle, where it was when the submap was built, they fall inside it, while the
        // farther ones would land outside and score nothing even at the true pose.
        let r2 = (half * half) as f32;
        self.loop_scan.clear();
        for q in self
            .scan
            .iter()
            .filter(|q| q.p[0] * q.p[0] + q.p[1] * q.p[1] <= r2)
        {
            let _ = self.loop_scan.push(*q);
        }
        let reach = self.cfg.submap_length.min(half);
        if l.search
            .start(self.loop_scan.as_slice(), &Se2::IDENTITY, reach, config)
            .is_err()
        {
            return (None, 0);
        }
        let found = loop {
            match l.search.step(&submap, &pyramid, u32::MAX) {
                Ok(FarStep::Working) => continue,
                Ok(FarStep::Done(found)) => break found,
                Err(_) => break None,
            }
        };
        let evaluated = l.search.evaluated();
        l.search.cancel();
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

/// Two world poses are distinct places (the far search's thresholds).
fn distinct(a: &Se2, b: &Se2) -> bool {
    let d = a.between(b);
    libm::hypot(d.x, d.y) > DISTINCT_XY || libm::fabs(d.theta) > DISTINCT_THETA
}
