//! Fixed-size occupancy-grid submaps.
//!
//! A submap is a square of `side x side` cells of `resolution` metres (82 x 82 at 5 cm for the
//! 4.1 m `home` submaps, 200 x 200 for the 10 m `large` ones) centred on its **origin pose** in
//! the world. Cells hold log-odds in `i8` units of [`LOG_ODDS_UNIT`] nats, clamped to
//! `[min, max]`; 0 is "unknown" (probability one half). The cells are a borrowed slice, so the
//! caller decides where they live (a pool of submaps in the mapper's resources, a local array
//! in a test).
//!
//! Cell `(ix, iy)` covers local `x` in `[-side*res/2 + ix*res, -side*res/2 + (ix+1)*res)` and
//! the same in `y`; the slice is row-major, `iy * side + ix`.
//!
//! Inserting a scan ray-traces (Bresenham) every beam from the sensor to its end point: the
//! cells it passes get a *miss* update and, after all rays, the end cells get a *hit* update, so
//! a wall cell grazed by a neighbouring ray still ends up occupied.

use core::fmt;

use crate::frontend::scan::{fit_normal, ScanPoint};
use crate::geom::{floor_to_i32, Se2};

/// Points (and sensor positions) farther than this many cells from the submap are ignored
/// (NaN included), so cell arithmetic never overflows.
const FAR_CELLS: f32 = 1.0e6;

/// Natural log-odds per integer unit stored in a cell.
pub const LOG_ODDS_UNIT: f32 = 0.1;

/// Submap parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct GridParams {
    /// Cells per side.
    pub side: u16,
    /// Cell edge, metres.
    pub resolution: f32,
    /// Log-odds units added to an end cell (positive).
    pub hit: i8,
    /// Log-odds units added to a traversed cell (negative).
    pub miss: i8,
    /// Lower clamp (negative).
    pub min: i8,
    /// Upper clamp (positive).
    pub max: i8,
}

impl GridParams {
    /// 4.1 m x 4.1 m at 5 cm: the paper's in-home submap.
    pub const HOME: GridParams = GridParams {
        side: 82,
        resolution: 0.05,
        hit: 9,
        miss: -4,
        min: -50,
        max: 50,
    };
    /// 10 m x 10 m at 5 cm: the paper's submap for large spaces.
    pub const LARGE: GridParams = GridParams {
        side: 200,
        ..GridParams::HOME
    };

    /// Number of cells.
    pub const fn cells(&self) -> usize {
        self.side as usize * self.side as usize
    }
}

/// Grid errors.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum GridError {
    /// The cell slice does not hold `side * side` cells.
    WrongStorage {
        /// Cells needed.
        needed: usize,
        /// Cells given.
        given: usize,
    },
    /// Resolution not positive and finite, zero side, or clamps/updates of the wrong sign.
    InvalidParams,
    /// The insertion pose is not finite, or absurdly far (over a million cells) from the
    /// submap.
    InvalidPose,
}

impl fmt::Display for GridError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            GridError::WrongStorage { needed, given } => {
                write!(f, "grid storage holds {given} cells, {needed} needed")
            }
            GridError::InvalidParams => f.write_str("invalid grid parameters"),
            GridError::InvalidPose => f.write_str("non-finite or far insertion pose"),
        }
    }
}

impl core::error::Error for GridError {}

/// Probability of a stored log-odds value.
#[inline]
pub fn probability(l: i8) -> f32 {
    1.0 / (1.0 + libm::expf(-(l as f32) * LOG_ODDS_UNIT))
}

/// Counts of one scan insertion.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct InsertStats {
    /// Hit updates applied.
    pub hits: u32,
    /// Miss updates applied.
    pub misses: u32,
    /// End points outside the submap.
    pub outside: u32,
}

/// An occupancy-grid submap over cells of any storage `S`: a borrowed slice (`&mut [i8]` to
/// update, `&[i8]` to read), or an owned array `[i8; N]` at the edge.
#[derive(Debug, Clone)]
pub struct Submap<S> {
    origin: Se2,
    params: GridParams,
    cells: S,
    /// Probability of every log-odds value, indexed by `l + 128`.
    table: [f32; 256],
}

fn check_params(origin: &Se2, p: &GridParams, len: usize) -> Result<(), GridError> {
    if !(p.resolution.is_finite()
        && p.resolution > 0.0
        && p.side > 0
        && p.hit > 0
        && p.miss < 0
        && p.min < 0
        && p.max > 0
        && origin.is_finite())
    {
        return Err(GridError::InvalidParams);
    }
    if len != p.cells() {
        return Err(GridError::WrongStorage {
            needed: p.cells(),
            given: len,
        });
    }
    Ok(())
}

