//! Loop-closure scan matching: a global search of a scan against a submap over a window of
//! `(x, y, theta)`, by branch and bound over max-pooled grids.
//!
//! The submap's probabilities are turned into bytes (level 0) and into coarser levels where
//! cell `(ix, iy)` of level `k` holds the maximum of level 0 over the `2^k x 2^k` cells
//! starting at `(ix, iy)`. All levels have the submap's size and live in caller-provided
//! storage ([`Pyramid`]). For every rotation in the window, the scan points are rotated once
//! and discretized; a candidate covering the translations `[dx, dx + 2^k) x [dy, dy + 2^k)`
//! (in cells) is bounded from above by the sum of level `k` at the points' cells shifted by
//! `(dx, dy)`. The search descends depth-first, best child first, and cuts every branch whose
//! bound does not beat the best exact score found so far (initially the score threshold), so
//! the result is the exact maximum of the level-0 score over the whole discretized window.
//!
//! The score is the mean occupancy probability at the scan's points, in `[0, 1]`. The
//! result is accurate to a cell and an angular step; [`icp`](crate::frontend::icp) refines it.

use core::fmt;

use crate::frontend::grid::Submap;
use crate::frontend::scan::{ScanPoint, MAX_POINTS};
use crate::geom::Se2;

/// Cell coordinates are clamped to this magnitude (far beyond any window).
const FAR: i32 = 1 << 24;

/// Most pyramid levels (level 0 included).
pub const MAX_LEVELS: usize = 8;
/// Most rotations tried in one search.
pub const MAX_ANGLES: usize = 1024;

/// Search parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct CsmConfig {
    /// Half-width of the translation window, metres.
    pub window_xy: f64,
    /// Half-width of the rotation window, radians.
    pub window_theta: f64,
    /// Rotation step, radians; `0` derives it from the scan's farthest point so that point
    /// moves by at most one cell per step.
    pub angular_step: f64,
    /// Smallest accepted score, in `[0, 1]`.
    pub min_score: f32,
}

impl Default for CsmConfig {
    fn default() -> Self {
        CsmConfig {
            window_xy: 1.5,
            window_theta: 0.5,
            angular_step: 0.0,
            min_score: 0.55,
        }
    }
}

/// The best pose found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CsmResult {
    /// Pose of the scan in the world.
    pub pose: Se2,
    /// Mean occupancy probability at the scan's points.
    pub score: f32,
    /// Candidates scored at any level (a measure of the work done).
    pub evaluated: u32,
}

/// Search failures.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum CsmError {
    /// The scan has no points.
    EmptyScan,
    /// The pyramid storage does not fit the submap or the level count is out of range.
    WrongStorage,
    /// Window, step or threshold not usable, or a non-finite seed.
    InvalidConfig,
    /// No pose scored at least the threshold.
    NoMatch,
}

impl fmt::Display for CsmError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            CsmError::EmptyScan => "empty scan",
            CsmError::WrongStorage => "pyramid storage does not fit the submap",
            CsmError::InvalidConfig => "invalid search window or seed",
            CsmError::NoMatch => "no pose above the score threshold",
        })
    }
}

impl core::error::Error for CsmError {}

/// Max-pooled levels of a submap in caller storage of `levels * side * side` bytes.
#[derive(Debug)]
pub struct Pyramid<'a> {
    side: usize,
    levels: usize,
    data: &'a mut [u8],
}

impl<'a> Pyramid<'a> {
    /// Bytes of storage needed for `levels` levels of a `side x side` submap.
    pub const fn storage_len(side: usize, levels: usize) -> usize {
        side * side * levels
    }

