//! Far loop search: loop closures beyond the windowed search of module `loops` (the paper's
//! loop constraints, section III-B.2, where the drift is too large for a local window),
//! proposed by a search over the whole submap and every heading the drift allows, and
//! accepted only when the match is unique and the following keyframes confirm it.
//!
//! **Where.** The windowed search looks for a revisit within a few standard deviations of the
//! front-end drift, clamped to `window_max` and `angle_max`. For a finished submap whose
//! uncertainty relative to the keyframe (the motion model over the front-end travel since the
//! submap's anchor, unclamped) outgrows that clamp, the true revisit may lie outside every
//! window: a long loop, a hall wider than the LiDAR's range, a heading lost without a gyro.
//! Such submaps within that uncertainty (plus a submap's half-diagonal) are searched with one
//! keyframe's scan (subsampled and kept here), nearest first, [`PER_KEYFRAME`] per keyframe,
//! the next keyframes continuing outwards.
//!
//! **How much work.** Each submap is searched by [`FarSearch`] (branch and bound at a coarse
//! level of the pyramid over the submap and the headings within the uncertainty, as
//! Cartographer's global constraint search does), then refined like a windowed match. The
//! search runs in the back-end's turn, at most [`STEP_BUDGET`] candidate evaluations per
//! back-end step, so it never delays a frame. It takes every turn the optimizer leaves idle
//! and, while both have work, every other turn: over a known map loops close at nearly every
//! keyframe and the optimizer is never idle, yet that is where a robot whose pose jumped (a
//! sensor outage, a wheel slip) must find its place again. Building a submap's search pyramid
//! and refining a found match (the tests of module `accept`) each take a back-end turn of
//! their own.
//!
//! **Accepting a far match.** A far match is a hypothesis, not yet a constraint: an aliased
//! place (a repeated office, a plain corridor, a new room like an old one) can match as well
//! as the true one, and one wrong edge across a large drift bends the whole map. Four tests,
//! each against a different way of being wrong:
//! 1. *Unique in its submap*: no pose distinct from it (1 m, 0.3 rad) scores
//!    [`AMBIGUITY`] of its score (a corridor or a symmetric room fails).
//! 2. *Consistent with the map's free space*: at most `accept::MAX_CONFLICT` of its points
//!    land where the submap saw only free space (a look-alike place puts walls where the map
//!    sees through).
//! 3. *Unique among the submaps*: every candidate submap is searched again for the same
//!    keyframe, with the threshold raised to [`AMBIGUITY`] of its score; a match at a distinct
//!    place in the world drops it (a repeated office in another submap).
//! 4. *Confirmed by the following keyframes*: each is matched, by the windowed search seeded
//!    where the hypothesis and the front-end motion since put it, in up to
//!    `accept::VERIFY_SUBMAPS` submaps around that place; a match there supports it (the pair
//!    is consistent around the cycle, as in pairwise consistency maximisation).
//!    `accept::SUPPORT` supporting keyframes spread over a submap length of travel and two
//!    submaps confirm it; `accept::REFUTE` keyframes whose scans do not fit there (a
//!    corridor's sliding match is no evidence either way), or
//!    `accept::VERIFY_SUBMAP_LENGTHS` submap lengths of travel, drop it.
//!
//! Tests 1, 2 and 4 and the acceptance are in module `accept`; this module plans and runs the
//! searches, the sweep of test 3 included.
//!
//! A confirmed hypothesis' matches join the graph as loop edges without the max-mixture null
//! hypothesis: their residual at the drifted estimate is large by construction, and the null
//! component would switch a true correction off.

pub(in crate::mapper) mod accept;

use super::loops::submap_and_pyramid;
use super::Mapper;
use crate::frontend::far_csm::{FarCsmConfig, FarMatch, FarSearch, FarStep, FAR_POINTS};
use crate::frontend::lidar::Travel;
use crate::frontend::scan::ScanPoint;
use crate::geom::{Info3, Se2};
use accept::SUPPORT_EDGES;

