//! Round trips and every kind of damage: a map read back is the map written; a truncated file,
//! any flipped bit, another version or storage too small is refused with its reason.

extern crate std;

use std::vec;
use std::vec::Vec;

use super::*;
use crate::frontend::lidar::Travel;
use crate::geom::{Info3, Se2};
use crate::graph::{EdgeKind, PoseGraph, RobustKernel};
use crate::mapper::NO_SUBMAP;
use crate::storage::NodeId;

const GRID: GridParams = GridParams {
    side: 6,
    ..GridParams::HOME
};
const SLOTS: usize = 4;
const NODES: usize = 7;

/// Owned parts of a small map: 7 nodes, odometry edges, two loop edges of other kernels, a
/// prior, and submaps in slots 0 and 2.
struct Owned {
    nodes: Vec<PoseNode>,
    meta: Vec<NodeMeta>,
    edges: Vec<PoseEdge>,
    submaps: Vec<SubmapMeta>,
    cells: Vec<i8>,
}

fn info(s: f64) -> Info3 {
    let mut m = Info3::identity() * s;
    m[(0, 1)] = 0.25 * s;
    m[(1, 0)] = 0.25 * s;
    m
}

fn sample() -> Owned {
    let nodes: Vec<PoseNode> = (0..NODES)
        .map(|i| PoseNode {
            pose: Se2::new(i as f64 * 0.7, 0.1 * i as f64, 0.05 * i as f64 - 0.1),
            fixed: i == 0,
        })
        .collect();
    let meta: Vec<NodeMeta> = (0..NODES)
        .map(|i| NodeMeta {
            serial: 3 * i as u32 + 1,
            stamp: 1_000_000_000 + i as i64 * 123_456_789,
            frontend: Se2::new(i as f64 * 0.69, 0.11 * i as f64, 0.049 * i as f64),
            travel: Travel {
                path: i as f64 * 0.7,
                rotation: i as f64 * 0.01,
            },
            submap: if i < 4 { 0 } else { 2 },
        })
        .collect();
    let mut edges: Vec<PoseEdge> = (1..NODES)
        .map(|i| {
            PoseEdge::new(
                NodeId(i as u32 - 1),
                NodeId(i as u32),
                nodes[i - 1].pose.between(&nodes[i].pose),
                info(100.0 + i as f64),
                EdgeKind::Odometry,
            )
        })
        .collect();
    let mut lp = PoseEdge::new(
        NodeId(1),
        NodeId(6),
        Se2::new(2.9, 0.4, 0.2),
        info(40.0),
        EdgeKind::Loop,
    );
    lp.robust = RobustKernel::max_mixture_with_null(0.01, 1e-4);
    edges.push(lp);
    let mut hub = PoseEdge::new(
        NodeId(0),
        NodeId(5),
        Se2::new(3.4, 0.5, 0.2),
        info(9.0),
        EdgeKind::Loop,
    );
    hub.robust = RobustKernel::Huber { delta: 1.5 };
    edges.push(hub);
    edges.push(PoseEdge::new(
        NodeId(3),
        NodeId(3),
        nodes[3].pose,
        info(1.0),
        EdgeKind::Prior,
    ));
    let mut submaps = vec![SubmapMeta::EMPTY; SLOTS];
    for (slot, anchor, active) in [(0, 0, false), (2, 4, true)] {
        submaps[slot] = SubmapMeta {
            in_use: true,
            active,
            anchor_serial: meta[anchor].serial,
            anchor_frontend: meta[anchor].frontend,
            keyframes: 4,
            anchor_travel: meta[anchor].travel,
            anchor_estimate: None,
        };
    }
    let per = GRID.cells();
    let cells = (0..SLOTS * per)
        .map(|i| ((i * 37 % 101) as i32 - 50).clamp(GRID.min as i32, GRID.max as i32) as i8)
        .collect();
    Owned {
        nodes,
        meta,
        edges,
        submaps,
        cells,
    }
}

fn map_ref(o: &Owned) -> MapRef<'_> {
    MapRef {
        grid: GRID,
        nodes: &o.nodes,
        meta: &o.meta,
        edges: &o.edges,
        submaps: &o.submaps,
        cells: &o.cells,
        next_serial: 40,
    }
}