impl<S: AsRef<[i8]> + AsMut<[i8]>> Submap<S> {
    /// A submap of unknown cells centred on `origin` (world frame); `cells` is cleared.
    ///
    /// # Errors
    /// [`GridError::WrongStorage`] when `cells` does not hold `side * side` cells,
    /// [`GridError::InvalidParams`] for bad parameters or a non-finite origin.
    pub fn new(origin: Se2, params: GridParams, mut cells: S) -> Result<Self, GridError> {
        check_params(&origin, &params, cells.as_ref().len())?;
        cells.as_mut().fill(0);
        Submap::from_cells(origin, params, cells)
    }

    fn update(&mut self, ix: i32, iy: i32, delta: i8) -> bool {
        let s = self.params.side as i32;
        if ix < 0 || iy < 0 || ix >= s || iy >= s {
            return false;
        }
        let (lo, hi) = (self.params.min, self.params.max);
        match self.cells.as_mut().get_mut((iy * s + ix) as usize) {
            Some(c) => {
                *c = c.saturating_add(delta).clamp(lo, hi);
                true
            }
            None => false,
        }
    }

    /// Inserts a scan taken at `robot_pose` (world) by a sensor at `sensor` in the robot frame;
    /// `points` are in the robot frame.
    ///
    /// # Errors
    /// [`GridError::InvalidPose`] for a non-finite pose.
    pub fn insert_scan(
        &mut self,
        robot_pose: &Se2,
        sensor: &Se2,
        points: &[ScanPoint],
    ) -> Result<InsertStats, GridError> {
        if !robot_pose.is_finite() || !sensor.is_finite() {
            return Err(GridError::InvalidPose);
        }
        let local = self.to_local(robot_pose);
        let (c, s) = (libm::cos(local.theta) as f32, libm::sin(local.theta) as f32);
        let (tx, ty) = (local.x as f32, local.y as f32);
        let to_local = |p: [f32; 2]| [tx + c * p[0] - s * p[1], ty + s * p[0] + c * p[1]];
        let start = self.local_to_cell(to_local([sensor.x as f32, sensor.y as f32]));
        if !(libm::fabsf(start[0]) < FAR_CELLS && libm::fabsf(start[1]) < FAR_CELLS) {
            return Err(GridError::InvalidPose);
        }
        let (sx, sy) = (floor_to_i32(start[0]), floor_to_i32(start[1]));
        let mut stats = InsertStats::default();
        // Longest ray walked: a diagonal of the grid plus the start's distance to it.
        let side = self.params.side as i32;
        let limit = 2 * side + sx.abs().max(sy.abs()) * 2 + 4;
        let miss = self.params.miss;
        for q in points {
            let e = self.local_to_cell(to_local(q.p));
            if !(libm::fabsf(e[0]) < FAR_CELLS && libm::fabsf(e[1]) < FAR_CELLS) {
                continue;
            }
            let (ex, ey) = (floor_to_i32(e[0]), floor_to_i32(e[1]));
            // Bresenham from the start cell, excluding the end cell.
            let (dx, dy) = ((ex - sx).abs(), -(ey - sy).abs());
            let (stx, sty) = (if sx < ex { 1 } else { -1 }, if sy < ey { 1 } else { -1 });
            let (mut x, mut y, mut err) = (sx, sy, dx + dy);
            let mut steps = 0;
            while (x != ex || y != ey) && steps < limit {
                if self.update(x, y, miss) {
                    stats.misses += 1;
                } else if (x < 0 && stx < 0)
                    || (y < 0 && sty < 0)
                    || (x >= side && stx > 0)
                    || (y >= side && sty > 0)
                {
                    // Left the grid and moving away: the rest is outside too.
                    break;
                }
                let e2 = 2 * err;
                if e2 >= dy {
                    err += dy;
                    x += stx;
                }
                if e2 <= dx {
                    err += dx;
                    y += sty;
                }
                steps += 1;
            }
        }
        let hit = self.params.hit;
        for q in points {
            let e = self.local_to_cell(to_local(q.p));
            if !(libm::fabsf(e[0]) < FAR_CELLS && libm::fabsf(e[1]) < FAR_CELLS) {
                stats.outside += 1;
                continue;
            }
            if self.update(floor_to_i32(e[0]), floor_to_i32(e[1]), hit) {
                stats.hits += 1;
            } else {
                stats.outside += 1;
            }
        }
        Ok(stats)
    }
}

