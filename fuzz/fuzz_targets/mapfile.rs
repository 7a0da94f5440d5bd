//! Saved maps (`.cloimap`) through the core's reader (`core-nostd/src/mapper/mapfile`) into
//! fixed storage: each input as it is, then with its header and section CRCs recomputed, so
//! that mutations reach the record checks instead of stopping at a checksum.
#![no_main]
use cloi_core::geom::{Info3, Se2};
use cloi_core::graph::{EdgeKind, PoseEdge, PoseGraph, PoseNode};
use cloi_core::mapper::mapfile::{MapReader, MapStorage};
use cloi_core::mapper::{NodeMeta, SubmapMeta};
use cloi_core::storage::NodeId;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    read(data);
    read(&cloi_fuzz::with_mapfile_crcs(data));
});

/// Storage of the fuzzed reads: a home-sized map at most.
const NODES: usize = 512;
const EDGES: usize = 1024;
const SLOTS: usize = 128;
const MOST_CELLS: usize = 100 * 100;

fn read(data: &[u8]) {
    let mut input = data;
    let Ok(reader) = MapReader::open(&mut input) else {
        return;
    };
    let s = reader.summary();
    if s.grid.cells() > MOST_CELLS {
        return;
    }
    let prior = PoseEdge::new(NodeId(0), NodeId(0), Se2::IDENTITY, Info3::identity(), EdgeKind::Prior);
    let mut nodes = vec![PoseNode::new(Se2::IDENTITY); NODES];
    let mut edges = vec![prior; EDGES];
    let mut meta = vec![NodeMeta::EMPTY; NODES];
    let mut submaps = vec![SubmapMeta::EMPTY; SLOTS];
    let mut cells = vec![0i8; SLOTS * s.grid.cells()];
    let _ = reader.read_into(&mut MapStorage {
        grid: s.grid,
        graph: PoseGraph::new(&mut nodes, &mut edges),
        meta: &mut meta,
        submaps: &mut submaps,
        cells: &mut cells,
    });
}
