//! The mapper: the paper's block diagram (Fig. 2) assembled over fixed storage, for a LiDAR
//! (sensor set L, below) or one camera (sensor set C: module `visual`, where camera 0's visual
//! keyframes become the frame nodes and the same GPE and back-end run on them).
//!
//! One scan ([`Mapper::push_scan`]) passes the stages in order:
//! 1. **preprocess**: the stamp is checked (a scan not later than the previous one is rejected
//!    and counted), invalid beams are counted and dropped, the points are moved into the robot
//!    frame by the scan's mounting;
//! 2. **front-end** (block a, [`LidarFrontend`]): the fused wheel odometry (and gyro) seeds
//!    ICP against the local point map; the result is the front-end pose, which drifts but is
//!    locally exact;
//! 3. **GPE** (block b, [`crate::gpe`]): the real-time global pose from the prediction, the
//!    reference node (the newest frame node) and the anchor node (from the last
//!    optimization), or the worst-case prediction when the caller's deadline has passed;
//! 4. **frame node** (module `frames`): a keyframe (moved or turned enough) becomes a node of
//!    the pose graph with an odometry edge from the previous one, and its scan enters the
//!    active submap and the local point map (module `submaps`);
//! 5. **loop search** (module `loops`), every few keyframes: against the finished submaps
//!    inside the pose uncertainty, giving max-mixture loop edges.
//!
//! The **back-end** (block c, [`Mapper::step_backend`] over
//! [`BackendSchedule`]) optimizes the graph in steps of at most
//! [`BackendConfig::work_budget`] work units each (a solve resumes where the last step left
//! it); a finished optimization chooses the GPE's anchor. The caller decides when to step it
//! (every scan, or late on purpose to test the GPE), or moves it to another thread with
//! [`Mapper::detach_backend`], the two parts then joined by fixed-capacity queues (module
//! `link`).
//!
//! # Frames and nodes
//! A frame node is created per keyframe; the LiDAR keyframe hangs off it with the identity
//! offset, and so does a visual keyframe in sensor set C (module `visual`). Camera keyframes
//! next to LiDAR ones (C+L: their own frame nodes tied by odometry, or by a zero-constraint
//! at the same time) are not made yet. Each node remembers its front-end pose; the pose
//! graph holds its global estimate. A submap's grid lives in the frame of its anchor node (the
//! keyframe that opened it), so its world pose is the anchor's estimate.
//!
//! Memory: everything lives in [`MapperResources`](crate::profile::MapperResources); the
//! mapper only borrows it. A full node or edge pool is pruned; if that frees nothing new
//! keyframes are dropped (counted in [`MapperStats::keyframes_dropped`]) instead of failing; a
//! full submap pool recycles the submap that newer ones cover best.

mod back;
mod cameras;
pub mod config;
mod far;
pub mod feed;
mod frames;
mod link;
mod localize;
mod loops;
pub mod mapfile;
mod mirror;
mod pool;
mod submaps;
pub mod sync;
mod turns;
mod types;
mod visual;

use crate::backend::prune::PruneScratch;
use crate::backend::schedule::BackendSchedule;
use crate::frontend::lidar::{FrontendStep, LidarFrontend};
use crate::frontend::odometry::{OdomError, OdomIncrement, OdometryFusion};
use crate::frontend::scan::{BeamGeometry, ScanPoint, ScanPoints};
use crate::frontend::{preprocess, PointMap, PreprocessConfig};
use crate::geom::Se2;
use crate::gpe::{GpeFrame, GpeTracker};
use crate::graph::PoseGraph;
use crate::solver::SolverBuffers;

pub use crate::backend::schedule::BackendStep;
pub use crate::gpe;
pub use cameras::{CameraParts, ImageOutput, MAX_CAMERAS};
pub use config::{BackendConfig, FrontendNoise, LoopConfig, MapperConfig};
pub use feed::{Feeder, Pushed, ScanSlots};
pub use frames::NodeMeta;
pub use gpe::GpeConfig;
pub use link::{BackendWorker, LinkQueues, LINK_CAPACITY, LINK_MAX_SUBMAPS};
pub use localize::{LocalizeCounters, GLOBAL_BUDGET, LOST_MISSES};
pub use submaps::SubmapMeta;
pub use types::{FrameOutput, MapperError, MapperStats, Probe, ScanInput, Section};
pub use visual::{
    CameraOdometry, VisualCounters, VisualParts, VisualState, VO_KEYFRAMES, VO_LANDMARKS,
    VO_OBSERVATIONS,
};

