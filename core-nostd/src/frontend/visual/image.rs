//! A borrowed grey image, the one pixel type of the visual front-end (paper section III-B.1).
//!
//! Corners and descriptors only need intensity, so every camera frame is reduced once to one
//! byte per pixel ([`GrayImage::from_sensor`]), and everything downstream reads that: one code
//! path for mono, RGB and BGR cameras. The view is borrowed, never owned: the frame's bytes
//! belong to the driver or to a caller-provided buffer, so the core holds no image memory of
//! its own.
//!
//! Reads outside the image return `None` ([`GrayImage::get`]) or the nearest border pixel
//! ([`GrayImage::clamped`]), so no coordinate, however wrong, makes a read panic.

use crate::sensor::{ImageError, ImageView, PixelFormat, Timestamp};

/// A checked, borrowed grey image: `height` rows of `stride` bytes, row 0 at the top.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GrayImage<'a> {
    data: &'a [u8],
    width: usize,
    height: usize,
    stride: usize,
}

impl<'a> GrayImage<'a> {
    /// Checks the sizes against the buffer.
    ///
    /// # Errors
    /// [`ImageError`] when a size is zero, a row does not fit the stride, or the buffer is
    /// shorter than `height` rows.
    pub fn new_checked(
        width: usize,
        height: usize,
        stride: usize,
        data: &'a [u8],
    ) -> Result<Self, ImageError> {
        // The size rules of a one-byte-per-pixel camera frame.
        ImageView::new_checked(
            Timestamp::from_nanos(0),
            width,
            height,
            stride,
            PixelFormat::Mono8,
            data,
        )?;
        Ok(Self {
            data,
            width,
            height,
            stride,
        })
    }

    /// The luminance of a camera frame written into `storage` (`width * height` bytes, no
    /// padding) and viewed as a grey image.
    ///
    /// # Errors
    /// [`ImageError::BufferTooSmall`] when `storage` cannot hold the frame.
    pub fn from_sensor(view: &ImageView<'_>, storage: &'a mut [u8]) -> Result<Self, ImageError> {
        let (w, h) = (view.width(), view.height());
        if w == 0 || h == 0 {
            return Err(ImageError::ZeroSize);
        }
        let needed = w.saturating_mul(h);
        let got = storage.len();
        let dst = storage
            .get_mut(..needed)
            .ok_or(ImageError::BufferTooSmall { needed, got })?;
        for (y, row) in dst.chunks_exact_mut(w).enumerate() {
            for (x, px) in row.iter_mut().enumerate() {
                *px = view.luminance(x, y).unwrap_or(0);
            }
        }
        Self::new_checked(w, h, w, storage)
    }

    /// Columns.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Rows.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Bytes from one row to the next.
    pub fn stride(&self) -> usize {
        self.stride
    }

    /// The underlying bytes: pixel (x, y) is at `y * stride + x`.
    pub fn data(&self) -> &'a [u8] {
        self.data
    }

    /// The pixels of row `y` (without padding), or `None` past the last row.
    pub fn row(&self, y: usize) -> Option<&'a [u8]> {
        if y >= self.height {
            return None;
        }
        let start = y.checked_mul(self.stride)?;
        self.data.get(start..start.checked_add(self.width)?)
    }

    /// Pixel (x, y), or `None` outside the image.
    pub fn get(&self, x: usize, y: usize) -> Option<u8> {
        if x >= self.width || y >= self.height {
            return None;
        }
        // In range: y * stride + x < (height - 1) * stride + width <= data.len().
        self.data.get(y * self.stride + x).copied()
    }

    /// Pixel (x, y) for signed coordinates, or `None` outside the image.
    pub fn at(&self, x: i32, y: i32) -> Option<u8> {
        self.get(usize::try_from(x).ok()?, usize::try_from(y).ok()?)
    }

    /// Pixel (x, y) with the coordinates clamped into the image (border replication).
    pub fn clamped(&self, x: isize, y: isize) -> u8 {
        let cx = x.clamp(0, self.width as isize - 1) as usize;
        let cy = y.clamp(0, self.height as isize - 1) as usize;
        self.get(cx, cy).unwrap_or(0)
    }

    /// Whether the square of half-size `margin` around (x, y) lies inside the image.
    pub fn contains_patch(&self, x: i32, y: i32, margin: i32) -> bool {
        let (w, h) = (self.width as i64, self.height as i64);
        let (x, y, m) = (i64::from(x), i64::from(y), i64::from(margin));
        x - m >= 0 && y - m >= 0 && x + m < w && y + m < h
    }
}

/// The bytes a smoothed copy of a `width` x `height` image needs.
pub const fn smoothed_bytes(width: usize, height: usize) -> usize {
    width * height
}

