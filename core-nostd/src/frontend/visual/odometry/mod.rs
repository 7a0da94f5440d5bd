//! Visual odometry between keyframes, the paper's section III-B.1: the frame-to-frame matches
//! of one camera ([`CameraTrack`](super::CameraTrack)) chained into feature tracks, visual
//! keyframes chosen among the frames, tracks seen from two keyframes triangulated into 3D
//! landmarks ([`triangulate`]), and the last `N` keyframes refined together with their
//! landmarks by the sliding-window bundle adjustment ([`BundleWindow`]), with the wheel+gyro
//! motion as a prior between consecutive keyframes. What comes out per keyframe is its planar
//! pose relative to the previous keyframe: the odometry edge of a visual frame node.
//!
//! # Per frame
//! Each feature of the new frame inherits the track id of the feature of the previous frame it
//! was matched to, or starts a new track. The frame then becomes a keyframe when one of the
//! paper's rules says so, in their simplest form:
//! * **distance travelled**: the wheel+gyro motion since the last keyframe reaches
//!   [`VoConfig::keyframe_distance`] or [`VoConfig::keyframe_heading`]. Triangulation needs a
//!   baseline, and a keyframe per fixed motion bounds the odometry drift between two visual
//!   corrections.
//! * **enough 2D/3D points**: fewer than [`VoConfig::min_tracked`] of the last keyframe's
//!   tracks survive in the frame, and fewer than half of them. A keyframe taken now still
//!   shares tracks with the last one; one taken later would share none, and nothing visual
//!   would link the two.
//! * **redundancy (chi2)**: a frame the motion rule selected is skipped while the tracked
//!   features have not moved in the image beyond their pixel noise: the sum of their squared
//!   displacements since the last keyframe, over the pixel variance, stays below the 95 %
//!   point of a chi2 with two degrees of freedom per feature. Such a frame sees what the last
//!   keyframe saw (wheels slipping on a stuck robot): it would add no parallax, only cost.
//!
//! # Per keyframe
//! 1. The keyframe's first pose is the previous keyframe's refined pose composed with the
//!    wheel+gyro motion between them.
//! 2. The window's landmarks that no feature of the frame continues are searched for again:
//!    each is projected with that first pose through the mounting and the camera model, and
//!    its descriptor (that of its latest sighting in a keyframe) is matched by
//!    [`match_guided`] within [`VoConfig::refind_radius_px`] of the prediction, against the
//!    features whose track started after the last keyframe. A feature so matched continues
//!    the landmark's track instead of starting a new one. A feature missed in a single frame
//!    would otherwise end its track for good: a longer track gives its landmark more
//!    observations, over wider baselines (the parallax that fixes its depth), and it is what
//!    the paper's low-feature measure of dropping landmarks seen in fewer than four keyframes
//!    presupposes. Tracks not yet triangulated keep no descriptor and are not re-found.
//! 3. Each of its tracks without a landmark is triangulated from the oldest keyframe of the
//!    window that saw it (the widest baseline) and this one; pairs with too little parallax
//!    or rays that miss each other are left for a later keyframe.
//! 4. The window is filled with the keyframes (oldest first), their landmarks, every sighting
//!    of a landmark in a keyframe, and the wheel+gyro motion priors between consecutive
//!    keyframes (information from [`VoConfig`]'s noise model), then solved.
//! 5. Observations the solve flags as outliers are dropped from their keyframe, and landmarks
//!    with more outlying than inlying sightings are dropped: a wrong match or a moving object.
//! 6. When the window is full, the oldest keyframe leaves it before the next one enters, with
//!    the landmarks no remaining keyframe sees. The oldest keyframe left is held fixed at its
//!    last solved pose (the gauge); nothing of the dropped keyframe is marginalised into a
//!    prior yet, so the information it carried about the others is lost.
//!
//! The output carries no covariance yet: the window does not expose its reduced system.
//!
//! # Bad input
//! A frame whose stamp does not advance is refused and leaves every state as it was (as
//! [`CameraTrack`](super::CameraTrack) refuses it too). A frame with a pose that is not finite,
//! without features, or (once there is a keyframe) without a single match to the previous
//! frame is refused and counted;
//! its features still become the previous frame of the next one (the camera's track moved on),
//! and without matches every feature starts a new track. Matches naming features that do not
//! exist, and features whose pixel is not finite, are skipped and counted. Features beyond the
//! frame's descriptors are not candidates for re-finding, and keep their landmark's descriptor
//! as it was.
//!
//! Nothing here allocates or recurses: features and landmarks are kept sorted by track id with
//! [`crate::sort`], and looked up by binary search.

