//! The mapper's pools on the host's heap, each allocated once at the profile's proven size.
//!
//! The firmware keeps a [`MapperResources`](cloi_core::profile::MapperResources) in a static;
//! the host needs one per run. Building that value and boxing it passes it through the stack
//! (there is no placement construction in safe Rust): on x86-64 the temporaries of the home
//! profile touched 190 MB of stack for its 10 MB of pools, the airport profile's 340 MB, which
//! is the whole process's peak memory. Here every pool is a vector filled element by element,
//! so nothing large ever sits on the stack, and the zero-filled pools the map has not reached
//! yet take no physical memory. The capacities are those of the profile's [`ProfileSpec`], the
//! ones `cloi-budget` proves; a test checks that the bytes allocated match the static
//! resources' size.

use cloi_core::frontend::odometry::{OdometryConfig, OdometryFusion};
use cloi_core::frontend::scan::{ScanPoint, ScanPoints};
use cloi_core::frontend::visual::frame::{scratch_bytes, MAX_FEATURES};
use cloi_core::frontend::visual::matching::Match;
use cloi_core::frontend::visual::{CameraExtrinsic, CameraModel, CameraTrack, Keypoint, VoConfig};
use cloi_core::frontend::{KeyframeConfig, PointMap};
use cloi_core::graph::{PoseEdge, PoseGraph, PoseNode};
use cloi_core::mapper::{
    CameraOdometry, CameraParts, Mapper, MapperConfig, MapperError, MapperParts, MapperState,
    NodeMeta, SubmapMeta, VisualParts, VisualState, LOCAL_MAP_POINTS, LOOP_REFERENCE_POINTS,
    MAX_CAMERAS, ODOMETRY_HISTORY, PYRAMID_LEVELS,
};
use cloi_core::profile::ProfileSpec;

use crate::optimize::HostWorkspace;
use crate::prune::OwnedPruneScratch;

/// All of a mapper's storage for one profile, on the heap.
#[derive(Debug)]
pub struct HeapResources {
    spec: ProfileSpec,
    grid_cells: Vec<i8>,
    nodes: Vec<PoseNode>,
    edges: Vec<PoseEdge>,
    solver: HostWorkspace,
    node_meta: Vec<NodeMeta>,
    submap_meta: Vec<SubmapMeta>,
    pyramid: Vec<u8>,
    loop_reference: Vec<ScanPoint>,
    local_map: Box<PointMap<LOCAL_MAP_POINTS>>,
    scan: Box<ScanPoints>,
    loop_scan: Box<ScanPoints>,
    odometry: Box<OdometryFusion<ODOMETRY_HISTORY>>,
    prune: OwnedPruneScratch,
    state: Box<MapperState>,
    cameras: HostCameras,
}

/// Largest camera frame the host's camera storage takes (bigger ones are refused and counted):
/// 1280 x 1024, above the VGA and 720p sensors of the robots this is for.
pub const MAX_FRAME: (usize, usize) = (1280, 1024);

/// Camera 0's calibration, for a mapper whose visual keyframes become frame nodes (sensor set
/// C).
#[derive(Debug, Clone, Copy)]
pub struct VisualCalibration {
    /// The lens.
    pub model: CameraModel,
    /// The mounting on the robot.
    pub mount: CameraExtrinsic,
    /// The visual odometry's parameters.
    pub config: VoConfig,
}

/// The camera stage's storage (module `cloi_core::mapper::cameras`): one track per camera and
/// the scratch of one frame of up to [`MAX_FRAME`] pixels; with a calibration, the visual
/// odometry's storage too.
#[derive(Debug)]
struct HostCameras {
    tracks: Vec<CameraTrack>,
    bytes: Vec<u8>,
    corners: Vec<Keypoint>,
    matches: Vec<Match>,
    visual: Option<(VisualCalibration, Box<CameraOdometry>)>,
}

impl HostCameras {
    fn new() -> Self {
        HostCameras {
            tracks: (0..MAX_CAMERAS).map(|_| CameraTrack::new()).collect(),
            bytes: vec![0; scratch_bytes(MAX_FRAME.0, MAX_FRAME.1)],
            corners: vec![Keypoint::default(); MAX_FEATURES],
            matches: vec![Match::default(); MAX_FEATURES],
            visual: None,
        }
    }

    /// Fresh tracks (and a fresh visual odometry) over the same storage.
    fn parts(&mut self) -> CameraParts<'_> {
        self.tracks.iter_mut().for_each(|t| *t = CameraTrack::new());
        let visual = self.visual.as_mut().map(|(cal, odometry)| {
            odometry.reset();
            VisualParts {
                odometry,
                model: cal.model,
                mount: cal.mount,
                config: cal.config,
                state: VisualState::NEW,
            }
        });
        CameraParts {
            tracks: &mut self.tracks,
            bytes: &mut self.bytes,
            corners: &mut self.corners,
            matches: &mut self.matches,
            visual,
        }
    }

    fn bytes(&self) -> usize {
        use std::mem::{size_of, size_of_val};
        size_of_val(&self.tracks[..])
            + self.bytes.len()
            + size_of_val(&self.corners[..])
            + size_of_val(&self.matches[..])
            + self
                .visual
                .as_ref()
                .map_or(0, |_| size_of::<CameraOdometry>())
    }
}