use back::BackEnd;
use frames::FrameState;
use link::BackLink;
use loops::LoopState;
use mirror::PoseMirror;
use submaps::SubmapState;

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

/// Small mutable state of the mapper, kept in the resources so the mapper itself is a set of
/// borrows: the real-time part's and the back-end's schedule, apart so each side owns its own.
#[derive(Clone, Debug)]
pub struct MapperState {
    pub(crate) rt: RealTimeState,
    pub(crate) schedule: BackendSchedule,
}

impl MapperState {
    /// The state before the first scan.
    pub const fn new(keyframe: crate::frontend::KeyframeConfig) -> Self {
        MapperState {
            rt: RealTimeState::new(keyframe),
            schedule: BackendSchedule::new(),
        }
    }
}

/// The real-time part's small state, one part per stage.
#[derive(Clone, Debug)]
pub(crate) struct RealTimeState {
    /// The mapper's own counters (the stages keep theirs).
    pub(crate) stats: MapperStats,
    pub(crate) last_stamp: Option<i64>,
    pub(crate) frontend: LidarFrontend,
    pub(crate) gpe: GpeTracker,
    pub(crate) frames: FrameState,
    pub(crate) submaps: SubmapState,
    pub(crate) loops: LoopState,
    pub(crate) far: far::FarState,
    /// The back-end's estimates the real-time part needs.
    pub(crate) mirror: PoseMirror,
    /// The localization-only mode's state; `None` when mapping.
    pub(crate) localize: Option<localize::LocalizeState>,
}

impl RealTimeState {
    /// The state before the first scan.
    pub(crate) const fn new(keyframe: crate::frontend::KeyframeConfig) -> Self {
        RealTimeState {
            stats: MapperStats::ZERO,
            last_stamp: None,
            frontend: LidarFrontend::new(),
            gpe: GpeTracker::new(),
            frames: FrameState::new(keyframe),
            submaps: SubmapState::NONE,
            loops: LoopState::new(),
            far: far::FarState::new(),
            mirror: PoseMirror::EMPTY,
            localize: None,
        }
    }
}

/// The borrowed parts of the resources the mapper works on; built by
/// [`MapperResources::mapper`](crate::profile::MapperResources::mapper).
pub struct Mapper<'r> {
    pub(crate) cfg: MapperConfig,
    /// The back-end (graph, node metadata, solver, pruning and schedule), or the link to it
    /// while another thread runs it.
    pub(crate) back: BackLink<'r>,
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
    /// The camera stage's storage, when the mapper takes images.
    pub(crate) cameras: Option<CameraParts<'r>>,
    pub(crate) st: &'r mut RealTimeState,
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
    /// Storage of the camera stage; `None` for a LiDAR-only mapper.
    pub cameras: Option<CameraParts<'r>>,
    /// Small state.
    pub state: &'r mut MapperState,
}

impl<'r> MapperParts<'r> {
    /// Starts a new, empty map over these parts: whatever they held is cleared (graph, submap
    /// slots, local map, scan, odometry history, small state, the solver's cached analysis)
    /// and the mapper is assembled with [`Mapper::new`]. The same path serves static resources
    /// ([`MapperResources::mapper`](crate::profile::MapperResources::mapper)) and a host's
    /// heap-allocated ones, so both start a map identically.
    ///
    /// # Errors
    /// [`MapperError::Storage`] when the storage was made for another submap grid than
    /// `config`'s (its pyramid holds [`PYRAMID_LEVELS`] grids of that size), else as
    /// [`Mapper::new`].
    pub fn start(mut self, config: MapperConfig) -> Result<Mapper<'r>, MapperError> {
        if self.pyramid.len() != PYRAMID_LEVELS * config.grid.cells() {
            return Err(MapperError::Storage(
                "submap grid size differs from the storage's",
            ));
        }
        self.graph.clear();
        self.submaps.fill(SubmapMeta::EMPTY);
        *self.local = PointMap::new(config.local_voxel);
        self.scan.clear();
        *self.odometry = OdometryFusion::new(config.odometry);
        *self.state = MapperState::new(config.keyframe);
        self.solver.invalidate();
        Mapper::new(config, self)
    }
}