use nalgebra::{Matrix3, Vector2, Vector3};

use super::brief::Descriptor;
use super::camera::{CameraExtrinsic, CameraModel};
use super::fast::Keypoint;
use super::frame::MAX_FEATURES;
use super::matching::{match_guided, Match, MatchConfig};
use super::triangulate::{
    triangulate, CameraPose, Observation, TriangulateConfig, TriangulateError, WorldPoint,
};
use super::window::{
    BundleWindow, LandmarkStatus, MotionPrior, ObservationStatus, PixelObservation, WindowConfig,
    WindowError, WindowSummary,
};
use crate::geom::Se2;

#[cfg(test)]
mod tests;

/// Track id of a feature that belongs to no track (dropped as an outlier, or unusable).
const NO_TRACK: u32 = u32::MAX;

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
    /// The frame's features ([`FrameFeatures::keypoints`](super::FrameFeatures::keypoints));
    /// those beyond [`MAX_FEATURES`] are ignored.
    pub keypoints: &'a [Keypoint],
    /// Matches to the previous frame given to the odometry: `query` indexes its keypoints,
    /// `train` this frame's (what [`CameraTrack::track`](super::CameraTrack::track) writes).
    pub matches: &'a [Match],
    /// The frame's descriptors, one per keypoint
    /// ([`FrameFeatures::descriptors`](super::FrameFeatures::descriptors)); empty, the window's
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
    /// Window solves that failed (the poses then keep their wheel+gyro guesses); the first
    /// keyframe's, which has nothing to solve, is not counted.
    pub solve_failures: u32,
}

/// One feature of a keyframe: its track and pixel.
#[derive(Clone, Copy, Debug, PartialEq)]
struct KeyFeature {
    track: u32,
    px: [f32; 2],
    level: u8,
}

const NO_FEATURE: KeyFeature = KeyFeature {
    track: NO_TRACK,
    px: [0.0; 2],
    level: 0,
};

/// A keyframe in the window; its features sorted by track id.
#[derive(Clone, Debug)]
struct Keyframe {
    odometry: Se2,
    pose: Se2,
    features: [KeyFeature; MAX_FEATURES],
    len: usize,
}

const EMPTY_KEYFRAME: Keyframe = Keyframe {
    odometry: Se2::IDENTITY,
    pose: Se2::IDENTITY,
    features: [NO_FEATURE; MAX_FEATURES],
    len: 0,
};

impl Keyframe {
    fn features(&self) -> &[KeyFeature] {
        self.features.get(..self.len).unwrap_or_default()
    }

    fn find(&self, track: u32) -> Option<(usize, &KeyFeature)> {
        let f = self.features();
        let i = f.binary_search_by_key(&track, |k| k.track).ok()?;
        Some((i, f.get(i)?))
    }

    /// Removes the features whose track was set to [`NO_TRACK`] (they sort last).
    fn compact(&mut self) {
        let f = self.features.get_mut(..self.len).unwrap_or_default();
        crate::sort::sort_by_key(f, |k| k.track);
        self.len = f.iter().take_while(|k| k.track != NO_TRACK).count();
    }
}

/// A triangulated track, with the descriptor of its latest sighting in a keyframe.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Landmark {
    track: u32,
    position: Vector3<f64>,
    descriptor: Descriptor,
}

const NO_LANDMARK: Landmark = Landmark {
    track: NO_TRACK,
    position: Vector3::new(0.0, 0.0, 0.0),
    descriptor: Descriptor([0; 8]),
};

/// Working space of the re-finding: the landmarks searched for (queries) and the frame's
/// features that may continue one (train), as [`match_guided`] takes them.
#[derive(Debug)]
struct RefindScratch<const M: usize> {
    query_track: [u32; M],
    query_descriptor: [Descriptor; M],
    query_px: [[f32; 2]; M],
    train_feature: [u16; MAX_FEATURES],
    train_descriptor: [Descriptor; MAX_FEATURES],
    train_px: [[f32; 2]; MAX_FEATURES],
    /// The frame's track ids, sorted.
    tracked: [u32; MAX_FEATURES],
    matches: [Match; MAX_FEATURES],
}

