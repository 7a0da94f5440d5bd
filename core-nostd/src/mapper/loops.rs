//! Loop closure of a new keyframe against the finished submaps (the paper's loop constraints,
//! section III-B.2, which become the max-mixture edges of eq. 12).
//!
//! Candidates are the finished submaps whose area contains the keyframe's estimated position,
//! widened by the search window, and whose anchor is old enough not to be a neighbour along the
//! odometry chain. The window is `sigmas` standard deviations of the front-end uncertainty
//! (a Mahalanobis gate in the metric of the motion model), clamped to a range, accumulated
//! either since the candidate submap was opened (`window_from_anchor`) or since the last loop
//! closure. The first is the drift between the submap and the keyframe as far as the front-end
//! knows: a loop closure, true or false, is only judged by the back-end later, and a local one
//! says nothing about the drift relative to an old submap, so the window must not shrink with
//! it. With `window_lever`, the position window also holds the heading uncertainty times a
//! lever arm proportional to the path. For each candidate, nearest first, a branch-and-bound
//! correlative search over the window finds the best pose of the scan in the submap; ICP
//! against the submap's occupied cells refines it without the degenerate-direction fallback
//! (a corridor match that does not fix every direction is rejected); the fitness, the RMS
//! residual and the agreement of the two matches decide. A match is believed only when a
//! second keyframe matched to the same submap agrees with it through the front-end motion
//! between the two; both then become loop edges from the submap's anchor with the ICP
//! information (floored) and a max-mixture null hypothesis.

use nalgebra::Matrix3;

use super::Mapper;
use crate::frontend::csm::{search, CsmConfig, Pyramid};
use crate::frontend::lidar::{MotionNoise, Travel};
use crate::frontend::scan::ScanPoint;
use crate::frontend::{align, IcpConfig, KdTree, MatchError, Submap};
use crate::geom::{information_in_frame_of, spd_inverse, Info3, Se2};
use crate::graph::RobustKernel;

/// Most candidates considered per keyframe before the `max_candidates` cut.
const MAX_CANDIDATES: usize = 8;
/// Occupied cells a scan is refined against, here and in a saved map (`localize`): log-odds
/// units at least this (probability ~0.73).
pub(in crate::mapper) const OCCUPIED: i8 = 10;
/// Radius, in cells, of the normal fit of points taken from a submap's cells (the
/// refinement's reference, a saved map's, a restarted local map's).
pub(in crate::mapper) const NORMAL_RADIUS: u8 = 2;
/// Matches waiting for confirmation (one per submap, the oldest dropped when full).
const UNCONFIRMED: usize = 4;
/// Share of the scan (one in this many points) that must fall inside the submap at the seed.
const MIN_INSIDE_ONE_IN: usize = 3;
/// Correspondence distance of the refinement, metres: the correlative match is already within
/// a few cells.
const REFINE_CORRESPONDENCE: f32 = 0.3;
/// The refinement may move the correlative match by at most this many grid cells.
const MAX_REFINE_SHIFT_CELLS: f64 = 4.0;
/// Allowed disagreement of two matches per metre between their keyframes (the front-end's
/// drift over that distance).
const AGREE_PER_METRE: f64 = 0.02;

/// A loop-closure match waiting for a second, agreeing one.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct LoopCandidate {
    slot: u16,
    serial: u32,
    /// Front-end pose of the keyframe.
    frontend: Se2,
    z: Se2,
    info: Info3,
}

/// The loop search's memory between keyframes.
#[derive(Clone, Debug)]
pub(crate) struct LoopState {
    /// Front-end travel at the last loop closure (the search window grows with the travel
    /// since).
    pub(crate) at_loop: Travel,
    /// Matches waiting for confirmation.
    unconfirmed: heapless::Vec<LoopCandidate, UNCONFIRMED>,
    /// The submap (slot and anchor serial) whose levels the pyramid storage holds.
    pub(crate) pyramid_of: Option<(u16, u32)>,
}

/// Why a match in a submap gave no pose.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum MatchMiss {
    /// Too little of the scan falls inside the submap at the seed: no test.
    Outside,
    /// No pose within the window scores `min_score`: the scan does not fit the map there.
    NoMatch,
    /// A pose within the window scores, but the refinement cannot fix every direction (a
    /// degenerate corridor geometry, or a refinement sliding along it beyond the shift
    /// limit): the place fits, the pose along one direction is undetermined.
    Unresolved,
    /// The refined match is poor (fitness, RMS residual, too few correspondences).
    Poor,
}

