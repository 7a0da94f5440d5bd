//! The camera half of the front-end (block a of Fig. 2, section III-B.1) as the mapper runs it:
//! each image is tracked against its camera's previous one ([`CameraTrack`]), giving the 2D
//! features and frame-to-frame matches the visual odometry starts from, and the low-feature
//! frames are counted.
//!
//! Camera frames do not become frame nodes yet: that needs the visual odometry (triangulation
//! and the sliding-window adjustment), after which a camera keyframe joins the graph like a
//! LiDAR one (module `frames`), tied by odometry or, when synchronized, by the zero-constraint
//! of eq. (1). Until then the LiDAR alone builds the map and the images are measured.
//!
//! The storage is optional ([`CameraParts`]): a mapper built without it (the LiDAR-only
//! firmware) refuses images with [`MapperError::NoCamera`] and the caller counts them.

use super::{Mapper, MapperError};
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
}

/// What the mapper did with one image.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ImageOutput {
    /// The image's stamp, ns.
    pub stamp: i64,
    /// Which camera.
    pub camera: u8,
    /// Features and matches to the camera's previous frame.
    pub track: TrackStep,
}

impl Mapper<'_> {
    /// Tracks image `view` of camera `camera`, taken at `stamp` ns.
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
        Ok(ImageOutput {
            stamp,
            camera,
            track: step,
        })
    }

    /// The counters of each camera the mapper has storage for (none without camera storage).
    pub fn camera_stats(&self) -> impl Iterator<Item = TrackStats> + '_ {
        let tracks = self.cameras.as_ref().map_or(&[][..], |p| &*p.tracks);
        tracks.iter().map(CameraTrack::stats)
    }
}
