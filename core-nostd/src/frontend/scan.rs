//! Scan preprocessing: from raw ranges to a fixed-capacity set of points with normals.
//!
//! Steps, in order:
//! 1. every beam is checked: NaN, infinite, below `range_min` or above `range_max` beams are
//!    dropped and counted in [`ScanStats`] (never an error);
//! 2. optional angular decimation keeps one beam in `decimation`;
//! 3. the kept beams become points in the **robot** frame through the sensor mounting offset;
//! 4. each point gets a normal from a line fitted (2x2 principal axes) to its angular
//!    neighbours that lie close to it; points on no clear line get a zero normal;
//! 5. optional voxel-grid downsampling: points are sorted in place by voxel key and every
//!    voxel is replaced by the centroid of its points (and the mean of their normals). No
//!    scratch memory is needed; the angular order is lost, which nothing later depends on.
//!
//! The beam geometry is the front-end's own small struct ([`BeamGeometry`]); the sensor's
//! mounting on the robot comes with the preprocessing parameters.

use core::fmt;

use crate::geom::Se2;

/// Largest number of points a scan keeps: one per beam of the largest scan the sensor layer
/// accepts ([`crate::sensor::MAX_BEAMS`]).
pub const MAX_POINTS: usize = crate::sensor::MAX_BEAMS;

/// One preprocessed point: position and unit normal in the robot frame (normal `[0, 0]` when
/// none could be estimated).
#[derive(Clone, Copy, Debug, PartialEq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ScanPoint {
    /// Position, metres.
    pub p: [f32; 2],
    /// Unit normal, or `[0, 0]`.
    pub n: [f32; 2],
}

impl ScanPoint {
    /// True when the point carries a normal.
    #[inline]
    pub fn has_normal(&self) -> bool {
        self.n[0] != 0.0 || self.n[1] != 0.0
    }
}

/// A preprocessed scan of at most `N` points.
pub type ScanPoints<const N: usize = MAX_POINTS> = heapless::Vec<ScanPoint, N>;

/// Longest sweep (first beam to last) taken as real, seconds: twice the period of the slowest
/// common planar LiDAR (1 Hz).
pub const MAX_SWEEP_SECONDS: f64 = 2.0;

/// Beam geometry of a planar range scanner.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct BeamGeometry {
    /// Angle of the first beam in the sensor frame, radians.
    pub angle_min: f32,
    /// Angle between consecutive beams, radians (may be negative).
    pub angle_increment: f32,
    /// Shortest valid range, metres.
    pub range_min: f32,
    /// Longest valid range, metres.
    pub range_max: f32,
    /// Time between consecutive beams, seconds; beam `i` is measured at the scan's stamp plus
    /// `i` times this (the stamp is the first beam's time, as in a ROS `LaserScan`). Zero when
    /// the beams carry no time: the scan is then taken as measured at once.
    pub time_increment: f32,
}

impl BeamGeometry {
    /// Time from the first beam to the last of a scan of `beams` beams, seconds; zero when
    /// the beams carry no usable time: a zero, negative or non-finite `time_increment`, or a
    /// sweep longer than [`MAX_SWEEP_SECONDS`] (no planar LiDAR turns that slowly; such a
    /// value is a unit error, and waiting for odometry to cover it would stall the input).
    pub fn sweep_seconds(&self, beams: usize) -> f64 {
        let dt = self.time_increment as f64;
        let sweep = dt * beams.saturating_sub(1) as f64;
        if dt.is_finite() && dt > 0.0 && sweep <= MAX_SWEEP_SECONDS {
            sweep
        } else {
            0.0
        }
    }
}

/// Preprocessing parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct PreprocessConfig {
    /// Pose of the sensor in the robot frame.
    pub mounting: Se2,
    /// Motion of the robot from the first beam's time to the last beam's, in the robot frame
    /// at the first beam (the identity when the beams carry no time or the robot stood). Each
    /// beam is moved back along it, at constant velocity, to where the robot was at the first
    /// beam: a scan taken while the robot moves is otherwise bent by the motion during its
    /// sweep, most visibly in turns.
    pub sweep: Se2,
    /// Keep one beam in `decimation` (1 keeps every beam; 0 is treated as 1).
    pub decimation: u16,
    /// Voxel edge for downsampling, metres; `0` disables it.
    pub voxel_size: f32,
    /// Angular neighbours on each side used for a normal.
    pub normal_neighbours: u8,
    /// Neighbours farther than this from the point are not used for its normal, metres.
    pub normal_max_distance: f32,
    /// A normal is kept only when the line fit is this flat: smallest over largest
    /// eigenvalue of the neighbours' scatter.
    pub normal_max_flatness: f32,
}

