//! The LiDAR mapper (sensor set L): the paper's pipeline assembled over fixed storage.
//!
//! Data flow per scan ([`Mapper::push_scan`]):
//! 1. the time stamp is checked (a scan not later than the previous one is rejected and
//!    counted), the ranges are preprocessed (invalid beams counted, points moved into the robot
//!    frame by the scan's mounting);
//! 2. **front-end**: the motion since the previous scan from the fused wheel odometry (and gyro)
//!    seeds ICP against the local point map; the result is the front-end pose `p_k` in the
//!    front-end frame, which drifts but is locally exact;
//! 3. **GPE** ([`gpe`]): the real-time global pose from the prediction, the reference node (the
//!    newest keyframe) and the anchor node (from the last optimization), or the worst-case
//!    prediction when the caller's deadline has passed;
//! 4. on a **keyframe** (moved or turned enough): a new frame node in the pose graph with an
//!    odometry edge from the previous one, the scan inserted into the active submap and the
//!    local point map, and every few keyframes a **loop-closure** search against the finished
//!    submaps inside the pose uncertainty (branch-and-bound correlative search refined by ICP),
//!    giving max-mixture loop edges.
//!
//! The **back-end** ([`Mapper::step_backend`]) optimizes the graph in steps of a few
//! Gauss-Newton iterations; a finished optimization makes its newest node the GPE's anchor.
//! The caller decides when to step it (every scan, in a background thread under a lock, or
//! late on purpose to test the GPE).
//!
//! # Frames and nodes
//! A frame node is created per keyframe; the LiDAR keyframe hangs off it with the identity
//! offset (a camera keyframe at another time would be its own frame node tied by odometry, one
//! at the same time by a zero-constraint). Each node remembers its front-end pose; the pose
//! graph holds its global estimate. A submap's grid lives in the frame of its anchor node (the
//! keyframe that opened it), so its world pose is the anchor's estimate.
//!
//! Memory: everything lives in [`MapperResources`](crate::profile::MapperResources); the
//! mapper only borrows it. A full node or edge pool is pruned (module `pool`); if that frees nothing
//! new keyframes are dropped (counted in
//! [`MapperStats::keyframes_dropped`]) instead of failing; a full submap pool recycles the
//! submap that newer ones cover best.

pub mod config;
pub mod feed;
pub mod gpe;
mod loops;
mod pool;

use crate::backend::prune::PruneScratch;
use crate::frontend::odometry::{OdomError, OdometryFusion};
use crate::frontend::scan::{BeamGeometry, ScanPoint, ScanPoints};
use crate::frontend::{align, preprocess, KeyframeSelector, PointMap, Submap};
use crate::geom::{spd_inverse, Cov3, Info3, Se2};
use crate::graph::{EdgeKind, PoseEdge, PoseGraph};
use crate::solver::{self, Method, SolveError, SolverBuffers, SolverOptions};
use crate::storage::NodeId;

pub use config::{BackendConfig, FrontendNoise, LoopConfig, MapperConfig};
pub use feed::Feeder;
pub use gpe::GpeConfig;

/// The parts of [`Mapper::push_scan`], in the order they run, for a caller that measures them
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

/// Told when [`Mapper::push_scan_probed`] enters each [`Section`]. It must not touch the
/// mapper; the unit type is the probe that does nothing.
pub trait Probe {
    /// `section` starts now (and the previous one ended).
    fn enter(&mut self, section: Section);
}

impl Probe for () {
    #[inline(always)]
    fn enter(&mut self, _section: Section) {}
}

/// Points of the front-end's local point map.
pub const LOCAL_MAP_POINTS: usize = 4096;
/// Reference points of a loop-closure refinement (occupied cells of one submap).
pub const LOOP_REFERENCE_POINTS: usize = 8192;
/// Most pyramid levels the mapper's storage holds.
pub const PYRAMID_LEVELS: usize = 5;
/// Odometry samples kept for interpolation.
pub const ODOMETRY_HISTORY: usize = 256;
/// `NodeMeta::submap` value of "no submap".
pub const NO_SUBMAP: u16 = u16::MAX;

/// What the mapper remembers about a frame node besides its pose-graph estimate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NodeMeta {
    /// Keyframe number, counting from 0 (stable while the graph's indices are not).
    pub serial: u32,
    /// Time stamp, ns.
    pub stamp: i64,
    /// Front-end pose when the keyframe was taken.
    pub frontend: Se2,
    /// Front-end path length at the keyframe, metres.
    pub path: f64,
    /// Front-end absolute rotation at the keyframe, radians.
    pub rotation: f64,
    /// Submap slot its scan went into.
    pub submap: u16,
}

