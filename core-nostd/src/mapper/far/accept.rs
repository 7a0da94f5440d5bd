//! Which far matches become loop edges (tests 1, 2 and 4 of the parent module; test 3, the
//! sweep of all candidate submaps, is part of the search there).
//!
//! A refined far match is proposed as a hypothesis when it is unique in its submap and agrees
//! with the submap's free space. While the sweep runs, each following keyframe tests it:
//! matched by the windowed search where the hypothesis and the front-end motion since put it,
//! it supports the hypothesis when it lands there (the cycle through the two matches closes,
//! the pairwise consistency of PCM), and speaks against it when its scan does not fit the map
//! there (nothing scores, the refined match is poor, lands elsewhere, or puts walls in seen
//! free space). A keyframe whose scan barely overlaps the submaps, or whose match fits but
//! cannot fix every direction (a corridor's axis: the refinement is degenerate or slides), is
//! no test either way: in a corridor every keyframe would otherwise vote against the true
//! place. A swept hypothesis with enough support, spread over enough travel and submaps,
//! becomes loop edges; [`REFUTE`] keyframes against it, or too much travel without
//! confirmation, drop it.

use super::{FarMatchEdge, Hypothesis, AMBIGUITY};
use crate::frontend::far_csm::FarMatch;
use crate::frontend::scan::ScanPoint;
use crate::frontend::Submap;
use crate::geom::Se2;
use crate::graph::RobustKernel;
use crate::mapper::loops::{MatchMiss, MatchSource};
use crate::mapper::Mapper;

/// Largest share of a match's points that may land where the map saw only free space (people,
/// doors and moved furniture cause a few).
const MAX_CONFLICT: f32 = 0.03;
/// Log-odds at or below which a cell counts as seen free (about three net free observations).
const FREE: i8 = -12;
/// Submaps a following keyframe is matched in to test a hypothesis.
pub const VERIFY_SUBMAPS: usize = 2;
/// Supporting keyframes that confirm a hypothesis ...
pub const SUPPORT: usize = 3;
/// ... spread over at least this many submap lengths of travel after the matched keyframe, so
/// that a structure repeated within a submap's extent cannot confirm itself ...
pub const SUPPORT_SUBMAPS: f64 = 1.0;
/// ... and in at least this many distinct submaps.
pub const SUPPORT_DISTINCT: usize = 2;
/// Most supporting matches kept as edges.
pub(super) const SUPPORT_EDGES: usize = 8;
/// Keyframes against a hypothesis (see the module documentation) that drop it.
pub const REFUTE: u8 = 3;
/// Travel after the matched keyframe within which a hypothesis must be confirmed, in submap
/// lengths.
pub const VERIFY_SUBMAP_LENGTHS: f64 = 3.0;
/// Allowed disagreement of a supporting match per metre of front-end motion and of graph
/// distance between the submaps (the drift over that distance).
const AGREE_PER_METRE: f64 = 0.02;

