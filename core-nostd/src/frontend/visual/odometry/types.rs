//! The visual odometry's configuration, its input frame, its errors, and what it reports per
//! keyframe and in all.

use super::*;

/// Visual odometry parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct VoConfig {
    /// Wheel+gyro distance since the last keyframe that makes a keyframe, metres.
    pub keyframe_distance: f64,
    /// Wheel+gyro heading change since the last keyframe that makes a keyframe, radians.
    pub keyframe_heading: f64,
    /// Fewer surviving tracks of the last keyframe than this (and fewer than half of them)
    /// makes a keyframe (20: the paper's feature count below which a feature-only system
    /// fails).
    pub min_tracked: usize,
    /// Standard normal quantile of the redundancy test (1.645: the 95 % point).
    pub redundancy_z: f64,
    /// Standard deviation of a level-0 feature position, pixels (doubled per pyramid level;
    /// 0.5: a FAST corner sits on its level's pixel grid).
    pub sigma_px: f64,
    /// Wheel+gyro noise between keyframes: position standard deviation, metres, a floor plus
    /// a share of the distance.
    pub odometry_sigma_xy: [f64; 2],
    /// Heading standard deviation, radians: a floor, per metre driven and per radian turned.
    pub odometry_sigma_theta: [f64; 3],
    /// Acceptance of a triangulated point.
    pub triangulate: TriangulateConfig,
    /// Farthest a landmark may lie from the camera of the newest keyframe, metres. Farther,
    /// a point is refused at triangulation or dropped after a solve: indoors nothing is seen
    /// that far, and a point the window pushes out along its ray has no depth worth keeping.
    pub max_range: f64,
    /// The window solve (at least one pose is always held fixed).
    pub window: WindowConfig,
    /// Radius around a landmark's predicted pixel in a new keyframe within which its
    /// descriptor is searched, level-0 pixels (0 turns the re-finding off).
    pub refind_radius_px: f32,
    /// Acceptance of a re-found landmark (distance and ratio tests of the guided matcher).
    pub refind: MatchConfig,
    /// The measures for scenes with few features.
    pub low_feature: LowFeatureConfig,
}

/// The paper's three measures for scenes with few features (section III-B.1), each turned
/// off by its own zero; see the `lowfeature` file of the odometry for what each does.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LowFeatureConfig {
    /// (a) Radius, level-0 pixels, around a window landmark's pixel predicted in an older
    /// keyframe of the window that does not see it, within which that keyframe's features
    /// whose track ended without a landmark are matched to it by descriptor (0: off).
    pub backfill_radius_px: f32,
    /// (a) Acceptance of such a sighting (distance and ratio tests of the guided matcher).
    pub backfill: MatchConfig,
    /// (b) Two landmarks closer than this, metres, with matching descriptors and never seen
    /// in the same keyframe, are merged into one (0: off).
    pub merge_distance: f64,
    /// (b) Largest Hamming distance between the descriptors of two landmarks merged.
    pub merge_max_hamming: u32,
    /// (c) A landmark seen in fewer keyframes than this when the oldest keyframe that saw it
    /// leaves the window is dropped from the window (below 2: off).
    pub min_sightings: usize,
}

impl Default for LowFeatureConfig {
    fn default() -> Self {
        LowFeatureConfig {
            // Tighter than the re-finding's: an older keyframe's pose is solved, so the
            // prediction is better than a new keyframe's wheel+gyro guess, and each extra pixel
            // lets in more look-alike ceiling corners (the solve refused a fifth of the
            // sightings found within 8 px in the simulated home). Measured in
            // docs/benchmarks.md: 4 to 8 px all help, 3 px loses true sightings.
            backfill_radius_px: 5.0,
            backfill: MatchConfig::default(),
            // Close enough that two neighbouring ceiling corners with similar descriptors stay
            // apart; a new landmark's two-view depth can be off by more, so some duplicates
            // wait for a solve to bring them together. 0.25 m merged two or three more a run in
            // the simulated home and did not help (docs/benchmarks.md).
            merge_distance: 0.1,
            merge_max_hamming: 64,
            // The paper's figure for indoor scenes.
            min_sightings: 4,
        }
    }
}

impl Default for VoConfig {
    fn default() -> Self {
        VoConfig {
            keyframe_distance: 0.25,
            keyframe_heading: 10f64.to_radians(),
            min_tracked: 20,
            redundancy_z: 1.645,
            sigma_px: 0.5,
            odometry_sigma_xy: [0.005, 0.05],
            odometry_sigma_theta: [0.002, 0.02, 0.05],
            // A first guess the window refines: a quarter of the depth is close enough for it
            // to converge, and a tenth would wait for baselines that short tracks never reach.
            triangulate: TriangulateConfig {
                max_relative_depth_error: 0.25,
                ..TriangulateConfig::default()
            },
            max_range: 20.0,
            window: WindowConfig::default(),
            // The wheel+gyro prediction over one keyframe's motion (a quarter metre, ten
            // degrees) moves a ceiling point by a few pixels at most on the 320 x 240 fisheye.
            refind_radius_px: 8.0,
            refind: MatchConfig::default(),
            low_feature: LowFeatureConfig::default(),
        }
    }
}

