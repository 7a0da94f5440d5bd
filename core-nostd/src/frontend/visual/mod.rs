//! The visual front-end of the paper's section III-B.1: what turns a camera frame into 2D
//! features that the visual odometry can relate to 3D points, `p_k = pi(M_k, P_{k-1})`.
//!
//! One job per file:
//! * [`camera`]: the projection `pi` (pinhole and Kannala-Brandt KB4), its inverse and its
//!   Jacobian, and the camera's mounting on the robot.
//! * [`image`]: the borrowed grey image every stage reads, and the smoothing the descriptor
//!   needs.
//! * [`matching`]: matching guided by the predicted pixel positions, and a brute-force
//!   fallback keeping mutual best matches.
//! * [`pyramid`]: levels of halving resolution over caller-provided bytes.
//! * [`brief`]: the rotated 256-bit binary descriptor and its Hamming distance.
//! * [`fast`]: FAST-9 corners, spread by a grid with a low-feature fallback, and oriented.
//! * [`frame`]: the features of one frame (the stages above in order) in fixed storage.
//! * [`track`]: one camera's frames matched to its previous frame, and the low-feature count.
//! * [`triangulate`]: a match between two frames of known pose as a 3D point.
//! * [`two_view`]: the heading change and direction of travel between two frames from their
//!   matches, the distance from the odometry.
//! * [`odometry`]: feature tracks over frames, visual keyframes, triangulated landmarks and
//!   the window solve: each keyframe's pose relative to the previous one.
//! * [`window`]: sliding-window bundle adjustment of planar keyframe poses and 3D landmarks,
//!   with the wheel+gyro motion as a prior between keyframes.
//! * [`vocab`]: place recognition: a vocabulary tree of binary words, bags of words per
//!   keyframe and the query for loop candidates.
//!
//! Everything works on borrowed or fixed-capacity storage: nothing allocates, nothing recurses,
//! nothing reads a clock, and no input makes it panic. Pixels are `f32`, geometry `f64`, and
//! every transcendental function comes from `libm`, so the Cortex-A9 and x86-64 agree.

pub mod brief;
pub mod camera;
pub mod fast;
pub mod frame;
pub mod image;
pub mod matching;
pub mod odometry;
pub mod pyramid;
pub mod track;
pub mod triangulate;
pub mod two_view;
pub mod vocab;
pub mod window;

pub use brief::{describe, describe_all, Descriptor};
pub use camera::{CameraError, CameraExtrinsic, CameraModel, Intrinsics, Kb4, Pinhole};
pub use fast::{detect, detect_pyramid, DetectStats, FastConfig, Keypoint};
pub use frame::{FrameError, FrameFeatures};
pub use image::{smooth_into, smoothed_bytes, GrayImage};
pub use matching::{match_brute_force, match_guided, Match, MatchConfig, MatchStats};
pub use odometry::{
    KeyframeOutput, KeyframeReason, LowFeatureConfig, VisualOdometry, VoConfig, VoError, VoFrame,
    VoStats, VoStep,
};
pub use pyramid::{pyramid_bytes, Pyramid, PyramidError};
pub use track::{CameraTrack, TrackConfig, TrackError, TrackScratch, TrackStats, TrackStep};
pub use window::{
    BundleWindow, LandmarkReport, LandmarkStatus, MotionPrior, ObservationReport,
    ObservationStatus, PixelObservation, Termination, WindowConfig, WindowError, WindowSummary,
};

#[cfg(test)]
pub(crate) mod synth;

#[cfg(test)]
mod tests {
    use super::*;

    /// What each feature costs, for the landmark and descriptor pools to come.
    #[test]
    fn feature_sizes() {
        assert_eq!(size_of::<Keypoint>(), 20);
        assert_eq!(size_of::<Descriptor>(), 32);
        // Two indices and a distance, padded to the index size.
        assert_eq!(size_of::<Match>(), 3 * size_of::<usize>());
    }
}