impl NodeMeta {
    /// Placeholder for storage initialisers.
    pub const EMPTY: NodeMeta = NodeMeta {
        serial: 0,
        stamp: 0,
        frontend: Se2::IDENTITY,
        path: 0.0,
        rotation: 0.0,
        submap: NO_SUBMAP,
    };
}

/// A submap slot.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SubmapMeta {
    /// The slot holds a submap.
    pub in_use: bool,
    /// Still receiving scans.
    pub active: bool,
    /// Serial of the anchor keyframe (the grid is in its frame).
    pub anchor_serial: u32,
    /// Front-end pose of the anchor.
    pub anchor_frontend: Se2,
    /// Keyframes inserted.
    pub keyframes: u32,
    /// Path length and absolute rotation of the robot (front-end) when the submap was started:
    /// the drift relative to the submap grows from there.
    pub anchor_motion: [f64; 2],
}

impl SubmapMeta {
    /// An empty slot.
    pub const EMPTY: SubmapMeta = SubmapMeta {
        in_use: false,
        active: false,
        anchor_serial: 0,
        anchor_frontend: Se2::IDENTITY,
        keyframes: 0,
        anchor_motion: [0.0; 2],
    };
}

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
    /// Times a full node or edge pool was pruned.
    pub prunes: u32,
    /// Nodes eliminated by pruning.
    pub nodes_pruned: u32,
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
}

impl core::fmt::Display for MapperError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            MapperError::Storage(what) => write!(f, "mapper storage does not fit: {what}"),
            MapperError::Config(what) => write!(f, "invalid mapper configuration: {what}"),
            MapperError::OutOfOrder => f.write_str("scan time stamp not after the previous one"),
            MapperError::EmptyScan => f.write_str("scan without usable points"),
            MapperError::BadSample => f.write_str("odometry or gyro sample rejected"),
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

/// The result of one accepted scan.
#[derive(Clone, Copy, Debug, PartialEq)]
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
}

/// What one back-end step did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BackendStep {
    /// Nothing to optimize.
    Idle,
    /// Iterations ran; the optimization continues on the next step.
    Working,
    /// An optimization finished; its result is the GPE's new anchor.
    Finished,
}

/// A loop-closure match waiting for a second, agreeing one.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct LoopCandidate {
    pub(crate) slot: u16,
    pub(crate) serial: u32,
    pub(crate) z: Se2,
    pub(crate) info: Info3,
}

/// Small mutable state of the mapper (kept in the resources so the mapper itself is a set of
/// borrows).
#[derive(Clone, Debug)]
pub struct MapperState {
    pub(crate) stats: MapperStats,
    pub(crate) last_stamp: Option<i64>,
    /// Previous accepted scan: front-end pose, real-time pose, odometry pose (if any).
    pub(crate) last: Option<(Se2, Se2, Option<Se2>)>,
    pub(crate) frontend: Se2,
    /// Motion the scan matcher measured while the odometry stood still, which the odometry
    /// has not reported yet: taken off its next increment.
    pub(crate) stall: Se2,
    pub(crate) path: f64,
    pub(crate) rotation: f64,
    pub(crate) keyframes: KeyframeSelector,
    pub(crate) local_origin: Option<Se2>,
    pub(crate) serial: u32,
    pub(crate) active_submap: Option<u16>,
    pub(crate) pyramid_of: Option<u16>,
    /// Path length at the last loop closure (the search window grows with the path since).
    pub(crate) path_at_loop: f64,
    pub(crate) rotation_at_loop: f64,
    /// Keyframes added since the last finished optimization, and whether a loop was added.
    pub(crate) pending_keyframes: u32,
    pub(crate) pending_loop: bool,
    pub(crate) optimizing: bool,
    pub(crate) iterations_done: u32,
    /// Serial of the anchor node (from the last finished optimization).
    pub(crate) anchor: Option<u32>,
    /// Loop matches waiting for confirmation.
    pub(crate) unconfirmed: heapless::Vec<LoopCandidate, 4>,
}