impl Mapper<'_> {
    /// A far match of the kept keyframe in submap `slot` (anchored at `anchor`): refined and, if
    /// it is unique in the submap and agrees with its free space, the hypothesis whose sweep
    /// of all candidate submaps starts now.
    pub(super) fn propose(&mut self, slot: usize, anchor: u32, m: &FarMatch) {
        debug!(
            "far match of keyframe {} in submap {}: score {} runner-up {} at {} {} {}",
            self.st.far.serial, anchor, m.score, m.runner_up, m.pose.x, m.pose.y, m.pose.theta
        );
        // An ambiguous place (a corridor, a repeated room) is no evidence of where the robot
        // is, however well it fits.
        if m.runner_up >= AMBIGUITY * m.score {
            return;
        }
        let serial = self.st.far.serial;
        let Some((z, info)) =
            self.match_in_submap(slot, MatchSource::Far, &m.pose, m.cell, m.angular_step)
        else {
            return;
        };
        let (inside, conflicting) = self.free_space_conflicts(slot, MatchSource::Far, &z);
        debug!(
            "far conflicts of keyframe {} in submap {}: {} of {}",
            serial, anchor, conflicting, inside
        );
        if !consistent_with_free_space(inside, conflicting) {
            return;
        }
        self.st.stats.far_hypotheses += 1;
        debug!(
            "far hypothesis: keyframe {} in submap {} at {} {} {}",
            serial, anchor, z.x, z.y, z.theta
        );
        let travel = self.st.far.travel;
        let Some(ga) = self.mirrored_pose(anchor) else {
            return;
        };
        self.st.far.hypothesis = Some(Hypothesis {
            first: FarMatchEdge {
                serial,
                anchor,
                z,
                info,
            },
            travel,
            frontend: self.st.far.frontend,
            support: heapless::Vec::new(),
            supporting: 0,
            unsupported: 0,
            world: ga.compose(&z),
            score: m.score,
            swept: false,
            last_band: false,
        });
        self.st.mirror.pinned = Some((anchor, Some(ga)));
        // Sweep every candidate again, from the nearest, for a distinct place that fits as
        // well.
        let far = &mut self.st.far;
        far.queue.clear();
        far.reached = -1.0;
        far.planned = true;
    }

    /// The kept scan's points at `pose` in submap `slot` that fall on cells the submap has
    /// observed, and those of them where it saw only free space all around (an obstacle where
    /// the map says there is none).
    pub(in crate::mapper) fn free_space_conflicts(
        &self,
        slot: usize,
        source: MatchSource,
        pose: &Se2,
    ) -> (u32, u32) {
        let per = self.cells_per_submap;
        let Some(cells) = self.cells.get(slot * per..(slot + 1) * per) else {
            return (0, 0);
        };
        let Ok(submap) = Submap::from_cells(Se2::IDENTITY, self.cfg.grid, cells) else {
            return (0, 0);
        };
        let (c, s) = (libm::cos(pose.theta) as f32, libm::sin(pose.theta) as f32);
        let (tx, ty) = (pose.x as f32, pose.y as f32);
        let (mut inside, mut conflicting) = (0u32, 0u32);
        let points: &[ScanPoint] = match source {
            MatchSource::Scan => self.scan.as_slice(),
            MatchSource::Far => self.st.far.scan(),
        };
        for q in points {
            let p = [tx + c * q.p[0] - s * q.p[1], ty + s * q.p[0] + c * q.p[1]];
            let g = submap.local_to_cell(p);
            let (ix, iy) = (libm::floorf(g[0]) as i32, libm::floorf(g[1]) as i32);
            let mut seen = false;
            let mut most = i8::MIN;
            for dy in -1..=1 {
                for dx in -1..=1 {
                    if let Some(v) = submap.cell(ix + dx, iy + dy) {
                        seen |= v != 0;
                        most = most.max(v);
                    }
                }
            }
            if seen {
                inside += 1;
                if most <= FREE {
                    conflicting += 1;
                }
            }
        }
        (inside, conflicting)
    }

    /// Tests the pending hypothesis with keyframe `serial`: matched where the hypothesis puts
    /// it, in the submaps around that place.
    pub(super) fn verify_far(&mut self, serial: u32) {
        let Some((first, since, fh)) =
            (self.st.far.hypothesis.as_ref()).map(|h| (h.first, h.travel, h.frontend))
        else {
            return;
        };
        let lc = self.cfg.loops;
        let travel = self.st.frontend.travel();
        let refute = |m: &mut Self| m.drop_hypothesis();
        let (Some(fs), Some(gh)) = (
            self.newest_if(serial).map(|n| n.tie.frontend),
            self.mirrored_pose(first.anchor),
        ) else {
            refute(self);
            return;
        };
        let side = self.cfg.grid.side as f64 * self.cfg.grid.resolution as f64;
        let travelled = travel.path - since.path;
        if travelled > VERIFY_SUBMAP_LENGTHS * side {
            refute(self);
            return;
        }
        let odo = fh.between(&fs);
        let moved = libm::hypot(odo.x, odo.y);
        // Where the hypothesis puts this keyframe in the world.
        let predicted = gh.compose(&first.z).compose(&odo);
        let half = self.cfg.grid.side as f64 * self.cfg.grid.resolution as f64 * 0.5;
        let mut near = heapless::Vec::<(f64, usize, u32), VERIFY_SUBMAPS>::new();
        for (slot, m) in self.submaps.iter().enumerate() {
            if !m.in_use || m.active || m.anchor_serial + lc.min_keyframe_gap > serial {
                continue;
            }
            let Some(ga) = m.anchor_estimate else {
                continue;
            };
            let local = ga.between(&predicted);
            if libm::fabs(local.x) > half || libm::fabs(local.y) > half {
                continue;
            }
            let d = libm::hypot(local.x, local.y);
            if near.is_full() {
                if let Some(far) = (0..near.len()).max_by(|&a, &b| near[a].0.total_cmp(&near[b].0))
                {
                    if near[far].0 > d {
                        near[far] = (d, slot, m.anchor_serial);
                    }
                }
            } else {
                let _ = near.push((d, slot, m.anchor_serial));
            }
        }
        if near.is_empty() {
            return;
        }
        // A keyframe supports the hypothesis when it matches where the hypothesis puts it; it
        // speaks against it when the scan does not fit the map there (no pose in the window
        // scores, the refined match is poor, disagrees, or puts walls in seen free space). A
        // place that fits but whose match cannot fix every direction (a corridor's axis) is
        // no test: it neither supports nor refutes.
        let mut supported = false;
        let mut against = false;
        for &(_, slot, anchor) in near.iter() {
            let Some(ga) = self.submaps.get(slot).and_then(|m| m.anchor_estimate) else {
                continue;
            };
            let seed = ga.between(&predicted);
            let (z, info) = match self.try_match_in_submap(
                slot,
                MatchSource::Scan,
                &seed,
                lc.window_min,
                lc.angle_min,
            ) {
                Ok(m) => m,
                Err(MatchMiss::NoMatch | MatchMiss::Poor) => {
                    against = true;
                    continue;
                }
                // Too little of the scan in the submap, or a fit that cannot fix every
                // direction: no test.
                Err(MatchMiss::Outside | MatchMiss::Unresolved) => continue,
            };
            let (inside, conflicting) = self.free_space_conflicts(slot, MatchSource::Scan, &z);
            if !consistent_with_free_space(inside, conflicting) {
                against = true;
                continue;
            }
            let e = seed.between(&z);
            let span = moved + libm::hypot(ga.x - gh.x, ga.y - gh.y);
            if libm::hypot(e.x, e.y) <= lc.agree_xy + AGREE_PER_METRE * span
                && libm::fabs(e.theta) <= lc.agree_theta
            {
                if let Some(hyp) = self.st.far.hypothesis.as_mut() {
                    let edge = FarMatchEdge {
                        serial,
                        anchor,
                        z,
                        info,
                    };
                    keep_support(&mut hyp.support, &hyp.first, edge);
                }
                supported = true;
            } else {
                against = true;
            }
        }
        let Some(hyp) = self.st.far.hypothesis.as_mut() else {
            return;
        };
        if supported {
            hyp.supporting += 1;
        } else if against {
            hyp.unsupported += 1;
        }
        debug!(
            "far hypothesis tested by keyframe {}: supported {} against {} ({} / {})",
            serial, supported, against, hyp.supporting, hyp.unsupported
        );
        if hyp.unsupported >= REFUTE {
            refute(self);
        } else if hyp.swept
            && hyp.supporting >= SUPPORT
            && travelled >= SUPPORT_SUBMAPS * side
            && distinct_anchors(&hyp.first, &hyp.support) >= SUPPORT_DISTINCT
        {
            self.accept_far();
        }
    }

    /// Adds the confirmed hypothesis' matches as loop edges.
    fn accept_far(&mut self) {
        let Some(h) = self.st.far.hypothesis.take() else {
            return;
        };
        self.st.mirror.pinned = None;
        let mut added = 0u32;
        for e in core::iter::once(&h.first).chain(h.support.iter()) {
            // Plain least squares: the group is the evidence, and the null component of a
            // max-mixture would reject a large correction at the drifted estimate.
            if self.add_loop_edge(e.anchor, e.serial, e.z, e.info, RobustKernel::None) {
                debug!("far loop edge: {} -> {}", e.anchor, e.serial);
                added += 1;
            }
        }
        // The next search starts again from the nearest submaps.
        self.st.far.reached = -1.0;
        if added > 0 {
            self.st.stats.far_confirmed += 1;
        }
    }
}