/// Submaps searched for one keyframe before the next keyframe takes over.
pub const PER_KEYFRAME: usize = 8;
/// Candidate evaluations of the far search per back-end step (1,300 to 5,700 Cortex-A9
/// instructions each with the scan's 160 points, as measured on intel.clf).
pub const STEP_BUDGET: u32 = 1100;
/// Pyramid level the far search scores at (4 cells per step at level 2).
pub(in crate::mapper) const BASE_LEVEL: u8 = 2;
/// A far match is ambiguous, and not taken, when a pose distinct from it (1 m or 0.3 rad away)
/// scores at least this share of its score.
pub(in crate::mapper) const AMBIGUITY: f32 = 0.9;
/// Two matches are distinct places when their poses in the world differ by more than this,
/// metres ...
pub(in crate::mapper) const DISTINCT_XY: f64 = 1.0;
/// ... or radians.
pub(in crate::mapper) const DISTINCT_THETA: f64 = 0.3;
/// A refined match of a keyframe in a submap.
#[derive(Clone, Copy, Debug, PartialEq)]
struct FarMatchEdge {
    /// Keyframe serial.
    serial: u32,
    /// Anchor serial of the submap (the edge's other node).
    anchor: u32,
    /// Pose of the keyframe in the anchor's frame.
    z: Se2,
    info: Info3,
}

/// A submap to search, with the keyframe's uncertainty relative to it.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Queued {
    distance: f64,
    slot: u16,
    anchor: u32,
    radius: f64,
    angle: f64,
}

/// A far match waiting for the following keyframes to confirm it.
#[derive(Clone, Debug)]
struct Hypothesis {
    first: FarMatchEdge,
    /// Front-end travel and pose at the matched keyframe.
    travel: Travel,
    frontend: Se2,
    support: heapless::Vec<FarMatchEdge, SUPPORT_EDGES>,
    /// The matched keyframe's pose in the world under the hypothesis.
    world: Se2,
    /// Coarse score of the far match.
    score: f32,
    /// Every candidate submap was searched again without a distinct place scoring as well.
    swept: bool,
    /// The sweep's last band is queued.
    last_band: bool,
    /// Distinct keyframes among the support.
    supporting: usize,
    /// Keyframes whose scans spoke against it.
    unsupported: u8,
}

/// The far search's memory between keyframes and back-end steps.
#[derive(Clone, Debug)]
pub(crate) struct FarState {
    search: FarSearch,
    /// The searched keyframe's scan, subsampled.
    scan: heapless::Vec<ScanPoint, FAR_POINTS>,
    /// Its serial and graph pose when the search was planned.
    serial: u32,
    pose: Se2,
    /// Submaps still to search for it, nearest last.
    queue: heapless::Vec<Queued, PER_KEYFRAME>,
    /// The submap being searched (slot, anchor serial).
    current: Option<(u16, u32)>,
    /// Its front-end pose and travel.
    frontend: Se2,
    travel: Travel,
    /// The keyframe is kept and its search is still to plan.
    planned: bool,
    /// Distance from the keyframe up to which the previous keyframes' searches covered the
    /// candidates, metres (negative: none).
    reached: f64,
    hypothesis: Option<Hypothesis>,
    /// A far match found in the last turn, refined and tested in the next (slot, anchor).
    found: Option<(u16, u32, FarMatch)>,
    /// The last turn built a search pyramid and searched nothing.
    built: bool,
    /// The optimizer took the last back-end turn while this search had work.
    waited: bool,
}

impl FarState {
    pub(crate) const fn new() -> Self {
        FarState {
            search: FarSearch::new(),
            scan: heapless::Vec::new(),
            serial: 0,
            pose: Se2::IDENTITY,
            frontend: Se2::IDENTITY,
            travel: Travel::ZERO,
            planned: false,
            queue: heapless::Vec::new(),
            current: None,
            reached: -1.0,
            hypothesis: None,
            found: None,
            built: false,
            waited: false,
        }
    }

