//! Camera pictures from ROS 2 messages as the mapper's camera stage reads them: the raw
//! `sensor_msgs/msg/Image` encodings the core views directly (`mono8`, `rgb8`, `bgr8`, and
//! `8UC1`, which drivers use for grey), and `sensor_msgs/msg/CompressedImage` (JPEG, PNG)
//! decoded to grey by the `image` crate. Anything else is refused with the reason, so the
//! caller can count and report it.

use anyhow::{anyhow, bail, Result};
use cloi_core::sensor::PixelFormat;

use crate::ros2::{CompressedImage, Image};

/// Largest side of a compressed image that is decoded, pixels.
pub const MAX_SIDE: u32 = 4096;
/// Most bytes a decoder may allocate for one compressed image (a 4096 x 4096 RGBA frame).
const MAX_DECODE_BYTES: u64 = 4 * 4096 * 4096;

/// Uncompressed pixels with their layout.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Pixels {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Bytes per row.
    pub stride: usize,
    /// Pixel layout.
    pub format: PixelFormat,
    /// `stride * height` bytes (at least).
    pub data: Vec<u8>,
}

/// The pixel layout of a raw image encoding, if the core reads it.
pub fn raw_format(encoding: &str) -> Option<PixelFormat> {
    match encoding.to_ascii_lowercase().as_str() {
        "mono8" | "8uc1" => Some(PixelFormat::Mono8),
        "rgb8" => Some(PixelFormat::Rgb8),
        "bgr8" => Some(PixelFormat::Bgr8),
        _ => None,
    }
}

/// The pixels of a raw image message.
///
/// # Errors
/// An encoding the core does not read (e.g. `mono16`, `bayer_rggb8`, `yuv422`), or sizes the
/// data does not hold.
pub fn from_raw(msg: Image) -> Result<Pixels> {
    let format = raw_format(&msg.encoding).ok_or_else(|| {
        anyhow!(
            "image encoding {:?} is not read (mono8, rgb8, bgr8)",
            msg.encoding
        )
    })?;
    let (width, height, stride) = (msg.width as usize, msg.height as usize, msg.step as usize);
    let needed = stride
        .checked_mul(height)
        .ok_or_else(|| anyhow!("image sizes overflow"))?;
    if width == 0
        || height == 0
        || stride < width * format.bytes_per_pixel()
        || msg.data.len() < needed
    {
        bail!(
            "image of {width}x{height}, {stride} bytes per row, holds {} bytes",
            msg.data.len()
        );
    }
    Ok(Pixels {
        width,
        height,
        stride,
        format,
        data: msg.data,
    })
}

/// A compressed image decoded to grey.
///
/// # Errors
/// Data the `image` crate cannot decode (JPEG and PNG are built in).
pub fn from_compressed(msg: &CompressedImage) -> Result<Pixels> {
    let not_decoded =
        |e: &dyn std::fmt::Display| anyhow!("compressed image ({:?}) not decoded: {e}", msg.format);
    let mut reader = image::ImageReader::new(std::io::Cursor::new(&msg.data))
        .with_guessed_format()
        .map_err(|e| not_decoded(&e))?;
    // A damaged or hostile header may claim any size: decode nothing larger than a camera
    // the mapper could take, and never allocate more than such a frame in colour needs.
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(MAX_SIDE);
    limits.max_image_height = Some(MAX_SIDE);
    limits.max_alloc = Some(MAX_DECODE_BYTES);
    reader.limits(limits);
    let img = reader.decode().map_err(|e| not_decoded(&e))?.into_luma8();
    let (width, height) = (img.width() as usize, img.height() as usize);
    Ok(Pixels {
        width,
        height,
        stride: width,
        format: PixelFormat::Mono8,
        data: img.into_raw(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros2::Header;

    fn raw(encoding: &str, w: u32, h: u32, step: u32, len: usize) -> Image {
        Image {
            header: Header::default(),
            height: h,
            width: w,
            encoding: encoding.into(),
            is_bigendian: 0,
            step,
            data: vec![7; len],
        }
    }

    #[test]
    fn raw_encodings_are_read_or_refused_with_the_reason() {
        let p = from_raw(raw("rgb8", 4, 3, 12, 36)).unwrap();
        assert_eq!(
            (p.width, p.height, p.stride, p.format),
            (4, 3, 12, PixelFormat::Rgb8)
        );
        assert_eq!(
            from_raw(raw("8UC1", 4, 3, 4, 12)).unwrap().format,
            PixelFormat::Mono8
        );
        let e = from_raw(raw("mono16", 4, 3, 8, 24))
            .unwrap_err()
            .to_string();
        assert!(e.contains("mono16"), "{e}");
        assert!(from_raw(raw("mono8", 4, 3, 4, 11)).is_err());
        assert!(from_raw(raw("mono8", 4, 3, 3, 12)).is_err());
        assert!(from_raw(raw("mono8", 0, 3, 4, 12)).is_err());
    }

    #[test]
    fn a_png_decodes_to_grey_and_garbage_is_refused() {
        let mut png = Vec::new();
        let img = image::GrayImage::from_fn(5, 2, |x, y| image::Luma([(10 * x + y) as u8]));
        img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        let msg = CompressedImage {
            header: Header::default(),
            format: "png".into(),
            data: png,
        };
        let p = from_compressed(&msg).unwrap();
        assert_eq!((p.width, p.height, p.format), (5, 2, PixelFormat::Mono8));
        assert_eq!(p.data, img.into_raw());
        let bad = CompressedImage {
            data: vec![1, 2, 3],
            ..msg
        };
        assert!(from_compressed(&bad).is_err());
    }

    #[test]
    fn a_png_claiming_a_huge_size_is_refused_before_decoding() {
        // A valid 1 x 1 grey PNG whose header (and its CRC) claims 20,000 x 20,000 pixels: 400 MB,
        // which the decoder would allocate under its own default limit of 512 MiB.
        let mut png = Vec::new();
        image::GrayImage::new(1, 1)
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        // IHDR data sits after the 8-byte signature and the chunk's length and type.
        let side = 20_000u32.to_be_bytes();
        png[16..20].copy_from_slice(&side);
        png[20..24].copy_from_slice(&side);
        let crc = crc32fast::hash(&png[12..29]);
        png[29..33].copy_from_slice(&crc.to_be_bytes());
        let msg = CompressedImage {
            header: Header::default(),
            format: "png".into(),
            data: png,
        };
        let e = from_compressed(&msg).unwrap_err().to_string();
        eprintln!("{e}");
        assert!(e.contains("not decoded") && e.contains("limit"), "{e}");
    }
}