impl MapperState {
    /// The state before the first scan.
    pub const fn new(keyframe: crate::frontend::KeyframeConfig) -> Self {
        MapperState {
            stats: MapperStats {
                scans: 0,
                scans_out_of_order: 0,
                scans_empty: 0,
                beams_invalid: 0,
                icp_failures: 0,
                icp_degenerate: 0,
                odometry_gaps: 0,
                odometry_rejected: 0,
                odometry_stalls: 0,
                keyframes: 0,
                keyframes_dropped: 0,
                submaps: 0,
                submaps_recycled: 0,
                loop_searches: 0,
                loop_closures: 0,
                loops_no_match: 0,
                loops_rejected: 0,
                loops_unconfirmed: 0,
                gpe_solved: 0,
                gpe_predicted: 0,
                optimizations: 0,
                backend_steps: 0,
                optimization_failures: 0,
                prunes: 0,
                nodes_pruned: 0,
            },
            last_stamp: None,
            last: None,
            frontend: Se2::IDENTITY,
            stall: Se2::IDENTITY,
            path: 0.0,
            rotation: 0.0,
            keyframes: KeyframeSelector::new(keyframe),
            local_origin: None,
            serial: 0,
            active_submap: None,
            pyramid_of: None,
            path_at_loop: 0.0,
            rotation_at_loop: 0.0,
            pending_keyframes: 0,
            pending_loop: false,
            optimizing: false,
            iterations_done: 0,
            anchor: None,
            unconfirmed: heapless::Vec::new(),
        }
    }
}

/// The borrowed parts of the resources the mapper works on; built by
/// [`MapperResources::mapper`](crate::profile::MapperResources::mapper).
pub struct Mapper<'r> {
    pub(crate) cfg: MapperConfig,
    pub(crate) graph: PoseGraph<'r>,
    pub(crate) solver: SolverBuffers<'r>,
    pub(crate) meta: &'r mut [NodeMeta],
    pub(crate) submaps: &'r mut [SubmapMeta],
    /// Cells of every submap, `cells_per_submap` each.
    pub(crate) cells: &'r mut [i8],
    pub(crate) cells_per_submap: usize,
    /// Pyramid of one submap (`levels * cells_per_submap` bytes).
    pub(crate) pyramid: &'r mut [u8],
    pub(crate) local: &'r mut PointMap<LOCAL_MAP_POINTS>,
    pub(crate) scan: &'r mut ScanPoints,
    pub(crate) reference: &'r mut [ScanPoint],
    pub(crate) loop_scan: &'r mut ScanPoints,
    pub(crate) odometry: &'r mut OdometryFusion<ODOMETRY_HISTORY>,
    pub(crate) prune: PruneScratch<'r>,
    pub(crate) st: &'r mut MapperState,
}

/// The parts of the resources a mapper is assembled from (see [`Mapper::new`]).
#[derive(Debug)]
pub struct MapperParts<'r> {
    /// The pose graph.
    pub graph: PoseGraph<'r>,
    /// The solver workspace.
    pub solver: SolverBuffers<'r>,
    /// One entry per graph node.
    pub meta: &'r mut [NodeMeta],
    /// One entry per submap.
    pub submaps: &'r mut [SubmapMeta],
    /// The cells of all submaps.
    pub cells: &'r mut [i8],
    /// Pyramid storage for one submap.
    pub pyramid: &'r mut [u8],
    /// Local point map.
    pub local: &'r mut PointMap<LOCAL_MAP_POINTS>,
    /// Preprocessed scan.
    pub scan: &'r mut ScanPoints,
    /// Loop-closure reference points.
    pub reference: &'r mut [ScanPoint],
    /// The part of the scan a loop-closure search uses.
    pub loop_scan: &'r mut ScanPoints,
    /// Odometry fusion.
    pub odometry: &'r mut OdometryFusion<ODOMETRY_HISTORY>,
    /// Scratch of the pool pruning (as large as the graph's capacity).
    pub prune: PruneScratch<'r>,
    /// Small state.
    pub state: &'r mut MapperState,
}

impl core::fmt::Debug for Mapper<'_> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("Mapper")
            .field("nodes", &self.graph.node_count())
            .field("edges", &self.graph.edge_count())
            .field("stats", &self.st.stats)
            .finish()
    }
}

fn fixed_info(cov: &Cov3) -> Info3 {
    spd_inverse(cov).unwrap_or_else(Info3::identity)
}