/// One camera frame as the odometry takes it.
#[derive(Clone, Copy, Debug)]
pub struct VoFrame<'a> {
    /// Capture time, nanoseconds.
    pub stamp: i64,
    /// Wheel+gyro pose of the robot at `stamp`, in the odometry frame.
    pub odometry: Se2,
    /// The frame's features ([`FrameFeatures::keypoints`](crate::frontend::visual::FrameFeatures::keypoints));
    /// those beyond [`MAX_FEATURES`] are ignored.
    pub keypoints: &'a [Keypoint],
    /// Matches to the previous frame given to the odometry: `query` indexes its keypoints,
    /// `train` this frame's (what [`CameraTrack::track`](crate::frontend::visual::CameraTrack::track) writes).
    pub matches: &'a [Match],
    /// The frame's descriptors, one per keypoint
    /// ([`FrameFeatures::descriptors`](crate::frontend::visual::FrameFeatures::descriptors)); empty, the window's
    /// landmarks are not searched for in the frame.
    pub descriptors: &'a [Descriptor],
}

/// Why a frame was refused (each counted in [`VoStats`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum VoError {
    /// The stamp is not later than the previous frame's.
    OutOfOrder,
    /// The wheel+gyro pose is not finite.
    BadPose,
    /// The frame has no usable feature.
    NoFeatures,
    /// No feature of the frame continues a track of the previous frame.
    NoMatches,
}

impl core::fmt::Display for VoError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::OutOfOrder => "frame stamp does not advance",
            Self::BadPose => "wheel+gyro pose is not finite",
            Self::NoFeatures => "frame has no usable feature",
            Self::NoMatches => "no feature matched to the previous frame",
        })
    }
}

impl core::error::Error for VoError {}

/// Which rule made a keyframe.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum KeyframeReason {
    /// The first accepted frame.
    First,
    /// Distance or heading travelled.
    Motion,
    /// Too few of the last keyframe's tracks survive.
    FewTracked,
}

/// What a new keyframe gave.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KeyframeOutput {
    /// The frame's stamp.
    pub stamp: i64,
    /// Why it became a keyframe.
    pub reason: KeyframeReason,
    /// Its refined pose relative to the previous keyframe's refined pose (`None` for the
    /// first keyframe): the odometry edge of its frame node.
    pub relative: Option<Se2>,
    /// Its refined pose in the odometry's frame (the first keyframe's wheel+gyro pose).
    pub pose: Se2,
    /// Landmarks it observes after the solve.
    pub landmarks_seen: usize,
    /// Landmarks triangulated at this keyframe.
    pub new_landmarks: usize,
    /// Landmarks whose track had broken, re-found in this keyframe near their predicted pixel.
    pub refound: usize,
    /// Observations dropped as outliers by this keyframe's solve.
    pub outliers_dropped: usize,
    /// Landmarks dropped because most of their sightings were outliers.
    pub landmarks_dropped: usize,
    /// Sightings of the window's landmarks found in older keyframes of the window (low-feature
    /// measure a).
    pub backfilled: usize,
    /// Landmarks merged into another one (low-feature measure b).
    pub merged: usize,
    /// Landmarks dropped, before this keyframe entered, for too few sightings (low-feature
    /// measure c).
    pub short_lived_dropped: usize,
    /// The solve, or why the window could not be solved (the poses then stay at their
    /// wheel+gyro guesses); [`WindowError::NoMeasurements`] for the first keyframe, which is
    /// not solved.
    pub solve: Result<WindowSummary, WindowError>,
}

/// What one frame gave.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VoStep {
    /// Features of the frame that continue a track.
    pub tracked: usize,
    /// The keyframe the frame became, if it did.
    pub keyframe: Option<KeyframeOutput>,
}

/// Counters of the odometry.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct VoStats {
    /// Frames accepted.
    pub frames: u32,
    /// Keyframes made.
    pub keyframes: u32,
    /// Frames the motion rule selected but the redundancy test skipped.
    pub redundant: u32,
    /// Frames refused: stamp not advancing.
    pub out_of_order: u32,
    /// Frames refused: pose not finite.
    pub bad_pose: u32,
    /// Frames refused: no usable feature.
    pub no_features: u32,
    /// Frames refused: no match to the previous frame.
    pub no_matches: u32,
    /// Matches skipped because they name features that do not exist, or a feature twice.
    pub bad_matches: u32,
    /// Features skipped because their pixel is not finite.
    pub bad_pixels: u32,
    /// Landmarks triangulated.
    pub landmarks: u32,
    /// Landmarks re-found in a keyframe after their track had broken.
    pub refound: u32,
    /// Tracks not triangulated for too little parallax between their two keyframes.
    pub low_parallax: u32,
    /// Tracks not triangulated otherwise: rays missing each other, behind a camera, no ray,
    /// or out of [`VoConfig::max_range`].
    pub triangulation_refused: u32,
    /// Landmarks or observations that found no room (landmark or observation storage full).
    pub capacity_dropped: u32,
    /// Outlying observations dropped.
    pub outliers_dropped: u32,
    /// Landmarks dropped for their outliers.
    pub landmarks_dropped: u32,
    /// Sightings of landmarks found in older keyframes of the window.
    pub backfilled: u32,
    /// Landmarks merged into a duplicate.
    pub merged: u32,
    /// Landmarks dropped for being seen in too few keyframes.
    pub short_lived_dropped: u32,
    /// Of the outlying observations, those found in an older keyframe.
    pub backfilled_outliers: u32,
    /// Window solves that failed (the poses then keep their wheel+gyro guesses); the first
    /// keyframe's, which has nothing to solve, is not counted.
    pub solve_failures: u32,
}