/// `src` smoothed by the 3x3 binomial kernel `[1 2 1]^T [1 2 1] / 16` (borders replicated),
/// written into `storage` without padding.
///
/// The descriptor compares single pixels; this blur is what keeps one noisy pixel from
/// flipping its bits, at a cost of nine reads per pixel.
///
/// # Errors
/// [`ImageError::BufferTooSmall`] when `storage` is shorter than
/// [`smoothed_bytes`]`(width, height)`.
pub fn smooth_into<'b>(
    src: &GrayImage<'_>,
    storage: &'b mut [u8],
) -> Result<GrayImage<'b>, ImageError> {
    let (w, h) = (src.width(), src.height());
    let needed = smoothed_bytes(w, h);
    let got = storage.len();
    let dst = storage
        .get_mut(..needed)
        .ok_or(ImageError::BufferTooSmall { needed, got })?;
    if w == 0 || h == 0 {
        return GrayImage::new_checked(w, h, w, storage);
    }
    for (y, row) in dst.chunks_exact_mut(w).enumerate() {
        // Rows y - 1, y, y + 1, replicated at the borders; the kernel is separable, so each
        // output pixel is a [1 2 1] sum over columns of [1 2 1] sums over rows.
        let rows = [y.saturating_sub(1), y, (y + 1).min(h - 1)];
        let [Some(a), Some(b), Some(c)] = rows.map(|r| src.row(r)) else {
            break;
        };
        // Column sums slide along the row: each is computed once, for the pixel to its right.
        let mut columns = a.iter().zip(b).zip(c);
        let mut col = || {
            columns
                .next()
                .map(|((&a, &b), &c)| u32::from(a) + 2 * u32::from(b) + u32::from(c))
        };
        let Some(first) = col() else {
            break;
        };
        let (mut left, mut centre) = (first, first);
        for px in row.iter_mut() {
            // Past the last column the border replicates it.
            let right = col().unwrap_or(centre);
            *px = u8::try_from((left + 2 * centre + right + 8) >> 4).unwrap_or(u8::MAX);
            (left, centre) = (centre, right);
        }
    }
    GrayImage::new_checked(w, h, w, storage)
}

#[cfg(test)]
mod tests {
    extern crate std;

    use super::*;
    use crate::sensor::{PixelFormat, Timestamp};
    use proptest::prelude::*;

    /// The 3x3 binomial blur written tap by tap with clamped reads: the definition the
    /// separable loop must reproduce exactly.
    fn smooth_reference(src: &GrayImage<'_>) -> std::vec::Vec<u8> {
        let k = [1u32, 2, 1];
        let (w, h) = (src.width(), src.height());
        let mut out = std::vec![0u8; w * h];
        for (i, px) in out.iter_mut().enumerate() {
            let (x, y) = ((i % w) as isize, (i / w) as isize);
            let mut sum = 0;
            for (dy, ky) in k.iter().enumerate() {
                for (dx, kx) in k.iter().enumerate() {
                    let v = src.clamped(x + dx as isize - 1, y + dy as isize - 1);
                    sum += ky * kx * u32::from(v);
                }
            }
            *px = ((sum + 8) >> 4) as u8;
        }
        out
    }

    proptest! {
        #[test]
        fn smoothing_equals_the_tap_by_tap_definition(
            w in 1usize..24, h in 1usize..24, seed in any::<u64>(),
        ) {
            let data: std::vec::Vec<u8> = (0..w * h)
                .map(|i| (seed.wrapping_mul(i as u64 + 1).rotate_left(17) >> 56) as u8)
                .collect();
            let src = GrayImage::new_checked(w, h, w, &data).unwrap();
            let mut out = std::vec![0u8; w * h];
            let fast = smooth_into(&src, &mut out).unwrap();
            prop_assert_eq!(fast.data(), &smooth_reference(&src)[..]);
        }
    }

    #[test]
    fn views_are_checked_and_reads_stay_inside() {
        let data = [0u8, 1, 2, 9, 3, 4, 5];
        assert_eq!(
            GrayImage::new_checked(0, 1, 1, &data),
            Err(ImageError::ZeroSize)
        );
        assert_eq!(
            GrayImage::new_checked(4, 1, 3, &data),
            Err(ImageError::StrideTooSmall)
        );
        assert!(GrayImage::new_checked(3, 3, 4, &data).is_err());
        // Two rows of three with one byte of padding; the last row needs no padding.
        let img = GrayImage::new_checked(3, 2, 4, &data).unwrap();
        assert_eq!(img.get(2, 1), Some(5));
        assert_eq!(img.get(3, 0), None);
        assert_eq!(img.get(0, 2), None);
        assert_eq!(img.at(-1, 0), None);
        assert_eq!(img.at(i32::MAX, i32::MIN), None);
        assert_eq!(img.clamped(-5, 100), 3);
        assert_eq!(img.clamped(isize::MAX, isize::MIN), 2);
        assert_eq!(img.row(1), Some(&data[4..7]));
        assert!(img.contains_patch(1, 0, 0) && !img.contains_patch(1, 1, 1));
    }

    #[test]
    fn colour_frames_become_luminance() {
        let rgb = [255u8, 0, 0, 0, 255, 0, 0, 0, 255, 10, 10, 10];
        let view = ImageView::new_checked(Timestamp(0), 2, 2, 6, PixelFormat::Rgb8, &rgb).unwrap();
        let mut buf = [0u8; 4];
        let grey = GrayImage::from_sensor(&view, &mut buf).unwrap();
        assert_eq!(grey.row(0), Some(&[76u8, 149][..]));
        assert_eq!(grey.row(1), Some(&[28u8, 10][..]));
        let mut small = [0u8; 3];
        assert!(GrayImage::from_sensor(&view, &mut small).is_err());
    }

    #[test]
    fn smoothing_keeps_flat_images_and_spreads_a_spike() {
        let mut data = [50u8; 25];
        let mut out = [0u8; 25];
        let flat = GrayImage::new_checked(5, 5, 5, &data).unwrap();
        let s = smooth_into(&flat, &mut out).unwrap();
        assert!((0..5).all(|y| s.row(y) == Some(&[50u8; 5][..])));
        data[12] = 210;
        let spike = GrayImage::new_checked(5, 5, 5, &data).unwrap();
        let s = smooth_into(&spike, &mut out).unwrap();
        assert_eq!(s.get(2, 2), Some(90)); // 50 + 160 * 4 / 16
        assert_eq!(s.get(1, 2), Some(70)); // 50 + 160 * 2 / 16
        assert_eq!(s.get(1, 1), Some(60)); // 50 + 160 / 16
        assert_eq!(s.get(0, 0), Some(50));
        let mut short = [0u8; 24];
        assert!(smooth_into(&spike, &mut short).is_err());
    }
}