impl<S: AsRef<[i8]>> Submap<S> {
    /// A submap over existing cells (e.g. one kept in a pool, or a read-only `&[i8]`).
    ///
    /// # Errors
    /// As [`Submap::new`].
    pub fn from_cells(origin: Se2, params: GridParams, cells: S) -> Result<Self, GridError> {
        check_params(&origin, &params, cells.as_ref().len())?;
        let mut table = [0.0f32; 256];
        for (i, t) in table.iter_mut().enumerate() {
            *t = probability((i as i32 - 128) as i8);
        }
        Ok(Submap {
            origin,
            params,
            cells,
            table,
        })
    }

    /// Gives the storage back.
    pub fn into_cells(self) -> S {
        self.cells
    }

    /// Origin pose in the world.
    pub fn origin(&self) -> Se2 {
        self.origin
    }

    /// Moves the submap (e.g. to its optimized pose); the cells are unchanged.
    pub fn set_origin(&mut self, origin: Se2) {
        self.origin = origin;
    }

    /// Parameters.
    pub fn params(&self) -> &GridParams {
        &self.params
    }

    /// The cells, row-major (`iy * side + ix`), for map assembly.
    pub fn cells(&self) -> &[i8] {
        self.cells.as_ref()
    }

    /// Log-odds of a cell, `None` outside.
    pub fn cell(&self, ix: i32, iy: i32) -> Option<i8> {
        let s = self.params.side as i32;
        if ix < 0 || iy < 0 || ix >= s || iy >= s {
            return None;
        }
        self.cells.as_ref().get((iy * s + ix) as usize).copied()
    }

    /// Probability of a cell; one half outside the submap.
    #[inline]
    pub fn cell_probability(&self, ix: i32, iy: i32) -> f32 {
        match self.cell(ix, iy) {
            Some(l) => self.table[(l as i32 + 128) as usize],
            None => 0.5,
        }
    }

    /// Half the submap's edge, metres.
    #[inline]
    fn half(&self) -> f32 {
        0.5 * self.params.side as f32 * self.params.resolution
    }

    /// Continuous cell coordinates of a point in the submap frame (cell `i` spans `[i, i+1)`).
    #[inline]
    pub fn local_to_cell(&self, p: [f32; 2]) -> [f32; 2] {
        let inv = 1.0 / self.params.resolution;
        [(p[0] + self.half()) * inv, (p[1] + self.half()) * inv]
    }

    /// Centre of a cell in the submap frame.
    #[inline]
    pub fn cell_centre(&self, ix: i32, iy: i32) -> [f32; 2] {
        let r = self.params.resolution;
        [
            (ix as f32 + 0.5) * r - self.half(),
            (iy as f32 + 0.5) * r - self.half(),
        ]
    }

    /// The pose `world_pose` expressed in the submap frame.
    pub fn to_local(&self, world_pose: &Se2) -> Se2 {
        self.origin.between(world_pose)
    }

    /// Bilinearly interpolated probability at a point of the submap frame, and its gradient
    /// (per metre, submap frame). Cell values sit at cell centres; outside is one half.
    pub fn interpolate_local(&self, p: [f32; 2]) -> (f32, [f32; 2]) {
        let c = self.local_to_cell(p);
        let (fx, fy) = (c[0] - 0.5, c[1] - 0.5);
        let (x0, y0) = (libm::floorf(fx), libm::floorf(fy));
        let (ax, ay) = (fx - x0, fy - y0);
        let (ix, iy) = (x0 as i32, y0 as i32);
        let p00 = self.cell_probability(ix, iy);
        let p10 = self.cell_probability(ix + 1, iy);
        let p01 = self.cell_probability(ix, iy + 1);
        let p11 = self.cell_probability(ix + 1, iy + 1);
        let bottom = p00 + ax * (p10 - p00);
        let top = p01 + ax * (p11 - p01);
        let value = bottom + ay * (top - bottom);
        let inv = 1.0 / self.params.resolution;
        let gx = ((1.0 - ay) * (p10 - p00) + ay * (p11 - p01)) * inv;
        let gy = (top - bottom) * inv;
        (value, [gx, gy])
    }

    /// [`Submap::interpolate_local`] at a world point, gradient in the world frame.
    pub fn interpolate_world(&self, p: [f64; 2]) -> (f32, [f32; 2]) {
        let o = &self.origin;
        let (c, s) = (libm::cos(o.theta), libm::sin(o.theta));
        let (dx, dy) = (p[0] - o.x, p[1] - o.y);
        let local = [(c * dx + s * dy) as f32, (-s * dx + c * dy) as f32];
        let (v, g) = self.interpolate_local(local);
        let (cf, sf) = (c as f32, s as f32);
        (v, [cf * g[0] - sf * g[1], sf * g[0] + cf * g[1]])
    }

