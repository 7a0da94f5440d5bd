//! Frame-to-frame tracking of one camera (section III-B.1): the features of each new frame
//! ([`FrameFeatures`]) are matched to those of the camera's previous frame, mutual best BRIEF
//! matches that pass the ratio test. These 2D-2D tracks are what the visual odometry
//! triangulates and what tells whether a frame can carry it at all: the paper's cheap cameras
//! under a plain ceiling see 20 features or fewer, where a feature-only system fails, so such
//! frames are counted as low-feature frames.
//!
//! Each camera keeps two feature sets (the previous and the current frame) and flips between
//! them; nothing is copied per frame.

use super::frame::{FrameError, FrameFeatures, MAX_FEATURES};
use super::matching::{match_brute_force, Match, MatchConfig};
use super::{FastConfig, Keypoint};
use crate::sensor::ImageView;

/// Tracking parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct TrackConfig {
    /// Corner detection.
    pub fast: FastConfig,
    /// Descriptor matching between consecutive frames.
    pub matching: MatchConfig,
    /// A frame with fewer features than this is a low-feature frame (the paper's threshold
    /// for a feature-only system: 20).
    pub low_features: usize,
}

impl Default for TrackConfig {
    fn default() -> Self {
        TrackConfig {
            fast: FastConfig::default(),
            matching: MatchConfig::default(),
            low_features: 20,
        }
    }
}

/// The storage one tracking step borrows (shared by all cameras: frames are processed one at
/// a time).
#[derive(Debug)]
pub struct TrackScratch<'a> {
    /// Grey copy, pyramid and smoothed level: at least
    /// [`scratch_bytes`](super::frame::scratch_bytes) of the largest frame accepted.
    pub bytes: &'a mut [u8],
    /// The detector's output.
    pub corners: &'a mut [Keypoint],
    /// The matcher's output.
    pub matches: &'a mut [Match],
}

/// Why a frame was not tracked (each counted in [`TrackStats`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum TrackError {
    /// The stamp is not later than the camera's previous frame.
    OutOfOrder,
    /// The frame could not be read (too large for the scratch, unusable sizes).
    Frame(FrameError),
}

/// What tracking one frame found.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct TrackStep {
    /// Features of the frame.
    pub features: usize,
    /// Of them, matched to the camera's previous frame (0 for its first frame).
    pub tracked: usize,
    /// Fewer features than [`TrackConfig::low_features`].
    pub low_features: bool,
}

/// Counters of one camera.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct TrackStats {
    /// Frames tracked.
    pub frames: u32,
    /// Frames rejected because their stamp did not advance.
    pub out_of_order: u32,
    /// Frames rejected because they could not be read.
    pub unreadable: u32,
    /// Tracked frames with fewer features than [`TrackConfig::low_features`].
    pub low_features: u32,
    /// Fewest features of a tracked frame (0 before the first).
    pub min_features: u32,
    /// Features over all tracked frames.
    pub features: u64,
    /// Matches to the previous frame over all tracked frames after the first.
    pub tracked: u64,
}

/// One camera's tracking state.
#[derive(Clone, Debug)]
pub struct CameraTrack {
    sets: [FrameFeatures; 2],
    /// Which of `sets` holds the newest frame.
    newest: usize,
    last_stamp: Option<i64>,
    stats: TrackStats,
}

impl Default for CameraTrack {
    fn default() -> Self {
        Self::new()
    }
}

impl CameraTrack {
    /// A camera that has seen no frame.
    pub const fn new() -> Self {
        CameraTrack {
            sets: [FrameFeatures::new(), FrameFeatures::new()],
            newest: 0,
            last_stamp: None,
            stats: TrackStats {
                frames: 0,
                out_of_order: 0,
                unreadable: 0,
                low_features: 0,
                min_features: 0,
                features: 0,
                tracked: 0,
            },
        }
    }

    /// Forgets every frame and counter, in place (the track is too large to rebuild on a small
    /// stack).
    pub fn reset(&mut self) {
        self.sets.iter_mut().for_each(FrameFeatures::clear);
        self.newest = 0;
        self.last_stamp = None;
        self.stats = TrackStats::default();
    }

