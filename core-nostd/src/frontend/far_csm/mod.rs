//! Far loop search: where in a submap a scan fits, over every heading and a translation window
//! as wide as the submap, by branch and bound over the max-pooled levels of [`csm`], with a
//! bounded amount of work per call.
//!
//! The paper's back-end (section III-C) only prunes and optimizes the constraints it is given;
//! when the drift between a revisit and the first visit is tens of metres and the heading is
//! unknown, the windowed search of [`csm`] never produces the constraint. This search widens
//! the window to a full turn and to the whole submap, and pays for it in two ways:
//!
//! * The leaves are scored at a coarse level `base` of the pyramid (a block of `2^base` cells
//!   per candidate, the maximum of the block per point), so the translations are stepped by
//!   `2^base` cells and the rotations by the angle that moves the farthest point by one coarse
//!   cell. The coarse maximum is an upper bound of the fine score around it; the caller refines
//!   the coarse pose with the windowed [`csm::search`] and ICP, which decide.
//! * The work is split into calls of at most about `budget` candidate evaluations. The state
//!   between calls ([`FarSearch`]) holds a copy of the scan's points (subsampled into fixed
//!   storage), the next rotation and top-level cell to visit and the best leaf so far, so the
//!   search can be spread over many back-end steps while the front-end keeps running.
//!
//! Rotations are visited nearest to the seed's heading first (0, +1, -1, +2, ...) so a good
//! estimate raises the best score early and cuts more of the remaining tree. Within one
//! rotation the search is the depth-first, best-child-first descent of [`csm`]: a branch
//! whose bound does not beat the best leaf found so far is cut, so the result is the exact
//! maximum of the coarse score over the discretized window.
//!
//! [`csm`]: crate::frontend::csm
//! [`csm::search`]: crate::frontend::csm::search

use core::f64::consts::PI;

use crate::frontend::csm::{children, CsmError, Frontier, Pyramid};
use crate::frontend::grid::Submap;
use crate::frontend::scan::ScanPoint;
use crate::geom::Se2;

/// Most scan points kept for the coarse search.
pub const FAR_POINTS: usize = 160;
/// Cell coordinates are clamped to this magnitude.
const FAR: i32 = 1 << 24;

/// Parameters of a far search.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FarCsmConfig {
    /// Pyramid level the leaves are scored at (`2^base` cells per candidate).
    pub base_level: u8,
    /// Smallest coarse score kept, in `[0, 1]` (the coarse score is an upper bound of the
    /// fine one, so this is at least the fine threshold).
    pub min_score: f32,
    /// The rotation step is derived from the scan's farthest point, but that distance is taken
    /// as at most this, metres (long beams would make the step needlessly fine).
    pub step_range: f32,
    /// Half-width of the rotation window around the seed's heading, radians (`PI` or more:
    /// every heading).
    pub window_theta: f64,
    /// Two leaves are distinct matches when their translations differ by more than this,
    /// metres, on either axis ...
    pub distinct_xy: f64,
    /// ... or their headings by more than this, radians: the runner-up
    /// ([`FarMatch::runner_up`]) is the best leaf distinct from the best one.
    pub distinct_theta: f64,
}

impl FarCsmConfig {
    /// Leaves at level 2, threshold 0.6, rotation step from at most 12 m, every heading,
    /// distinct beyond 1 m or 0.3 rad.
    pub const DEFAULT: FarCsmConfig = FarCsmConfig {
        base_level: 2,
        min_score: 0.6,
        step_range: 12.0,
        window_theta: PI,
        distinct_xy: 1.0,
        distinct_theta: 0.3,
    };
}

impl Default for FarCsmConfig {
    fn default() -> Self {
        FarCsmConfig::DEFAULT
    }
}

