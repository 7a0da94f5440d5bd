//! The camera half of the front-end (block a of Fig. 2, section III-B.1) as the mapper runs it:
//! each image is tracked against its camera's previous one ([`CameraTrack`]), giving the 2D
//! features and frame-to-frame matches the visual odometry starts from, and the low-feature
//! frames are counted.
//!
//! With the visual odometry's storage ([`CameraParts::visual`]), camera 0's images go on to
//! the visual odometry and its keyframes become frame nodes (module `visual`): the mapper of
//! sensor set C. Without it the images are only tracked and measured; that is also how a
//! mapper with a LiDAR takes them, the LiDAR alone building the map (tying camera keyframes
//! to LiDAR ones, by odometry or by the zero-constraint of eq. (1), is not done yet).
//!
//! The storage is optional ([`CameraParts`]): a mapper built without it (the LiDAR-only
//! firmware) refuses images with [`MapperError::NoCamera`] and the caller counts them.

use super::visual::VisualParts;
use super::{FrameOutput, Mapper, MapperError};
use crate::frontend::visual::matching::Match;
use crate::frontend::visual::track::{CameraTrack, TrackScratch, TrackStats, TrackStep};
use crate::frontend::visual::Keypoint;
use crate::sensor::ImageView;

/// Most cameras a mapper tracks (the paper's sensor sets C and 2C).
pub const MAX_CAMERAS: usize = 2;

/// The storage of the camera stage, lent by the caller like the rest of the resources.
#[derive(Debug)]
pub struct CameraParts<'r> {
    /// One track per camera; camera `i` uses `tracks[i]`.
    pub tracks: &'r mut [CameraTrack],
    /// Scratch of one frame: at least
    /// [`scratch_bytes`](crate::frontend::visual::frame::scratch_bytes) of the largest frame
    /// accepted (larger ones are refused and counted).
    pub bytes: &'r mut [u8],
    /// The detector's output ([`MAX_FEATURES`](crate::frontend::visual::frame::MAX_FEATURES)
    /// is enough).
    pub corners: &'r mut [Keypoint],
    /// The matcher's output (as many as `corners`).
    pub matches: &'r mut [Match],
    /// The visual odometry of camera 0 and its calibration: with it, camera 0's keyframes
    /// become frame nodes (sensor set C); without it, images are only tracked.
    pub visual: Option<VisualParts<'r>>,
}

/// What the mapper did with one image.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ImageOutput {
    /// The image's stamp, ns.
    pub stamp: i64,
    /// Which camera.
    pub camera: u8,
    /// Features and matches to the camera's previous frame.
    pub track: TrackStep,
    /// The robot's pose at the image, when the mapper runs the visual odometry (as a scan's
    /// for a LiDAR).
    pub frame: Option<FrameOutput>,
}

impl Mapper<'_> {
    /// Tracks image `view` of camera `camera`, taken at `stamp` ns; with the visual odometry,
    /// camera 0's image then gets a pose (the GPE's, or the worst-case prediction when
    /// `deadline_passed`) and its keyframes become frame nodes (module `visual`).
    ///
    /// # Errors
    /// [`MapperError::NoCamera`] when the mapper has no camera storage or no track for
    /// `camera`; [`MapperError::Image`] when the image is out of order or unreadable (counted
    /// in the camera's [`TrackStats`]).
    pub fn push_image(
        &mut self,
        camera: u8,
        stamp: i64,
        view: &ImageView<'_>,
        deadline_passed: bool,
    ) -> Result<ImageOutput, MapperError> {
        let cfg = self.cfg.camera;
        let parts = self.cameras.as_mut().ok_or(MapperError::NoCamera)?;
        let track = parts
            .tracks
            .get_mut(usize::from(camera))
            .ok_or(MapperError::NoCamera)?;
        let mut scratch = TrackScratch {
            bytes: parts.bytes,
            corners: parts.corners,
            matches: parts.matches,
        };
        let step = track
            .track(stamp, view, &cfg, &mut scratch)
            .map_err(MapperError::Image)?;
        let frame = if camera == 0 {
            self.visual_frame(stamp, step.tracked, deadline_passed)
        } else {
            None
        };
        Ok(ImageOutput {
            stamp,
            camera,
            track: step,
            frame,
        })
    }

    /// The counters of each camera the mapper has storage for (none without camera storage).
    pub fn camera_stats(&self) -> impl Iterator<Item = TrackStats> + '_ {
        let tracks = self.cameras.as_ref().map_or(&[][..], |p| &*p.tracks);
        tracks.iter().map(CameraTrack::stats)
    }
}
