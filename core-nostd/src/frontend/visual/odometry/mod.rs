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
//! 4. The low-feature measures of the paper (see `lowfeature`): landmarks that are one point
//!    triangulated twice are merged, and the window's landmarks are searched for in the older
//!    keyframes that do not see them yet, by projection and descriptor.
//! 5. The window is filled with the keyframes (oldest first), their landmarks, every sighting
//!    of a landmark in a keyframe, and the wheel+gyro motion priors between consecutive
//!    keyframes (information from [`VoConfig`]'s noise model), then solved.
//! 6. Observations the solve flags as outliers are dropped from their keyframe, and landmarks
//!    with more outlying than inlying sightings are dropped: a wrong match or a moving object.
//! 7. When the window is full, the oldest keyframe leaves it before the next one enters, with
//!    the landmarks no remaining keyframe sees; just before, the landmarks it sees that are
//!    seen in fewer than [`LowFeatureConfig::min_sightings`] keyframes are dropped (the third
//!    low-feature measure). The oldest keyframe left is held fixed at its
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
//!
//! Files: `types` (configuration, input frame, errors, outputs), `landmarks` (re-finding and
//! triangulating landmarks), `lowfeature` (the paper's three measures for few features),
//! `bundle` (filling, solving and sliding the window).

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
use crate::geom::{chi2_quantile, Se2};

mod bundle;
mod landmarks;
mod lowfeature;
#[cfg(test)]
mod tests;
mod types;

use bundle::*;
pub use types::*;

/// Track id of a feature that belongs to no track (dropped as an outlier, or unusable).
const NO_TRACK: u32 = u32::MAX;

/// One feature of a keyframe: its track and pixel.
#[derive(Clone, Copy, Debug, PartialEq)]
struct KeyFeature {
    track: u32,
    px: [f32; 2],
    level: u8,
    /// Whether low-feature measure (a) added the sighting after the keyframe was made: counted
    /// when the solve refuses it, to judge the measure.
    backfilled: bool,
    /// What a landmark is matched against when it is searched for in an older keyframe.
    descriptor: Option<Descriptor>,
}

const NO_FEATURE: KeyFeature = KeyFeature {
    track: NO_TRACK,
    px: [0.0; 2],
    level: 0,
    backfilled: false,
    descriptor: None,
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

/// A triangulated track, with the descriptor of its latest sighting in a keyframe (none
/// while no keyframe that saw it came with descriptors).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Landmark {
    track: u32,
    position: Vector3<f64>,
    descriptor: Option<Descriptor>,
}

const NO_LANDMARK: Landmark = Landmark {
    track: NO_TRACK,
    position: Vector3::new(0.0, 0.0, 0.0),
    descriptor: None,
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
                backfilled: 0,
                merged: 0,
                short_lived_dropped: 0,
                backfilled_outliers: 0,
                solve_failures: 0,
            },
        }
    }

    /// Forgets every frame, keyframe and landmark and zeroes the counters, in place: the value
    /// is too large to be replaced through the stack.
    pub fn reset(&mut self) {
        self.keyframe_count = 0;
        self.landmark_count = 0;
        self.previous_len = 0;
        self.next_track = 0;
        self.last_stamp = None;
        self.window.clear();
        self.stats = VoStats::default();
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
        let mut short_lived_dropped = 0;
        if self.keyframe_count == N {
            short_lived_dropped = self.drop_short_lived(cfg);
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
                backfilled: 0,
                merged: 0,
                short_lived_dropped,
                solve: Err(WindowError::Full),
            };
        };
        kf.odometry = frame.odometry;
        kf.pose = guess;
        kf.len = 0;
        for (i, (&id, kp)) in self
            .current
            .iter()
            .zip(frame.keypoints.iter().take(n))
            .enumerate()
        {
            if let (true, Some(f)) = (id != NO_TRACK, kf.features.get_mut(kf.len)) {
                *f = KeyFeature {
                    track: id,
                    px: kp.position(),
                    level: kp.level,
                    backfilled: false,
                    descriptor: frame.descriptors.get(i).copied(),
                };
                kf.len += 1;
            }
        }
        kf.compact();
        self.keyframe_count += 1;
        self.stats.keyframes += 1;
        let new_landmarks = self.triangulate_new(slot, model, mount, cfg);
        self.remember_descriptors(frame);
        let merged = self.merge_duplicates(cfg);
        let backfilled = self.backfill(model, mount, cfg);
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
            backfilled,
            merged,
            short_lived_dropped,
            solve,
        }
    }

    fn landmark_index(&self, track: u32) -> Option<usize> {
        self.landmarks
            .get(..self.landmark_count)?
            .binary_search_by_key(&track, |l| l.track)
            .ok()
    }
}