/// The coarse result of a finished search.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FarMatch {
    /// Pose of the scan in the world (the submap's origin composed with the local pose).
    pub pose: Se2,
    /// Mean of the coarse (max-pooled) occupancy at the scan's points.
    pub score: f32,
    /// The same for the best pose distinct from this one (see
    /// [`FarCsmConfig::distinct_xy`]), or the threshold when none reached it: how ambiguous
    /// the match is (a corridor or a repeated room scores a shifted pose as high).
    pub runner_up: f32,
    /// Rotation step of the search, radians (the refinement's angular window).
    pub angular_step: f64,
    /// Translation step of the leaves, metres (the refinement's translation window).
    pub cell: f64,
}

/// Outcome of one call of [`FarSearch::step`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FarStep {
    /// The budget ran out; call again with the same submap.
    Working,
    /// The window has been searched; the best coarse match above the threshold, if any.
    Done(Option<FarMatch>),
}

/// A resumable far search of one scan in one submap, in fixed storage.
#[derive(Clone, Debug)]
pub struct FarSearch {
    points: heapless::Vec<[f32; 2], FAR_POINTS>,
    seed: Se2,
    window_xy: f64,
    config: FarCsmConfig,
    started: bool,
    next_angle: u32,
    next_top: u32,
    best: u32,
    best_at: Option<(u32, i32, i32)>,
    second: u32,
    evaluated: u64,
}

impl Default for FarSearch {
    fn default() -> Self {
        FarSearch::new()
    }
}

struct Bnb<'p, 'a> {
    pyramid: &'p Pyramid<'a>,
    base: usize,
    window: i32,
    best: u32,
    best_at: Option<(u32, i32, i32)>,
    /// Best score of a leaf distinct from `best_at`.
    second: u32,
    /// Rotations in a full turn, and the distinctness thresholds in rotation steps and cells.
    angles: i64,
    distinct_steps: i64,
    distinct_cells: i32,
    evaluated: u64,
}

impl Bnb<'_, '_> {
    fn score(&mut self, cells: &[[i32; 2]], k: usize, dx: i32, dy: i32) -> u32 {
        self.evaluated += 1;
        cells
            .iter()
            .map(|c| self.pyramid.bound(k, c[0] + dx, c[1] + dy))
            .sum()
    }

    /// Whether the leaf `(angle, dx, dy)` is a match distinct from the best one.
    fn distinct(&self, angle: u32, dx: i32, dy: i32) -> bool {
        let Some((a, x, y)) = self.best_at else {
            return true;
        };
        let d = (angle_offset(angle) - angle_offset(a)).rem_euclid(self.angles);
        d.min(self.angles - d) > self.distinct_steps
            || (dx - x).abs() > self.distinct_cells
            || (dy - y).abs() > self.distinct_cells
    }

    fn descend(&mut self, cells: &[[i32; 2]], angle: u32, k: usize, dx: i32, dy: i32, b: u32) {
        let mut frontier = Frontier::new((b, k, dx, dy));
        while let Some((b, k, dx, dy)) = frontier.pop() {
            // Cut only what can beat neither the best nor the runner-up.
            if b <= self.second {
                continue;
            }
            if k == self.base {
                if b > self.best {
                    if self.best_at.is_some() && self.distinct(angle, dx, dy) {
                        self.second = self.second.max(self.best);
                    }
                    self.best = b;
                    self.best_at = Some((angle, dx, dy));
                } else if self.distinct(angle, dx, dy) {
                    self.second = b;
                }
                continue;
            }
            let window = self.window;
            let (children, n) = children(window, k, dx, dy, |k, x, y| self.score(cells, k, x, y));
            frontier.push_children(k - 1, &children[..n]);
        }
    }
}

/// Signed rotation index of the `i`-th rotation visited: 0, 1, -1, 2, -2, ...
fn angle_offset(i: u32) -> i64 {
    let i = i as i64;
    if i % 2 == 1 {
        (i + 1) / 2
    } else {
        -(i / 2)
    }
}