fn encode(map: &MapRef<'_>) -> Vec<u8> {
    let mut buf = vec![0u8; 1 << 16];
    let mut sink: &mut [u8] = &mut buf;
    let n = write_map(map, &mut sink).expect("fits the buffer");
    buf.truncate(n as usize);
    buf
}

/// Storage a map is read into.
struct Target {
    nodes: Vec<PoseNode>,
    edges: Vec<PoseEdge>,
    meta: Vec<NodeMeta>,
    submaps: Vec<SubmapMeta>,
    cells: Vec<i8>,
}

impl Target {
    fn new(nodes: usize, edges: usize, slots: usize) -> Self {
        Target {
            nodes: vec![PoseNode::new(Se2::IDENTITY); nodes],
            edges: vec![
                PoseEdge::new(
                    NodeId(0),
                    NodeId(0),
                    Se2::IDENTITY,
                    Info3::identity(),
                    EdgeKind::Prior
                );
                edges
            ],
            meta: vec![NodeMeta::EMPTY; nodes],
            submaps: vec![SubmapMeta::EMPTY; slots],
            cells: vec![0; slots * GRID.cells()],
        }
    }

    /// Reads `bytes`; on success the map read, as owned parts.
    fn read(&mut self, bytes: &[u8]) -> Result<Owned, MapFileError> {
        let mut input = bytes;
        let reader = MapReader::open(&mut input)?;
        let mut storage = MapStorage {
            grid: GRID,
            graph: PoseGraph::new(&mut self.nodes, &mut self.edges),
            meta: &mut self.meta,
            submaps: &mut self.submaps,
            cells: &mut self.cells,
        };
        let s = reader.read_into(&mut storage)?;
        assert!(input.is_empty(), "the whole file is read");
        Ok(Owned {
            nodes: storage.graph.nodes().to_vec(),
            edges: storage.graph.edges().to_vec(),
            meta: storage.meta[..s.nodes as usize].to_vec(),
            submaps: storage.submaps.to_vec(),
            cells: storage.cells.to_vec(),
        })
    }
}

fn assert_same(a: &Owned, b: &Owned) {
    assert_eq!(a.nodes, b.nodes);
    assert_eq!(a.meta, b.meta);
    assert_eq!(a.edges, b.edges);
    assert_eq!(a.submaps, b.submaps);
    let per = GRID.cells();
    for (slot, m) in a.submaps.iter().enumerate().filter(|(_, m)| m.in_use) {
        assert!(m.in_use);
        assert_eq!(
            a.cells[slot * per..(slot + 1) * per],
            b.cells[slot * per..(slot + 1) * per]
        );
    }
}

#[test]
fn a_map_read_back_is_the_map_written() {
    let map = sample();
    let bytes = encode(&map_ref(&map));
    let summary = MapReader::open(&mut &bytes[..]).expect("opens").summary();
    assert_eq!(
        summary,
        MapSummary {
            grid: GRID,
            nodes: NODES as u32,
            edges: map.edges.len() as u32,
            submap_slots: SLOTS as u32,
            submaps: 2,
            next_serial: 40,
        }
    );
    let back = Target::new(16, 32, SLOTS).read(&bytes).expect("reads");
    assert_same(&map, &back);
    // Writing what was read gives the same bytes.
    let again = MapRef {
        nodes: &back.nodes,
        meta: &back.meta,
        edges: &back.edges,
        submaps: &back.submaps,
        cells: &back.cells,
        ..map_ref(&map)
    };
    assert_eq!(encode(&again), bytes);
    let _ = NO_SUBMAP;
}

#[test]
fn a_truncated_file_is_refused_at_every_length() {
    let bytes = encode(&map_ref(&sample()));
    let mut target = Target::new(16, 32, SLOTS);
    for len in 0..bytes.len() {
        let err = target
            .read(&bytes[..len])
            .map(|_| ())
            .expect_err("truncated");
        assert!(
            matches!(err, MapFileError::Truncated),
            "length {len} of {}: {err:?}",
            bytes.len()
        );
    }
}

#[test]
fn every_flipped_bit_is_refused() {
    let bytes = encode(&map_ref(&sample()));
    let mut target = Target::new(16, 32, SLOTS);
    for byte in 0..bytes.len() {
        for bit in 0..8 {
            let mut bad = bytes.clone();
            bad[byte] ^= 1 << bit;
            let err = target.read(&bad).map(|_| ()).expect_err("flipped bit");
            assert!(
                !matches!(err, MapFileError::Io(_) | MapFileError::TooLarge(..)),
                "byte {byte} bit {bit}: {err:?}"
            );
        }
    }
}

