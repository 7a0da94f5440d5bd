//! A fixed-capacity image pyramid over caller-provided bytes (paper section III-B.1).
//!
//! Corners are detected on every level so that a ceiling feature seen from farther away (or
//! blurred by motion) is still found at a coarser scale. Level 0 is the camera frame itself,
//! borrowed; levels 1.. are written into one `&mut [u8]` whose size [`pyramid_bytes`] gives at
//! compile time, so a memory profile can reserve it statically.
//!
//! Why a scale factor of 2 (and not ORB's 1.2):
//! * The robot moves in a plane under a ceiling at a nearly constant height, so the scale of a
//!   ceiling feature changes little between keyframes; fine scale steps buy little here.
//! * All levels together cost 1/3 of the frame (1.2 with eight levels costs more than twice
//!   the frame), which matters for memory and for the per-frame instruction budget.
//! * An exact halving needs no interpolation: each output pixel is the `[1 3 3 1] / 8`
//!   separable filter over a 4x4 block of the level above (smoothing and decimation in one
//!   pass, borders replicated), in integers, so every target computes the same bytes.

use core::fmt;

use super::image::GrayImage;

/// The most levels a pyramid holds, level 0 included.
pub const MAX_LEVELS: usize = 5;
/// A level is only built while both its sides are at least this many pixels.
pub const MIN_LEVEL_SIDE: usize = 24;

/// Why a pyramid cannot be built.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum PyramidError {
    /// The storage is shorter than [`pyramid_bytes`] for the levels asked.
    StorageTooSmall {
        /// Bytes needed.
        needed: usize,
        /// Bytes given.
        got: usize,
    },
}

impl fmt::Display for PyramidError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::StorageTooSmall { needed, got } => {
                write!(f, "the pyramid needs {needed} bytes but has {got}")
            }
        }
    }
}

impl core::error::Error for PyramidError {}

/// How many levels a `width` x `height` frame gets when `requested` are asked: at least one,
/// at most [`MAX_LEVELS`], and none smaller than [`MIN_LEVEL_SIDE`].
pub const fn level_count(width: usize, height: usize, requested: usize) -> usize {
    let mut n = 1;
    while n < requested && n < MAX_LEVELS {
        if (width >> n) < MIN_LEVEL_SIDE || (height >> n) < MIN_LEVEL_SIDE {
            break;
        }
        n += 1;
    }
    n
}

/// The bytes of storage levels 1.. of a pyramid take ([`level_count`] applied).
pub const fn pyramid_bytes(width: usize, height: usize, requested: usize) -> usize {
    let n = level_count(width, height, requested);
    let mut bytes = 0;
    let mut l = 1;
    while l < n {
        bytes += (width >> l) * (height >> l);
        l += 1;
    }
    bytes
}

/// Where one stored level lies in the storage.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct LevelRect {
    offset: usize,
    width: usize,
    height: usize,
}

/// Levels of halving resolution; level `l` pixel `(x, y)` covers level-0 pixel
/// `(2^l (x + 0.5) - 0.5, 2^l (y + 0.5) - 0.5)`.
#[derive(Clone, Copy, Debug)]
pub struct Pyramid<'a> {
    base: GrayImage<'a>,
    store: &'a [u8],
    rects: [LevelRect; MAX_LEVELS],
    count: usize,
}

impl<'a> Pyramid<'a> {
    /// Builds up to `requested` levels of `base` into `storage`.
    ///
    /// # Errors
    /// [`PyramidError::StorageTooSmall`] when `storage` is shorter than
    /// [`pyramid_bytes`]`(width, height, requested)`.
    pub fn build(
        base: GrayImage<'a>,
        requested: usize,
        storage: &'a mut [u8],
    ) -> Result<Self, PyramidError> {
        let (w, h) = (base.width(), base.height());
        let count = level_count(w, h, requested);
        let needed = pyramid_bytes(w, h, requested);
        if storage.len() < needed {
            return Err(PyramidError::StorageTooSmall {
                needed,
                got: storage.len(),
            });
        }
        let mut rects = [LevelRect::default(); MAX_LEVELS];
        let mut offset = 0;
        for (l, rect) in rects.iter_mut().enumerate().take(count).skip(1) {
            *rect = LevelRect {
                offset,
                width: w >> l,
                height: h >> l,
            };
            offset += rect.width * rect.height;
        }
        for l in 1..count {
            let (Some(dst_rect), Some(src_rect)) = (rects.get(l), rects.get(l - 1)) else {
                break;
            };
            let (done, rest) = storage.split_at_mut(dst_rect.offset);
            let dst = rest
                .get_mut(..dst_rect.width * dst_rect.height)
                .unwrap_or_default();
            let src = if l == 1 {
                Some(base)
            } else {
                done.get(src_rect.offset..).and_then(|bytes| {
                    GrayImage::new_checked(src_rect.width, src_rect.height, src_rect.width, bytes)
                        .ok()
                })
            };
            if let Some(src) = src {
                halve(&src, dst, dst_rect.width);
            }
        }
        Ok(Self {
            base,
            store: storage,
            rects,
            count,
        })
    }

