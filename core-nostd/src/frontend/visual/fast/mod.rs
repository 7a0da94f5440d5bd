//! FAST-9 corners, spread over the image by a grid, with an orientation (paper section
//! III-B.1).
//!
//! The visual odometry needs 2D points that come back in the next frames. A pixel is a corner
//! when 9 contiguous pixels of the 16 on a radius-3 circle around it are all brighter than it
//! by more than a threshold, or all darker: a test of a few integer comparisons, which is why
//! FAST suits the Cortex-A9 budget.
//!
//! Why the rest is built this way:
//! * **Score and non-maximum suppression.** A corner's score is the summed contrast of its
//!   circle pixels beyond the threshold; a corner is kept only when no 8-neighbour scores
//!   higher (ties go to the earlier pixel in raster order, so a plateau keeps exactly one).
//!   Neighbour scores are recomputed where needed instead of stored, so no score image is
//!   allocated.
//! * **Grid bucketing.** A ceiling is mostly plain with a few strong lights; ranked globally,
//!   all features would sit on the lights and the pose would be poorly constrained. The
//!   interior is cut into square cells and each keeps only its best `per_cell` corners.
//! * **Adaptive fallback.** A cell with no corner at the threshold is scanned again at a lower
//!   one: the paper's low-feature case (dim, plain ceilings, exposure changes) is the normal
//!   case, so weak corners are taken where nothing better exists. Only on the halved levels
//!   by default ([`FastConfig::relax_from_level`]): the full-resolution frame carries the
//!   sensor's whole pixel noise (a few grey levels on a cheap camera, so differences of two
//!   pixels spread by more than the lower threshold) and a relaxed scan there finds noise,
//!   corners that never come back; each halving averages 16 pixels with weights 1-3-3-1 and
//!   divides independent noise by about 3, so the same threshold is safe from level 1.
//! * **Orientation by intensity centroid.** The angle from the corner to the centroid of the
//!   intensities in a disk of radius [`PATCH_RADIUS`] is stable under rotation of the image,
//!   and it steers the descriptor (`brief.rs`), so a robot turning under the same ceiling still
//!   matches its features.
//!
//! Keypoints go into a caller-provided slice; the work per frame is bounded by the pixel count.

use super::image::GrayImage;
use super::pyramid::Pyramid;

/// The 16 offsets of the radius-3 Bresenham circle, clockwise from the top.
pub const CIRCLE: [(i8, i8); 16] = [
    (0, -3),
    (1, -3),
    (2, -2),
    (3, -1),
    (3, 0),
    (3, 1),
    (2, 2),
    (1, 3),
    (0, 3),
    (-1, 3),
    (-2, 2),
    (-3, 1),
    (-3, 0),
    (-3, -1),
    (-2, -2),
    (-1, -3),
];
/// Contiguous circle pixels a corner needs (FAST-9).
pub const ARC: usize = 9;
/// Radius of the disk used for the orientation and by the descriptor.
pub const PATCH_RADIUS: i32 = 15;
/// Pixels from the image edge where no corner is sought: the patch must fit.
pub const BORDER: usize = PATCH_RADIUS as usize + 1;
/// The most corners one grid cell can keep.
pub const MAX_PER_CELL: usize = 8;

/// Half-widths of the rows of the orientation disk: `floor(sqrt(R^2 - dy^2))`.
const DISK_HALF_WIDTH: [i32; PATCH_RADIUS as usize + 1] = disk_half_widths();

const fn disk_half_widths() -> [i32; PATCH_RADIUS as usize + 1] {
    let mut out = [0; PATCH_RADIUS as usize + 1];
    let r2 = PATCH_RADIUS * PATCH_RADIUS;
    let mut dy = 0;
    while dy <= PATCH_RADIUS {
        let mut w = 0;
        while (w + 1) * (w + 1) + dy * dy <= r2 {
            w += 1;
        }
        out[dy as usize] = w;
        dy += 1;
    }
    out
}

/// A detected corner.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Keypoint {
    /// Column in the pixels of its level.
    pub x: f32,
    /// Row in the pixels of its level.
    pub y: f32,
    /// Pyramid level (0 is the frame).
    pub level: u8,
    /// FAST score: summed contrast beyond the threshold.
    pub score: f32,
    /// Orientation in radians, image axes (`x` right, `y` down).
    pub angle: f32,
}

impl Keypoint {
    /// The position in level-0 pixels.
    pub fn position(&self) -> [f32; 2] {
        Pyramid::to_level0(usize::from(self.level), [self.x, self.y])
    }
}