impl<const M: usize> RefindScratch<M> {
    const fn new() -> Self {
        const NO_MATCH: Match = Match {
            query: 0,
            train: 0,
            distance: 0,
        };
        RefindScratch {
            query_track: [NO_TRACK; M],
            query_descriptor: [Descriptor([0; 8]); M],
            query_px: [[0.0; 2]; M],
            train_feature: [0; MAX_FEATURES],
            train_descriptor: [Descriptor([0; 8]); MAX_FEATURES],
            train_px: [[0.0; 2]; MAX_FEATURES],
            tracked: [NO_TRACK; MAX_FEATURES],
            matches: [NO_MATCH; MAX_FEATURES],
        }
    }
}

/// Where a window observation came from: keyframe slot and feature index.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct ObservationSource {
    keyframe: u16,
    feature: u16,
}

/// Visual odometry of one camera: at most `N` keyframes in the window, `M` landmarks and `K`
/// observations.
///
/// The value is large (the window's storage, `N` keyframes of [`MAX_FEATURES`] features, and
/// the re-finding's working space for `M` landmarks and [`MAX_FEATURES`] features): build it
/// where it will live, not as a local on a small stack.
#[derive(Debug)]
pub struct VisualOdometry<const N: usize, const M: usize, const K: usize> {
    keyframes: [Keyframe; N],
    keyframe_count: usize,
    landmarks: [Landmark; M],
    landmark_count: usize,
    /// Track ids of the previous frame's features, by keypoint index.
    previous: [u32; MAX_FEATURES],
    previous_len: usize,
    /// Track ids of the frame being processed.
    current: [u32; MAX_FEATURES],
    next_track: u32,
    last_stamp: Option<i64>,
    sources: [ObservationSource; K],
    window: BundleWindow<N, M, K>,
    refind: RefindScratch<M>,
    stats: VoStats,
}

impl<const N: usize, const M: usize, const K: usize> Default for VisualOdometry<N, M, K> {
    fn default() -> Self {
        Self::new()
    }
}

/// The 95 % (for `z = 1.645`) point of a chi2 with `dof` degrees of freedom, by the
/// Wilson-Hilferty cube approximation.
fn chi2_quantile(dof: f64, z: f64) -> f64 {
    let a = 2.0 / (9.0 * dof);
    let c = 1.0 - a + z * libm::sqrt(a);
    dof * c * c * c
}

impl<const N: usize, const M: usize, const K: usize> VisualOdometry<N, M, K> {
    /// An odometry that has seen no frame.
    pub const fn new() -> Self {
        VisualOdometry {
            keyframes: [EMPTY_KEYFRAME; N],
            keyframe_count: 0,
            landmarks: [NO_LANDMARK; M],
            landmark_count: 0,
            previous: [NO_TRACK; MAX_FEATURES],
            previous_len: 0,
            current: [NO_TRACK; MAX_FEATURES],
            next_track: 0,
            last_stamp: None,
            sources: [ObservationSource {
                keyframe: 0,
                feature: 0,
            }; K],
            window: BundleWindow::new(),
            refind: RefindScratch::new(),
            stats: VoStats {
                frames: 0,
                keyframes: 0,
                redundant: 0,
                out_of_order: 0,
                bad_pose: 0,
                no_features: 0,
                no_matches: 0,
                bad_matches: 0,
                bad_pixels: 0,
                landmarks: 0,
                refound: 0,
                low_parallax: 0,
                triangulation_refused: 0,
                capacity_dropped: 0,
                outliers_dropped: 0,
                landmarks_dropped: 0,
                solve_failures: 0,
            },
        }
    }

    /// The counters so far.
    pub fn stats(&self) -> VoStats {
        self.stats
    }

    /// Keyframes in the window.
    pub fn keyframe_count(&self) -> usize {
        self.keyframe_count
    }

    /// Landmarks in the window.
    pub fn landmark_count(&self) -> usize {
        self.landmark_count
    }

    /// The refined pose of the newest keyframe.
    pub fn last_keyframe_pose(&self) -> Option<Se2> {
        let last = self.keyframe_count.checked_sub(1)?;
        Some(self.keyframes.get(last)?.pose)
    }