impl Default for PreprocessConfig {
    fn default() -> Self {
        PreprocessConfig {
            mounting: Se2::IDENTITY,
            sweep: Se2::IDENTITY,
            decimation: 1,
            voxel_size: 0.0,
            normal_neighbours: 3,
            normal_max_distance: 0.25,
            normal_max_flatness: 0.1,
        }
    }
}

/// What preprocessing dropped and kept.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ScanStats {
    /// Beams in the input.
    pub beams: u32,
    /// NaN ranges.
    pub nan: u32,
    /// Infinite ranges.
    pub infinite: u32,
    /// Ranges below `range_min` (including negative ones).
    pub too_short: u32,
    /// Ranges above `range_max`.
    pub too_long: u32,
    /// Valid beams skipped by angular decimation.
    pub decimated: u32,
    /// Valid beams dropped because the point set was full.
    pub overflow: u32,
    /// Points merged away by voxel downsampling.
    pub voxel_merged: u32,
    /// Points left.
    pub points: u32,
    /// Points left with a normal.
    pub with_normal: u32,
}

/// Scan preprocessing errors (bad beams are counted, not errors).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ScanError {
    /// The beam geometry is not finite, `range_min` is negative or above `range_max`, or
    /// the mounting pose is not finite.
    InvalidGeometry,
}

impl fmt::Display for ScanError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ScanError::InvalidGeometry => f.write_str("invalid scan geometry or mounting pose"),
        }
    }
}

impl core::error::Error for ScanError {}

/// Preprocesses one scan into `out` (cleared first) and returns the counts.
///
/// # Errors
/// [`ScanError::InvalidGeometry`] for a geometry that cannot describe a scan.
pub fn preprocess<const N: usize>(
    ranges: &[f32],
    geometry: &BeamGeometry,
    config: &PreprocessConfig,
    out: &mut ScanPoints<N>,
) -> Result<ScanStats, ScanError> {
    out.clear();
    let g = geometry;
    if !(g.angle_min.is_finite()
        && g.angle_increment.is_finite()
        && g.range_min.is_finite()
        && g.range_max.is_finite()
        && g.range_min >= 0.0
        && g.range_min <= g.range_max
        && config.mounting.is_finite()
        && config.sweep.is_finite())
    {
        return Err(ScanError::InvalidGeometry);
    }
    let mut stats = ScanStats {
        beams: ranges.len() as u32,
        ..ScanStats::default()
    };
    let decimation = config.decimation.max(1) as u32;
    let (ms, mc) = (
        libm::sin(config.mounting.theta) as f32,
        libm::cos(config.mounting.theta) as f32,
    );
    let (mx, my) = (config.mounting.x as f32, config.mounting.y as f32);
    let deskew = Deskew::new(&config.sweep, ranges.len());
    let mut valid = 0u32;
    for (i, &r) in ranges.iter().enumerate() {
        if r.is_nan() {
            stats.nan += 1;
            continue;
        }
        if r.is_infinite() {
            stats.infinite += 1;
            continue;
        }
        if r < g.range_min {
            stats.too_short += 1;
            continue;
        }
        if r > g.range_max {
            stats.too_long += 1;
            continue;
        }
        valid += 1;
        if !(valid - 1).is_multiple_of(decimation) {
            stats.decimated += 1;
            continue;
        }
        let a = g.angle_min + g.angle_increment * i as f32;
        let (sx, sy) = (r * libm::cosf(a), r * libm::sinf(a));
        let p = deskew.apply(i, [mx + mc * sx - ms * sy, my + ms * sx + mc * sy]);
        if out.push(ScanPoint { p, n: [0.0, 0.0] }).is_err() {
            stats.overflow += 1;
        }
    }
    estimate_normals(out, [mx, my], config);
    if config.voxel_size > 0.0 && config.voxel_size.is_finite() {
        stats.voxel_merged = voxel_downsample(out, config.voxel_size) as u32;
    }
    stats.points = out.len() as u32;
    stats.with_normal = out.iter().filter(|p| p.has_normal()).count() as u32;
    Ok(stats)
}

