//! The values that cross the mapper's API: the scan lent in, the result of a frame, the
//! counters of a run and the errors.

use crate::frontend::scan::BeamGeometry;
use crate::geom::Se2;

/// Counters of a run.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct MapperStats {
    /// Scans accepted.
    pub scans: u32,
    /// Scans rejected because their stamp was not after the previous scan's.
    pub scans_out_of_order: u32,
    /// Scans rejected with no usable point (empty, all invalid) or a bad geometry.
    pub scans_empty: u32,
    /// Beams dropped as NaN or infinite.
    pub beams_invalid: u32,
    /// Scans whose beams carry times but whose sweep the odometry did not cover, so they were
    /// taken as measured at once (not corrected for the motion during the sweep).
    pub scans_not_deskewed: u32,
    /// Scans whose ICP failed or was too weak (the odometry seed was used).
    pub icp_failures: u32,
    /// Scans matched with a degenerate direction left at the seed.
    pub icp_degenerate: u32,
    /// Scans without an odometry increment (no wheel data around their time).
    pub odometry_gaps: u32,
    /// Odometry and gyro samples rejected (order, non-finite).
    pub odometry_rejected: u32,
    /// Scans whose odometry stood still (an increment of exactly zero) while the scan matcher
    /// saw the robot move: a stalled odometry stream, whose motion arrives later in one burst.
    pub odometry_stalls: u32,
    /// Keyframes (frame nodes) created.
    pub keyframes: u32,
    /// Keyframes not created because a pool was full.
    pub keyframes_dropped: u32,
    /// Messages to a detached back-end lost to a full queue (module `link`).
    pub link_overflows: u32,
    /// Submaps opened.
    pub submaps: u32,
    /// Submaps recycled because the pool was full.
    pub submaps_recycled: u32,
    /// Loop-closure searches (one per candidate submap).
    pub loop_searches: u32,
    /// Loop closures added.
    pub loop_closures: u32,
    /// Searches where the correlative search found nothing above the score threshold.
    pub loops_no_match: u32,
    /// Correlative matches rejected by the refinement (ICP failure, fitness, RMS, degeneracy).
    pub loops_rejected: u32,
    /// Matches not (yet) confirmed by a second agreeing one.
    pub loops_unconfirmed: u32,
    /// Submaps searched by the far loop search (every heading, the whole submap).
    pub far_searches: u32,
    /// Far matches refined and held as hypotheses.
    pub far_hypotheses: u32,
    /// Hypotheses confirmed by the following keyframes (their matches became loop edges).
    pub far_confirmed: u32,
    /// Hypotheses dropped for lack of support.
    pub far_refuted: u32,
    /// GPE updates solved.
    pub gpe_solved: u32,
    /// Frames that used the worst-case prediction.
    pub gpe_predicted: u32,
    /// Back-end optimizations finished.
    pub optimizations: u32,
    /// Back-end steps run.
    pub backend_steps: u32,
    /// Back-end optimizations that failed (the estimate was kept).
    pub optimization_failures: u32,
    /// Groups of loop closures (one revisit of one place each) removed as inconsistent with
    /// the rest of the graph.
    pub loop_groups_removed: u32,
    /// Loop edges in those groups.
    pub loop_edges_removed: u32,
    /// Rounds of the consistency test of the loop groups.
    pub consistency_rounds: u32,
    /// Loop groups tested in them.
    pub loop_groups_tested: u32,
    /// Times a full node or edge pool was pruned.
    pub prunes: u32,
    /// Nodes eliminated by pruning.
    pub nodes_pruned: u32,
}

impl MapperStats {
    /// All counters at zero.
    pub const ZERO: MapperStats = MapperStats {
        scans: 0,
        scans_out_of_order: 0,
        scans_empty: 0,
        beams_invalid: 0,
        scans_not_deskewed: 0,
        icp_failures: 0,
        icp_degenerate: 0,
        odometry_gaps: 0,
        odometry_rejected: 0,
        odometry_stalls: 0,
        keyframes: 0,
        keyframes_dropped: 0,
        link_overflows: 0,
        submaps: 0,
        submaps_recycled: 0,
        loop_searches: 0,
        loop_closures: 0,
        loops_no_match: 0,
        loops_rejected: 0,
        loops_unconfirmed: 0,
        far_searches: 0,
        far_hypotheses: 0,
        far_confirmed: 0,
        far_refuted: 0,
        gpe_solved: 0,
        gpe_predicted: 0,
        optimizations: 0,
        backend_steps: 0,
        optimization_failures: 0,
        loop_groups_removed: 0,
        loop_edges_removed: 0,
        consistency_rounds: 0,
        loop_groups_tested: 0,
        prunes: 0,
        nodes_pruned: 0,
    };
}