impl HeapResources {
    /// Empty pools of the capacities of `spec`.
    pub fn new(spec: ProfileSpec) -> Self {
        HeapResources {
            spec,
            grid_cells: vec![0; spec.max_submaps * spec.submap_cells],
            nodes: vec![PoseNode::EMPTY; spec.max_nodes],
            edges: vec![PoseEdge::EMPTY; spec.max_edges],
            solver: HostWorkspace::new(spec.max_nodes, spec.max_edges, spec.max_factor_blocks),
            node_meta: vec![NodeMeta::EMPTY; spec.max_nodes],
            submap_meta: vec![SubmapMeta::EMPTY; spec.max_submaps],
            pyramid: vec![0; PYRAMID_LEVELS * spec.submap_cells],
            loop_reference: vec![
                ScanPoint {
                    p: [0.0, 0.0],
                    n: [0.0, 0.0],
                };
                LOOP_REFERENCE_POINTS
            ],
            local_map: Box::new(PointMap::new(0.05)),
            scan: Box::new(ScanPoints::new()),
            loop_scan: Box::new(ScanPoints::new()),
            odometry: Box::new(OdometryFusion::new(OdometryConfig::DEFAULT)),
            prune: OwnedPruneScratch::new(spec.max_nodes, spec.max_edges),
            state: Box::new(MapperState::new(KeyframeConfig {
                distance: 0.2,
                angle: 0.35,
            })),
            cameras: HostCameras::new(),
        }
    }

    /// The capacities these pools were made for.
    pub fn spec(&self) -> &ProfileSpec {
        &self.spec
    }

    /// Bytes held by the pools (what the static resources of the profile occupy, up to the
    /// padding between fields).
    pub fn bytes(&self) -> usize {
        use std::mem::{size_of, size_of_val as vec_bytes};
        vec_bytes(&self.grid_cells[..])
            + vec_bytes(&self.nodes[..])
            + vec_bytes(&self.edges[..])
            + self.solver.bytes()
            + vec_bytes(&self.node_meta[..])
            + vec_bytes(&self.submap_meta[..])
            + vec_bytes(&self.pyramid[..])
            + vec_bytes(&self.loop_reference[..])
            + size_of::<PointMap<LOCAL_MAP_POINTS>>()
            + 2 * size_of::<ScanPoints>()
            + size_of::<OdometryFusion<ODOMETRY_HISTORY>>()
            + self.prune.bytes()
            + size_of::<MapperState>()
    }

    /// Runs the visual odometry on camera 0 with `calibration`, its keyframes becoming frame
    /// nodes (sensor set C), in the mappers started from now on.
    pub fn enable_visual(&mut self, calibration: VisualCalibration) {
        let odometry = match self.cameras.visual.take() {
            Some((_, odometry)) => odometry,
            // Built once per run; its few hundred kilobytes pass through the stack here.
            None => Box::new(CameraOdometry::new()),
        };
        self.cameras.visual = Some((calibration, odometry));
    }

    /// Bytes of the camera stage's storage, on top of [`HeapResources::bytes`] (the firmware's
    /// LiDAR-only resources have none).
    pub fn camera_bytes(&self) -> usize {
        self.cameras.bytes()
    }

    /// Starts a new, empty map over these pools with `config` (see [`MapperParts::start`]).
    ///
    /// # Errors
    /// [`MapperError`] when the configuration does not fit the pools (e.g. a submap grid of
    /// another size than the profile's).
    pub fn mapper(&mut self, config: MapperConfig) -> Result<Mapper<'_>, MapperError> {
        self.parts().start(config)
    }

    /// The pools as the parts a mapper is assembled from, as they are (to read a saved map
    /// into, then [`MapperParts::localize`]).
    pub fn parts(&mut self) -> MapperParts<'_> {
        MapperParts {
            graph: PoseGraph::new(&mut self.nodes, &mut self.edges),
            solver: self.solver.buffers(),
            meta: &mut self.node_meta,
            submaps: &mut self.submap_meta,
            cells: &mut self.grid_cells,
            pyramid: &mut self.pyramid,
            local: &mut self.local_map,
            scan: &mut self.scan,
            reference: &mut self.loop_reference,
            loop_scan: &mut self.loop_scan,
            odometry: &mut self.odometry,
            prune: self.prune.scratch(),
            cameras: Some(self.cameras.parts()),
            state: &mut self.state,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use cloi_core::profile::{
        AirportResources, HomeResources, OfficeResources, AIRPORT, HOME, OFFICE,
    };

    #[test]
    fn heap_pools_have_the_proven_sizes() {
        for (spec, proven) in [
            (HOME, size_of::<HomeResources>()),
            (OFFICE, size_of::<OfficeResources>()),
            (AIRPORT, size_of::<AirportResources>()),
        ] {
            let r = HeapResources::new(spec);
            let bytes = r.bytes();
            // The same elements; the two differ only in the padding between fields.
            assert!(
                bytes.abs_diff(proven) < 4096,
                "{}: heap {bytes} B, static {proven} B",
                spec.name
            );
        }
    }

    #[test]
    fn a_heap_mapper_starts_empty_and_refuses_another_grid() {
        let mut r = HeapResources::new(HOME);
        let config = MapperConfig::home();
        {
            let m = r.mapper(config).expect("home config fits home pools");
            assert_eq!(m.graph().node_capacity(), HOME.max_nodes);
            assert_eq!(m.stats().scans, 0);
        }
        let mut other = config;
        other.grid.side += 2;
        assert!(matches!(r.mapper(other), Err(MapperError::Storage(_))));
    }
}