    /// The anchor of the pending hypothesis' first match, whose estimate the real-time part
    /// keeps (module `mirror`).
    pub(crate) fn pinned_serial(&self) -> Option<u32> {
        self.hypothesis.as_ref().map(|h| h.first.anchor)
    }

    /// The kept keyframe scan.
    pub(crate) fn scan(&self) -> &[ScanPoint] {
        &self.scan
    }

    /// Keeps `points` (evenly subsampled) as the scan matched with
    /// [`MatchSource::Far`](super::loops::MatchSource::Far): the far loop search's keyframe, or
    /// the localization's global search (the far loop search does not run while localizing).
    pub(in crate::mapper) fn keep_scan(&mut self, points: &[ScanPoint]) {
        self.scan.clear();
        let stride = points.len().div_ceil(FAR_POINTS).max(1);
        for q in points.iter().step_by(stride) {
            let _ = self.scan.push(*q);
        }
    }

    /// No search planned or running.
    fn idle(&self) -> bool {
        self.current.is_none() && self.queue.is_empty() && self.found.is_none()
    }

    /// Nothing kept, planned or running.
    fn free(&self) -> bool {
        self.idle() && !self.planned
    }

    /// Whether the next back-end turn is the far search's although the optimizer has work:
    /// the two share the back-end turn about turn while both have work (see
    /// [`Mapper::step_backend`](crate::mapper::Mapper::step_backend)). Records that the
    /// optimizer takes this turn otherwise.
    pub(crate) fn takes_turn(&mut self) -> bool {
        let has_work = !self.free() || self.hypothesis.as_ref().is_some_and(|h| !h.swept);
        let turn = has_work && self.waited;
        self.waited = has_work && !turn;
        turn
    }
}