    /// The counters so far.
    pub fn stats(&self) -> TrackStats {
        self.stats
    }

    /// The features of the newest tracked frame.
    pub fn newest(&self) -> Option<&FrameFeatures> {
        self.last_stamp?;
        self.sets.get(self.newest)
    }

    /// Extracts the features of `view` (taken at `stamp` ns) and matches them to the previous
    /// frame's.
    ///
    /// # Errors
    /// [`TrackError`] (counted); the camera's state is then as before the call, so the next
    /// frame is matched to the last good one.
    pub fn track(
        &mut self,
        stamp: i64,
        view: &ImageView<'_>,
        cfg: &TrackConfig,
        scratch: &mut TrackScratch<'_>,
    ) -> Result<TrackStep, TrackError> {
        if self.last_stamp.is_some_and(|t| stamp <= t) {
            self.stats.out_of_order += 1;
            return Err(TrackError::OutOfOrder);
        }
        let next = 1 - self.newest;
        let [a, b] = &mut self.sets;
        let (previous, current) = if next == 1 { (a, b) } else { (b, a) };
        let n = scratch.corners.len().min(MAX_FEATURES);
        let corners = scratch.corners.get_mut(..n).unwrap_or_default();
        if let Err(e) = current.extract(view, &cfg.fast, scratch.bytes, corners) {
            self.stats.unreadable += 1;
            return Err(TrackError::Frame(e));
        }
        let tracked = if self.last_stamp.is_some() {
            match_brute_force(
                previous.descriptors(),
                current.descriptors(),
                &cfg.matching,
                scratch.matches,
            )
            .matched
        } else {
            0
        };
        let features = current.len();
        let step = TrackStep {
            features,
            tracked,
            low_features: features < cfg.low_features,
        };
        self.newest = next;
        self.last_stamp = Some(stamp);
        let s = &mut self.stats;
        let n = u32::try_from(features).unwrap_or(u32::MAX);
        s.min_features = if s.frames == 0 {
            n
        } else {
            s.min_features.min(n)
        };
        s.frames += 1;
        s.low_features += u32::from(step.low_features);
        s.features += features as u64;
        s.tracked += tracked as u64;
        Ok(step)
    }
}

#[cfg(test)]
mod tests {
    extern crate std;

    use super::*;
    use crate::frontend::visual::frame::scratch_bytes;
    use crate::frontend::visual::synth::{Scene, View};
    use crate::sensor::{PixelFormat, Timestamp};

    struct Bench {
        bytes: std::vec::Vec<u8>,
        corners: std::vec::Vec<Keypoint>,
        matches: std::vec::Vec<Match>,
    }

    impl Bench {
        fn new(w: usize, h: usize) -> Self {
            Bench {
                bytes: std::vec![0; scratch_bytes(w, h)],
                corners: std::vec![Keypoint::default(); MAX_FEATURES],
                matches: std::vec![Match::default(); MAX_FEATURES],
            }
        }

        fn track(
            &mut self,
            cam: &mut CameraTrack,
            stamp: i64,
            img: &[u8],
            w: usize,
            h: usize,
        ) -> Result<TrackStep, TrackError> {
            let view = ImageView::new_checked(
                Timestamp::from_nanos(stamp),
                w,
                h,
                w,
                PixelFormat::Mono8,
                img,
            )
            .expect("valid sizes");
            let mut s = TrackScratch {
                bytes: &mut self.bytes,
                corners: &mut self.corners,
                matches: &mut self.matches,
            };
            cam.track(stamp, &view, &TrackConfig::default(), &mut s)
        }
    }

