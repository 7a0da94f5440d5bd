//! Saved maps (`.cloimap`) on disk: the core's format (`cloi_core::mapper::mapfile`) written
//! atomically, and read into owned storage no larger than the largest profile's pools.

use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use cloi_core::frontend::GridParams;
use cloi_core::geom::{Info3, Se2};
use cloi_core::graph::{EdgeKind, PoseEdge, PoseGraph, PoseNode};
use cloi_core::mapper::mapfile::{write_map, MapReader, MapRef, MapStorage, MapSummary};
use cloi_core::mapper::{MapperParts, NodeMeta, SubmapMeta};
use cloi_core::profile::PROFILES;
use cloi_core::storage::NodeId;
use embedded_io_adapters::std::FromStd;

use crate::atomic::AtomicFile;

/// Writes `map` to `path` (atomically: the file appears whole or not at all); returns its size
/// in bytes.
///
/// # Errors
/// The folder is not writable, the disk is full, or the map's parts disagree.
pub fn save_map(map: &MapRef<'_>, path: &Path) -> Result<u64> {
    let mut file = AtomicFile::create(path)?;
    let bytes = write_map(map, &mut FromStd::new(file.writer()))
        .map_err(|e| anyhow!("writing the map {}: {e}", path.display()))?;
    file.commit()?;
    Ok(bytes)
}

/// A map read from a file.
#[derive(Debug, Clone)]
pub struct LoadedMap {
    /// What the file's map section says.
    pub summary: MapSummary,
    /// Graph nodes.
    pub nodes: Vec<PoseNode>,
    /// Graph edges.
    pub edges: Vec<PoseEdge>,
    /// One entry per node.
    pub meta: Vec<NodeMeta>,
    /// The saved submap slots.
    pub submaps: Vec<SubmapMeta>,
    /// Their cells.
    pub cells: Vec<i8>,
}

impl LoadedMap {
    /// The map as the core's writer takes it.
    pub fn map_ref(&self) -> MapRef<'_> {
        MapRef {
            grid: self.summary.grid,
            nodes: &self.nodes,
            meta: &self.meta,
            edges: &self.edges,
            submaps: &self.submaps,
            cells: &self.cells,
            next_serial: self.summary.next_serial,
        }
    }

    /// Every stored submap: its anchor node's pose and its cells.
    pub fn submaps(&self) -> impl Iterator<Item = (Se2, &[i8])> + '_ {
        let per = self.summary.grid.cells();
        self.submaps
            .iter()
            .enumerate()
            .filter(|(_, m)| m.in_use)
            .filter_map(move |(slot, m)| {
                let node = self
                    .meta
                    .binary_search_by_key(&m.anchor_serial, |n| n.serial);
                let pose = self.nodes.get(node.ok()?)?.pose;
                Some((pose, self.cells.get(slot * per..(slot + 1) * per)?))
            })
    }
}

/// Reads the map file at `path` into a mapper's `parts` (whose submap grid is `grid`), for
/// [`MapperParts::localize`]; returns what the file holds.
///
/// # Errors
/// The file cannot be opened, is not a map, is of another version, truncated or corrupt, was
/// made with another submap grid, or does not fit the parts' pools.
pub fn read_map_into(
    path: &Path,
    grid: GridParams,
    parts: &mut MapperParts<'_>,
) -> Result<MapSummary> {
    let file = File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let mut input = FromStd::new(BufReader::with_capacity(1 << 16, file));
    let fail = |e| anyhow!("reading the map {}: {e}", path.display());
    let reader = MapReader::open(&mut input).map_err(fail)?;
    reader.read_into_parts(grid, parts).map_err(fail)
}

/// The submap grid of the map file at `path` (to choose the profile it was made with).
///
/// # Errors
/// As [`read_map_into`], before the sections are read.
pub fn map_grid(path: &Path) -> Result<GridParams> {
    let file = File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let mut input = FromStd::new(BufReader::new(file));
    let reader = MapReader::open(&mut input)
        .map_err(|e| anyhow!("reading the map {}: {e}", path.display()))?;
    Ok(reader.summary().grid)
}

/// Reads a map file. Its counts must fit the largest profile's pools (so no file sizes more
/// memory than a robot could hold).
///
/// # Errors
/// The file cannot be opened, is not a map, is of another version, truncated or corrupt.
pub fn load_map(path: &Path) -> Result<LoadedMap> {
    let file = File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let mut input = FromStd::new(BufReader::with_capacity(1 << 16, file));
    let fail = |e| anyhow!("reading the map {}: {e}", path.display());
    let reader = MapReader::open(&mut input).map_err(fail)?;
    let s = reader.summary();
    let most = |f: fn(&cloi_core::profile::ProfileSpec) -> usize| {
        PROFILES.iter().map(f).max().unwrap_or(0)
    };
    let limits = [
        ("nodes", s.nodes as usize, most(|p| p.max_nodes)),
        ("edges", s.edges as usize, most(|p| p.max_edges)),
        (
            "submap slots",
            s.submap_slots as usize,
            most(|p| p.max_submaps),
        ),
        ("cells per submap", s.grid.cells(), most(|p| p.submap_cells)),
    ];
    for (what, need, most) in limits {
        if need > most {
            bail!(
                "reading the map {}: {need} {what}, more than any profile holds ({most})",
                path.display()
            );
        }
    }
    let placeholder = PoseEdge::new(
        NodeId(0),
        NodeId(0),
        Se2::IDENTITY,
        Info3::identity(),
        EdgeKind::Prior,
    );
    let mut nodes = vec![PoseNode::new(Se2::IDENTITY); s.nodes as usize];
    let mut edges = vec![placeholder; s.edges as usize];
    let mut meta = vec![NodeMeta::EMPTY; s.nodes as usize];
    let mut submaps = vec![SubmapMeta::EMPTY; s.submap_slots as usize];
    let mut cells = vec![0i8; s.submap_slots as usize * s.grid.cells()];
    reader
        .read_into(&mut MapStorage {
            grid: s.grid,
            graph: PoseGraph::new(&mut nodes, &mut edges),
            meta: &mut meta,
            submaps: &mut submaps,
            cells: &mut cells,
        })
        .map_err(fail)?;
    Ok(LoadedMap {
        summary: s,
        nodes,
        edges,
        meta,
        submaps,
        cells,
    })
}
