//! The saved map (`.cloimap`): what a session leaves for the next one (localization in the
//! same building, a later session extending the map), written and read without a heap so the
//! firmware loads the same file as the host.
//!
//! A map is the back-end's pruned pose graph (frame nodes with their [`NodeMeta`], and every
//! edge) and the finished submaps (log-odds grids in their anchor node's frame), which is all
//! the paper's loop search and GPE need of past sessions (sections III-B and III-D). The loop
//! search's pyramids are derived from the grids and rebuilt on demand, so they are not stored.
//!
//! # Layout (version 1, every number little endian, floats as their bits)
//! Header, [`HEADER_LEN`] bytes: magic `CLOIMAP` and `0x1a` ([`MAGIC`]), `u16` version
//! ([`VERSION`]), `u16` section count (at most [`MAX_SECTIONS`]), `u32` reserved (0). Then one
//! [`TABLE_ENTRY_LEN`]-byte entry per section: `u16` kind, `u16` reserved, `u32` length, `u32`
//! CRC-32 of the section's bytes, `u32` reserved; then the `u32` CRC-32 of the header and
//! table. The sections follow back to back in table order:
//!
//! | kind | section | contents |
//! |---|---|---|
//! | 1 | map | grid (`u16` side, `f32` resolution, `i8` hit, miss, min, max), `u32` nodes, edges, submap slots, submaps stored, next serial |
//! | 2 | nodes | per node: `u32` serial, `i64` stamp, pose `x, y, theta: f64`, `u8` fixed, front-end pose, travel `path, rotation: f64`, `u16` submap slot |
//! | 3 | edges | per edge: `u32` from, to (node indices), measurement, the information's upper triangle (6 `f64`), `u8` kind, robust kernel (`u8` tag, `f64` parameter, `u8` components, 3 x (`f32` weight, `f32` scale)) |
//! | 4 | submaps | per stored submap: `u16` slot, `u8` active, `u32` anchor serial, anchor front-end pose, `u32` keyframes, anchor travel, then `side^2` `i8` cells |
//!
//! Kinds 1 to 4 are required, once each and in this order; a reader skips (and checks the CRC
//! of) sections of other kinds, which is where visual landmarks and their vocabulary will go.
//! Nodes are listed in graph order with increasing serials; an edge names nodes by index.
//!
//! # Reading
//! [`MapReader::open`] checks the header, the table and the map section and gives the
//! [`MapSummary`] (so a caller can size or choose its storage); [`MapReader::read_into`] then
//! fills a graph, node metadata and submap storage, checking every section's CRC and every
//! value (finite poses, edges between stored nodes, serials increasing, cells within the
//! grid's clamps, submap anchors that are nodes). Any fault is a [`MapFileError`]; nothing
//! panics, whatever the bytes.

mod codec;
mod read;
#[cfg(test)]
mod tests;
mod write;

use super::frames::NodeMeta;
use super::submaps::SubmapMeta;
use crate::frontend::GridParams;
use crate::graph::{PoseEdge, PoseNode};

pub use read::{MapReader, MapStorage};
pub use write::write_map;

/// First bytes of a map file.
pub const MAGIC: [u8; 8] = *b"CLOIMAP\x1a";
/// Version written and the only one read.
pub const VERSION: u16 = 1;
/// Bytes of the fixed header.
pub const HEADER_LEN: usize = 16;
/// Bytes of one section-table entry.
pub const TABLE_ENTRY_LEN: usize = 16;
/// Most sections a reader accepts.
pub const MAX_SECTIONS: usize = 16;

/// Section kinds.
pub(crate) mod kind {
    pub const MAP: u16 = 1;
    pub const NODES: u16 = 2;
    pub const EDGES: u16 = 3;
    pub const SUBMAPS: u16 = 4;
}

/// A map to save, borrowed from a mapper ([`Mapper::saved_map`](super::Mapper::saved_map)) or
/// from storage a map was read into.
#[derive(Clone, Copy, Debug)]
pub struct MapRef<'a> {
    /// Submap grid of every stored submap.
    pub grid: GridParams,
    /// Graph nodes, in graph order.
    pub nodes: &'a [PoseNode],
    /// One entry per node.
    pub meta: &'a [NodeMeta],
    /// Graph edges.
    pub edges: &'a [PoseEdge],
    /// Submap slots (those not in use are not stored).
    pub submaps: &'a [SubmapMeta],
    /// Cells of every slot, `grid.cells()` each.
    pub cells: &'a [i8],
    /// Serial the next frame node would take.
    pub next_serial: u32,
}

impl super::Mapper<'_> {
    /// The map as it stands (graph, node metadata and submaps), to save with [`write_map`].
    pub fn saved_map(&self) -> MapRef<'_> {
        MapRef {
            grid: self.cfg.grid,
            nodes: self.back.graph().nodes(),
            meta: self.nodes(),
            edges: self.back.graph().edges(),
            submaps: self.submaps,
            cells: self.cells,
            next_serial: self.st.frames.next_serial(),
        }
    }
}

/// What a map file holds, from its map section.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MapSummary {
    /// Submap grid.
    pub grid: GridParams,
    /// Frame nodes.
    pub nodes: u32,
    /// Edges.
    pub edges: u32,
    /// Submap slots of the map that was saved (the highest stored slot is below it).
    pub submap_slots: u32,
    /// Submaps stored.
    pub submaps: u32,
    /// Serial the next frame node takes.
    pub next_serial: u32,
}

/// Why a map could not be written or read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MapFileError {
    /// The byte source or sink failed.
    Io(embedded_io::ErrorKind),
    /// The file ended inside its header, table or a section.
    Truncated,
    /// The file does not start with [`MAGIC`].
    NotAMap,
    /// A version this reader does not know.
    Version(u16),
    /// The header and table's CRC does not match.
    HeaderChecksum,
    /// A section's CRC does not match (its kind).
    Checksum(u16),
    /// A value that cannot be right (what).
    Corrupt(&'static str),
    /// The storage is too small for the map (what, needed, available).
    TooLarge(&'static str, u32, u32),
    /// The map's submap grid differs from the storage's.
    GridMismatch,
}

impl core::fmt::Display for MapFileError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match *self {
            MapFileError::Io(k) => write!(f, "input/output error ({k:?})"),
            MapFileError::Truncated => write!(f, "the map file is truncated"),
            MapFileError::NotAMap => write!(f, "not a CLOi map file (bad magic)"),
            MapFileError::Version(v) => {
                write!(
                    f,
                    "map file version {v}; this build reads version {VERSION}"
                )
            }
            MapFileError::HeaderChecksum => write!(f, "the map file's header is corrupt (CRC)"),
            MapFileError::Checksum(k) => write!(f, "section {k} of the map file is corrupt (CRC)"),
            MapFileError::Corrupt(what) => write!(f, "the map file is corrupt: {what}"),
            MapFileError::TooLarge(what, need, have) => {
                write!(f, "the map needs {need} {what}, the storage holds {have}")
            }
            MapFileError::GridMismatch => {
                write!(f, "the map's submap grid differs from the profile's")
            }
        }
    }
}

impl<E: embedded_io::Error> From<embedded_io::ReadExactError<E>> for MapFileError {
    fn from(e: embedded_io::ReadExactError<E>) -> Self {
        match e {
            embedded_io::ReadExactError::UnexpectedEof => MapFileError::Truncated,
            embedded_io::ReadExactError::Other(e) => MapFileError::Io(e.kind()),
        }
    }
}