    /// Takes one camera frame: chains its tracks, and when it becomes a keyframe, triangulates,
    /// solves the window and slides it.
    ///
    /// # Errors
    /// [`VoError`] (counted; see the module docs for what a refused frame still changes).
    pub fn process(
        &mut self,
        frame: &VoFrame<'_>,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        cfg: &VoConfig,
    ) -> Result<VoStep, VoError> {
        if self.last_stamp.is_some_and(|t| frame.stamp <= t) {
            self.stats.out_of_order += 1;
            return Err(VoError::OutOfOrder);
        }
        self.last_stamp = Some(frame.stamp);
        let (features, tracked) = self.chain_tracks(frame);
        if !frame.odometry.is_finite() {
            self.stats.bad_pose += 1;
            return Err(VoError::BadPose);
        }
        if features == 0 {
            self.stats.no_features += 1;
            return Err(VoError::NoFeatures);
        }
        if tracked == 0 && self.keyframe_count > 0 {
            self.stats.no_matches += 1;
            return Err(VoError::NoMatches);
        }
        self.stats.frames += 1;
        let Some(reason) = self.keyframe_reason(frame, cfg) else {
            return Ok(VoStep {
                tracked,
                keyframe: None,
            });
        };
        let keyframe = self.add_keyframe(frame, reason, model, mount, cfg);
        Ok(VoStep {
            tracked,
            keyframe: Some(keyframe),
        })
    }

    /// Gives each feature of `frame` its track id (in `current`, then moved to `previous`).
    /// Returns the usable features and those continuing a track.
    fn chain_tracks(&mut self, frame: &VoFrame<'_>) -> (usize, usize) {
        let n = frame.keypoints.len().min(MAX_FEATURES);
        self.current.fill(NO_TRACK);
        let mut tracked = 0;
        for m in frame.matches {
            let from = self
                .previous
                .get(m.query)
                .filter(|_| m.query < self.previous_len);
            let to = self.current.get_mut(m.train).filter(|_| m.train < n);
            match (from, to) {
                (Some(&id), Some(slot)) if *slot == NO_TRACK && id != NO_TRACK => {
                    *slot = id;
                    tracked += 1;
                }
                (Some(&NO_TRACK), Some(_)) => {}
                _ => self.stats.bad_matches += 1,
            }
        }
        let mut features = 0;
        for (id, kp) in self.current.iter_mut().zip(frame.keypoints.iter().take(n)) {
            if !(kp.x.is_finite() && kp.y.is_finite()) {
                self.stats.bad_pixels += 1;
                if *id != NO_TRACK {
                    tracked -= 1;
                }
                *id = NO_TRACK;
                continue;
            }
            features += 1;
            if *id == NO_TRACK {
                *id = self.next_track;
                // Ids only need to differ within the window; wrapping keeps NO_TRACK out.
                self.next_track = self.next_track.wrapping_add(1) % NO_TRACK;
            }
        }
        self.previous = self.current;
        self.previous_len = n;
        (features, tracked)
    }

    /// Whether the frame (with ids in `current`) becomes a keyframe, and by which rule.
    fn keyframe_reason(&mut self, frame: &VoFrame<'_>, cfg: &VoConfig) -> Option<KeyframeReason> {
        let last = match self.keyframe_count.checked_sub(1) {
            Some(i) => self.keyframes.get(i)?,
            None => return Some(KeyframeReason::First),
        };
        let n = frame.keypoints.len().min(MAX_FEATURES);
        let (mut survivors, mut chi2) = (0usize, 0.0);
        for (&id, kp) in self.current.iter().zip(frame.keypoints.iter().take(n)) {
            let Some((_, f)) = self.last_track(last, id) else {
                continue;
            };
            survivors += 1;
            let sigma = cfg.sigma_px * f64::from(1u16 << f.level.min(8));
            let dx = f64::from(kp.position()[0] - f.px[0]);
            let dy = f64::from(kp.position()[1] - f.px[1]);
            chi2 += (dx * dx + dy * dy) / (sigma * sigma);
        }
        if survivors < cfg.min_tracked && 2 * survivors < last.len {
            return Some(KeyframeReason::FewTracked);
        }
        let motion = last.odometry.between(&frame.odometry);
        let moved = libm::hypot(motion.x, motion.y) >= cfg.keyframe_distance
            || libm::fabs(motion.theta) >= cfg.keyframe_heading;
        if !moved {
            return None;
        }
        let redundant =
            survivors > 0 && chi2 < chi2_quantile(2.0 * survivors as f64, cfg.redundancy_z);
        if redundant {
            self.stats.redundant += 1;
            return None;
        }
        Some(KeyframeReason::Motion)
    }