/// Detection parameters.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FastConfig {
    /// Intensity difference a circle pixel needs to count as brighter or darker.
    pub threshold: u8,
    /// The lower threshold tried in a cell that has no corner at `threshold`.
    pub min_threshold: u8,
    /// Side of a grid cell, in pixels of the level.
    pub cell_size: usize,
    /// Corners kept per cell, at most [`MAX_PER_CELL`].
    pub per_cell: usize,
    /// The first pyramid level where an empty cell is scanned again at `min_threshold`.
    pub relax_from_level: u8,
}

impl Default for FastConfig {
    fn default() -> Self {
        Self {
            threshold: 20,
            min_threshold: 7,
            cell_size: 32,
            per_cell: 3,
            relax_from_level: 1,
        }
    }
}

/// What one detection did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct DetectStats {
    /// Keypoints written.
    pub kept: usize,
    /// Grid cells scanned.
    pub cells: usize,
    /// Cells that needed the lower threshold.
    pub relaxed_cells: usize,
    /// Cells without any corner, even at the lower threshold.
    pub empty_cells: usize,
    /// Corners dropped because the output was full.
    pub dropped: usize,
}

/// The FAST-9 score of pixel (x, y) at threshold `t`, or `None` when it is not a corner.
pub fn corner_score(img: &GrayImage<'_>, x: i32, y: i32, t: u8) -> Option<u32> {
    // The whole circle must be inside; this also keeps the offsets below from overflowing.
    if !img.contains_patch(x, y, 3) {
        return None;
    }
    let data = img.data();
    let stride = isize::try_from(img.stride()).ok()?;
    let base = usize::try_from(y)
        .ok()?
        .checked_mul(img.stride())?
        .checked_add(usize::try_from(x).ok()?)?;
    let p = i32::from(*data.get(base)?);
    let t = i32::from(t);
    let read = |(dx, dy): (i8, i8)| {
        let offset = isize::from(dy).checked_mul(stride)? + isize::from(dx);
        data.get(base.checked_add_signed(offset)?)
            .map(|&v| i32::from(v))
    };
    // Any arc of 9 covers at least two of the four compass pixels (0, 4, 8, 12): reading
    // those first rejects most pixels after four reads.
    let (mut bright4, mut dark4) = (0, 0);
    for i in [0, 4, 8, 12] {
        let v = read(*CIRCLE.get(i)?)?;
        bright4 += usize::from(v > p + t);
        dark4 += usize::from(v < p - t);
    }
    if bright4 < 2 && dark4 < 2 {
        return None;
    }
    let mut ring = [0i32; 16];
    for (v, offset) in ring.iter_mut().zip(CIRCLE) {
        *v = read(offset)?;
    }
    let (mut bright, mut dark) = (0u16, 0u16);
    let (mut sum_bright, mut sum_dark) = (0u32, 0u32);
    for (i, &v) in ring.iter().enumerate() {
        if v > p + t {
            bright |= 1 << i;
            sum_bright += (v - p - t).unsigned_abs();
        } else if v < p - t {
            dark |= 1 << i;
            sum_dark += (p - t - v).unsigned_abs();
        }
    }
    let score = match (has_arc(bright), has_arc(dark)) {
        (true, true) => sum_bright.max(sum_dark),
        (true, false) => sum_bright,
        (false, true) => sum_dark,
        (false, false) => return None,
    };
    Some(score)
}

/// Whether the 16-bit circular mask has [`ARC`] contiguous set bits.
fn has_arc(mask: u16) -> bool {
    let doubled = u32::from(mask) | (u32::from(mask) << 16);
    let mut run = doubled;
    for shift in 1..ARC {
        run &= doubled >> shift;
    }
    run != 0
}

/// Whether (x, y), a corner of score `score`, is the strongest of its 8 neighbours.
fn is_local_max(img: &GrayImage<'_>, x: i32, y: i32, t: u8, score: u32) -> bool {
    for dy in -1..=1 {
        for dx in -1..=1 {
            if dx == 0 && dy == 0 {
                continue;
            }
            if let Some(s) = corner_score(img, x + dx, y + dy, t) {
                let earlier = dy < 0 || (dy == 0 && dx < 0);
                if s > score || (s == score && earlier) {
                    return false;
                }
            }
        }
    }
    true
}

