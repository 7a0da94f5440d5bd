//! Memory profiles: the capacities that fix the mapper's static footprint for a class of
//! deployment, and the resources value that owns all of the mapper's storage.
//!
//! The capacities are chosen from the area to be mapped, never from the time driven: pruning
//! keeps at most a couple of nodes per grid cell, so the pools only have to hold what one
//! building needs. `cloi-budget` checks at compile time that each profile fits its budget.
//!
//! The resources hold everything the mapper works on: the pose graph and its solver workspace,
//! the submap cells and their metadata, the loop-closure search's pyramid and reference points,
//! the front-end's local point map, scan buffer and odometry history, and the mapper's small
//! state. [`MapperResources::mapper`] lends them to a [`Mapper`].

use crate::backend::prune::PruneStorage;
use crate::frontend::odometry::{OdometryConfig, OdometryFusion};
use crate::frontend::scan::{ScanPoint, ScanPoints};
use crate::frontend::{GridParams, KeyframeConfig, PointMap};
use crate::graph::{GraphStorage, PoseGraph};
use crate::mapper::{
    Mapper, MapperConfig, MapperError, MapperParts, MapperState, NodeMeta, SubmapMeta,
    LOCAL_MAP_POINTS, LOOP_REFERENCE_POINTS, ODOMETRY_HISTORY, PYRAMID_LEVELS,
};
use crate::solver::SolverWorkspace;

/// The capacities and budget of one deployment class.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ProfileSpec {
    /// Short name used on the command line (`home`, `office`, `airport`).
    pub name: &'static str,
    /// Floor area the profile is sized for, square metres.
    pub area_m2: u32,
    /// Static memory budget, bytes.
    pub budget_bytes: usize,
    /// Pose-graph nodes.
    pub max_nodes: usize,
    /// Pose-graph edges.
    pub max_edges: usize,
    /// Occupancy-grid submaps.
    pub max_submaps: usize,
    /// Cells per submap (side x side).
    pub submap_cells: usize,
    /// Off-diagonal 3x3 blocks of the pose-graph solver's Cholesky factor (fill included).
    pub max_factor_blocks: usize,
}

const MIB: usize = 1024 * 1024;

/// A 330 m^2 home mapped by a cleaning robot: 4.1 m submaps at 5 cm.
pub const HOME: ProfileSpec = ProfileSpec {
    name: "home",
    area_m2: 330,
    budget_bytes: 16 * MIB,
    max_nodes: 4096,
    max_edges: 12288,
    max_submaps: 96,
    submap_cells: 82 * 82,
    max_factor_blocks: 16 * 4096,
};

/// A 3,000 m^2 office floor: 10 m submaps at 5 cm.
pub const OFFICE: ProfileSpec = ProfileSpec {
    name: "office",
    area_m2: 3_000,
    budget_bytes: 64 * MIB,
    max_nodes: 16384,
    max_edges: 49152,
    max_submaps: 160,
    submap_cells: 200 * 200,
    max_factor_blocks: 16 * 16384,
};

/// A 60,000 m^2 airport hall mapped by a guide robot: 10 m submaps at 10 cm.
pub const AIRPORT: ProfileSpec = ProfileSpec {
    name: "airport",
    area_m2: 60_000,
    budget_bytes: 200 * MIB,
    max_nodes: 98304,
    max_edges: 294912,
    max_submaps: 1600,
    submap_cells: 100 * 100,
    // 1.6 nodes per square metre: the pruning keeps about one per 1 m cell plus the recent
    // window. Six factor blocks per node: M3500 needs 5.5 after minimum-degree ordering; denser
    // graphs are pruned before they reach the airport's node count.
    max_factor_blocks: 6 * 98304,
};

/// Every built-in profile.
pub const PROFILES: [ProfileSpec; 3] = [HOME, OFFICE, AIRPORT];

/// All of the mapper's storage, sized by const generics. One value of this type per robot,
/// typically in a `static`; the mapper borrows it once.
#[derive(Debug)]
pub struct MapperResources<
    const NODES: usize,
    const EDGES: usize,
    const SUBMAPS: usize,
    const CELLS: usize,
    const FACTOR: usize,
> {
    /// Occupancy cells of every submap (log-odds in compact integers).
    pub grid_cells: [[i8; CELLS]; SUBMAPS],
    /// The pose graph that the back-end optimizes.
    pub pose_graph: GraphStorage<NODES, EDGES>,
    /// The pose-graph solver's workspace (ordering, factor, iteration state).
    pub solver: SolverWorkspace<NODES, EDGES, FACTOR>,
    /// Per graph node: keyframe serial, stamp, front-end pose, submap.
    pub node_meta: [NodeMeta; NODES],
    /// Per submap: anchor and state.
    pub submap_meta: [SubmapMeta; SUBMAPS],
    /// Max-pooled levels of the submap being searched for a loop closure.
    pub pyramid: [[u8; CELLS]; PYRAMID_LEVELS],
    /// Occupied cells of the submap a loop closure is refined against.
    pub loop_reference: [ScanPoint; LOOP_REFERENCE_POINTS],
    /// The front-end's local point map.
    pub local_map: PointMap<LOCAL_MAP_POINTS>,
    /// The preprocessed scan.
    pub scan: ScanPoints,
    /// The part of the scan a loop-closure search uses.
    pub loop_scan: ScanPoints,
    /// Wheel odometry and gyro history.
    pub odometry: OdometryFusion<ODOMETRY_HISTORY>,
    /// Scratch of the pruning that makes room when a pool is full.
    pub prune: PruneStorage<NODES, EDGES>,
    /// Counters and the front-end's and back-end's small state.
    pub state: MapperState,
}