    /// Computes the levels of `submap` into `storage`.
    ///
    /// # Errors
    /// [`CsmError::WrongStorage`] when `levels` is not in `1..=MAX_LEVELS` or the storage
    /// does not have [`Pyramid::storage_len`] bytes.
    pub fn build(
        submap: &Submap<impl AsRef<[i8]>>,
        levels: usize,
        storage: &'a mut [u8],
    ) -> Result<Self, CsmError> {
        let side = submap.params().side as usize;
        if levels == 0 || levels > MAX_LEVELS || storage.len() != Pyramid::storage_len(side, levels)
        {
            return Err(CsmError::WrongStorage);
        }
        let n = side * side;
        let (base, _) = storage.split_at_mut(n);
        for (i, v) in base.iter_mut().enumerate() {
            let p = submap.cell_probability((i % side) as i32, (i / side) as i32);
            *v = (p * 255.0 + 0.5) as u8;
        }
        for k in 1..levels {
            let h = 1usize << (k - 1);
            let (done, rest) = storage.split_at_mut(k * n);
            let prev = &done[(k - 1) * n..];
            let at = |x: usize, y: usize| -> u8 {
                if x < side && y < side {
                    prev[y * side + x]
                } else {
                    0
                }
            };
            for (i, v) in rest[..n].iter_mut().enumerate() {
                let (x, y) = (i % side, i / side);
                *v = at(x, y)
                    .max(at(x + h, y))
                    .max(at(x, y + h))
                    .max(at(x + h, y + h));
            }
        }
        Ok(Pyramid {
            side,
            levels,
            data: storage,
        })
    }

    /// The levels already in `storage` from an earlier [`Pyramid::build`] of a `side x side`
    /// submap with `levels` levels; the caller knows which submap they belong to.
    ///
    /// # Errors
    /// As [`Pyramid::build`] for the sizes.
    pub fn reuse(side: usize, levels: usize, storage: &'a mut [u8]) -> Result<Self, CsmError> {
        if levels == 0 || levels > MAX_LEVELS || storage.len() != Pyramid::storage_len(side, levels)
        {
            return Err(CsmError::WrongStorage);
        }
        Ok(Pyramid {
            side,
            levels,
            data: storage,
        })
    }

    /// Levels stored.
    pub fn levels(&self) -> usize {
        self.levels
    }

    /// Cells per side of every level.
    pub fn side(&self) -> usize {
        self.side
    }

    /// Value of level `k` for the window starting at `(x, y)`: an upper bound of the cells of
    /// the window inside the submap, 0 when none is.
    #[inline]
    pub(crate) fn bound(&self, k: usize, x: i32, y: i32) -> u32 {
        let w = 1i32 << k;
        let s = self.side as i32;
        if x <= -w || y <= -w || x >= s || y >= s {
            return 0;
        }
        // A window sticking out below 0 is covered by the window starting at 0.
        let (x, y) = (x.max(0) as usize, y.max(0) as usize);
        self.data
            .get(k * self.side * self.side + y * self.side + x)
            .map_or(0, |&v| v as u32)
    }
}

struct Search<'p, 'a> {
    pyramid: &'p Pyramid<'a>,
    window: i32,
    best: u32,
    best_at: Option<(usize, i32, i32)>,
    evaluated: u32,
}

impl Search<'_, '_> {
    fn score(&mut self, cells: &[[i32; 2]], k: usize, dx: i32, dy: i32) -> u32 {
        self.evaluated += 1;
        cells
            .iter()
            .map(|c| self.pyramid.bound(k, c[0] + dx, c[1] + dy))
            .sum()
    }

    fn descend(
        &mut self,
        cells: &[[i32; 2]],
        angle: usize,
        k: usize,
        dx: i32,
        dy: i32,
        bound: u32,
    ) {
        let mut frontier = Frontier::new((bound, k, dx, dy));
        while let Some((bound, k, dx, dy)) = frontier.pop() {
            if bound <= self.best {
                continue;
            }
            if k == 0 {
                self.best = bound;
                self.best_at = Some((angle, dx, dy));
                continue;
            }
            let window = self.window;
            let (children, n) = children(window, k, dx, dy, |k, x, y| self.score(cells, k, x, y));
            frontier.push_children(k - 1, &children[..n]);
        }
    }
}