/// The motion correction of the beams of one scan: beam `i` of `n` was measured when the robot
/// had moved by the fraction `i / (n - 1)` of the sweep's motion, at constant velocity (the
/// motion over one sweep, a tenth to a fifth of a second, is short enough for that).
struct Deskew {
    /// Per-beam translation and rotation, or `None` when there is nothing to correct.
    step: Option<([f64; 2], f64)>,
}

impl Deskew {
    fn new(sweep: &Se2, beams: usize) -> Self {
        let moved = sweep.x != 0.0 || sweep.y != 0.0 || sweep.theta != 0.0;
        let step = (moved && beams > 1).then(|| {
            let k = 1.0 / (beams - 1) as f64;
            ([sweep.x * k, sweep.y * k], sweep.theta * k)
        });
        Deskew { step }
    }

    /// Point `p` of beam `i` (robot frame at the beam's time) in the robot frame at the first
    /// beam.
    fn apply(&self, i: usize, p: [f32; 2]) -> [f32; 2] {
        let Some(([dx, dy], dth)) = self.step else {
            return p;
        };
        let f = i as f64;
        let (s, c) = (libm::sin(dth * f), libm::cos(dth * f));
        let (x, y) = (p[0] as f64, p[1] as f64);
        [
            (dx * f + c * x - s * y) as f32,
            (dy * f + s * x + c * y) as f32,
        ]
    }
}

/// Unit normal of the best line through `pts` (principal axis of least spread), with the
/// ratio of the smallest to the largest scatter eigenvalue. `None` for fewer than 3 points.
pub fn fit_normal(pts: impl Iterator<Item = [f32; 2]> + Clone) -> Option<([f32; 2], f32)> {
    let (mut n, mut sx, mut sy) = (0u32, 0.0f32, 0.0f32);
    for p in pts.clone() {
        n += 1;
        sx += p[0];
        sy += p[1];
    }
    if n < 3 {
        return None;
    }
    let (cx, cy) = (sx / n as f32, sy / n as f32);
    let (mut a, mut b, mut c) = (0.0f32, 0.0f32, 0.0f32);
    for p in pts {
        let (dx, dy) = (p[0] - cx, p[1] - cy);
        a += dx * dx;
        b += dx * dy;
        c += dy * dy;
    }
    // Eigenvalues of [[a, b], [b, c]].
    let half_tr = 0.5 * (a + c);
    let disc = libm::sqrtf(0.25 * (a - c) * (a - c) + b * b);
    let (l_max, l_min) = (half_tr + disc, half_tr - disc);
    if l_max <= 0.0 {
        return None;
    }
    // Eigenvector of the smallest eigenvalue.
    let (vx, vy) = if libm::fabsf(b) > 1e-12 * l_max {
        (b, l_min - a)
    } else if a <= c {
        (1.0, 0.0)
    } else {
        (0.0, 1.0)
    };
    let norm = libm::sqrtf(vx * vx + vy * vy);
    if norm <= 0.0 {
        return None;
    }
    Some(([vx / norm, vy / norm], l_min.max(0.0) / l_max))
}

fn estimate_normals<const N: usize>(
    pts: &mut ScanPoints<N>,
    sensor: [f32; 2],
    c: &PreprocessConfig,
) {
    let k = c.normal_neighbours as usize;
    let max_d2 = c.normal_max_distance * c.normal_max_distance;
    for i in 0..pts.len() {
        let centre = pts[i].p;
        let lo = i.saturating_sub(k);
        let hi = (i + k + 1).min(pts.len());
        let near = pts[lo..hi].iter().map(|q| q.p).filter(move |q| {
            let (dx, dy) = (q[0] - centre[0], q[1] - centre[1]);
            dx * dx + dy * dy <= max_d2
        });
        let normal = match fit_normal(near) {
            Some((n, flat)) if flat <= c.normal_max_flatness => {
                // Point the normal towards the sensor.
                let to_sensor = [sensor[0] - centre[0], sensor[1] - centre[1]];
                if n[0] * to_sensor[0] + n[1] * to_sensor[1] < 0.0 {
                    [-n[0], -n[1]]
                } else {
                    n
                }
            }
            _ => [0.0, 0.0],
        };
        pts[i].n = normal;
    }
}