/// The intensity-centroid angle of the disk of radius [`PATCH_RADIUS`] around (x, y), or
/// `None` when the disk leaves the image.
pub fn orientation(img: &GrayImage<'_>, x: i32, y: i32) -> Option<f32> {
    if !img.contains_patch(x, y, PATCH_RADIUS) {
        return None;
    }
    let (mut m10, mut m01) = (0i32, 0i32);
    for dy in -PATCH_RADIUS..=PATCH_RADIUS {
        let half = *DISK_HALF_WIDTH.get(dy.unsigned_abs() as usize)?;
        let row = img.row(usize::try_from(y + dy).ok()?)?;
        let from = usize::try_from(x - half).ok()?;
        let to = usize::try_from(x + half).ok()?;
        let mut row_sum = 0;
        for (dx, &v) in (-half..=half).zip(row.get(from..=to)?) {
            m10 += dx * i32::from(v);
            row_sum += i32::from(v);
        }
        m01 += dy * row_sum;
    }
    Some(libm::atan2f(m01 as f32, m10 as f32))
}

/// The best corners of one cell (at most [`MAX_PER_CELL`]), strongest first.
#[derive(Clone, Copy, Debug)]
struct CellBest {
    items: [(u32, i32, i32); MAX_PER_CELL],
    len: usize,
    cap: usize,
}

impl CellBest {
    fn new(cap: usize) -> Self {
        Self {
            items: [(0, 0, 0); MAX_PER_CELL],
            len: 0,
            cap: cap.min(MAX_PER_CELL),
        }
    }

    /// Inserts a corner if it ranks among the best; equal scores keep the earlier corner first.
    fn offer(&mut self, item: (u32, i32, i32)) {
        let pos = self
            .as_slice()
            .iter()
            .position(|p| p.0 < item.0)
            .unwrap_or(self.len);
        if pos >= self.cap {
            return;
        }
        // Shift the weaker ones down one slot; the last falls off when the cell is full.
        let end = self.len.min(self.cap - 1);
        let mut i = end;
        while i > pos {
            if let Some(prev) = self.items.get(i - 1).copied() {
                if let Some(slot) = self.items.get_mut(i) {
                    *slot = prev;
                }
            }
            i -= 1;
        }
        if let Some(slot) = self.items.get_mut(pos) {
            *slot = item;
        }
        self.len = end + 1;
    }

    fn as_slice(&self) -> &[(u32, i32, i32)] {
        self.items.get(..self.len).unwrap_or(&[])
    }
}

/// Scans the cell `[x0, x1) x [y0, y1)` at threshold `t`.
///
/// Most pixels of a frame fail the compass test of [`corner_score`] (two of the pixels 3
/// above, right, below and left brighter, or two darker), so it runs first here, straight on
/// the three rows it needs, and only the pixels that pass it get the full score.
fn scan_cell(img: &GrayImage<'_>, rect: [i32; 4], t: u8, best: &mut CellBest) {
    let [x0, y0, x1, y1] = rect;
    let ti = i32::from(t);
    for y in y0..y1 {
        let Some((up, mid, down)) = compass_rows(img, x0, x1, y) else {
            // A cell touching the image edge (not made by `detect`): score every pixel.
            (x0..x1).for_each(|x| offer_corner(img, x, y, t, best));
            continue;
        };
        let len = up.len().min(down.len()).min(mid.len().saturating_sub(6));
        let (up, down) = (up.get(..len).unwrap_or(&[]), down.get(..len).unwrap_or(&[]));
        let (west, mid) = (mid.get(..len).unwrap_or(&[]), mid.get(3..).unwrap_or(&[]));
        let (centre, east) = (
            mid.get(..len).unwrap_or(&[]),
            mid.get(3..3 + len).unwrap_or(&[]),
        );
        let pixels = up.iter().zip(down).zip(west).zip(centre).zip(east);
        for (x, ((((&n, &s), &w), &p), &e)) in (x0..).zip(pixels) {
            let (hi, lo) = (i32::from(p) + ti, i32::from(p) - ti);
            let (n, e, s, w) = (i32::from(n), i32::from(e), i32::from(s), i32::from(w));
            let bright = u8::from(n > hi) + u8::from(e > hi) + u8::from(s > hi) + u8::from(w > hi);
            let dark = u8::from(n < lo) + u8::from(e < lo) + u8::from(s < lo) + u8::from(w < lo);
            if bright >= 2 || dark >= 2 {
                offer_corner(img, x, y, t, best);
            }
        }
    }
}