    /// Occupied cells (log-odds at least `min_log_odds`) as points in the **world** frame with
    /// normals fitted to the occupied cells within `normal_radius` cells; written to `out`,
    /// returns how many were written (stops when `out` is full). These are the reference points
    /// of scan-to-submap ICP.
    pub fn occupied_points(
        &self,
        min_log_odds: i8,
        normal_radius: u8,
        out: &mut [ScanPoint],
    ) -> usize {
        let side = self.params.side as i32;
        let r = normal_radius as i32;
        let o = &self.origin;
        let (c, s) = (libm::cos(o.theta) as f32, libm::sin(o.theta) as f32);
        let (ox, oy) = (o.x as f32, o.y as f32);
        let occupied = |x: i32, y: i32| self.cell(x, y).is_some_and(|l| l >= min_log_odds);
        let mut n = 0;
        for iy in 0..side {
            for ix in 0..side {
                if !occupied(ix, iy) {
                    continue;
                }
                let Some(slot) = out.get_mut(n) else {
                    return n;
                };
                let near = (-r..=r)
                    .flat_map(move |dy| (-r..=r).map(move |dx| (ix + dx, iy + dy)))
                    .filter(|&(x, y)| occupied(x, y))
                    .map(|(x, y)| self.cell_centre(x, y));
                let normal = match fit_normal(near) {
                    Some((nv, flat)) if flat < 0.2 => nv,
                    _ => [0.0, 0.0],
                };
                let p = self.cell_centre(ix, iy);
                *slot = ScanPoint {
                    p: [ox + c * p[0] - s * p[1], oy + s * p[0] + c * p[1]],
                    n: [c * normal[0] - s * normal[1], s * normal[0] + c * normal[1]],
                };
                n += 1;
            }
        }
        n
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pt(x: f32, y: f32) -> ScanPoint {
        ScanPoint {
            p: [x, y],
            n: [0.0, 0.0],
        }
    }

    proptest::proptest! {
        #[test]
        fn cells_stay_within_the_clamps(
            scans in proptest::collection::vec(
                (
                    (-3.0f64..3.0, -3.0f64..3.0, -4.0f64..4.0),
                    proptest::collection::vec((-6.0f32..6.0, -6.0f32..6.0), 0..40),
                ),
                1..6,
            ),
        ) {
            let params = GridParams { side: 40, ..GridParams::HOME };
            let mut cells = [0i8; 40 * 40];
            let mut m = Submap::new(Se2::new(0.1, -0.2, 0.3), params, &mut cells[..]).unwrap();
            for ((x, y, t), pts) in &scans {
                let pts: heapless::Vec<ScanPoint, 40> = pts.iter().map(|p| pt(p.0, p.1)).collect();
                let s = m.insert_scan(&Se2::new(*x, *y, *t), &Se2::IDENTITY, &pts).unwrap();
                proptest::prop_assert_eq!((s.hits + s.outside) as usize, pts.len());
            }
            for &c in m.cells() {
                proptest::prop_assert!((params.min..=params.max).contains(&c));
            }
        }
    }

    #[test]
    fn storage_and_params_are_checked() {
        let mut small = [0i8; 10];
        assert_eq!(
            Submap::new(Se2::IDENTITY, GridParams::HOME, &mut small).unwrap_err(),
            GridError::WrongStorage {
                needed: 82 * 82,
                given: 10
            }
        );
        let mut cells = [0i8; 82 * 82];
        let bad = GridParams {
            resolution: f32::NAN,
            ..GridParams::HOME
        };
        assert_eq!(
            Submap::new(Se2::IDENTITY, bad, &mut cells).unwrap_err(),
            GridError::InvalidParams
        );
    }

    #[test]
    fn hit_and_free_updates_with_clamping() {
        let mut cells = [0i8; 82 * 82];
        let mut m = Submap::new(Se2::IDENTITY, GridParams::HOME, &mut cells).unwrap();
        // Sensor at the submap centre, one beam 1 m along +x.
        let stats = m
            .insert_scan(&Se2::IDENTITY, &Se2::IDENTITY, &[pt(1.0 + 0.025, 0.01)])
            .unwrap();
        assert_eq!(stats.hits, 1);
        // Cells 41..61 along x at row 41 are free; cell 61 is the hit.
        assert_eq!(stats.misses, 20);
        assert_eq!(m.cell(61, 41), Some(9));
        for ix in 41..61 {
            assert_eq!(m.cell(ix, 41), Some(-4), "cell {ix}");
        }
        assert_eq!(m.cell(40, 41), Some(0));
        assert_eq!(m.cell(62, 41), Some(0));
        // Repeated insertions saturate at the clamps.
        for _ in 0..40 {
            m.insert_scan(&Se2::IDENTITY, &Se2::IDENTITY, &[pt(1.025, 0.01)])
                .unwrap();
        }
        assert_eq!(m.cell(61, 41), Some(50));
        assert_eq!(m.cell(50, 41), Some(-50));
        assert!(m.cell_probability(61, 41) > 0.99);
        assert!(m.cell_probability(50, 41) < 0.01);
        assert_eq!(m.cell_probability(-1, 0), 0.5);
        // A point outside the submap: misses up to the border, no hit.
        let s = m
            .insert_scan(&Se2::IDENTITY, &Se2::IDENTITY, &[pt(0.01, -30.0)])
            .unwrap();
        assert_eq!((s.hits, s.outside, s.misses), (0, 1, 42));
        assert_eq!(
            m.insert_scan(&Se2::new(f64::NAN, 0.0, 0.0), &Se2::IDENTITY, &[]),
            Err(GridError::InvalidPose)
        );
        assert_eq!(
            m.insert_scan(&Se2::new(1e12, 0.0, 0.0), &Se2::IDENTITY, &[]),
            Err(GridError::InvalidPose)
        );
        // Absurd points are counted outside, never traced.
        let s = m
            .insert_scan(
                &Se2::IDENTITY,
                &Se2::IDENTITY,
                &[pt(f32::MAX, 1.0), pt(f32::NAN, 0.0)],
            )
            .unwrap();
        assert_eq!((s.hits, s.misses, s.outside), (0, 0, 2));
    }

    #[test]
    fn origin_pose_and_world_points() {
        let mut cells = [0i8; 82 * 82];
        let origin = Se2::new(10.0, 5.0, core::f64::consts::FRAC_PI_2);
        let mut m = Submap::new(origin, GridParams::HOME, &mut cells).unwrap();
        // Robot at the origin facing +y (world); a point 1 m ahead is world (10, 6).
        m.insert_scan(&origin, &Se2::IDENTITY, &[pt(1.0, 0.0)])
            .unwrap();
        let mut out = [ScanPoint::default(); 4];
        let n = m.occupied_points(5, 2, &mut out);
        assert_eq!(n, 1);
        assert!((out[0].p[0] - 10.0).abs() < 0.05 && (out[0].p[1] - 6.0).abs() < 0.05);
        let (v, _) = m.interpolate_world([out[0].p[0] as f64, out[0].p[1] as f64]);
        assert!((v - probability(9)).abs() < 1e-5);
    }

    #[test]
    fn interpolation_and_gradient() {
        let mut cells = [0i8; 82 * 82];
        let mut m = Submap::new(Se2::IDENTITY, GridParams::HOME, &mut cells).unwrap();
        // Make cell (50, 41) occupied and (51, 41) free by direct updates.
        for _ in 0..3 {
            m.update(50, 41, 9);
            m.update(51, 41, -4);
        }
        let c0 = m.cell_centre(50, 41);
        let c1 = m.cell_centre(51, 41);
        let (p0, p1) = (probability(27), probability(-12));
        let (v, g) = m.interpolate_local(c0);
        assert!((v - p0).abs() < 1e-6);
        // Halfway: the mean; gradient along x is the slope.
        let mid = [0.5 * (c0[0] + c1[0]), c0[1]];
        let (v, g2) = m.interpolate_local(mid);
        assert!((v - 0.5 * (p0 + p1)).abs() < 1e-5);
        assert!((g2[0] - (p1 - p0) / 0.05).abs() < 1e-3, "{g2:?}");
        let _ = g;
        // Numeric gradient check at a generic point.
        let q = [c0[0] + 0.013, c0[1] + 0.021];
        let (_, g) = m.interpolate_local(q);
        let h = 1e-3;
        let num_x = (m.interpolate_local([q[0] + h, q[1]]).0
            - m.interpolate_local([q[0] - h, q[1]]).0)
            / (2.0 * h);
        let num_y = (m.interpolate_local([q[0], q[1] + h]).0
            - m.interpolate_local([q[0], q[1] - h]).0)
            / (2.0 * h);
        assert!((g[0] - num_x).abs() < 0.05 && (g[1] - num_y).abs() < 0.05);
    }
}