fn voxel_key(p: &[f32; 2], inv: f32) -> (i32, i32) {
    (
        crate::geom::floor_to_i32(p[0] * inv),
        crate::geom::floor_to_i32(p[1] * inv),
    )
}

/// Replaces the points of every voxel by their centroid (normals averaged and renormalised;
/// zero when they cancel or none had one). Returns how many points were merged away.
pub fn voxel_downsample<const N: usize>(pts: &mut ScanPoints<N>, voxel: f32) -> usize {
    let inv = 1.0 / voxel;
    // The order inside a voxel sets the rounding of the centroid's sums, and the maps of the
    // CARMEN logs still change under such a rounding change (mit-csail's loop closures, issue
    // 15), so core's sort stays here until they do not: `crate::sort::sort_by` with a
    // total order on the points as the tie-break is the recursion-free replacement.
    pts.sort_unstable_by_key(|a| voxel_key(&a.p, inv));
    merge_runs(pts, |a| voxel_key(&a.p, inv), |run| centroid(run))
}

/// A total order on points (position, then normal, by their IEEE total order): equal only for
/// identical points, so sorting by it gives one result whatever the algorithm.
pub(crate) fn point_order(a: &ScanPoint, b: &ScanPoint) -> core::cmp::Ordering {
    a.p[0]
        .total_cmp(&b.p[0])
        .then_with(|| a.p[1].total_cmp(&b.p[1]))
        .then_with(|| a.n[0].total_cmp(&b.n[0]))
        .then_with(|| a.n[1].total_cmp(&b.n[1]))
}

/// Sorts `items` by the voxel of their point (`point(item)`), then by a total order on the
/// points, and replaces every voxel's run by `merge(run)`. Returns how many items were merged
/// away. The total order makes the rounding of the merged sums independent of the sort
/// algorithm, and `crate::sort` has no recursion (the firmware's stack has a static bound).
pub(crate) fn merge_voxels<T: Copy, const N: usize>(
    items: &mut heapless::Vec<T, N>,
    voxel: f32,
    point: impl Fn(&T) -> &ScanPoint,
    merge: impl FnMut(&[T]) -> T,
) -> usize {
    let inv = 1.0 / voxel;
    let key = |t: &T| voxel_key(&point(t).p, inv);
    crate::sort::sort_by(&mut items[..], |a, b| {
        key(a)
            .cmp(&key(b))
            .then_with(|| point_order(point(a), point(b)))
    });
    merge_runs(items, key, merge)
}

/// Replaces every run of consecutive items with equal `key` by `merge(run)` (the items are
/// sorted by it). Returns how many items were merged away.
fn merge_runs<T: Copy, K: PartialEq, const N: usize>(
    items: &mut heapless::Vec<T, N>,
    key: impl Fn(&T) -> K,
    mut merge: impl FnMut(&[T]) -> T,
) -> usize {
    let before = items.len();
    let mut write = 0usize;
    let mut read = 0usize;
    while read < before {
        let k = key(&items[read]);
        let mut end = read + 1;
        while end < before && key(&items[end]) == k {
            end += 1;
        }
        items[write] = merge(&items[read..end]);
        write += 1;
        read = end;
    }
    items.truncate(write);
    before - write
}

/// The centroid of `run` (not empty), with the mean of its normals: each normal's sign is
/// first aligned with the first one's, and the mean is renormalised (zero when the normals
/// cancel or none had one).
pub(crate) fn centroid<'a>(run: impl IntoIterator<Item = &'a ScanPoint>) -> ScanPoint {
    let mut count = 0u32;
    let (mut sx, mut sy, mut nx, mut ny) = (0.0f32, 0.0f32, 0.0f32, 0.0f32);
    let mut first_n = None;
    for q in run {
        count += 1;
        sx += q.p[0];
        sy += q.p[1];
        let f: [f32; 2] = *first_n.get_or_insert(q.n);
        let sign = if q.n[0] * f[0] + q.n[1] * f[1] < 0.0 {
            -1.0
        } else {
            1.0
        };
        nx += sign * q.n[0];
        ny += sign * q.n[1];
    }
    let count = count.max(1) as f32;
    let norm = libm::sqrtf(nx * nx + ny * ny);
    let n = if norm > 1e-3 {
        [nx / norm, ny / norm]
    } else {
        [0.0, 0.0]
    };
    ScanPoint {
        p: [sx / count, sy / count],
        n,
    }
}

#[cfg(test)]
pub(crate) mod tests;
