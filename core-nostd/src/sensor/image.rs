//! Camera pictures as borrowed byte views.

use core::fmt;

use super::Timestamp;

/// Pixel layouts the core accepts (8 bits per channel).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum PixelFormat {
    /// One grey byte per pixel.
    Mono8,
    /// Red, green, blue.
    Rgb8,
    /// Blue, green, red (OpenCV's order).
    Bgr8,
}

impl PixelFormat {
    /// Bytes per pixel.
    pub const fn bytes_per_pixel(self) -> usize {
        match self {
            Self::Mono8 => 1,
            Self::Rgb8 | Self::Bgr8 => 3,
        }
    }
}

/// Why a picture cannot be viewed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ImageError {
    /// Width or height is zero.
    ZeroSize,
    /// A row (`stride` bytes) is shorter than `width` pixels.
    StrideTooSmall,
    /// The buffer is shorter than `height` rows.
    BufferTooSmall {
        /// Bytes needed.
        needed: usize,
        /// Bytes given.
        got: usize,
    },
}

impl fmt::Display for ImageError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::ZeroSize => write!(f, "the image has zero width or height"),
            Self::StrideTooSmall => write!(f, "the row stride is shorter than a row of pixels"),
            Self::BufferTooSmall { needed, got } => {
                write!(f, "the image needs {needed} bytes but has {got}")
            }
        }
    }
}

impl core::error::Error for ImageError {}

/// A checked, borrowed picture: `height` rows of `stride` bytes, row 0 at the top.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageView<'a> {
    stamp: Timestamp,
    width: usize,
    height: usize,
    stride: usize,
    format: PixelFormat,
    data: &'a [u8],
}

impl<'a> ImageView<'a> {
    /// Checks sizes against the buffer.
    ///
    /// # Errors
    /// [`ImageError`] when the sizes are zero or do not fit the buffer.
    pub fn new_checked(
        stamp: Timestamp,
        width: usize,
        height: usize,
        stride: usize,
        format: PixelFormat,
        data: &'a [u8],
    ) -> Result<Self, ImageError> {
        if width == 0 || height == 0 {
            return Err(ImageError::ZeroSize);
        }
        let row = width
            .checked_mul(format.bytes_per_pixel())
            .ok_or(ImageError::StrideTooSmall)?;
        if stride < row {
            return Err(ImageError::StrideTooSmall);
        }
        // The last row needs only its pixels, not the padding after them.
        let needed = stride
            .checked_mul(height - 1)
            .and_then(|n| n.checked_add(row))
            .ok_or(ImageError::BufferTooSmall {
                needed: usize::MAX,
                got: data.len(),
            })?;
        if data.len() < needed {
            return Err(ImageError::BufferTooSmall {
                needed,
                got: data.len(),
            });
        }
        Ok(Self {
            stamp,
            width,
            height,
            stride,
            format,
            data,
        })
    }

    /// When the picture was taken.
    pub fn stamp(&self) -> Timestamp {
        self.stamp
    }

    /// Columns.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Rows.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Pixel layout.
    pub fn format(&self) -> PixelFormat {
        self.format
    }

    /// Bytes from one row to the next.
    pub fn stride(&self) -> usize {
        self.stride
    }

    /// The whole buffer, rows `stride` bytes apart.
    pub fn bytes(&self) -> &'a [u8] {
        self.data
    }

    /// The pixels of row `y` (without padding), or `None` past the last row.
    pub fn row(&self, y: usize) -> Option<&'a [u8]> {
        let start = y.checked_mul(self.stride)?;
        let len = self.width * self.format.bytes_per_pixel();
        if y >= self.height {
            return None;
        }
        self.data.get(start..start + len)
    }

    /// The grey value of pixel (x, y): the byte itself for mono8, else the integer
    /// Rec. 601 luma `(77 R + 150 G + 29 B) / 256`.
    pub fn luminance(&self, x: usize, y: usize) -> Option<u8> {
        if x >= self.width {
            return None;
        }
        let row = self.row(y)?;
        let bpp = self.format.bytes_per_pixel();
        let px = row.get(x * bpp..x * bpp + bpp)?;
        let (r, g, b) = match (self.format, px) {
            (PixelFormat::Mono8, [v]) => return Some(*v),
            (PixelFormat::Rgb8, [r, g, b]) => (*r, *g, *b),
            (PixelFormat::Bgr8, [b, g, r]) => (*r, *g, *b),
            _ => return None,
        };
        let luma = (77 * u32::from(r) + 150 * u32::from(g) + 29 * u32::from(b)) >> 8;
        u8::try_from(luma).ok()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checks_sizes() {
        let data = [0u8; 20];
        assert_eq!(
            ImageView::new_checked(Timestamp(0), 0, 1, 1, PixelFormat::Mono8, &data),
            Err(ImageError::ZeroSize)
        );
        assert_eq!(
            ImageView::new_checked(Timestamp(0), 3, 1, 8, PixelFormat::Rgb8, &data),
            Err(ImageError::StrideTooSmall)
        );
        assert_eq!(
            ImageView::new_checked(Timestamp(0), 3, 3, 9, PixelFormat::Rgb8, &data),
            Err(ImageError::BufferTooSmall {
                needed: 27,
                got: 20
            })
        );
        // Two rows of 2 RGB pixels with 4 bytes of padding, the last row unpadded: 10+6.
        assert!(
            ImageView::new_checked(Timestamp(0), 2, 2, 10, PixelFormat::Rgb8, &data[..16]).is_ok()
        );
    }

    #[test]
    fn luminance_of_each_format() {
        let rgb = [255, 0, 0, 0, 0, 255];
        let v = ImageView::new_checked(Timestamp(0), 2, 1, 6, PixelFormat::Rgb8, &rgb).unwrap();
        assert_eq!(v.luminance(0, 0), Some(76));
        assert_eq!(v.luminance(1, 0), Some(28));
        let v = ImageView::new_checked(Timestamp(0), 2, 1, 6, PixelFormat::Bgr8, &rgb).unwrap();
        assert_eq!(v.luminance(0, 0), Some(28));
        assert_eq!(v.luminance(2, 0), None);
        assert_eq!(v.luminance(0, 1), None);
        let mono = [1, 2, 3, 4, 9, 9];
        let v =
            ImageView::new_checked(Timestamp(0), 2, 2, 3, PixelFormat::Mono8, &mono[..5]).unwrap();
        assert_eq!(v.row(1), Some(&[4u8, 9][..]));
        assert_eq!(v.luminance(1, 1), Some(9));
    }
}