    #[test]
    fn a_small_motion_keeps_most_features_tracked() {
        let (w, h) = (320, 240);
        let scene = Scene::random(11, w, h, 40);
        let mut bench = Bench::new(w, h);
        let mut cam = CameraTrack::new();
        let first = bench
            .track(
                &mut cam,
                1,
                &scene.render(&View::new(w, h, 0.0, [0.0, 0.0])),
                w,
                h,
            )
            .expect("tracked");
        assert_eq!(first.tracked, 0);
        let second = bench
            .track(
                &mut cam,
                2,
                &scene.render(&View::new(w, h, 0.05, [4.0, -3.0])),
                w,
                h,
            )
            .expect("tracked");
        assert!(second.features >= 40, "{second:?}");
        assert!(2 * second.tracked >= second.features, "{second:?}");
        let s = cam.stats();
        assert_eq!((s.frames, s.low_features), (2, 0));
        assert_eq!(s.tracked, second.tracked as u64);
    }

    #[test]
    fn bad_frames_are_counted_and_leave_the_last_good_one() {
        let (w, h) = (320, 240);
        let scene = Scene::random(3, w, h, 40);
        let img = scene.render(&View::new(w, h, 0.0, [0.0, 0.0]));
        let mut bench = Bench::new(w, h);
        let mut cam = CameraTrack::new();
        let first = bench.track(&mut cam, 10, &img, w, h).expect("tracked");
        assert_eq!(
            bench.track(&mut cam, 10, &img, w, h),
            Err(TrackError::OutOfOrder)
        );
        let big = std::vec![0u8; (w + 8) * h];
        assert_eq!(
            bench.track(&mut cam, 11, &big, w + 8, h),
            Err(TrackError::Frame(FrameError::TooLarge))
        );
        // The same picture again: every feature is found and matched to the kept frame.
        let again = bench.track(&mut cam, 12, &img, w, h).expect("tracked");
        assert_eq!(again.features, first.features);
        assert!(again.tracked * 10 >= again.features * 9, "{again:?}");
        let s = cam.stats();
        assert_eq!((s.frames, s.out_of_order, s.unreadable), (2, 1, 1));
    }

    proptest::proptest! {
        /// Any frame a driver can lend (every size, stride, pixel format and content, stamps in
        /// any order) is tracked or refused with a counted error, never a panic.
        #[test]
        fn any_frame_is_tracked_or_refused(
            w in 1usize..90, h in 1usize..70, pad in 0usize..5, colour in proptest::bool::ANY,
            seed in proptest::num::u64::ANY, stamps in proptest::collection::vec(-3i64..3, 1..4),
        ) {
            let format = if colour { PixelFormat::Bgr8 } else { PixelFormat::Mono8 };
            let stride = w * format.bytes_per_pixel() + pad;
            let data: std::vec::Vec<u8> = (0..stride * h)
                .map(|i| (seed.wrapping_mul(i as u64 | 1).rotate_left(29) >> 56) as u8)
                .collect();
            // Scratch for frames up to 64 x 48: larger ones must be refused.
            let mut bench = Bench::new(64, 48);
            let mut cam = CameraTrack::new();
            for &t in &stamps {
                let view = ImageView::new_checked(Timestamp::from_nanos(t), w, h, stride, format, &data)
                    .expect("valid sizes");
                let mut s = TrackScratch {
                    bytes: &mut bench.bytes,
                    corners: &mut bench.corners,
                    matches: &mut bench.matches,
                };
                match cam.track(t, &view, &TrackConfig::default(), &mut s) {
                    Ok(step) => proptest::prop_assert!(step.tracked <= step.features),
                    Err(TrackError::Frame(FrameError::TooLarge)) => {
                        proptest::prop_assert!(scratch_bytes(w, h) > scratch_bytes(64, 48));
                    }
                    Err(_) => {}
                }
            }
            let st = cam.stats();
            proptest::prop_assert_eq!(
                (st.frames + st.out_of_order + st.unreadable) as usize,
                stamps.len()
            );
        }
    }

    #[test]
    fn a_plain_ceiling_is_a_low_feature_frame() {
        let (w, h) = (160, 120);
        let mut bench = Bench::new(w, h);
        let mut cam = CameraTrack::new();
        let step = bench
            .track(&mut cam, 1, &std::vec![70u8; w * h], w, h)
            .expect("tracked");
        assert!(step.low_features && step.features == 0);
        assert_eq!(cam.stats().low_features, 1);
    }
}