/// Searches the window around `seed` (world pose of the scan) for the pose where `scan`
/// (robot frame) best fits `submap`.
///
/// # Errors
/// [`CsmError`]: empty scan, mismatched pyramid, bad window, or nothing above the threshold.
pub fn search(
    scan: &[ScanPoint],
    submap: &Submap<impl AsRef<[i8]>>,
    pyramid: &Pyramid<'_>,
    seed: &Se2,
    config: &CsmConfig,
) -> Result<CsmResult, CsmError> {
    if scan.is_empty() {
        return Err(CsmError::EmptyScan);
    }
    let res = submap.params().resolution as f64;
    if pyramid.side != submap.params().side as usize {
        return Err(CsmError::WrongStorage);
    }
    let c = config;
    if !(seed.is_finite()
        && c.window_xy.is_finite()
        && c.window_xy >= 0.0
        && c.window_theta.is_finite()
        && c.window_theta >= 0.0
        && c.angular_step.is_finite()
        && c.angular_step >= 0.0
        && (0.0..=1.0).contains(&c.min_score))
    {
        return Err(CsmError::InvalidConfig);
    }
    // At most MAX_POINTS points, evenly strided.
    let stride = scan.len().div_ceil(MAX_POINTS);
    let points = scan.iter().step_by(stride);
    let count = scan.len().div_ceil(stride);
    let step = if c.angular_step > 0.0 {
        c.angular_step
    } else {
        let far = points
            .clone()
            .map(|q| libm::sqrtf(q.p[0] * q.p[0] + q.p[1] * q.p[1]))
            .fold(0.0f32, f32::max) as f64;
        let far = far.max(3.0 * res);
        libm::acos(1.0 - res * res / (2.0 * far * far))
    };
    let half_angles = libm::ceil(c.window_theta / step) as usize;
    if 2 * half_angles + 1 > MAX_ANGLES {
        return Err(CsmError::InvalidConfig);
    }
    let window = libm::ceil(c.window_xy / res) as i32;
    let local = submap.to_local(seed);
    let top = pyramid.levels - 1;
    let span = 1i32 << top;
    let mut cells: heapless::Vec<[i32; 2], MAX_POINTS> = heapless::Vec::new();
    let threshold = (c.min_score as f64 * 255.0 * count as f64) as u32;
    let mut search = Search {
        pyramid,
        window,
        best: threshold.saturating_sub(1),
        best_at: None,
        evaluated: 0,
    };
    for a in 0..=2 * half_angles {
        let theta = local.theta + (a as f64 - half_angles as f64) * step;
        let (ct, st) = (libm::cos(theta) as f32, libm::sin(theta) as f32);
        let (tx, ty) = (local.x as f32, local.y as f32);
        cells.clear();
        for q in points.clone() {
            let p = [
                tx + ct * q.p[0] - st * q.p[1],
                ty + st * q.p[0] + ct * q.p[1],
            ];
            let g = submap.local_to_cell(p);
            // Cannot overflow: at most MAX_POINTS points.
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
        let mut dy = -window;
        while dy <= window {
            let mut dx = -window;
            while dx <= window {
                let b = search.score(&cells, top, dx, dy);
                search.descend(&cells, a, top, dx, dy, b);
                dx += span;
            }
            dy += span;
        }
    }
    let Some((a, dx, dy)) = search.best_at else {
        return Err(CsmError::NoMatch);
    };
    let best_angle = local.theta + (a as f64 - half_angles as f64) * step;
    let found = Se2::new(
        local.x + dx as f64 * res,
        local.y + dy as f64 * res,
        best_angle,
    );
    Ok(CsmResult {
        pose: submap.origin().compose(&found),
        score: (search.best as f64 / (255.0 * count as f64)) as f32,
        evaluated: search.evaluated,
    })
}

/// The children of the window cell `(dx, dy)` at pyramid level `k` (its four quarters at level
/// `k - 1`) that start inside the search window `window`, scored by `score(level, dx, dy)`,
/// best first: the branching step of the branch and bound here and in
/// [`far_csm`](crate::frontend::far_csm).
pub(crate) fn children(
    window: i32,
    k: usize,
    dx: i32,
    dy: i32,
    mut score: impl FnMut(usize, i32, i32) -> u32,
) -> ([(u32, i32, i32); 4], usize) {
    let h = 1i32 << (k - 1);
    let mut children = [(0u32, 0i32, 0i32); 4];
    let mut n = 0;
    for (ox, oy) in [(0, 0), (h, 0), (0, h), (h, h)] {
        let (cx, cy) = (dx + ox, dy + oy);
        if cx > window || cy > window {
            continue;
        }
        children[n] = (score(k - 1, cx, cy), cx, cy);
        n += 1;
    }
    crate::sort::sort_by_key(&mut children[..n], |c| core::cmp::Reverse(c.0));
    (children, n)
}

/// A candidate of the branch and bound: `(bound, level, dx, dy)`.
pub(crate) type Candidate = (u32, usize, i32, i32);

/// Most candidates waiting in a [`Frontier`]: expanding a candidate of level `k` replaces it by
/// at most four of level `k - 1`, one of which is expanded next, so at most three wait per
/// level below the root, and one at the root's.
const FRONTIER: usize = 3 * MAX_LEVELS + 1;

/// The candidates of a depth-first branch and bound still to visit, in fixed storage, so the
/// descent needs no recursion: the last pushed is visited first.
#[derive(Debug)]
pub(crate) struct Frontier {
    items: heapless::Vec<Candidate, FRONTIER>,
}

impl Frontier {
    /// A frontier holding the root candidate only.
    pub(crate) fn new(root: Candidate) -> Self {
        Frontier {
            items: heapless::Vec::from_array([root]),
        }
    }

    /// The next candidate to visit.
    pub(crate) fn pop(&mut self) -> Option<Candidate> {
        self.items.pop()
    }

    /// Queues the `children` (best first, as [`children`] gives them) of a candidate, at level
    /// `k`, so that the best is visited first. Levels below [`MAX_LEVELS`] never fill the
    /// frontier (see [`FRONTIER`]).
    pub(crate) fn push_children(&mut self, k: usize, children: &[(u32, i32, i32)]) {
        for &(b, x, y) in children.iter().rev() {
            if self.items.push((b, k, x, y)).is_err() {
                return;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frontend::grid::GridParams;
    use crate::frontend::icp::{align, IcpConfig};
    use crate::frontend::pointmap::PointMap;
    use crate::frontend::scan::tests::{room, scan_at};
    use crate::frontend::scan::{preprocess, PreprocessConfig, ScanPoints};

    fn scan(pose: Se2, voxel: f32, out: &mut ScanPoints) {
        let mut ranges = [0.0f32; 720];
        let g = scan_at(pose, 720, &room(), &mut ranges);
        let cfg = PreprocessConfig {
            voxel_size: voxel,
            ..PreprocessConfig::default()
        };
        preprocess(&ranges, &g, &cfg, out).unwrap();
    }

    const SIDE: usize = 120;

    fn params() -> GridParams {
        GridParams {
            side: SIDE as u16,
            ..GridParams::HOME
        }
    }

    #[test]
    fn pyramid_levels_are_window_maxima() {
        let mut cells = [0i8; SIDE * SIDE];
        let mut map = Submap::new(Se2::new(0.5, 0.5, 0.0), params(), &mut cells).unwrap();
        let mut s: ScanPoints = heapless::Vec::new();
        scan(Se2::IDENTITY, 0.0, &mut s);
        map.insert_scan(&Se2::IDENTITY, &Se2::IDENTITY, &s).unwrap();
        let mut storage = [0u8; SIDE * SIDE * 4];
        assert_eq!(
            Pyramid::build(&map, 4, &mut storage[..10]).unwrap_err(),
            CsmError::WrongStorage
        );
        let pyr = Pyramid::build(&map, 4, &mut storage).unwrap();
        for k in 0..4 {
            let w = 1i32 << k;
            for (x, y) in [(0, 0), (17, 33), (100, 5), (119, 119), (-3, 40), (60, -7)] {
                let mut want = 0u32;
                for yy in y..y + w {
                    for xx in x..x + w {
                        if map.cell(xx, yy).is_some() {
                            want = want.max((map.cell_probability(xx, yy) * 255.0 + 0.5) as u32);
                        }
                    }
                }
                let got = pyr.bound(k, x, y);
                // Exact inside; an upper bound where the window sticks out below 0.
                if x >= 0 && y >= 0 {
                    assert_eq!(got, want, "level {k} at ({x}, {y})");
                } else {
                    assert!(got >= want);
                }
            }
        }
    }

    #[test]
    fn finds_a_one_metre_twenty_degree_offset_and_icp_refines_it() {
        let mut cells = [0i8; SIDE * SIDE];
        let mut map = Submap::new(Se2::new(0.5, 0.5, 0.0), params(), &mut cells).unwrap();
        let mut pm = PointMap::<2048>::new(0.05);
        let mut s: ScanPoints = heapless::Vec::new();
        for pose in [
            Se2::IDENTITY,
            Se2::new(-0.5, 0.8, -0.3),
            Se2::new(2.0, -0.7, 1.0),
        ] {
            scan(pose, 0.0, &mut s);
            map.insert_scan(&pose, &Se2::IDENTITY, &s).unwrap();
            pm.insert(&pose, &s, 30.0);
        }
        let mut storage = [0u8; SIDE * SIDE * 5];
        let pyr = Pyramid::build(&map, 5, &mut storage).unwrap();
        let truth = Se2::new(0.9, 0.1, 2.5);
        let mut query: ScanPoints = heapless::Vec::new();
        scan(truth, 0.05, &mut query);
        let seed = truth.compose(&Se2::new(0.8, -0.6, 20f64.to_radians()));
        let cfg = CsmConfig {
            window_xy: 1.2,
            window_theta: 25f64.to_radians(),
            ..CsmConfig::default()
        };
        let r = search(&query, &map, &pyr, &seed, &cfg).unwrap();
        let d = r.pose.between(&truth);
        assert!(
            libm::sqrt(d.x * d.x + d.y * d.y) < 0.06 && libm::fabs(d.theta) < 0.02,
            "{r:?}"
        );
        assert!(r.score > 0.7, "{r:?}");
        // ICP against the submap's points takes it to the truth.
        let tree = pm.tree();
        let fine = align(&query, &tree, &r.pose, &IcpConfig::default()).unwrap();
        let d = fine.pose.between(&truth);
        assert!(libm::sqrt(d.x * d.x + d.y * d.y) < 0.01 && libm::fabs(d.theta) < 0.0035);
        // A threshold above the best score: no match.
        let strict = CsmConfig {
            min_score: 0.999,
            ..cfg
        };
        assert_eq!(
            search(&query, &map, &pyr, &seed, &strict),
            Err(CsmError::NoMatch)
        );
        assert_eq!(
            search(&[], &map, &pyr, &seed, &cfg),
            Err(CsmError::EmptyScan)
        );
    }

    #[test]
    fn branch_and_bound_equals_exhaustive_search() {
        let mut cells = [0i8; SIDE * SIDE];
        let mut map = Submap::new(Se2::new(0.5, 0.5, 0.0), params(), &mut cells).unwrap();
        let mut s: ScanPoints = heapless::Vec::new();
        scan(Se2::IDENTITY, 0.0, &mut s);
        map.insert_scan(&Se2::IDENTITY, &Se2::IDENTITY, &s).unwrap();
        let mut q: ScanPoints = heapless::Vec::new();
        scan(Se2::new(0.1, 0.05, 0.03), 0.1, &mut q);
        let cfg = CsmConfig {
            window_xy: 0.3,
            window_theta: 0.05,
            angular_step: 0.01,
            min_score: 0.0,
        };
        let seed = Se2::new(0.0, 0.1, 0.0);
        let mut st1 = [0u8; SIDE * SIDE];
        let flat = Pyramid::build(&map, 1, &mut st1).unwrap();
        let mut st4 = [0u8; SIDE * SIDE * 4];
        let deep = Pyramid::build(&map, 4, &mut st4).unwrap();
        let a = search(&q, &map, &flat, &seed, &cfg).unwrap();
        let b = search(&q, &map, &deep, &seed, &cfg).unwrap();
        assert_eq!(a.score, b.score);
        assert!(b.evaluated < a.evaluated, "{a:?} {b:?}");
    }
}