    fn last_track<'k>(&self, last: &'k Keyframe, id: u32) -> Option<(usize, &'k KeyFeature)> {
        if id == NO_TRACK {
            return None;
        }
        last.find(id)
    }

    /// Makes a keyframe of the frame, triangulates, solves and slides.
    fn add_keyframe(
        &mut self,
        frame: &VoFrame<'_>,
        reason: KeyframeReason,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        cfg: &VoConfig,
    ) -> KeyframeOutput {
        if self.keyframe_count == N {
            self.slide();
        }
        let guess = match self.keyframe_count.checked_sub(1) {
            Some(i) => self.keyframes.get(i).map_or(frame.odometry, |k| {
                k.pose.compose(&k.odometry.between(&frame.odometry))
            }),
            None => frame.odometry,
        };
        let slot = self.keyframe_count;
        let n = frame.keypoints.len().min(MAX_FEATURES);
        let refound = self.refind_landmarks(frame, &guess, model, mount, cfg);
        let Some(kf) = self.keyframes.get_mut(slot) else {
            // N == 0: no window at all.
            return KeyframeOutput {
                stamp: frame.stamp,
                reason,
                relative: None,
                pose: guess,
                landmarks_seen: 0,
                new_landmarks: 0,
                refound,
                outliers_dropped: 0,
                landmarks_dropped: 0,
                solve: Err(WindowError::Full),
            };
        };
        kf.odometry = frame.odometry;
        kf.pose = guess;
        kf.len = 0;
        for (&id, kp) in self.current.iter().zip(frame.keypoints.iter().take(n)) {
            if let (true, Some(f)) = (id != NO_TRACK, kf.features.get_mut(kf.len)) {
                *f = KeyFeature {
                    track: id,
                    px: kp.position(),
                    level: kp.level,
                };
                kf.len += 1;
            }
        }
        kf.compact();
        self.keyframe_count += 1;
        self.stats.keyframes += 1;
        let new_landmarks = self.triangulate_new(slot, model, mount, cfg);
        self.remember_descriptors(frame);
        let (solve, outliers_dropped, landmarks_dropped) = self.solve(model, mount, cfg);
        let pose = self.keyframes.get(slot).map_or(guess, |k| k.pose);
        let relative = slot
            .checked_sub(1)
            .and_then(|i| self.keyframes.get(i))
            .map(|p| p.pose.between(&pose));
        let landmarks_seen = self.keyframes.get(slot).map_or(0, |k| {
            k.features()
                .iter()
                .filter(|f| self.landmark_index(f.track).is_some())
                .count()
        });
        KeyframeOutput {
            stamp: frame.stamp,
            reason,
            relative,
            pose,
            landmarks_seen,
            new_landmarks,
            refound,
            outliers_dropped,
            landmarks_dropped,
            solve,
        }
    }

    fn landmark_index(&self, track: u32) -> Option<usize> {
        self.landmarks
            .get(..self.landmark_count)?
            .binary_search_by_key(&track, |l| l.track)
            .ok()
    }

    /// Searches the window's landmarks whose track no feature of `frame` continues near their
    /// pixel predicted from `guess` (the keyframe's first pose), by descriptor. A feature so
    /// matched takes the landmark's track id, in this frame and as the previous frame of the
    /// next. Only features whose track is in no keyframe of the window (started since the
    /// last keyframe) are candidates: an older track is not taken from its own sightings.
    /// Returns the landmarks re-found.
    fn refind_landmarks(
        &mut self,
        frame: &VoFrame<'_>,
        guess: &Se2,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        cfg: &VoConfig,
    ) -> usize {
        let radius = cfg.refind_radius_px;
        if radius.is_nan() || radius <= 0.0 || self.landmark_count == 0 {
            return 0;
        }
        let n = frame
            .keypoints
            .len()
            .min(frame.descriptors.len())
            .min(MAX_FEATURES);
        let s = &mut self.refind;
        // The frame's tracks, sorted, to tell which landmarks it already continues.
        let tracked = s.tracked.get_mut(..n).unwrap_or_default();
        tracked.copy_from_slice(self.current.get(..n).unwrap_or_default());
        crate::sort::sort_by_key(tracked, |&t| t);
        let camera = CameraPose::of_robot(guess, mount);
        let mut queries = 0;
        for l in self.landmarks.iter().take(self.landmark_count) {
            if tracked.binary_search(&l.track).is_ok() {
                continue;
            }
            let Some(px) = model.project(&camera.world_to_camera(&l.position)) else {
                continue;
            };
            let (Some(t), Some(d), Some(p)) = (
                s.query_track.get_mut(queries),
                s.query_descriptor.get_mut(queries),
                s.query_px.get_mut(queries),
            ) else {
                break;
            };
            *t = l.track;
            *d = l.descriptor;
            // Off-image and non-finite predictions simply find no candidate.
            *p = [px.x as f32, px.y as f32];
            queries += 1;
        }
        let keyframes = self
            .keyframes
            .get(..self.keyframe_count)
            .unwrap_or_default();
        let mut candidates = 0;
        for (i, ((&id, kp), d)) in self
            .current
            .iter()
            .zip(frame.keypoints)
            .zip(frame.descriptors)
            .enumerate()
            .take(n)
        {
            if id == NO_TRACK || keyframes.iter().any(|k| k.find(id).is_some()) {
                continue;
            }
            let (Some(f), Some(td), Some(tp), Ok(index)) = (
                s.train_feature.get_mut(candidates),
                s.train_descriptor.get_mut(candidates),
                s.train_px.get_mut(candidates),
                u16::try_from(i),
            ) else {
                break;
            };
            *f = index;
            *td = *d;
            *tp = kp.position();
            candidates += 1;
        }
        if queries == 0 || candidates == 0 {
            return 0;
        }
        let stats = match_guided(
            s.query_descriptor.get(..queries).unwrap_or_default(),
            s.query_px.get(..queries).unwrap_or_default(),
            s.train_descriptor.get(..candidates).unwrap_or_default(),
            s.train_px.get(..candidates).unwrap_or_default(),
            cfg.refind_radius_px,
            &cfg.refind,
            &mut s.matches,
        );
        let mut refound = 0;
        for m in s.matches.iter().take(stats.matched) {
            let (Some(&track), Some(&feature)) =
                (s.query_track.get(m.query), s.train_feature.get(m.train))
            else {
                continue;
            };
            let feature = usize::from(feature);
            if let (Some(c), Some(p)) = (
                self.current.get_mut(feature),
                self.previous.get_mut(feature),
            ) {
                *c = track;
                *p = track;
                refound += 1;
            }
        }
        self.stats.refound += u32::try_from(refound).unwrap_or(u32::MAX);
        refound
    }

    /// Gives each landmark the descriptor of its sighting in `frame` (the newest keyframe).
    fn remember_descriptors(&mut self, frame: &VoFrame<'_>) {
        let n = frame.keypoints.len().min(MAX_FEATURES);
        let landmarks = self
            .landmarks
            .get_mut(..self.landmark_count)
            .unwrap_or_default();
        for (&id, d) in self.current.iter().zip(frame.descriptors).take(n) {
            if let Ok(i) = landmarks.binary_search_by_key(&id, |l| l.track) {
                if let Some(l) = landmarks.get_mut(i) {
                    l.descriptor = *d;
                }
            }
        }
    }

    /// Triangulates the tracks of keyframe `slot` that have no landmark yet from the oldest
    /// keyframe that saw them. Returns the landmarks added.
    fn triangulate_new(
        &mut self,
        slot: usize,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        cfg: &VoConfig,
    ) -> usize {
        let Some(kf) = self.keyframes.get(slot) else {
            return 0;
        };
        let pose_b = CameraPose::of_robot(&kf.pose, mount);
        let before = self.landmark_count;
        let mut count = self.landmark_count;
        for f in kf.features() {
            if self.landmark_index(f.track).is_some() {
                continue;
            }
            let Some((older, g)) = self
                .keyframes
                .get(..slot)
                .unwrap_or_default()
                .iter()
                .find_map(|k| Some((k, k.find(f.track)?.1)))
            else {
                continue;
            };
            let pose_a = CameraPose::of_robot(&older.pose, mount);
            let result = triangulate(
                model,
                &pose_a,
                &observation(g, cfg.sigma_px),
                &pose_b,
                &observation(f, cfg.sigma_px),
                &cfg.triangulate,
            );
            let in_range = |p: &WorldPoint| (p.position - pose_b.centre).norm() <= cfg.max_range;
            let point = match result {
                Ok(p) if in_range(&p) => p,
                Err(TriangulateError::LowParallax) => {
                    self.stats.low_parallax += 1;
                    continue;
                }
                _ => {
                    self.stats.triangulation_refused += 1;
                    continue;
                }
            };
            // Appended after the sorted ones; sorted below, so lookups here see only the old.
            match self.landmarks.get_mut(count) {
                Some(l) => {
                    *l = Landmark {
                        track: f.track,
                        position: point.position,
                        descriptor: Descriptor([0; 8]),
                    };
                    count += 1;
                }
                None => self.stats.capacity_dropped += 1,
            }
        }
        self.landmark_count = count;
        if let Some(l) = self.landmarks.get_mut(..count) {
            crate::sort::sort_by_key(l, |l| l.track);
        }
        let added = count - before;
        self.stats.landmarks += u32::try_from(added).unwrap_or(u32::MAX);
        added
    }

    /// Fills the window, solves it, copies the estimates back and drops the outliers.
    /// Returns the solve, the observations and the landmarks dropped.
    fn solve(
        &mut self,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        cfg: &VoConfig,
    ) -> (Result<WindowSummary, WindowError>, usize, usize) {
        if self.keyframe_count < 2 {
            // One keyframe: the fixed gauge alone, nothing to solve.
            return (Err(WindowError::NoMeasurements), 0, 0);
        }
        let filled = self.fill(cfg);
        let mut window_cfg = cfg.window;
        window_cfg.fixed_poses = 1;
        let summary = filled.and_then(|()| self.window.solve(model, mount, &window_cfg));
        if summary.is_err() {
            self.stats.solve_failures += 1;
            return (summary, 0, 0);
        }
        for (i, kf) in self
            .keyframes
            .iter_mut()
            .enumerate()
            .take(self.keyframe_count)
        {
            if let Some(p) = self.window.pose(i) {
                kf.pose = p;
            }
        }
        // Outlying sightings leave their keyframe.
        let mut dropped = 0;
        for (o, src) in self
            .sources
            .iter()
            .enumerate()
            .take(self.window.observation_count())
        {
            let outlier = self
                .window
                .observation_report(o)
                .is_some_and(|r| r.status == ObservationStatus::Outlier);
            let feature = self
                .keyframes
                .get_mut(usize::from(src.keyframe))
                .and_then(|k| k.features.get_mut(usize::from(src.feature)));
            if let (true, Some(f)) = (outlier, feature) {
                f.track = NO_TRACK;
                dropped += 1;
            }
        }
        if dropped > 0 {
            self.keyframes
                .iter_mut()
                .take(self.keyframe_count)
                .for_each(Keyframe::compact);
        }
        // Landmarks: new positions; those mostly seen as outliers, or pushed out of range,
        // leave.
        let newest = self
            .keyframe_count
            .checked_sub(1)
            .and_then(|i| self.keyframes.get(i))
            .map_or(Se2::IDENTITY, |k| k.pose);
        let centre = CameraPose::of_robot(&newest, mount).centre;
        let mut lost = 0;
        for (i, l) in self
            .landmarks
            .iter_mut()
            .enumerate()
            .take(self.landmark_count)
        {
            let Some(r) = self.window.landmark_report(i) else {
                continue;
            };
            if r.status == LandmarkStatus::Active {
                l.position = r.position;
                let range = (r.position - centre).norm();
                let far = range.is_nan() || range > cfg.max_range;
                if far || 2 * r.outliers > r.observations {
                    l.track = NO_TRACK;
                    lost += 1;
                }
            }
        }
        if lost > 0 {
            self.compact_landmarks();
        }
        self.stats.outliers_dropped += u32::try_from(dropped).unwrap_or(u32::MAX);
        self.stats.landmarks_dropped += u32::try_from(lost).unwrap_or(u32::MAX);
        (summary, dropped, lost)
    }

    /// Puts the keyframes, landmarks, sightings and motion priors into the window.
    fn fill(&mut self, cfg: &VoConfig) -> Result<(), WindowError> {
        let w = &mut self.window;
        w.clear();
        for kf in self.keyframes.iter().take(self.keyframe_count) {
            w.push_pose(kf.pose)?;
        }
        for l in self.landmarks.iter().take(self.landmark_count) {
            w.push_landmark(l.position)?;
        }
        let landmarks = self
            .landmarks
            .get(..self.landmark_count)
            .unwrap_or_default();
        let mut used = 0;
        'keyframes: for (k, kf) in self.keyframes.iter().enumerate().take(self.keyframe_count) {
            for (i, f) in kf.features().iter().enumerate() {
                let Ok(landmark) = landmarks.binary_search_by_key(&f.track, |l| l.track) else {
                    continue;
                };
                let Some(src) = self.sources.get_mut(used) else {
                    self.stats.capacity_dropped += 1;
                    break 'keyframes;
                };
                let sigma = cfg.sigma_px * f64::from(1u16 << f.level.min(8));
                let obs = PixelObservation {
                    keyframe: k,
                    landmark,
                    px: Vector2::new(f64::from(f.px[0]), f64::from(f.px[1])),
                    sigma_px: sigma,
                };
                if w.push_observation(obs).is_err() {
                    self.stats.capacity_dropped += 1;
                    continue;
                }
                *src = ObservationSource {
                    keyframe: u16::try_from(k).unwrap_or(u16::MAX),
                    feature: u16::try_from(i).unwrap_or(u16::MAX),
                };
                used += 1;
            }
        }
        let count = self.keyframe_count;
        for (k, pair) in self
            .keyframes
            .get(..count)
            .unwrap_or_default()
            .windows(2)
            .enumerate()
        {
            let [a, b] = pair else { continue };
            let motion = a.odometry.between(&b.odometry);
            w.push_motion_prior(MotionPrior {
                from: k,
                to: k + 1,
                motion,
                information: odometry_information(&motion, cfg),
            })?;
        }
        Ok(())
    }

    /// Drops the oldest keyframe and the landmarks no remaining keyframe sees.
    fn slide(&mut self) {
        let Some(kfs) = self
            .keyframes
            .get_mut(..self.keyframe_count)
            .filter(|k| !k.is_empty())
        else {
            return;
        };
        kfs.rotate_left(1);
        self.keyframe_count -= 1;
        let kfs = self
            .keyframes
            .get(..self.keyframe_count)
            .unwrap_or_default();
        for l in self.landmarks.iter_mut().take(self.landmark_count) {
            if !kfs.iter().any(|k| k.find(l.track).is_some()) {
                l.track = NO_TRACK;
            }
        }
        self.compact_landmarks();
    }

    fn compact_landmarks(&mut self) {
        let l = self
            .landmarks
            .get_mut(..self.landmark_count)
            .unwrap_or_default();
        crate::sort::sort_by_key(l, |l| l.track);
        self.landmark_count = l.iter().take_while(|l| l.track != NO_TRACK).count();
    }
}

/// A keyframe feature as a triangulation input.
fn observation(f: &KeyFeature, sigma_px: f64) -> Observation {
    Observation {
        px: Vector2::new(f64::from(f.px[0]), f64::from(f.px[1])),
        sigma_px: sigma_px * f64::from(1u16 << f.level.min(8)),
    }
}

/// Information of the wheel+gyro `motion` under the configured noise model.
fn odometry_information(motion: &Se2, cfg: &VoConfig) -> Matrix3<f64> {
    let d = libm::hypot(motion.x, motion.y);
    let [xy0, xy_m] = cfg.odometry_sigma_xy;
    let [t0, t_m, t_rad] = cfg.odometry_sigma_theta;
    let sxy = xy0 + xy_m * d;
    let st = t0 + t_m * d + t_rad * libm::fabs(motion.theta);
    let (a, b) = (1.0 / (sxy * sxy), 1.0 / (st * st));
    if a.is_finite() && b.is_finite() {
        Matrix3::new(a, 0.0, 0.0, 0.0, a, 0.0, 0.0, 0.0, b)
    } else {
        Matrix3::zeros()
    }
}