    /// Levels held, level 0 included.
    pub fn len(&self) -> usize {
        self.count
    }

    /// Always false: level 0 is the frame.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Level `l`, or `None` past the last one.
    pub fn level(&self, l: usize) -> Option<GrayImage<'a>> {
        if l == 0 {
            return Some(self.base);
        }
        if l >= self.count {
            return None;
        }
        let r = self.rects.get(l)?;
        let bytes = self.store.get(r.offset..)?;
        GrayImage::new_checked(r.width, r.height, r.width, bytes).ok()
    }

    /// Level-0 pixels per pixel of level `l` (`2^l`).
    pub fn scale(l: usize) -> f32 {
        let shift = l.min(MAX_LEVELS) as u32;
        (1u32 << shift) as f32
    }

    /// The level-0 position of a level-`l` pixel position.
    pub fn to_level0(l: usize, p: [f32; 2]) -> [f32; 2] {
        let s = Self::scale(l);
        [s * (p[0] + 0.5) - 0.5, s * (p[1] + 0.5) - 0.5]
    }
}

/// Writes `src` halved into `dst` (`dst_width` bytes a row).
fn halve(src: &GrayImage<'_>, dst: &mut [u8], dst_width: usize) {
    if dst_width == 0 || src.width() == 0 || src.height() == 0 {
        return;
    }
    let last_row = src.height() - 1;
    for (y, row) in dst.chunks_exact_mut(dst_width).enumerate() {
        // The kernel's four rows, 2y - 1 .. 2y + 2, replicated at the borders.
        let rows = [0usize, 1, 2, 3].map(|k| (2 * y + k).saturating_sub(1).min(last_row));
        let [Some(r0), Some(r1), Some(r2), Some(r3)] = rows.map(|r| src.row(r)) else {
            return;
        };
        for (x, px) in row.iter_mut().enumerate() {
            let h = |r: &[u8]| weigh_1331(r, 2 * x);
            let sum = h(r0) + 3 * (h(r1) + h(r2)) + h(r3);
            *px = u8::try_from((sum + 32) >> 6).unwrap_or(u8::MAX);
        }
    }
}

/// `r[c - 1] + 3 r[c] + 3 r[c + 1] + r[c + 2]`, the columns replicated at the row's ends.
#[inline(always)]
fn weigh_1331(r: &[u8], c: usize) -> u32 {
    let v = |i: u8| u32::from(i);
    if let Some(&[a, b, cc, d]) = c.checked_sub(1).and_then(|s| r.get(s..s + 4)) {
        return v(a) + 3 * (v(b) + v(cc)) + v(d);
    }
    // A border column: clamp each tap.
    let last = r.len().saturating_sub(1);
    let at = |i: usize| v(r.get(i.min(last)).copied().unwrap_or(0));
    at(c.saturating_sub(1)) + 3 * (at(c) + at(c + 1)) + at(c + 2)
}

#[cfg(test)]
mod tests {
    extern crate std;

    use super::*;
    use proptest::prelude::*;