impl core::fmt::Debug for Mapper<'_> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("Mapper")
            .field("nodes", &self.back.graph().node_count())
            .field("edges", &self.back.graph().edge_count())
            .field("stats", &self.stats())
            .finish()
    }
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
        let n_submaps = parts.cells.len() / cells_per_submap;
        if parts.submaps.len() < n_submaps || n_submaps < 2 {
            return Err(MapperError::Storage("submap slots"));
        }
        if !(cfg.submap_length > 0.0 && cfg.local_reset > 0.0 && cfg.loops.every > 0) {
            return Err(MapperError::Config(
                "lengths and loop interval must be positive",
            ));
        }
        let MapperState { rt, schedule } = parts.state;
        let mut mapper = Mapper {
            cfg,
            back: BackLink::Local(BackEnd::new(
                parts.graph,
                parts.solver,
                parts.meta,
                parts.prune,
                schedule,
            )),
            submaps: &mut parts.submaps[..n_submaps],
            cells: &mut parts.cells[..n_submaps * cells_per_submap],
            cells_per_submap,
            pyramid: &mut parts.pyramid[..levels * cells_per_submap],
            local: parts.local,
            scan: parts.scan,
            reference: parts.reference,
            loop_scan: parts.loop_scan,
            odometry: parts.odometry,
            cameras: parts.cameras,
            st: rt,
        };
        mapper.refresh_mirror();
        Ok(mapper)
    }

    /// The configuration.
    pub fn config(&self) -> &MapperConfig {
        &self.cfg
    }

    /// Counters so far, the stages' included.
    pub fn stats(&self) -> MapperStats {
        let mut s = self.st.stats;
        let o = self.odometry.stats();
        s.odometry_rejected = o.out_of_order + o.non_finite;
        let f = self.st.frontend.counters();
        s.icp_failures = f.icp_failures;
        s.icp_degenerate = f.icp_degenerate;
        s.odometry_gaps = f.odometry_gaps;
        s.odometry_stalls = f.odometry_stalls;
        let g = self.st.gpe.counters();
        s.gpe_solved = g.solved;
        s.gpe_predicted = g.predicted;
        let b = self.back.counters();
        s.backend_steps = b.steps;
        s.optimizations = b.optimizations;
        s.optimization_failures = b.failures;
        s.loop_groups_removed = b.loop_groups_removed;
        s.loop_edges_removed = b.loop_edges_removed;
        s.consistency_rounds = b.consistency_rounds;
        s.loop_groups_tested = b.loop_groups_tested;
        s
    }

    /// The pose graph (read-only).
    pub fn graph(&self) -> &PoseGraph<'r> {
        self.back.graph()
    }

    /// Metadata of the graph's nodes (same indices as the graph).
    pub fn nodes(&self) -> &[NodeMeta] {
        self.back.nodes()
    }

    /// Graph index of the keyframe `serial`, if it is in the graph.
    pub fn node_of(&self, serial: u32) -> Option<usize> {
        self.back.node_of(serial)
    }

    /// Front-end pose of keyframe `serial` when it is a frame node: any node's while the
    /// back-end is interleaved, the newest node's while it is detached (the one a frame's
    /// [`FrameOutput::reference_serial`] names when mapping).
    pub fn keyframe_frontend(&self, serial: u32) -> Option<Se2> {
        let newest = self.st.mirror.newest.filter(|n| n.serial == serial);
        newest.map(|n| n.tie.frontend).or_else(|| {
            let i = self.back.node_of(serial)?;
            self.back.nodes().get(i).map(|m| m.frontend)
        })
    }

    /// Current global estimate of keyframe `serial`.
    pub fn keyframe_pose(&self, serial: u32) -> Option<Se2> {
        self.back.pose_of(serial)
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
        let out = self.frame(scan, deadline_passed, probe);
        probe.enter(Section::Done);
        out
    }

    /// The per-frame step: the stages of the block diagram in order.
    fn frame(
        &mut self,
        scan: &ScanInput<'_>,
        deadline_passed: bool,
        probe: &mut impl Probe,
    ) -> Result<FrameOutput, MapperError> {
        // A detached back-end's reports since the last frame.
        self.take_reports();
        // Preprocess: stamp order, range limits and mounting; the points land in `self.scan`.
        let previous = self.st.last_stamp;
        self.preprocess(scan)?;

        // Front-end (III-B.2): LiDAR odometry, seeded and constrained by the fused odometry.
        let (odometry, motion) = self.odometry_at(previous, scan.stamp);
        let lidar = self.cfg.lidar();
        let front =
            (self.st.frontend).track(self.scan, self.local, odometry, motion.as_ref(), &lidar);
        self.odometry.set_gyro_bias(self.st.frontend.gyro_bias());
        if self.localizing() {
            return Ok(self.localize_frame(scan.stamp, &front, deadline_passed, probe));
        }

        // GPE (III-C): the real-time global pose, or the worst-case prediction.
        probe.enter(Section::Gpe);
        let frame = self.gpe_frame(&front, deadline_passed);
        let global = self.st.gpe.update(&frame, &self.cfg.gpe, &self.cfg.noise);

        // Frame node (III-B.3): a keyframe joins the pose graph, its submap and the local map.
        probe.enter(Section::Keyframe);
        let mut out = FrameOutput {
            stamp: scan.stamp,
            pose: global.pose,
            frontend: front.pose,
            reference_serial: self.st.frames.newest_serial(),
            keyframe: false,
            predicted: global.predicted,
            loops: 0,
            localized: true,
        };
        if let Some(serial) = self.keyframe(scan.stamp, &front.pose, &global.pose) {
            out.keyframe = true;
            out.reference_serial = serial;

            // Loop search (III-B.2, loop constraints): every `loops.every` keyframes.
            if serial % self.cfg.loops.every == 0 {
                probe.enter(Section::LoopSearch);
                out.loops = self.close_loops(serial);
            }
            // Far loop search (beyond the window): a pending far match is tested with this
            // keyframe, or the keyframe is kept for a search in the back-end's turn.
            self.far_keyframe(serial);
        }
        Ok(out)
    }

    /// The fused odometry pose at `stamp` and its motion since the `previous` scan's stamp,
    /// for the front-end.
    fn odometry_at(
        &self,
        previous: Option<i64>,
        stamp: i64,
    ) -> (Option<Se2>, Option<OdomIncrement>) {
        let pose = self.odometry.pose_at(stamp).ok();
        let motion = previous.and_then(|t| self.odometry.increment(t, stamp).ok());
        (pose, motion)
    }

    /// The robot's motion during the sweep of `scan` (first beam to last), from the fused
    /// odometry; the identity when the beams carry no time or the odometry does not cover the
    /// sweep (counted).
    fn sweep_motion(&mut self, scan: &ScanInput<'_>) -> Se2 {
        let seconds = scan.geometry.sweep_seconds(scan.ranges.len());
        if seconds <= 0.0 {
            return Se2::IDENTITY;
        }
        let end = scan.stamp.saturating_add(libm::round(seconds * 1e9) as i64);
        match self.odometry.increment(scan.stamp, end) {
            Ok(inc) => inc.motion.pose,
            // Without any odometry (a LiDAR-only input) there is nothing to correct with.
            Err(OdomError::NoData) => Se2::IDENTITY,
            Err(_) => {
                self.st.stats.scans_not_deskewed += 1;
                Se2::IDENTITY
            }
        }
    }

    /// Checks the stamp and preprocesses `scan` into `self.scan`.
    fn preprocess(&mut self, scan: &ScanInput<'_>) -> Result<(), MapperError> {
        if self.st.last_stamp.is_some_and(|t| scan.stamp <= t) {
            self.st.stats.scans_out_of_order += 1;
            return Err(MapperError::OutOfOrder);
        }
        let geometry = BeamGeometry {
            range_max: scan.geometry.range_max.min(self.cfg.max_range),
            ..scan.geometry
        };
        let pre = PreprocessConfig {
            mounting: scan.mounting,
            sweep: self.sweep_motion(scan),
            ..self.cfg.preprocess
        };
        let Ok(stats) = preprocess(scan.ranges, &geometry, &pre, self.scan) else {
            self.st.stats.scans_empty += 1;
            return Err(MapperError::EmptyScan);
        };
        self.st.stats.beams_invalid += stats.nan + stats.infinite;
        if (stats.points as usize) < self.cfg.icp.min_points as usize {
            self.st.stats.scans_empty += 1;
            return Err(MapperError::EmptyScan);
        }
        self.st.last_stamp = Some(scan.stamp);
        self.st.stats.scans += 1;
        Ok(())
    }

    /// What the GPE needs of this frame: the front-end's result and the reference and anchor
    /// nodes.
    fn gpe_frame(&self, front: &FrontendStep, deadline_passed: bool) -> GpeFrame {
        let mirror = &self.st.mirror;
        let reference = mirror.newest;
        let anchor = mirror
            .anchor
            .filter(|a| reference.is_none_or(|r| r.serial != a.serial));
        GpeFrame {
            step: front.step,
            frontend: front.pose,
            travel: self.st.frontend.travel(),
            reference: reference.map(|n| n.tie),
            anchor: anchor.map(|n| n.tie),
            deadline_passed,
        }
    }
}

#[cfg(test)]
mod tests;