#[test]
fn another_version_and_other_files_are_refused() {
    let mut bytes = encode(&map_ref(&sample()));
    let mut target = Target::new(16, 32, SLOTS);
    bytes[8] = 2;
    assert_eq!(
        target.read(&bytes).map(|_| ()),
        Err(MapFileError::Version(2))
    );
    assert_eq!(
        target
            .read(b"CLOILOG\x1a\x01\x00\x10\x00\x00\x00\x00\x00")
            .map(|_| ()),
        Err(MapFileError::NotAMap)
    );
}

#[test]
fn storage_too_small_or_of_another_grid_is_refused_before_reading() {
    let bytes = encode(&map_ref(&sample()));
    let edges = sample().edges.len();
    assert_eq!(
        Target::new(6, 32, SLOTS).read(&bytes).map(|_| ()),
        Err(MapFileError::TooLarge("nodes", 7, 6))
    );
    assert_eq!(
        Target::new(16, edges - 1, SLOTS).read(&bytes).map(|_| ()),
        Err(MapFileError::TooLarge(
            "edges",
            edges as u32,
            edges as u32 - 1
        ))
    );
    // A map saved with four submap slots needs four.
    let mut two = Target::new(16, 32, 2);
    assert_eq!(
        two.read(&bytes).map(|_| ()),
        Err(MapFileError::TooLarge("submap slots", 4, 2))
    );
    assert_eq!(two.nodes.len(), 16);
    let mut input = &bytes[..];
    let reader = MapReader::open(&mut input).expect("opens");
    let (mut nodes, mut edges) = (
        vec![PoseNode::new(Se2::IDENTITY); 16],
        Target::new(0, 32, 0).edges,
    );
    let (mut meta, mut submaps, mut cells) = (
        vec![NodeMeta::EMPTY; 16],
        vec![SubmapMeta::EMPTY; SLOTS],
        vec![0; 4096],
    );
    let other = GridParams { side: 8, ..GRID };
    let got = reader.read_into(&mut MapStorage {
        grid: other,
        graph: PoseGraph::new(&mut nodes, &mut edges),
        meta: &mut meta,
        submaps: &mut submaps,
        cells: &mut cells,
    });
    assert_eq!(got, Err(MapFileError::GridMismatch));
}

#[test]
fn values_that_cannot_be_right_are_refused_even_with_a_valid_crc() {
    let base = sample();
    let mut target = Target::new(16, 32, SLOTS);
    // Serials out of order.
    let mut bad = sample();
    bad.meta.swap(2, 3);
    let err = target.read(&encode(&MapRef {
        meta: &bad.meta,
        ..map_ref(&base)
    }));
    assert_eq!(
        err.map(|_| ()),
        Err(MapFileError::Corrupt("node serials out of order"))
    );
    // An edge to a node that is not stored.
    let mut bad = sample();
    bad.edges[2].to = NodeId(NODES as u32);
    let err = target.read(&encode(&MapRef {
        edges: &bad.edges,
        ..map_ref(&base)
    }));
    assert_eq!(
        err.map(|_| ()),
        Err(MapFileError::Corrupt("an edge's nodes or values"))
    );
    // A submap anchored at a pruned node.
    let mut bad = sample();
    bad.submaps[2].anchor_serial = 2;
    let err = target.read(&encode(&MapRef {
        submaps: &bad.submaps,
        ..map_ref(&base)
    }));
    assert_eq!(
        err.map(|_| ()),
        Err(MapFileError::Corrupt("a submap's anchor is not a node"))
    );
    // A cell beyond the grid's clamps.
    let mut bad = sample();
    bad.cells[5] = GRID.max + 1;
    let err = target.read(&encode(&MapRef {
        cells: &bad.cells,
        ..map_ref(&base)
    }));
    assert_eq!(
        err.map(|_| ()),
        Err(MapFileError::Corrupt("a cell outside the grid's clamps"))
    );
    // After a refusal the storage holds no map.
    assert!(target.submaps.iter().all(|m| !m.in_use));
}