    /// The [1 3 3 1]^2 / 64 halving written tap by tap with clamped reads: the definition the
    /// separable loop must reproduce exactly.
    fn halve_reference(src: &GrayImage<'_>, dst_w: usize, dst_h: usize) -> std::vec::Vec<u8> {
        let k = [1u32, 3, 3, 1];
        let mut out = std::vec![0u8; dst_w * dst_h];
        for (i, px) in out.iter_mut().enumerate() {
            let (x, y) = ((i % dst_w) as isize, (i / dst_w) as isize);
            let mut sum = 0;
            for (dy, ky) in k.iter().enumerate() {
                for (dx, kx) in k.iter().enumerate() {
                    let v = src.clamped(2 * x - 1 + dx as isize, 2 * y - 1 + dy as isize);
                    sum += ky * kx * u32::from(v);
                }
            }
            *px = ((sum + 32) >> 6) as u8;
        }
        out
    }

    proptest! {
        #[test]
        fn halving_equals_the_tap_by_tap_definition(
            w in 2usize..40, h in 2usize..40, seed in any::<u64>(),
        ) {
            let data: std::vec::Vec<u8> = (0..w * h)
                .map(|i| (seed.wrapping_mul(i as u64 + 1).rotate_left(23) >> 56) as u8)
                .collect();
            let src = GrayImage::new_checked(w, h, w, &data).unwrap();
            let (dw, dh) = (w / 2, h / 2);
            let mut out = std::vec![0u8; dw * dh];
            halve(&src, &mut out, dw);
            prop_assert_eq!(out, halve_reference(&src, dw, dh));
        }
    }

    const W: usize = 96;
    const H: usize = 96;

    #[test]
    fn sizes_are_known_at_compile_time() {
        assert_eq!(level_count(320, 240, 4), 4);
        assert_eq!(level_count(320, 240, 99), 4); // 20 < 24 stops the fifth
        assert_eq!(level_count(320, 240, 0), 1);
        assert_eq!(pyramid_bytes(320, 240, 4), 160 * 120 + 80 * 60 + 40 * 30);
        assert_eq!(pyramid_bytes(320, 240, 1), 0);
        const BYTES: usize = pyramid_bytes(W, H, 3);
        assert_eq!(BYTES, 48 * 48 + 24 * 24);
    }

    #[test]
    fn a_checkerboard_halves_into_a_checkerboard() {
        let mut data = [0u8; W * H];
        for (i, px) in data.iter_mut().enumerate() {
            let (x, y) = (i % W, i / W);
            *px = if (x / 8 + y / 8) % 2 == 0 { 40 } else { 200 };
        }
        let base = GrayImage::new_checked(W, H, W, &data).unwrap();
        let mut store = [0u8; pyramid_bytes(W, H, 3)];
        let pyr = Pyramid::build(base, 3, &mut store).unwrap();
        assert_eq!(pyr.len(), 3);
        let l1 = pyr.level(1).unwrap();
        assert_eq!((l1.width(), l1.height()), (48, 48));
        // Inside a 4-pixel square (away from its edges) the value is the square's.
        assert_eq!(l1.get(1, 1), Some(40));
        assert_eq!(l1.get(5, 1), Some(200));
        assert_eq!(l1.get(5, 6), Some(40));
        // On an edge between squares, the average.
        assert_eq!(l1.get(4, 1), Some(180)); // (1 * 40 + 7 * 200) / 8
        let l2 = pyr.level(2).unwrap();
        assert_eq!((l2.width(), l2.height()), (24, 24));
        assert_eq!(l2.get(0, 0), Some(40));
        assert!(pyr.level(3).is_none());
        assert_eq!(Pyramid::to_level0(2, [0.0, 1.0]), [1.5, 5.5]);
    }

    #[test]
    fn short_storage_is_refused_and_flat_frames_stay_flat() {
        let data = [77u8; W * H];
        let base = GrayImage::new_checked(W, H, W, &data).unwrap();
        let mut short = [0u8; 10];
        assert_eq!(
            Pyramid::build(base, 2, &mut short).err(),
            Some(PyramidError::StorageTooSmall {
                needed: 48 * 48,
                got: 10
            })
        );
        let mut store = [0u8; pyramid_bytes(W, H, MAX_LEVELS)];
        let pyr = Pyramid::build(base, MAX_LEVELS, &mut store).unwrap();
        for l in 0..pyr.len() {
            let img = pyr.level(l).unwrap();
            assert!((0..img.height()).all(|y| img.row(y).unwrap().iter().all(|&v| v == 77)));
        }
    }
}
