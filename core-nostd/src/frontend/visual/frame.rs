//! The 2D features of one camera frame, the `p_p` of the paper's section III-B.1: the frame's
//! luminance, its pyramid, FAST corners spread by the grid, and a rotated BRIEF descriptor for
//! each corner whose patch fits its level, all in fixed storage.
//!
//! The scratch bytes (grey copy, pyramid levels, one smoothed level) are lent by the caller and
//! sized for the largest frame it accepts ([`scratch_bytes`]); the result, [`FrameFeatures`],
//! is a fixed array that outlives the scratch so the next frame can be matched against it.

use super::brief::describe;
use super::fast::detect_pyramid;
use super::image::{smooth_into, smoothed_bytes};
use super::pyramid::pyramid_bytes;
use super::{Descriptor, DetectStats, FastConfig, GrayImage, Keypoint, Pyramid};
use crate::sensor::{ImageError, ImageView, PixelFormat};

/// Most features one frame keeps (a quarter-VGA frame at the default grid gives about 60 on a
/// textured ceiling; the rest is headroom for larger frames).
pub const MAX_FEATURES: usize = 256;

/// Pyramid levels asked for (halving each): corners at four scales cover the size change of a
/// ceiling feature as the robot passes under it.
pub const LEVELS: usize = 4;

/// Bytes of scratch a `width` x `height` frame needs: its grey copy, the pyramid's levels
/// below it, and one smoothed level (the largest) reused for every level.
pub const fn scratch_bytes(width: usize, height: usize) -> usize {
    width * height + pyramid_bytes(width, height, LEVELS) + smoothed_bytes(width, height)
}

/// Why a frame gave no features.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum FrameError {
    /// The frame is larger than the scratch was sized for.
    TooLarge,
    /// The frame's sizes are unusable.
    Image(ImageError),
}

impl From<ImageError> for FrameError {
    fn from(e: ImageError) -> Self {
        FrameError::Image(e)
    }
}

/// The features of one frame: keypoints (in the pixels of their level) and descriptors, paired
/// by index.
#[derive(Clone, Debug)]
pub struct FrameFeatures {
    keypoints: [Keypoint; MAX_FEATURES],
    descriptors: [Descriptor; MAX_FEATURES],
    len: usize,
    /// What the detector did on this frame.
    pub detect: DetectStats,
}

impl Default for FrameFeatures {
    fn default() -> Self {
        Self::new()
    }
}

impl FrameFeatures {
    /// No features.
    pub const fn new() -> Self {
        FrameFeatures {
            keypoints: [Keypoint {
                x: 0.0,
                y: 0.0,
                level: 0,
                score: 0.0,
                angle: 0.0,
            }; MAX_FEATURES],
            descriptors: [Descriptor([0; 8]); MAX_FEATURES],
            len: 0,
            detect: DetectStats {
                kept: 0,
                cells: 0,
                relaxed_cells: 0,
                empty_cells: 0,
                dropped: 0,
            },
        }
    }

    /// How many features there are.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether there is none.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The keypoints.
    pub fn keypoints(&self) -> &[Keypoint] {
        self.keypoints.get(..self.len).unwrap_or(&[])
    }

    /// The descriptors, one per keypoint.
    pub fn descriptors(&self) -> &[Descriptor] {
        self.descriptors.get(..self.len).unwrap_or(&[])
    }

    /// Forgets every feature.
    pub fn clear(&mut self) {
        self.len = 0;
        self.detect = DetectStats::default();
    }

