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
mod matching;

use super::far::accept::SUPPORT;
use super::loops::MatchSource;
use super::{
    FrameOutput, Mapper, MapperConfig, MapperError, MapperParts, MapperState, Probe, Section,
    PYRAMID_LEVELS,
};
use crate::frontend::far_csm::FarSearch;
use crate::frontend::lidar::FrontendStep;
use crate::frontend::odometry::OdometryFusion;
use crate::frontend::PointMap;
use crate::geom::{Info3, Se2};
use crate::gpe::{GpeFrame, NodeTie};
use matching::MapReference;

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
    pub fn localizing(&self) -> bool {
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
            self.update_local_map(&front.pose, &travel);
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
}