impl<'r> Mapper<'r> {
    /// Assembles a mapper over `parts`, checking that they fit `cfg`. The parts are used as
    /// they are (a fresh [`MapperResources`](crate::profile::MapperResources) starts empty).
    ///
    /// # Errors
    /// [`MapperError::Storage`] or [`MapperError::Config`].
    pub fn new(cfg: MapperConfig, parts: MapperParts<'r>) -> Result<Self, MapperError> {
        let cells_per_submap = cfg.grid.cells();
        if cells_per_submap == 0 || parts.cells.len() < cells_per_submap {
            return Err(MapperError::Storage("submap cells"));
        }
        let levels = cfg.loops.pyramid_levels as usize;
        if levels == 0 || levels > PYRAMID_LEVELS || parts.pyramid.len() < levels * cells_per_submap
        {
            return Err(MapperError::Storage("pyramid levels"));
        }
        if parts.meta.len() < parts.graph.node_capacity() {
            return Err(MapperError::Storage("node metadata"));
        }
        let submap_slots = parts.cells.len() / cells_per_submap;
        if parts.submaps.len() < submap_slots || submap_slots < 2 {
            return Err(MapperError::Storage("submap slots"));
        }
        if !(cfg.submap_length > 0.0 && cfg.local_reset > 0.0 && cfg.loops.every > 0) {
            return Err(MapperError::Config(
                "lengths and loop interval must be positive",
            ));
        }
        let n_submaps = submap_slots;
        Ok(Mapper {
            cfg,
            graph: parts.graph,
            solver: parts.solver,
            meta: parts.meta,
            submaps: &mut parts.submaps[..n_submaps],
            cells: &mut parts.cells[..n_submaps * cells_per_submap],
            cells_per_submap,
            pyramid: &mut parts.pyramid[..levels * cells_per_submap],
            local: parts.local,
            scan: parts.scan,
            reference: parts.reference,
            loop_scan: parts.loop_scan,
            odometry: parts.odometry,
            prune: parts.prune,
            st: parts.state,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &MapperConfig {
        &self.cfg
    }

    /// Counters so far.
    pub fn stats(&self) -> MapperStats {
        let mut s = self.st.stats;
        let o = self.odometry.stats();
        s.odometry_rejected = o.out_of_order + o.non_finite;
        s
    }

    /// The pose graph (read-only).
    pub fn graph(&self) -> &PoseGraph<'r> {
        &self.graph
    }

    /// Metadata of the graph's nodes (same indices as the graph).
    pub fn nodes(&self) -> &[NodeMeta] {
        &self.meta[..self.graph.node_count()]
    }

    /// Graph index of the keyframe `serial`, if it is in the graph.
    pub fn node_of(&self, serial: u32) -> Option<usize> {
        self.nodes()
            .binary_search_by_key(&serial, |m| m.serial)
            .ok()
    }

    /// Current global estimate of keyframe `serial`.
    pub fn keyframe_pose(&self, serial: u32) -> Option<Se2> {
        let i = self.node_of(serial)?;
        self.graph.nodes().get(i).map(|n| n.pose)
    }

    /// The submaps in use: world pose (the anchor's estimate), parameters and cells.
    pub fn submaps(&self) -> impl Iterator<Item = (Se2, &[i8])> + '_ {
        let per = self.cells_per_submap;
        self.submaps
            .iter()
            .enumerate()
            .filter(|(_, m)| m.in_use)
            .filter_map(move |(i, m)| {
                let pose = self.keyframe_pose(m.anchor_serial)?;
                let cells = self.cells.get(i * per..(i + 1) * per)?;
                Some((pose, cells))
            })
    }

    /// Adds a wheel-odometry pose measured at `stamp` ns.
    ///
    /// # Errors
    /// [`MapperError::BadSample`] for a sample out of order or non-finite (counted).
    pub fn push_odometry(&mut self, stamp: i64, pose: Se2) -> Result<(), MapperError> {
        self.odometry
            .push_wheel(stamp, pose)
            .map_err(|_| MapperError::BadSample)
    }

    /// Adds a gyro yaw rate (rad/s) measured at `stamp` ns.
    ///
    /// # Errors
    /// [`MapperError::BadSample`] for a sample out of order or non-finite (counted).
    pub fn push_gyro(&mut self, stamp: i64, yaw_rate: f64) -> Result<(), MapperError> {
        self.odometry
            .push_gyro(stamp, yaw_rate)
            .map_err(|_| MapperError::BadSample)
    }

    /// Processes one scan: front-end, GPE (or the worst-case prediction when
    /// `deadline_passed`), keyframe and loop closure.
    ///
    /// # Errors
    /// [`MapperError::OutOfOrder`] or [`MapperError::EmptyScan`]; the scan is counted and
    /// nothing else changes.
    pub fn push_scan(
        &mut self,
        scan: &ScanInput<'_>,
        deadline_passed: bool,
    ) -> Result<FrameOutput, MapperError> {
        self.push_scan_probed(scan, deadline_passed, &mut ())
    }

    /// [`Mapper::push_scan`], telling `probe` when each [`Section`] starts: `Frontend` first,
    /// `Done` last, always; the result does not depend on the probe.
    ///
    /// # Errors
    /// As [`Mapper::push_scan`].
    pub fn push_scan_probed(
        &mut self,
        scan: &ScanInput<'_>,
        deadline_passed: bool,
        probe: &mut impl Probe,
    ) -> Result<FrameOutput, MapperError> {
        probe.enter(Section::Frontend);
        let out = self.scan_sections(scan, deadline_passed, probe);
        probe.enter(Section::Done);
        out
    }

    fn scan_sections(
        &mut self,
        scan: &ScanInput<'_>,
        deadline_passed: bool,
        probe: &mut impl Probe,
    ) -> Result<FrameOutput, MapperError> {
        if self.st.last_stamp.is_some_and(|t| scan.stamp <= t) {
            self.st.stats.scans_out_of_order += 1;
            return Err(MapperError::OutOfOrder);
        }
        let geometry = BeamGeometry {
            range_max: scan.geometry.range_max.min(self.cfg.max_range),
            ..scan.geometry
        };
        let pre = crate::frontend::PreprocessConfig {
            mounting: scan.mounting,
            ..self.cfg.preprocess
        };
        let stats = match preprocess(scan.ranges, &geometry, &pre, self.scan) {
            Ok(s) => s,
            Err(_) => {
                self.st.stats.scans_empty += 1;
                return Err(MapperError::EmptyScan);
            }
        };
        if (stats.points as usize) < self.cfg.icp.min_points as usize {
            self.st.stats.scans_empty += 1;
            self.st.stats.beams_invalid += stats.nan + stats.infinite;
            return Err(MapperError::EmptyScan);
        }
        self.st.stats.beams_invalid += stats.nan + stats.infinite;
        self.st.last_stamp = Some(scan.stamp);
        self.st.stats.scans += 1;

        // Front-end: odometry seed, ICP against the local map.
        let odom = match self.odometry.pose_at(scan.stamp) {
            Ok(p) => Some(p),
            Err(OdomError::NoData | OdomError::TooOld | OdomError::TooNew) => None,
            Err(_) => None,
        };
        let (pose_prev, gpe_prev, odom_prev) = match self.st.last {
            Some(l) => l,
            None => (Se2::IDENTITY, Se2::IDENTITY, odom),
        };
        let (increment, odometry_still) = match (odom_prev, odom) {
            (Some(a), Some(b)) if a == b => (Se2::IDENTITY, true),
            // The first increment after a stall carries the motion the stall hid, part of
            // which the scan matcher has already measured.
            (Some(a), Some(b)) => (self.st.stall.inverse().compose(&a.between(&b)), false),
            _ => {
                if self.st.last.is_some() {
                    self.st.stats.odometry_gaps += 1;
                }
                (Se2::IDENTITY, false)
            }
        };
        let seed = pose_prev.compose(&increment);
        let mut pose = seed;
        if !self.local.points().is_empty() {
            let tree = self.local.tree();
            let mut best = align(self.scan, &tree, &seed, &self.cfg.icp);
            let turn = libm::fabs(increment.theta);
            // A primary match whose residual is at the noise level has found its basin:
            // the rotated seeds are for rescuing the ones that have not.
            let settled = matches!(&best, Ok(b) if b.rms <= self.cfg.turn_reseed_rms);
            if self.cfg.turn_reseed > 0.0 && turn > self.cfg.turn_reseed && !settled {
                for k in [-2.0, -1.0, 1.0, 2.0] {
                    let alt = Se2::new(seed.x, seed.y, seed.theta + k * turn);
                    let Ok(r) = align(self.scan, &tree, &alt, &self.cfg.icp) else {
                        continue;
                    };

                    let better = match &best {
                        // Clearly better only: a wrong minimum near a good one must not
                        // win on noise.
                        Ok(b) => r.fitness >= b.fitness - 0.05 && r.rms < 0.7 * b.rms,
                        Err(_) => true,
                    };
                    if better {
                        best = Ok(r);
                    }
                }
            }
            match best {
                Ok(r) if r.fitness >= self.cfg.min_fitness => {
                    pose = r.pose;
                    if r.degenerate.is_some() {
                        self.st.stats.icp_degenerate += 1;
                    }
                }
                _ => self.st.stats.icp_failures += 1,
            }
        }
        let step = pose_prev.between(&pose);
        if let (true, Some(d)) = (odometry_still, self.cfg.stall_motion) {
            if libm::sqrt(step.x * step.x + step.y * step.y) > d[0] || libm::fabs(step.theta) > d[1]
            {
                self.st.stats.odometry_stalls += 1;
                self.st.stall = self.st.stall.compose(&step);
            }
        } else {
            self.st.stall = Se2::IDENTITY;
        }
        if self.st.last.is_some() {
            self.st.path += libm::sqrt(step.x * step.x + step.y * step.y);
            self.st.rotation += libm::fabs(step.theta);
        }
        self.st.frontend = pose;

        // Real-time pose.
        probe.enter(Section::Gpe);
        let (gpe_pose, predicted) = self.estimate(&gpe_prev, &step, deadline_passed);
        self.st.last = Some((pose, gpe_pose, odom));

        // Keyframe.
        probe.enter(Section::Keyframe);
        let mut out = FrameOutput {
            stamp: scan.stamp,
            pose: gpe_pose,
            frontend: pose,
            reference_serial: self.st.serial.saturating_sub(1),
            keyframe: false,
            predicted,
            loops: 0,
        };
        if self.st.keyframes.is_keyframe(&pose) {
            if let Some(serial) = self.add_keyframe(scan.stamp, &pose, &gpe_pose) {
                self.st.keyframes.accept(pose);
                out.keyframe = true;
                out.reference_serial = serial;
                if serial % self.cfg.loops.every == 0 {
                    probe.enter(Section::LoopSearch);
                    out.loops = self.close_loops(serial);
                }
            }
        }
        Ok(out)
    }

    /// The GPE update, or the worst-case prediction.
    fn estimate(&mut self, previous: &Se2, step: &Se2, deadline_passed: bool) -> (Se2, bool) {
        let prediction = gpe::worst_case(previous, step);
        let n = self.graph.node_count();
        if n == 0 || self.st.last.is_none() {
            return (prediction, false);
        }
        if deadline_passed {
            self.st.stats.gpe_predicted += 1;
            return (prediction, true);
        }
        let cfg = self.cfg;
        let dist = libm::sqrt(step.x * step.x + step.y * step.y);
        let mut cov = cfg.noise.covariance(dist, step.theta);
        let [ps_xy, ps_th] = cfg.gpe.process_sigma;
        cov[(0, 0)] += ps_xy * ps_xy;
        cov[(1, 1)] += ps_xy * ps_xy;
        cov[(2, 2)] += ps_th * ps_th;
        let mut terms = heapless::Vec::<gpe::PoseTerm, { gpe::MAX_TERMS }>::new();
        let _ = terms.push(gpe::PoseTerm::from_local(prediction, &cov, f64::INFINITY));
        let [ns_xy, ns_th] = cfg.gpe.node_sigma;
        // The reference node (newest keyframe) and the anchor (last optimized).
        let reference = n - 1;
        let anchor = self.st.anchor.and_then(|s| self.node_of(s));
        for i in [Some(reference), anchor.filter(|&a| a != reference)]
            .into_iter()
            .flatten()
        {
            let (Some(node), Some(m)) = (self.graph.nodes().get(i), self.meta.get(i)) else {
                continue;
            };
            let rel = m.frontend.between(&self.st.frontend);
            let mut c = cfg
                .noise
                .covariance(self.st.path - m.path, self.st.rotation - m.rotation);
            c[(0, 0)] += ns_xy * ns_xy;
            c[(1, 1)] += ns_xy * ns_xy;
            c[(2, 2)] += ns_th * ns_th;
            let _ = terms.push(gpe::PoseTerm::from_local(
                node.pose.compose(&rel),
                &c,
                cfg.gpe.huber,
            ));
        }
        match gpe::solve(&terms, &cfg.gpe) {
            Some(s) if s.converged => {
                self.st.stats.gpe_solved += 1;
                (s.pose, false)
            }
            _ => {
                self.st.stats.gpe_predicted += 1;
                (prediction, true)
            }
        }
    }

    /// Adds a frame node for the keyframe at front-end pose `pose`; `None` when a pool is full.
    fn add_keyframe(&mut self, stamp: i64, pose: &Se2, global: &Se2) -> Option<u32> {
        let n = self.graph.node_count();
        let odometry_edge = if n > 0 {
            let prev = self.meta.get(n - 1).copied()?;
            let rel = prev.frontend.between(pose);
            let cov = self
                .cfg
                .noise
                .covariance(self.st.path - prev.path, self.st.rotation - prev.rotation);
            Some(PoseEdge::new(
                NodeId((n - 1) as u32),
                NodeId(n as u32),
                rel,
                fixed_info(&cov),
                EdgeKind::Odometry,
            ))
        } else {
            None
        };
        if self.pool_nearly_full() {
            self.prune_pool();
        }
        let n = self.graph.node_count();
        let odometry_edge = odometry_edge.map(|e| PoseEdge {
            from: NodeId((n - 1) as u32),
            to: NodeId(n as u32),
            ..e
        });
        if n >= self.graph.node_capacity()
            || (odometry_edge.is_some() && self.graph.edge_count() >= self.graph.edge_capacity())
        {
            self.st.stats.keyframes_dropped += 1;
            return None;
        }
        let id = self.graph.add_node(*global).ok()?;
        if let Some(e) = odometry_edge {
            if self.graph.add_edge(e).is_err() {
                // Cannot happen after the capacity check; undo the node to stay consistent.
                self.graph.truncate_nodes(n);
                self.st.stats.keyframes_dropped += 1;
                return None;
            }
        }
        let serial = self.st.serial;
        self.st.serial += 1;
        self.st.stats.keyframes += 1;
        self.st.pending_keyframes += 1;
        let submap = self.submap_for(serial, pose);
        if let Some(m) = self.meta.get_mut(id.0 as usize) {
            *m = NodeMeta {
                serial,
                stamp,
                frontend: *pose,
                path: self.st.path,
                rotation: self.st.rotation,
                submap: submap.unwrap_or(NO_SUBMAP),
            };
        }
        if let Some(slot) = submap {
            self.insert_into_submap(slot, pose);
        }
        // Local point map of the front-end.
        let restart = match self.st.local_origin {
            Some(o) => libm::hypot(pose.x - o.x, pose.y - o.y) > self.cfg.local_reset,
            None => true,
        };
        if restart {
            self.local.clear();
            self.st.local_origin = Some(*pose);
            if self.cfg.local_from_submaps {
                self.reseed_local(pose);
            }
        }
        self.local.insert(pose, self.scan, self.cfg.local_radius);
        Some(serial)
    }

    /// Refills the cleared local point map with the occupied cells of the newest submaps
    /// (the active one and the one before) near `pose`, so the front-end keeps matching
    /// against the recent past instead of a single scan after a restart.
    fn reseed_local(&mut self, pose: &Se2) {
        let per = self.cells_per_submap;
        let inv = pose.inverse();
        // The two submaps with the newest anchors.
        let mut newest: [Option<(u32, usize)>; 2] = [None, None];
        for (i, m) in self.submaps.iter().enumerate() {
            if !m.in_use {
                continue;
            }
            let e = Some((m.anchor_serial, i));
            if newest[0].is_none_or(|(s, _)| m.anchor_serial > s) {
                newest[1] = newest[0];
                newest[0] = e;
            } else if newest[1].is_none_or(|(s, _)| m.anchor_serial > s) {
                newest[1] = e;
            }
        }
        for (_, slot) in newest.into_iter().flatten().rev() {
            let Some(meta) = self.submaps.get(slot) else {
                continue;
            };
            let origin = inv.compose(&meta.anchor_frontend);
            let Some(cells) = self.cells.get(slot * per..(slot + 1) * per) else {
                continue;
            };
            let Ok(grid) = Submap::from_cells(origin, self.cfg.grid, cells) else {
                continue;
            };
            let n = grid.occupied_points(self.cfg.local_min_log_odds, 2, self.reference);
            if let Some(points) = self.reference.get(..n) {
                self.local.insert(pose, points, self.cfg.local_radius);
            }
        }
    }

    /// The submap slot the keyframe goes into, opening a new one when the robot left the
    /// active one.
    fn submap_for(&mut self, serial: u32, pose: &Se2) -> Option<u16> {
        if let Some(a) = self.st.active_submap {
            if let Some(m) = self.submaps.get(a as usize) {
                let o = m.anchor_frontend;
                if libm::hypot(pose.x - o.x, pose.y - o.y) <= self.cfg.submap_length {
                    return Some(a);
                }
            }
            if let Some(m) = self.submaps.get_mut(a as usize) {
                m.active = false;
            }
        }
        let slot = match self.submaps.iter().position(|m| !m.in_use) {
            Some(s) => s,
            None => {
                let s = self.recycle_submap()?;
                self.st.stats.submaps_recycled += 1;
                s
            }
        };
        let per = self.cells_per_submap;
        let cells = self.cells.get_mut(slot * per..(slot + 1) * per)?;
        cells.fill(0);
        *self.submaps.get_mut(slot)? = SubmapMeta {
            in_use: true,
            active: true,
            anchor_serial: serial,
            anchor_frontend: *pose,
            keyframes: 0,
            anchor_motion: [self.st.path, self.st.rotation],
        };
        if self.st.pyramid_of == Some(slot as u16) {
            self.st.pyramid_of = None;
        }
        self.st.active_submap = Some(slot as u16);
        self.st.stats.submaps += 1;
        Some(slot as u16)
    }

    /// The finished submap whose anchor is nearest to a newer submap's anchor: the one the
    /// map loses least by.
    fn recycle_submap(&mut self) -> Option<usize> {
        let mut best: Option<(usize, f64)> = None;
        for (i, a) in self.submaps.iter().enumerate() {
            if !a.in_use || a.active {
                continue;
            }
            let Some(pa) = self.keyframe_pose(a.anchor_serial) else {
                return Some(i);
            };
            for b in self.submaps.iter() {
                if !b.in_use || b.anchor_serial <= a.anchor_serial {
                    continue;
                }
                let Some(pb) = self.keyframe_pose(b.anchor_serial) else {
                    continue;
                };
                let d = libm::hypot(pa.x - pb.x, pa.y - pb.y);
                if best.is_none_or(|(_, bd)| d < bd) {
                    best = Some((i, d));
                }
            }
        }
        best.map(|(i, _)| i)
    }

    fn insert_into_submap(&mut self, slot: u16, pose: &Se2) {
        let per = self.cells_per_submap;
        let s = slot as usize;
        let Some(meta) = self.submaps.get_mut(s) else {
            return;
        };
        let local = meta.anchor_frontend.between(pose);
        meta.keyframes += 1;
        let Some(cells) = self.cells.get_mut(s * per..(s + 1) * per) else {
            return;
        };
        if let Ok(mut grid) = Submap::from_cells(Se2::IDENTITY, self.cfg.grid, cells) {
            let _ = grid.insert_scan(&local, &Se2::IDENTITY, self.scan);
        }
        if self.st.pyramid_of == Some(slot) {
            self.st.pyramid_of = None;
        }
    }

    /// Asks for an optimization at the next back-end step even without new loop closures (e.g.
    /// to settle the map at the end of a run).
    pub fn request_optimization(&mut self) {
        self.st.pending_loop = true;
    }

    /// Runs one back-end step of at most `iterations` Gauss-Newton iterations.
    pub fn step_backend(&mut self, iterations: u32) -> BackendStep {
        if !self.st.optimizing {
            let due = self.st.pending_loop
                || self.st.pending_keyframes >= self.cfg.backend.every_keyframes;
            if !due || self.graph.node_count() < 2 {
                return BackendStep::Idle;
            }
            self.st.optimizing = true;
            self.st.iterations_done = 0;
            self.st.pending_loop = false;
            self.st.pending_keyframes = 0;
        }
        self.st.stats.backend_steps += 1;
        let budget = iterations.max(1).min(
            self.cfg
                .backend
                .max_iterations
                .saturating_sub(self.st.iterations_done)
                .max(1),
        );
        let options = SolverOptions {
            method: Method::GaussNewton,
            max_iterations: budget,
            linear_init: false,
            gate_chi2: self.cfg.backend.gate_chi2,
            ..SolverOptions::default()
        };
        let result = solver::solve(&mut self.graph, &mut self.solver, &options);
        let (done, failed) = match result {
            Ok(r) => {
                self.st.iterations_done += r.iterations;
                (true, false)
            }
            Err(f) if f.error == SolveError::MaxIterations => {
                self.st.iterations_done += f.report.iterations;
                (
                    self.st.iterations_done >= self.cfg.backend.max_iterations,
                    false,
                )
            }
            Err(_) => (true, true),
        };
        if !done {
            return BackendStep::Working;
        }
        self.st.optimizing = false;
        if failed {
            self.st.stats.optimization_failures += 1;
        }
        self.st.stats.optimizations += 1;
        self.st.anchor = self.choose_anchor();
        BackendStep::Finished
    }

    /// The anchor: among the optimized nodes of the newest submaps, the one nearest to the
    /// newest optimized node in squared Mahalanobis distance under the front-end uncertainty
    /// between them (the newest node itself unless it was removed).
    fn choose_anchor(&self) -> Option<u32> {
        let nodes = self.nodes();
        let last = nodes.last()?;
        let f = self.graph.nodes().get(nodes.len() - 1)?.pose;
        let mut best: Option<(u32, f64)> = None;
        for (i, m) in nodes.iter().enumerate().rev().take(32) {
            let Some(node) = self.graph.nodes().get(i) else {
                continue;
            };
            let cov = self
                .cfg
                .noise
                .covariance(last.path - m.path, last.rotation - m.rotation);
            let d = crate::geom::pose_squared_mahalanobis(&node.pose, &f, &cov)
                .unwrap_or(f64::INFINITY);
            if best.is_none_or(|(_, b)| d < b) {
                best = Some((m.serial, d));
            }
        }
        best.map(|(s, _)| s)
    }
}

#[cfg(test)]
mod tests;