impl Mapper<'_> {
    /// After keyframe `serial` was made: tests a pending hypothesis with it, or keeps its scan
    /// for a far search, which is planned and run in the back-end's turn.
    pub(crate) fn far_keyframe(&mut self, serial: u32) {
        if !self.cfg.loops.far_search {
            return;
        }
        if self.st.far.hypothesis.is_some() {
            self.verify_far(serial);
            return;
        }
        if !self.st.far.free() {
            return;
        }
        let Some(newest) = self.newest_if(serial) else {
            return;
        };
        let far = &mut self.st.far;
        far.keep_scan(self.scan.as_slice());
        far.serial = serial;
        far.pose = newest.tie.estimate;
        far.frontend = newest.tie.frontend;
        far.travel = newest.tie.travel;
        far.planned = true;
    }

    /// The uncertainty of the kept keyframe relative to the submap `m` (`sigmas` standard
    /// deviations of the front-end motion since its anchor, unclamped): position radius and
    /// heading half-width, at least the windowed search's; and whether either exceeds what the
    /// windowed search covers.
    fn far_window(&self, m: &super::SubmapMeta) -> (f64, f64, bool) {
        let lc = &self.cfg.loops;
        let (radius, angle) = self.uncertainty(&self.st.far.travel.since(&m.anchor_travel));
        let due = radius > lc.window_max || angle > lc.angle_max;
        (radius.max(lc.window_max), angle.max(lc.angle_max), due)
    }

    /// Queues the submaps the kept keyframe is searched in: the finished ones within its
    /// uncertainty relative to them (plus a submap's half-diagonal) and, unless a hypothesis
    /// is being swept for alternatives, only those where that uncertainty exceeds the
    /// windowed search's; the nearest beyond the distance the previous searches reached
    /// (starting again from the nearest when they have passed them all).
    fn plan_far(&mut self) {
        let sweeping = self.st.far.hypothesis.is_some();
        self.st.far.planned = false;
        let lc = self.cfg.loops;
        let (serial, gk) = (self.st.far.serial, self.st.far.pose);
        let half = self.cfg.grid.side as f64 * self.cfg.grid.resolution as f64 * 0.5;
        let beyond = self.st.far.reached;
        let mut taken = heapless::Vec::<Queued, PER_KEYFRAME>::new();
        for (i, m) in self.submaps.iter().enumerate() {
            if !m.in_use || m.active || m.anchor_serial + lc.min_keyframe_gap > serial {
                continue;
            }
            let (radius, angle, due) = self.far_window(m);
            let Some(ga) = m.anchor_estimate.filter(|_| due || sweeping) else {
                continue;
            };
            let d = libm::hypot(ga.x - gk.x, ga.y - gk.y);
            if d > radius + half * core::f64::consts::SQRT_2 || d <= beyond {
                continue;
            }
            let q = Queued {
                distance: d,
                slot: i as u16,
                anchor: m.anchor_serial,
                radius,
                angle,
            };
            if !taken.is_full() {
                let _ = taken.push(q);
            } else if let Some(far) =
                (0..taken.len()).max_by(|&a, &b| taken[a].distance.total_cmp(&taken[b].distance))
            {
                if taken[far].distance > d {
                    taken[far] = q;
                }
            }
        }
        self.st.far.reached = if taken.is_full() {
            taken.iter().map(|q| q.distance).fold(beyond, f64::max)
        } else {
            -1.0
        };
        if !taken.is_empty() {
            debug!(
                "far search of keyframe {}: {} submaps beyond {} m",
                serial,
                taken.len(),
                beyond
            );
        }
        // Nearest last: the queue is popped from the end.
        crate::sort::sort_by(&mut taken, |a, b| b.distance.total_cmp(&a.distance));
        self.st.far.queue = taken;
    }

    /// One back-end step of the far search; whether it did any work.
    pub(crate) fn step_far(&mut self) -> bool {
        if let Some((slot, anchor, m)) = self.st.far.found.take() {
            // The submap may have been recycled meanwhile.
            let valid = self
                .submaps
                .get(slot as usize)
                .is_some_and(|s| s.in_use && !s.active && s.anchor_serial == anchor);
            if valid {
                self.propose(slot as usize, anchor, &m);
            }
            return true;
        }
        let sweeping = match &self.st.far.hypothesis {
            Some(h) if h.swept => return false,
            Some(_) => true,
            None => false,
        };
        if !self.cfg.loops.far_search {
            return false;
        }
        if self.st.far.planned && self.st.far.idle() {
            self.plan_far();
            if sweeping {
                if self.st.far.reached < 0.0 {
                    // The last band: the sweep ends with it.
                    if let Some(h) = self.st.far.hypothesis.as_mut() {
                        h.last_band = true;
                    }
                } else {
                    self.st.far.planned = true;
                }
                if self.st.far.queue.is_empty() {
                    self.end_band();
                }
                return true;
            }
            // Planning alone, with nothing to search, is not work worth a back-end turn.
            return !self.st.far.queue.is_empty();
        }
        let Some((slot, anchor)) = self.far_current() else {
            // A sweep whose last submaps were gone (recycled) ends here.
            if sweeping && !self.st.far.planned {
                self.end_band();
            }
            return false;
        };
        let build = self.st.loops.pyramid_of != Some((slot, anchor));
        let Some((submap, pyramid)) = submap_and_pyramid(
            self.cells,
            self.submaps,
            self.pyramid,
            &mut self.st.loops.pyramid_of,
            &self.cfg,
            slot as usize,
        ) else {
            self.st.far.current = None;
            return true;
        };
        // A pyramid built in this turn is searched in the next, unless it had to be built
        // again (the windowed loop search shares its storage): then a quarter turn's search
        // follows the build.
        if build && !self.st.far.built {
            self.st.far.built = true;
            return true;
        }
        self.st.far.built = false;
        let budget = if build { STEP_BUDGET / 4 } else { STEP_BUDGET };
        let step = self.st.far.search.step(&submap, &pyramid, budget);
        let found = match step {
            Ok(FarStep::Working) => return true,
            Ok(FarStep::Done(found)) => found,
            Err(_) => None,
        };
        self.st.far.current = None;
        self.st.far.search.cancel();
        if sweeping {
            self.sweep_match(anchor, found.as_ref());
            if self.st.far.queue.is_empty() && !self.st.far.planned {
                self.end_band();
            }
            return true;
        }
        self.st.far.found = found.map(|m| (slot, anchor, m));
        true
    }

    /// A search of the sweep finished in the submap anchored at `anchor`: a match above the
    /// sweep's threshold at a place distinct from the hypothesis' makes it ambiguous.
    fn sweep_match(&mut self, anchor: u32, found: Option<&FarMatch>) {
        let (Some(m), Some(ga)) = (found, self.mirrored_pose(anchor)) else {
            return;
        };
        let Some(h) = self.st.far.hypothesis.as_ref() else {
            return;
        };
        let d = h.world.between(&ga.compose(&m.pose));
        if libm::hypot(d.x, d.y) > DISTINCT_XY || libm::fabs(d.theta) > DISTINCT_THETA {
            debug!(
                "far hypothesis of keyframe {} ambiguous: submap {} scores {} (hypothesis {})",
                h.first.serial, anchor, m.score, h.score
            );
            self.drop_hypothesis();
        }
    }

    /// The searches of one band of the sweep are done; after the last band the hypothesis is
    /// unique within its uncertainty.
    fn end_band(&mut self) {
        if let Some(h) = self.st.far.hypothesis.as_mut() {
            debug!(
                "far sweep of keyframe {}: band done (last {})",
                h.first.serial, h.last_band
            );
            if h.last_band {
                h.swept = true;
                self.st.far.planned = false;
            }
        }
    }

    /// Forgets the hypothesis and the search state (counted as refuted).
    fn drop_hypothesis(&mut self) {
        let far = &mut self.st.far;
        far.hypothesis = None;
        self.st.mirror.pinned = None;
        far.queue.clear();
        far.current = None;
        far.search.cancel();
        far.planned = false;
        far.reached = -1.0;
        far.found = None;
        self.st.stats.far_refuted += 1;
    }

    /// The submap being searched, starting the search of the next queued one when needed.
    fn far_current(&mut self) -> Option<(u16, u32)> {
        if let Some(c) = self.st.far.current {
            return Some(c);
        }
        let lc = self.cfg.loops;
        while let Some(Queued {
            slot,
            anchor,
            radius,
            angle,
            ..
        }) = self.st.far.queue.pop()
        {
            let Some(ga) = self
                .submaps
                .get(slot as usize)
                .filter(|m| m.in_use && !m.active && m.anchor_serial == anchor)
                .and_then(|m| m.anchor_estimate)
            else {
                continue;
            };
            // Over the part of the submap within the uncertainty (all of it when that is wider)
            // and the headings within it, nearest to the estimated heading first.
            let half = self.cfg.grid.side as f64 * self.cfg.grid.resolution as f64 * 0.5;
            let local = ga.between(&self.st.far.pose);
            let (seed, window) = if radius >= half {
                (Se2::new(0.0, 0.0, local.theta), half)
            } else {
                let x = local.x.clamp(-half, half);
                let y = local.y.clamp(-half, half);
                (Se2::new(x, y, local.theta), radius)
            };
            // The sweep of a hypothesis only looks for places that score as well as it.
            let min_score = match &self.st.far.hypothesis {
                Some(h) => lc.min_score.max(AMBIGUITY * h.score),
                None => lc.min_score,
            };
            let config = FarCsmConfig {
                base_level: BASE_LEVEL.min(lc.pyramid_levels.saturating_sub(2)),
                min_score,
                window_theta: angle,
                ..FarCsmConfig::default()
            };
            let far = &mut self.st.far;
            if far.search.start(&far.scan, &seed, window, &config).is_ok() {
                far.current = Some((slot, anchor));
                self.st.stats.far_searches += 1;
                return Some((slot, anchor));
            }
        }
        None
    }
}