impl FarSearch {
    /// An idle search.
    pub const fn new() -> Self {
        FarSearch {
            points: heapless::Vec::new(),
            seed: Se2::IDENTITY,
            window_xy: 0.0,
            config: FarCsmConfig::DEFAULT,
            started: false,
            next_angle: 0,
            next_top: 0,
            best: 0,
            best_at: None,
            second: 0,
            evaluated: 0,
        }
    }

    /// Whether a search was started and has not finished.
    pub fn is_active(&self) -> bool {
        self.started
    }

    /// Candidates scored since [`FarSearch::start`].
    pub fn evaluated(&self) -> u64 {
        self.evaluated
    }

    /// Forgets the search in progress.
    pub fn cancel(&mut self) {
        self.started = false;
    }

    /// Starts a search of `scan` (robot frame) around the world pose `seed`, over translations
    /// within `window_xy` metres on each axis and the headings within `config.window_theta`.
    ///
    /// # Errors
    /// [`CsmError::EmptyScan`] without points, [`CsmError::InvalidConfig`] for a non-finite
    /// seed or window or a threshold outside `[0, 1]`.
    pub fn start(
        &mut self,
        scan: &[ScanPoint],
        seed: &Se2,
        window_xy: f64,
        config: &FarCsmConfig,
    ) -> Result<(), CsmError> {
        self.started = false;
        if scan.is_empty() {
            return Err(CsmError::EmptyScan);
        }
        if !(seed.is_finite()
            && window_xy.is_finite()
            && window_xy >= 0.0
            && (0.0..=1.0).contains(&config.min_score)
            && config.step_range.is_finite()
            && config.step_range > 0.0
            && config.window_theta >= 0.0
            && config.distinct_xy >= 0.0
            && config.distinct_theta >= 0.0)
        {
            return Err(CsmError::InvalidConfig);
        }
        self.points.clear();
        let stride = scan.len().div_ceil(FAR_POINTS);
        for q in scan.iter().step_by(stride) {
            if q.p[0].is_finite() && q.p[1].is_finite() {
                let _ = self.points.push(q.p);
            }
        }
        if self.points.is_empty() {
            return Err(CsmError::EmptyScan);
        }
        self.seed = *seed;
        self.window_xy = window_xy;
        self.config = *config;
        self.started = true;
        self.next_angle = 0;
        self.next_top = 0;
        self.best = 0;
        self.best_at = None;
        self.second = 0;
        self.evaluated = 0;
        Ok(())
    }