    /// Extracts the features of `view` into `self`, using `scratch` (at least
    /// [`scratch_bytes`] of the frame's size) and `corners` (the detector's output, which
    /// bounds how many corners are looked at; [`MAX_FEATURES`] is enough).
    ///
    /// Corners whose descriptor patch leaves their level are dropped; the order is the
    /// detector's (level by level, cells in raster order), so equal inputs give equal features.
    ///
    /// # Errors
    /// [`FrameError::TooLarge`] when `scratch` is too small for the frame, or
    /// [`FrameError::Image`] for unusable sizes; `self` is then empty.
    pub fn extract(
        &mut self,
        view: &ImageView<'_>,
        cfg: &FastConfig,
        scratch: &mut [u8],
        corners: &mut [Keypoint],
    ) -> Result<(), FrameError> {
        self.clear();
        let (w, h) = (view.width(), view.height());
        let area = w.checked_mul(h).ok_or(FrameError::TooLarge)?;
        if scratch.len() < scratch_bytes(w, h) {
            return Err(FrameError::TooLarge);
        }
        let (grey_bytes, rest) = scratch.split_at_mut(area);
        let (pyramid_store, smooth_store) = rest.split_at_mut(pyramid_bytes(w, h, LEVELS));
        // A grey frame is read where it lies; colour is converted into the scratch.
        let grey = match view.format() {
            PixelFormat::Mono8 => GrayImage::new_checked(w, h, view.stride(), view.bytes())?,
            PixelFormat::Rgb8 | PixelFormat::Bgr8 => GrayImage::from_sensor(view, grey_bytes)?,
        };
        let pyramid =
            Pyramid::build(grey, LEVELS, pyramid_store).map_err(|_| FrameError::TooLarge)?;
        self.detect = detect_pyramid(&pyramid, cfg, corners);
        let found = corners.get(..self.detect.kept).unwrap_or(&[]);
        for l in 0..pyramid.len() {
            let Some(level) = pyramid.level(l) else {
                break;
            };
            // A level without corners needs no smoothed copy.
            if !found.iter().any(|k| usize::from(k.level) == l) {
                continue;
            }
            let smoothed = smooth_into(&level, smooth_store)?;
            for kp in found.iter().filter(|k| usize::from(k.level) == l) {
                let Some(d) = describe(&smoothed, kp) else {
                    continue;
                };
                let (Some(k), Some(s)) = (
                    self.keypoints.get_mut(self.len),
                    self.descriptors.get_mut(self.len),
                ) else {
                    return Ok(());
                };
                (*k, *s) = (*kp, d);
                self.len += 1;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    extern crate std;

    use super::*;
    use crate::frontend::visual::synth::{features_of, Scene, View};
    use crate::sensor::{PixelFormat, Timestamp};

    fn view(data: &[u8], w: usize, h: usize) -> ImageView<'_> {
        ImageView::new_checked(Timestamp::from_nanos(0), w, h, w, PixelFormat::Mono8, data)
            .expect("valid sizes")
    }

    /// The features of `frame` with the default settings and scratch of its size.
    fn features(frame: &ImageView<'_>) -> FrameFeatures {
        let mut f = FrameFeatures::new();
        let mut scratch = std::vec![0u8; scratch_bytes(frame.width(), frame.height())];
        let mut corners = [Keypoint::default(); MAX_FEATURES];
        f.extract(frame, &FastConfig::default(), &mut scratch, &mut corners)
            .expect("sized scratch");
        f
    }

    #[test]
    fn features_of_a_textured_frame_match_the_single_level_pipeline() {
        let (w, h) = (320, 240);
        let img = Scene::random(7, w, h, 40).render(&View::new(w, h, 0.0, [0.0, 0.0]));
        let f = features(&view(&img, w, h));
        assert!(f.len() >= 40, "{} features", f.len());
        assert_eq!(f.keypoints().len(), f.descriptors().len());
        // Every level-0 feature is one the plain single-level detector and descriptor find.
        let single = features_of(&img, w, h);
        let level0 = f.keypoints().iter().zip(f.descriptors());
        for (kp, d) in level0.filter(|(k, _)| k.level == 0) {
            assert!(
                single
                    .iter()
                    .any(|(s, sd)| s.x == kp.x && s.y == kp.y && sd == d),
                "feature at ({}, {}) not found by the single-level pipeline",
                kp.x,
                kp.y
            );
        }
        assert!(f.keypoints().iter().any(|k| k.level > 0));
    }

    #[test]
    fn a_grey_colour_frame_gives_the_grey_frames_features() {
        let (w, h) = (160, 120);
        let grey = Scene::random(9, w, h, 20).render(&View::new(w, h, 0.3, [0.0, 0.0]));
        let rgb: std::vec::Vec<u8> = grey.iter().flat_map(|&v| [v, v, v]).collect();
        let colour = ImageView::new_checked(
            Timestamp::from_nanos(0),
            w,
            h,
            3 * w,
            PixelFormat::Rgb8,
            &rgb,
        )
        .expect("valid sizes");
        let (a, b) = (features(&view(&grey, w, h)), features(&colour));
        assert!(a.len() > 10);
        assert_eq!(a.keypoints(), b.keypoints());
        assert_eq!(a.descriptors(), b.descriptors());
    }

    #[test]
    fn a_frame_larger_than_the_scratch_is_refused_and_leaves_no_features() {
        let (w, h) = (64, 48);
        let img = std::vec![128u8; w * h];
        let mut f = FrameFeatures::new();
        let mut small = std::vec![0u8; scratch_bytes(w, h) - 1];
        let mut corners = [Keypoint::default(); 8];
        let r = f.extract(
            &view(&img, w, h),
            &FastConfig::default(),
            &mut small,
            &mut corners,
        );
        assert_eq!(r, Err(FrameError::TooLarge));
        assert!(f.is_empty());
    }

    #[test]
    fn a_plain_frame_has_no_features() {
        let (w, h) = (160, 120);
        let img = std::vec![90u8; w * h];
        assert!(features(&view(&img, w, h)).is_empty());
    }
}