/// Which scan a loop match uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum MatchSource {
    /// The current scan.
    Scan,
    /// The keyframe scan kept by the far search.
    Far,
}

impl LoopState {
    pub(crate) const fn new() -> Self {
        LoopState {
            at_loop: Travel::ZERO,
            unconfirmed: heapless::Vec::new(),
            pyramid_of: None,
        }
    }
}

impl Mapper<'_> {
    /// Searches loop closures for keyframe `serial`; returns how many were added.
    pub(crate) fn close_loops(&mut self, serial: u32) -> u8 {
        let Some(newest) = self.newest_if(serial) else {
            return 0;
        };
        let gk = newest.tie.estimate;
        let lc = self.cfg.loops;
        let travel = self.st.frontend.travel();
        let (window, angle) = self.search_window(&travel.since(&self.st.loops.at_loop));
        let half = self.cfg.grid.side as f64 * self.cfg.grid.resolution as f64 * 0.5;

        let mut candidates = heapless::Vec::<(f64, usize, u32), MAX_CANDIDATES>::new();
        for (slot, m) in self.submaps.iter().enumerate() {
            if !m.in_use || m.active || m.anchor_serial + lc.min_keyframe_gap > serial {
                continue;
            }
            let Some(ga) = m.anchor_estimate else {
                continue;
            };
            let (window, _) = self.window_to(slot, (window, angle));
            let local = ga.between(&gk);
            if libm::fabs(local.x) > half + window || libm::fabs(local.y) > half + window {
                continue;
            }
            let d = libm::hypot(local.x, local.y);
            if candidates.is_full() {
                // Replace the farthest if this one is nearer.
                let Some((far, _)) = candidates
                    .iter()
                    .enumerate()
                    .max_by(|a, b| a.1 .0.total_cmp(&b.1 .0))
                else {
                    continue;
                };
                if candidates.get(far).is_some_and(|c| c.0 > d) {
                    if let Some(c) = candidates.get_mut(far) {
                        *c = (d, slot, m.anchor_serial);
                    }
                }
            } else {
                let _ = candidates.push((d, slot, m.anchor_serial));
            }
        }
        crate::sort::sort_by(&mut candidates, |a, b| a.0.total_cmp(&b.0));

        let mut added = 0u8;
        for &(_, slot, anchor_serial) in candidates.iter().take(lc.max_candidates as usize) {
            let Some(ga) = self.submaps.get(slot).and_then(|m| m.anchor_estimate) else {
                continue;
            };
            self.st.stats.loop_searches += 1;
            let (window, angle) = self.window_to(slot, (window, angle));
            let seed = ga.between(&gk);
            let Some((z, info)) =
                self.match_in_submap(slot, MatchSource::Scan, &seed, window, angle)
            else {
                continue;
            };
            debug!(
                "loop match: {} -> {} window {} angle {} seed {} {} {} z {} {} {}",
                anchor_serial, serial, window, angle, seed.x, seed.y, seed.theta, z.x, z.y, z.theta
            );
            // A match is only believed when a second keyframe matched to the same submap
            // agrees with it through the front-end motion between the two.
            let candidate = LoopCandidate {
                slot: slot as u16,
                serial,
                frontend: newest.tie.frontend,
                z,
                info,
            };
            let confirmed = match self
                .st
                .loops
                .unconfirmed
                .iter()
                .position(|c| c.slot == slot as u16)
            {
                Some(i) => {
                    let c = self.st.loops.unconfirmed[i];
                    if self.loops_agree(&c, &candidate) {
                        let _ = self.st.loops.unconfirmed.swap_remove(i);
                        Some(c)
                    } else {
                        self.st.loops.unconfirmed[i] = candidate;
                        None
                    }
                }
                None => {
                    if self.st.loops.unconfirmed.is_full() {
                        let _ = self.st.loops.unconfirmed.remove(0);
                    }
                    let _ = self.st.loops.unconfirmed.push(candidate);
                    None
                }
            };
            let Some(first) = confirmed else {
                self.st.stats.loops_unconfirmed += 1;
                continue;
            };
            let robust = RobustKernel::max_mixture_with_null(lc.null_weight, lc.null_scale);
            for c in [first, candidate] {
                if self.add_loop_edge(anchor_serial, c.serial, c.z, c.info, robust) {
                    added += 1;
                }
            }
        }
        added
    }

    /// Adds a loop edge from the keyframe `anchor` (a submap's anchor) to keyframe `serial`
    /// measuring `z` with `info`; counts it, asks for an optimization and restarts the travel
    /// since the last loop closure. Whether it was added (a keyframe may have been pruned).
    pub(crate) fn add_loop_edge(
        &mut self,
        anchor: u32,
        serial: u32,
        z: Se2,
        info: Info3,
        robust: RobustKernel,
    ) -> bool {
        let added = self.back.add_loop_edge(anchor, serial, z, info, robust);
        self.st.mirror.counts = self.back.counts();
        if !added {
            return false;
        }
        self.st.stats.loop_closures += 1;
        self.st.loops.at_loop = self.st.frontend.travel();
        true
    }

    /// Half-widths `(metres, radians)` of the search after a front-end `travel`: `sigmas`
    /// standard deviations of the motion model, clamped.
    fn search_window(&self, travel: &Travel) -> (f64, f64) {
        let lc = &self.cfg.loops;
        let (xy, theta) = self.uncertainty(travel);
        (
            xy.clamp(lc.window_min, lc.window_max),
            theta.clamp(lc.angle_min, lc.angle_max),
        )
    }

    /// `sigmas` standard deviations `(metres, radians)` of the position (with the heading's
    /// lever arm) and heading uncertainty of the front-end motion over `travel`, unclamped.
    pub(crate) fn uncertainty(&self, travel: &Travel) -> (f64, f64) {
        let lc = &self.cfg.loops;
        let cov = self.cfg.noise.over(travel);
        let lever = lc.window_lever * libm::fabs(travel.path);
        let var_xy = cov[(0, 0)].max(cov[(1, 1)]) + cov[(2, 2)] * lever * lever;
        (
            lc.sigmas * libm::sqrt(var_xy),
            lc.sigmas * libm::sqrt(cov[(2, 2)]),
        )
    }

    /// The search window for a match against the submap in `slot`: from the front-end motion
    /// since the submap was started when `window_from_anchor`, else `global` (from the motion
    /// since the last loop closure).
    fn window_to(&self, slot: usize, global: (f64, f64)) -> (f64, f64) {
        if !self.cfg.loops.window_from_anchor {
            return global;
        }
        let Some(m) = self.submaps.get(slot) else {
            return global;
        };
        self.search_window(&self.st.frontend.travel().since(&m.anchor_travel))
    }

    /// Whether two matches against one submap agree with the front-end motion between their
    /// keyframes.
    fn loops_agree(&self, a: &LoopCandidate, b: &LoopCandidate) -> bool {
        let odo = a.frontend.between(&b.frontend);
        let e = odo.between(&a.z.between(&b.z));
        let d = libm::hypot(odo.x, odo.y);
        let lc = &self.cfg.loops;
        libm::hypot(e.x, e.y) <= lc.agree_xy + AGREE_PER_METRE * d
            && libm::fabs(e.theta) <= lc.agree_theta
    }

    /// Matches the scan of `source` in submap `slot` around `seed` (pose in the submap's
    /// frame); the measured pose and its information when accepted.
    pub(crate) fn match_in_submap(
        &mut self,
        slot: usize,
        source: MatchSource,
        seed: &Se2,
        window: f64,
        angle: f64,
    ) -> Option<(Se2, Matrix3<f64>)> {
        self.try_match_in_submap(slot, source, seed, window, angle)
            .ok()
    }

    /// [`Self::match_in_submap`], with the reason when it gives no pose.
    pub(crate) fn try_match_in_submap(
        &mut self,
        slot: usize,
        source: MatchSource,
        seed: &Se2,
        window: f64,
        angle: f64,
    ) -> Result<(Se2, Matrix3<f64>), MatchMiss> {
        let lc = self.cfg.loops;
        // Only the points that fall inside the submap at the seed take part: the others would
        // dilute the score and the fitness of a good match.
        let half = self.cfg.grid.side as f32 * self.cfg.grid.resolution * 0.5;
        let (c, s) = (libm::cos(seed.theta) as f32, libm::sin(seed.theta) as f32);
        let (tx, ty) = (seed.x as f32, seed.y as f32);
        let points: &[ScanPoint] = match source {
            MatchSource::Scan => self.scan.as_slice(),
            MatchSource::Far => self.st.far.scan(),
        };
        let total = points.len();
        self.loop_scan.clear();
        for q in points {
            let x = tx + c * q.p[0] - s * q.p[1];
            let y = ty + s * q.p[0] + c * q.p[1];
            if libm::fabsf(x) < half && libm::fabsf(y) < half {
                let _ = self.loop_scan.push(*q);
            }
        }
        if MIN_INSIDE_ONE_IN * self.loop_scan.len() < total
            || (self.loop_scan.len() as u32) < self.cfg.icp.min_points.min(total as u32)
        {
            self.st.stats.loops_no_match += 1;
            return Err(MatchMiss::Outside);
        }
        let (submap, pyramid) = submap_and_pyramid(
            self.cells,
            self.submaps,
            self.pyramid,
            &mut self.st.loops.pyramid_of,
            &self.cfg,
            slot,
        )
        .ok_or(MatchMiss::Outside)?;
        let csm = CsmConfig {
            window_xy: window,
            window_theta: angle,
            angular_step: 0.0,
            min_score: lc.min_score,
        };
        let Ok(found) = search(self.loop_scan, &submap, &pyramid, seed, &csm) else {
            self.st.stats.loops_no_match += 1;
            return Err(MatchMiss::NoMatch);
        };
        let n = submap.occupied_points(OCCUPIED, NORMAL_RADIUS, self.reference);
        let tree = KdTree::build(self.reference.get_mut(..n).ok_or(MatchMiss::Poor)?);
        let icp = IcpConfig {
            allow_degenerate: false,
            degeneracy_ratio: lc.degeneracy_ratio,
            max_correspondence: REFINE_CORRESPONDENCE,
            ..self.cfg.icp
        };
        let refined = match align(self.loop_scan, &tree, &found.pose, &icp) {
            Ok(r) => r,
            Err(e) => {
                debug!(
                    "loop refinement failed (score {}): {} ({} query, {} reference)",
                    found.score,
                    e,
                    self.loop_scan.len(),
                    n
                );
                self.st.stats.loops_rejected += 1;
                return Err(match e {
                    MatchError::Degenerate { .. } => MatchMiss::Unresolved,
                    _ => MatchMiss::Poor,
                });
            }
        };
        let moved = found.pose.between(&refined.pose);
        let res = self.cfg.grid.resolution as f64;
        if refined.fitness < lc.min_fitness
            || refined.rms > lc.max_rms
            || libm::hypot(moved.x, moved.y) > MAX_REFINE_SHIFT_CELLS * res
        {
            debug!(
                "loop rejected: score {} fitness {} rms {} moved {}",
                found.score,
                refined.fitness,
                refined.rms,
                libm::hypot(moved.x, moved.y)
            );
            self.st.stats.loops_rejected += 1;
            // A good fit that slid beyond the shift limit slid along a weak direction.
            let good = refined.fitness >= lc.min_fitness && refined.rms <= lc.max_rms;
            return Err(if good {
                MatchMiss::Unresolved
            } else {
                MatchMiss::Poor
            });
        }
        let [sxy, sth] = lc.min_sigma;
        let mut cov = spd_inverse(&refined.information).ok_or(MatchMiss::Unresolved)?;
        cov[(0, 0)] += sxy * sxy;
        cov[(1, 1)] += sxy * sxy;
        cov[(2, 2)] += sth * sth;
        // The match's information is over world-axis steps of the submap frame; the loop
        // edge's residual has its translation in the measurement's frame.
        let info = spd_inverse(&cov).ok_or(MatchMiss::Unresolved)?;
        Ok((refined.pose, information_in_frame_of(&info, &refined.pose)))
    }
}

/// The submap in `slot` (in its anchor's frame) and its search pyramid in `storage`, built
/// unless `pyramid_of` says the storage already holds this submap's levels.
pub(crate) fn submap_and_pyramid<'a>(
    cells: &'a [i8],
    submaps: &[super::SubmapMeta],
    storage: &'a mut [u8],
    pyramid_of: &mut Option<(u16, u32)>,
    cfg: &super::MapperConfig,
    slot: usize,
) -> Option<(Submap<&'a [i8]>, Pyramid<'a>)> {
    let key = (slot as u16, submaps.get(slot)?.anchor_serial);
    let per = cfg.grid.cells();
    let cells = cells.get(slot * per..(slot + 1) * per)?;
    let submap = Submap::from_cells(Se2::IDENTITY, cfg.grid, cells).ok()?;
    let levels = cfg.loops.pyramid_levels as usize;
    let side = cfg.grid.side as usize;
    let pyramid = if *pyramid_of == Some(key) {
        Pyramid::reuse(side, levels, storage).ok()?
    } else {
        *pyramid_of = None;
        let p = Pyramid::build(&submap, levels, storage).ok()?;
        *pyramid_of = Some(key);
        p
    };
    Some((submap, pyramid))
}