/// Errors of the mapper.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum MapperError {
    /// The resources do not match the configuration (grid size, pyramid levels).
    Storage(&'static str),
    /// The configuration is not usable.
    Config(&'static str),
    /// The scan's stamp is not after the previous scan's (rejected, counted).
    OutOfOrder,
    /// The scan has no usable point or an invalid geometry (rejected, counted).
    EmptyScan,
    /// A sample with a bad order or value (rejected, counted).
    BadSample,
    /// A scan that had to wait for odometry has more beams than a held slot takes
    /// ([`MAX_POINTS`](crate::frontend::scan::MAX_POINTS); rejected, counted by the feeder).
    TooManyBeams,
    /// An image for a camera the mapper has no storage for (rejected; the caller counts it).
    NoCamera,
    /// An image out of order or unreadable (rejected, counted per camera).
    Image(crate::frontend::visual::TrackError),
}

impl core::fmt::Display for MapperError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            MapperError::Storage(what) => write!(f, "mapper storage does not fit: {what}"),
            MapperError::Config(what) => write!(f, "invalid mapper configuration: {what}"),
            MapperError::OutOfOrder => f.write_str("scan time stamp not after the previous one"),
            MapperError::EmptyScan => f.write_str("scan without usable points"),
            MapperError::BadSample => f.write_str("odometry or gyro sample rejected"),
            MapperError::TooManyBeams => {
                f.write_str("scan waiting for odometry has more beams than a held slot takes")
            }
            MapperError::NoCamera => {
                f.write_str("image from a camera the mapper has no storage for")
            }
            MapperError::Image(crate::frontend::visual::TrackError::OutOfOrder) => {
                f.write_str("image time stamp not after the camera's previous one")
            }
            MapperError::Image(crate::frontend::visual::TrackError::Frame(_)) => {
                f.write_str("image larger than the camera storage or unusable")
            }
        }
    }
}

impl core::error::Error for MapperError {}

/// One laser scan lent to the mapper.
#[derive(Clone, Copy, Debug)]
pub struct ScanInput<'a> {
    /// Time stamp, ns.
    pub stamp: i64,
    /// Ranges, metres (NaN / infinite beams are dropped and counted).
    pub ranges: &'a [f32],
    /// Beam geometry.
    pub geometry: BeamGeometry,
    /// Pose of the scanner on the robot.
    pub mounting: Se2,
}

/// The result of one accepted scan (or camera image, in sensor set C).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FrameOutput {
    /// Time stamp, ns.
    pub stamp: i64,
    /// Real-time global pose of the robot (GPE or worst-case prediction).
    pub pose: Se2,
    /// Front-end pose (LiDAR odometry, drifting frame).
    pub frontend: Se2,
    /// Serial of the reference keyframe the pose hangs off (the newest at this scan).
    pub reference_serial: u32,
    /// This scan became a keyframe.
    pub keyframe: bool,
    /// The pose is the worst-case prediction (deadline passed or GPE not converged).
    pub predicted: bool,
    /// Loop closures added for this scan.
    pub loops: u8,
    /// The pose is tied to the map: always when mapping; in localization-only mode once a
    /// match with the saved map is confirmed, until tracking is lost.
    pub localized: bool,
}

/// The parts of [`Mapper::push_scan`](super::Mapper::push_scan), in the order they run, for a caller that measures them
/// (the firmware counts the instructions of each under QEMU).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Section {
    /// Checks, preprocessing and ICP against the local map (entered first, on every scan).
    Frontend,
    /// The GPE update or the worst-case prediction (accepted scans).
    Gpe,
    /// Keyframe selection and, for a keyframe, the frame node, submap and local map updates.
    Keyframe,
    /// The loop-closure search (keyframes whose serial is a multiple of `loops.every`).
    LoopSearch,
    /// `push_scan` returns (entered last, on every scan).
    Done,
}

/// Told when [`Mapper::push_scan_probed`](super::Mapper::push_scan_probed) enters each [`Section`]. It must not touch the
/// mapper; the unit type is the probe that does nothing.
pub trait Probe {
    /// `section` starts now (and the previous one ended).
    fn enter(&mut self, section: Section);
}

impl Probe for () {
    #[inline(always)]
    fn enter(&mut self, _section: Section) {}
}