    /// Continues the search in `submap` (with its `pyramid`) for about `budget` more candidate
    /// evaluations (a top-level cell's subtree is finished once begun, so a call may overrun
    /// by one subtree). Placing the scan's points at a new rotation costs about as much as an
    /// evaluation (one pass over the points) and counts as one. The submap and pyramid must be the same on every call of one search.
    ///
    /// # Errors
    /// [`CsmError::InvalidConfig`] when no search is active or the base level is not below the
    /// pyramid's top; [`CsmError::WrongStorage`] when the pyramid does not fit the submap.
    pub fn step(
        &mut self,
        submap: &Submap<impl AsRef<[i8]>>,
        pyramid: &Pyramid<'_>,
        budget: u32,
    ) -> Result<FarStep, CsmError> {
        if !self.started {
            return Err(CsmError::InvalidConfig);
        }
        if pyramid.side() != submap.params().side as usize {
            return Err(CsmError::WrongStorage);
        }
        let top = pyramid.levels() - 1;
        let base = self.config.base_level as usize;
        if base >= top {
            self.started = false;
            return Err(CsmError::InvalidConfig);
        }
        let res = submap.params().resolution as f64;
        let coarse = res * (1u32 << base) as f64;
        let far = self
            .points
            .iter()
            .map(|p| libm::sqrtf(p[0] * p[0] + p[1] * p[1]))
            .fold(0.0f32, f32::max)
            .min(self.config.step_range) as f64;
        let far = far.max(3.0 * coarse);
        let step = libm::acos(1.0 - coarse * coarse / (2.0 * far * far));
        let full = libm::ceil(2.0 * PI / step) as u32;
        // Within the rotation window: the seed's heading and `n` steps to each side.
        let angles = if self.config.window_theta >= PI {
            full
        } else {
            full.min(2 * (libm::floor(self.config.window_theta / step) as u32) + 1)
        };
        let window = libm::ceil(self.window_xy / res) as i32;
        let span = 1i32 << top;
        let per_row = (2 * window) / span + 1;
        let tops = (per_row * per_row) as u32;
        let count = self.points.len();
        let threshold = (self.config.min_score as f64 * 255.0 * count as f64) as u32;
        let local = submap.to_local(&self.seed);
        let floor = threshold.saturating_sub(1);
        let mut bnb = Bnb {
            pyramid,
            base,
            window,
            best: self.best.max(floor),
            best_at: self.best_at,
            second: self.second.max(floor),
            angles: full as i64,
            distinct_steps: libm::floor(self.config.distinct_theta / step) as i64,
            distinct_cells: libm::floor(self.config.distinct_xy / res) as i32,
            evaluated: 0,
        };
        let mut cells: heapless::Vec<[i32; 2], FAR_POINTS> = heapless::Vec::new();
        let mut cells_angle = u32::MAX;
        let mut rotations = 0u64;
        while self.next_angle < angles && bnb.evaluated + rotations < budget as u64 {
            let a = self.next_angle;
            if cells_angle != a {
                let theta = local.theta + angle_offset(a) as f64 * step;
                let (ct, st) = (libm::cos(theta) as f32, libm::sin(theta) as f32);
                let (tx, ty) = (local.x as f32, local.y as f32);
                cells.clear();
                for q in self.points.iter() {
                    let g = submap
                        .local_to_cell([tx + ct * q[0] - st * q[1], ty + st * q[0] + ct * q[1]]);
                    // Far or NaN points land far outside (score 0) without overflowing.
                    let clamp = |v: f32| {
                        if v.is_nan() {
                            FAR
                        } else {
                            crate::geom::floor_to_i32(v).clamp(-FAR, FAR)
                        }
                    };
                    let _ = cells.push([clamp(g[0]), clamp(g[1])]);
                }
                cells_angle = a;
                rotations += 1;
            }
            let t = self.next_top as i32;
            let dx = -window + (t % per_row) * span;
            let dy = -window + (t / per_row) * span;
            let b = bnb.score(&cells, top, dx, dy);
            bnb.descend(&cells, a, top, dx, dy, b);
            self.next_top += 1;
            if self.next_top >= tops {
                self.next_top = 0;
                self.next_angle += 1;
            }
        }
        self.best = bnb.best;
        self.best_at = bnb.best_at;
        self.second = bnb.second;
        self.evaluated += bnb.evaluated;
        if self.next_angle < angles {
            return Ok(FarStep::Working);
        }
        self.started = false;
        let Some((a, dx, dy)) = self.best_at else {
            return Ok(FarStep::Done(None));
        };
        // The leaf covers `2^base` cells from its corner: report its middle.
        let mid = 0.5 * ((1u32 << base) as f64 - 1.0);
        let found = Se2::new(
            local.x + (dx as f64 + mid) * res,
            local.y + (dy as f64 + mid) * res,
            crate::geom::wrap_angle(local.theta + angle_offset(a) as f64 * step),
        );
        Ok(FarStep::Done(Some(FarMatch {
            pose: submap.origin().compose(&found),
            score: (self.best as f64 / (255.0 * count as f64)) as f32,
            runner_up: if self.second < threshold {
                0.0
            } else {
                (self.second as f64 / (255.0 * count as f64)) as f32
            },
            angular_step: step,
            cell: coarse,
        })))
    }
}

#[cfg(test)]
mod tests;