/// Row `y - 3` and row `y + 3` over columns `[x0, x1)`, and row `y` over `[x0 - 3, x1 + 3)`,
/// when all lie inside the image.
fn compass_rows<'a>(
    img: &GrayImage<'a>,
    x0: i32,
    x1: i32,
    y: i32,
) -> Option<(&'a [u8], &'a [u8], &'a [u8])> {
    let (x0, x1, y) = (
        usize::try_from(x0).ok()?,
        usize::try_from(x1).ok()?,
        usize::try_from(y).ok()?,
    );
    let up = img.row(y.checked_sub(3)?)?.get(x0..x1)?;
    let mid = img.row(y)?.get(x0.checked_sub(3)?..x1.checked_add(3)?)?;
    let down = img.row(y.checked_add(3)?)?.get(x0..x1)?;
    Some((up, mid, down))
}

/// Offers pixel (x, y) to `best` if it is a corner at threshold `t` and the strongest of its
/// neighbours.
fn offer_corner(img: &GrayImage<'_>, x: i32, y: i32, t: u8, best: &mut CellBest) {
    if let Some(s) = corner_score(img, x, y, t) {
        if is_local_max(img, x, y, t, s) {
            best.offer((s, x, y));
        }
    }
}

/// FAST-9 corners of one pyramid level, bucketed and oriented, written into `out`.
///
/// Corners are sought at least [`BORDER`] pixels from the edges. Cells are visited in raster
/// order, each contributing its best `per_cell` corners; when `out` is full the remaining ones
/// are counted in [`DetectStats::dropped`].
pub fn detect(
    img: &GrayImage<'_>,
    level: u8,
    cfg: &FastConfig,
    out: &mut [Keypoint],
) -> DetectStats {
    let mut stats = DetectStats::default();
    let (w, h) = (img.width(), img.height());
    if w <= 2 * BORDER || h <= 2 * BORDER || cfg.cell_size == 0 {
        return stats;
    }
    let cell = cfg.cell_size;
    let (iw, ih) = (w - 2 * BORDER, h - 2 * BORDER);
    let (nx, ny) = (iw.div_ceil(cell), ih.div_ceil(cell));
    let relax = cfg.min_threshold < cfg.threshold && level >= cfg.relax_from_level;
    for cy in 0..ny {
        for cx in 0..nx {
            stats.cells += 1;
            let x0 = BORDER + cx * cell;
            let y0 = BORDER + cy * cell;
            let rect = [
                x0 as i32,
                y0 as i32,
                (x0 + cell).min(w - BORDER) as i32,
                (y0 + cell).min(h - BORDER) as i32,
            ];
            let mut best = CellBest::new(cfg.per_cell);
            scan_cell(img, rect, cfg.threshold, &mut best);
            if best.len == 0 && relax {
                stats.relaxed_cells += 1;
                scan_cell(img, rect, cfg.min_threshold, &mut best);
            }
            if best.len == 0 {
                stats.empty_cells += 1;
            }
            for &(score, x, y) in best.as_slice() {
                let Some(slot) = out.get_mut(stats.kept) else {
                    stats.dropped += 1;
                    continue;
                };
                *slot = Keypoint {
                    x: x as f32,
                    y: y as f32,
                    level,
                    score: score as f32,
                    angle: orientation(img, x, y).unwrap_or(0.0),
                };
                stats.kept += 1;
            }
        }
    }
    stats
}

/// Corners of every level of `pyr`, each level given a share of `out` proportional to its
/// area (so the coarse levels are not crowded out by the frame). Returns the summed stats.
pub fn detect_pyramid(pyr: &Pyramid<'_>, cfg: &FastConfig, out: &mut [Keypoint]) -> DetectStats {
    let mut total = DetectStats::default();
    let area = |l: usize| pyr.level(l).map_or(0, |i| i.width() * i.height());
    let all: usize = (0..pyr.len()).map(area).sum();
    let capacity = out.len();
    for l in 0..pyr.len() {
        let (Some(img), Ok(level)) = (pyr.level(l), u8::try_from(l)) else {
            break;
        };
        let share = if l + 1 == pyr.len() {
            capacity - total.kept
        } else {
            capacity
                .saturating_mul(area(l))
                .checked_div(all)
                .unwrap_or(0)
        };
        let end = (total.kept + share).min(capacity);
        let Some(slice) = out.get_mut(total.kept..end) else {
            break;
        };
        let s = detect(&img, level, cfg, slice);
        total.kept += s.kept;
        total.cells += s.cells;
        total.relaxed_cells += s.relaxed_cells;
        total.empty_cells += s.empty_cells;
        total.dropped += s.dropped;
    }
    total
}

#[cfg(test)]
mod tests;
