//! Static footprint of every memory profile.

use core::mem::size_of;

use cloi_core::backend::prune::PruneStorage;
use cloi_core::frontend::odometry::OdometryFusion;
use cloi_core::frontend::scan::{ScanPoint, ScanPoints};
use cloi_core::frontend::PointMap;
use cloi_core::graph::{PoseEdge, PoseNode};
use cloi_core::mapper::{
    MapperState, NodeMeta, SubmapMeta, LOCAL_MAP_POINTS, LOOP_REFERENCE_POINTS, ODOMETRY_HISTORY,
    PYRAMID_LEVELS,
};
use cloi_core::profile::{
    AirportResources, HomeResources, OfficeResources, ProfileSpec, AIRPORT, HOME, OFFICE,
};
use cloi_core::solver::SolverWorkspace;

// The proof: the build fails if a profile's resources exceed its budget on the target being
// compiled for (host and ARM alike, since pointer widths differ).
const _: () = assert!(
    size_of::<HomeResources>() <= HOME.budget_bytes,
    "home exceeds its budget"
);
const _: () = assert!(
    size_of::<OfficeResources>() <= OFFICE.budget_bytes,
    "office exceeds its budget"
);
const _: () = assert!(
    size_of::<AirportResources>() <= AIRPORT.budget_bytes,
    "airport exceeds its budget"
);

/// One pool of a profile.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PoolRow {
    /// Pool name.
    pub name: &'static str,
    /// Number of elements.
    pub count: usize,
    /// Bytes per element.
    pub element_bytes: usize,
    /// Total bytes.
    pub bytes: usize,
}

/// The footprint of one profile.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ProfileFootprint {
    /// The profile.
    pub spec: ProfileSpec,
    /// `size_of` of its resources value on this target.
    pub total_bytes: usize,
    /// Its pools.
    pub pools: Vec<PoolRow>,
}

impl ProfileFootprint {
    /// True when the resources fit the budget.
    pub fn fits(&self) -> bool {
        self.total_bytes <= self.spec.budget_bytes
    }
}

fn row(name: &'static str, count: usize, element_bytes: usize) -> PoolRow {
    PoolRow {
        name,
        count,
        element_bytes,
        bytes: count * element_bytes,
    }
}

fn footprint_of(
    spec: ProfileSpec,
    total_bytes: usize,
    solver_bytes: usize,
    prune_bytes: usize,
) -> ProfileFootprint {
    ProfileFootprint {
        spec,
        total_bytes,
        pools: vec![
            row(
                "grid cells",
                spec.max_submaps * spec.submap_cells,
                size_of::<i8>(),
            ),
            row("graph nodes", spec.max_nodes, size_of::<PoseNode>()),
            row("graph edges", spec.max_edges, size_of::<PoseEdge>()),
            row("solver", 1, solver_bytes),
            row("node metadata", spec.max_nodes, size_of::<NodeMeta>()),
            row("submap metadata", spec.max_submaps, size_of::<SubmapMeta>()),
            row(
                "loop-search pyramid",
                PYRAMID_LEVELS * spec.submap_cells,
                size_of::<u8>(),
            ),
            row(
                "loop reference points",
                LOOP_REFERENCE_POINTS,
                size_of::<ScanPoint>(),
            ),
            row(
                "local point map",
                1,
                size_of::<PointMap<LOCAL_MAP_POINTS>>(),
            ),
            row("scan buffers", 2, size_of::<ScanPoints>()),
            row(
                "odometry history",
                1,
                size_of::<OdometryFusion<ODOMETRY_HISTORY>>(),
            ),
            row("pruning scratch", 1, prune_bytes),
            row("mapper state", 1, size_of::<MapperState>()),
        ],
    }
}

/// The footprint of every built-in profile, measured with `size_of` on this target.
pub fn all_profiles() -> Vec<ProfileFootprint> {
    vec![
        footprint_of(
            HOME,
            size_of::<HomeResources>(),
            size_of::<
                SolverWorkspace<{ HOME.max_nodes }, { HOME.max_edges }, { HOME.max_factor_blocks }>,
            >(),
            size_of::<PruneStorage<{ HOME.max_nodes }, { HOME.max_edges }>>(),
        ),
        footprint_of(
            OFFICE,
            size_of::<OfficeResources>(),
            size_of::<
                SolverWorkspace<
                    { OFFICE.max_nodes },
                    { OFFICE.max_edges },
                    { OFFICE.max_factor_blocks },
                >,
            >(),
            size_of::<PruneStorage<{ OFFICE.max_nodes }, { OFFICE.max_edges }>>(),
        ),
        footprint_of(
            AIRPORT,
            size_of::<AirportResources>(),
            size_of::<
                SolverWorkspace<
                    { AIRPORT.max_nodes },
                    { AIRPORT.max_edges },
                    { AIRPORT.max_factor_blocks },
                >,
            >(),
            size_of::<PruneStorage<{ AIRPORT.max_nodes }, { AIRPORT.max_edges }>>(),
        ),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pools_add_up_to_the_resources_size() {
        for p in all_profiles() {
            let sum: usize = p.pools.iter().map(|r| r.bytes).sum();
            assert!(
                sum <= p.total_bytes,
                "{}: pools {} > total {}",
                p.spec.name,
                sum,
                p.total_bytes
            );
            // Padding between fields is small: the table accounts for nearly every byte.
            assert!(
                p.total_bytes - sum < 64,
                "{}: unaccounted bytes",
                p.spec.name
            );
            assert!(p.fits());
        }
    }
}