impl<
        const NODES: usize,
        const EDGES: usize,
        const SUBMAPS: usize,
        const CELLS: usize,
        const FACTOR: usize,
    > MapperResources<NODES, EDGES, SUBMAPS, CELLS, FACTOR>
{
    /// Empty resources, usable as a `static` initialiser.
    pub const fn new() -> Self {
        MapperResources {
            grid_cells: [[0; CELLS]; SUBMAPS],
            pose_graph: GraphStorage::new(),
            solver: SolverWorkspace::new(),
            node_meta: [NodeMeta::EMPTY; NODES],
            submap_meta: [SubmapMeta::EMPTY; SUBMAPS],
            pyramid: [[0; CELLS]; PYRAMID_LEVELS],
            loop_reference: [ScanPoint {
                p: [0.0, 0.0],
                n: [0.0, 0.0],
            }; LOOP_REFERENCE_POINTS],
            local_map: PointMap::new(0.05),
            scan: ScanPoints::new(),
            loop_scan: ScanPoints::new(),
            odometry: OdometryFusion::new(OdometryConfig::DEFAULT),
            prune: PruneStorage::new(),
            state: MapperState::new(KeyframeConfig {
                distance: 0.2,
                angle: 0.35,
            }),
        }
    }

    /// Starts a new, empty map over these resources with `config`.
    ///
    /// # Errors
    /// [`MapperError`] when the configuration does not fit the resources (e.g. a submap grid
    /// of another size than `CELLS`).
    pub fn mapper(&mut self, config: MapperConfig) -> Result<Mapper<'_>, MapperError> {
        self.parts().start(config)
    }

    /// The resources as the parts a mapper is assembled from, as they are (to read a saved map
    /// into, then [`MapperParts::localize`]).
    pub fn parts(&mut self) -> MapperParts<'_> {
        MapperParts {
            graph: PoseGraph::new(&mut self.pose_graph.nodes, &mut self.pose_graph.edges),
            solver: self.solver.buffers(),
            meta: &mut self.node_meta,
            submaps: &mut self.submap_meta,
            cells: self.grid_cells.as_flattened_mut(),
            pyramid: self.pyramid.as_flattened_mut(),
            local: &mut self.local_map,
            scan: &mut self.scan,
            reference: &mut self.loop_reference,
            loop_scan: &mut self.loop_scan,
            odometry: &mut self.odometry,
            prune: self.prune.scratch(),
            cameras: None,
            state: &mut self.state,
        }
    }

    /// The graph, node metadata and submap storage, for reading a saved map into
    /// ([`MapReader::read_into`](crate::mapper::mapfile::MapReader::read_into)) with the
    /// submap grid `grid` (which must have `CELLS` cells).
    pub fn map_storage(&mut self, grid: GridParams) -> crate::mapper::mapfile::MapStorage<'_> {
        crate::mapper::mapfile::MapStorage {
            grid,
            graph: PoseGraph::new(&mut self.pose_graph.nodes, &mut self.pose_graph.edges),
            meta: &mut self.node_meta,
            submaps: &mut self.submap_meta,
            cells: self.grid_cells.as_flattened_mut(),
        }
    }
}

impl<
        const NODES: usize,
        const EDGES: usize,
        const SUBMAPS: usize,
        const CELLS: usize,
        const FACTOR: usize,
    > Default for MapperResources<NODES, EDGES, SUBMAPS, CELLS, FACTOR>
{
    fn default() -> Self {
        Self::new()
    }
}

/// Resources of the `home` profile.
pub type HomeResources = MapperResources<
    { HOME.max_nodes },
    { HOME.max_edges },
    { HOME.max_submaps },
    { HOME.submap_cells },
    { HOME.max_factor_blocks },
>;
/// Resources of the `office` profile.
pub type OfficeResources = MapperResources<
    { OFFICE.max_nodes },
    { OFFICE.max_edges },
    { OFFICE.max_submaps },
    { OFFICE.submap_cells },
    { OFFICE.max_factor_blocks },
>;
/// Resources of the `airport` profile.
pub type AirportResources = MapperResources<
    { AIRPORT.max_nodes },
    { AIRPORT.max_edges },
    { AIRPORT.max_submaps },
    { AIRPORT.submap_cells },
    { AIRPORT.max_factor_blocks },
>;