/// Whether a match whose points fall on `inside` observed cells, `conflicting` of them where
/// the map saw only free space, agrees with the map's free space: a revisit sees the walls
/// the map has; a place that merely looks alike puts some of its walls where the map saw
/// through.
pub(in crate::mapper) fn consistent_with_free_space(inside: u32, conflicting: u32) -> bool {
    inside > 0 && (conflicting as f32) <= MAX_CONFLICT * inside as f32
}

/// Adds `edge` to a hypothesis' `support`; when full, a match in a submap not yet among them
/// replaces one whose submap is represented twice, so the distinct submaps are kept.
fn keep_support(
    support: &mut heapless::Vec<FarMatchEdge, SUPPORT_EDGES>,
    first: &FarMatchEdge,
    edge: FarMatchEdge,
) {
    let Err(edge) = support.push(edge) else {
        return;
    };
    if first.anchor == edge.anchor || support.iter().any(|e| e.anchor == edge.anchor) {
        return;
    }
    let twice = (0..support.len()).rev().find(|&i| {
        let a = support[i].anchor;
        a == first.anchor || support.iter().filter(|e| e.anchor == a).count() > 1
    });
    if let Some(i) = twice {
        support[i] = edge;
    }
}

/// Distinct submaps among a hypothesis' matches.
fn distinct_anchors(first: &FarMatchEdge, support: &[FarMatchEdge]) -> usize {
    let all = || core::iter::once(first).chain(support.iter());
    all()
        .enumerate()
        .filter(|&(i, e)| all().take(i).all(|f| f.anchor != e.anchor))
        .count()
}
