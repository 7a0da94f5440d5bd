//! Reading a map file from a byte stream into caller-lent storage, section by section, each
//! checked against its CRC and every value against what the storage and the map allow.

use super::codec::{
    get_edge, get_grid, get_node, get_submap_head, Fields, EDGE_LEN, MAP_LEN, NODE_LEN,
    SUBMAP_HEAD_LEN,
};
use super::{
    kind, MapFileError, MapSummary, HEADER_LEN, MAGIC, MAX_SECTIONS, TABLE_ENTRY_LEN, VERSION,
};
use crate::frontend::GridParams;
use crate::graph::PoseGraph;
use crate::mapper::frames::{node_index, NodeMeta};
use crate::mapper::submaps::SubmapMeta;
use crate::mapper::NO_SUBMAP;

/// Where [`MapReader::read_into`] puts a map: the storage of a mapper
/// ([`MapperResources::map_storage`](crate::profile::MapperResources::map_storage)) or of a
/// map viewer.
#[derive(Debug)]
pub struct MapStorage<'g> {
    /// The submap grid the storage's cells are laid out for.
    pub grid: GridParams,
    /// The graph (cleared, then filled).
    pub graph: PoseGraph<'g>,
    /// One entry per graph node.
    pub meta: &'g mut [NodeMeta],
    /// Submap slots (all reset; stored submaps return to their saved slots).
    pub submaps: &'g mut [SubmapMeta],
    /// Cells of every slot, `grid.cells()` each.
    pub cells: &'g mut [i8],
}

/// One table entry.
#[derive(Clone, Copy, Debug, Default)]
struct Entry {
    kind: u16,
    len: u32,
    crc: u32,
}

/// A section being read: its bytes left and their running CRC.
struct Section {
    entry: Entry,
    left: u32,
    crc: crc32fast::Hasher,
}

/// A map file whose header, table and map section have been read and checked.
#[derive(Debug)]
pub struct MapReader<'i, R> {
    input: &'i mut R,
    table: [Entry; MAX_SECTIONS],
    sections: usize,
    /// Index of the next table entry to read.
    next: usize,
    summary: MapSummary,
}

impl<'i, R: embedded_io::Read> MapReader<'i, R> {
    /// Reads and checks the header, the section table and the map section.
    ///
    /// # Errors
    /// [`MapFileError::NotAMap`], [`MapFileError::Version`], [`MapFileError::HeaderChecksum`],
    /// [`MapFileError::Truncated`], [`MapFileError::Checksum`], [`MapFileError::Corrupt`] (a
    /// section missing, repeated, out of order or of a length its counts do not give), or
    /// [`MapFileError::Io`].
    pub fn open(input: &'i mut R) -> Result<Self, MapFileError> {
        let mut head = [0u8; HEADER_LEN];
        input.read_exact(&mut head)?;
        if head.get(..8) != Some(&MAGIC[..]) {
            return Err(MapFileError::NotAMap);
        }
        let mut f = Fields::new(head.get(8..).unwrap_or_default());
        let version = f.u16();
        if version != VERSION {
            return Err(MapFileError::Version(version));
        }
        let sections = f.u16() as usize;
        if sections == 0 || sections > MAX_SECTIONS {
            return Err(MapFileError::Corrupt("section count"));
        }
        let mut raw = [0u8; MAX_SECTIONS * TABLE_ENTRY_LEN + 4];
        let raw = raw
            .get_mut(..sections * TABLE_ENTRY_LEN + 4)
            .ok_or(MapFileError::Corrupt("section count"))?;
        input.read_exact(raw)?;
        let (entries, stored_crc) = raw.split_at(sections * TABLE_ENTRY_LEN);
        let mut crc = crc32fast::Hasher::new();
        crc.update(&head);
        crc.update(entries);
        if crc.finalize() != Fields::new(stored_crc).u32() {
            return Err(MapFileError::HeaderChecksum);
        }
        let mut table = [Entry::default(); MAX_SECTIONS];
        for (e, bytes) in table.iter_mut().zip(entries.chunks(TABLE_ENTRY_LEN)) {
            let mut f = Fields::new(bytes);
            e.kind = f.u16();
            let _reserved = f.u16();
            e.len = f.u32();
            e.crc = f.u32();
        }
        // The required kinds, once each and in order; others may sit anywhere.
        let mut expect = kind::MAP;
        for e in table.iter().take(sections) {
            if (kind::MAP..=kind::SUBMAPS).contains(&e.kind) {
                if e.kind != expect {
                    return Err(MapFileError::Corrupt("sections missing or out of order"));
                }
                expect += 1;
            }
        }
        if expect != kind::SUBMAPS + 1 {
            return Err(MapFileError::Corrupt("a required section is missing"));
        }
        let mut reader = MapReader {
            input,
            table,
            sections,
            next: 0,
            summary: MapSummary {
                grid: GridParams::HOME,
                nodes: 0,
                edges: 0,
                submap_slots: 0,
                submaps: 0,
                next_serial: 0,
            },
        };
        let mut s = reader.section_of(kind::MAP)?;
        if s.entry.len as usize != MAP_LEN {
            return Err(MapFileError::Corrupt("map section length"));
        }
        let mut bytes = [0u8; MAP_LEN];
        reader.take(&mut s, &mut bytes)?;
        reader.finish(s)?;
        let mut f = Fields::new(&bytes);
        reader.summary = MapSummary {
            grid: get_grid(&mut f),
            nodes: f.u32(),
            edges: f.u32(),
            submap_slots: f.u32(),
            submaps: f.u32(),
            next_serial: f.u32(),
        };
        reader.check_lengths()?;
        Ok(reader)
    }

    /// What the file holds.
    pub fn summary(&self) -> MapSummary {
        self.summary
    }

    /// Reads the nodes, edges and submaps into `storage`. On an error the graph is left
    /// empty and the submap slots unused.
    ///
    /// # Errors
    /// [`MapFileError::GridMismatch`], [`MapFileError::TooLarge`] before anything is read;
    /// then any fault of the sections (see [`MapReader::open`]).
    pub fn read_into(self, storage: &mut MapStorage<'_>) -> Result<MapSummary, MapFileError> {
        self.read_parts(
            storage.grid,
            &mut storage.graph,
            storage.meta,
            storage.submaps,
            storage.cells,
        )
    }

    /// [`MapReader::read_into`] the parts of a mapper's storage (for a mapper that then
    /// starts from the map: [`MapperParts::localize`](crate::mapper::MapperParts::localize)).
    ///
    /// # Errors
    /// As [`MapReader::read_into`].
    pub fn read_into_parts(
        self,
        grid: GridParams,
        parts: &mut crate::mapper::MapperParts<'_>,
    ) -> Result<MapSummary, MapFileError> {
        self.read_parts(
            grid,
            &mut parts.graph,
            parts.meta,
            parts.submaps,
            parts.cells,
        )
    }

    fn read_parts(
        mut self,
        grid: GridParams,
        graph: &mut PoseGraph<'_>,
        meta: &mut [NodeMeta],
        submaps: &mut [SubmapMeta],
        cells: &mut [i8],
    ) -> Result<MapSummary, MapFileError> {
        let s = self.summary;
        if s.grid != grid {
            return Err(MapFileError::GridMismatch);
        }
        let node_room = graph.node_capacity().min(meta.len());
        fits("nodes", s.nodes, node_room)?;
        fits("edges", s.edges, graph.edge_capacity())?;
        fits("submap slots", s.submap_slots, submaps.len())?;
        let per = s.grid.cells();
        if cells.len() < submaps.len() * per {
            return Err(MapFileError::TooLarge(
                "submap cells",
                (submaps.len() * per) as u32,
                cells.len() as u32,
            ));
        }
        graph.clear();
        submaps.fill(SubmapMeta::EMPTY);
        let read = self.read_sections(graph, meta, submaps, cells);
        if read.is_err() {
            graph.clear();
            submaps.fill(SubmapMeta::EMPTY);
        }
        read.map(|()| s)
    }

    fn read_sections(
        &mut self,
        graph: &mut PoseGraph<'_>,
        meta: &mut [NodeMeta],
        submaps: &mut [SubmapMeta],
        cells: &mut [i8],
    ) -> Result<(), MapFileError> {
        let s = self.summary;
        let mut sec = self.section_of(kind::NODES)?;
        for i in 0..s.nodes as usize {
            let mut bytes = [0u8; NODE_LEN];
            self.take(&mut sec, &mut bytes)?;
            let (node, m) = get_node(&bytes)?;
            let after_previous = i == 0 || meta.get(i - 1).is_some_and(|p| p.serial < m.serial);
            if !after_previous || m.serial >= s.next_serial {
                return Err(MapFileError::Corrupt("node serials out of order"));
            }
            if m.submap != NO_SUBMAP && u32::from(m.submap) >= s.submap_slots {
                return Err(MapFileError::Corrupt("a node's submap slot"));
            }
            graph
                .add_node_full(node)
                .map_err(|_| MapFileError::Corrupt("a node"))?;
            *meta.get_mut(i).ok_or(MapFileError::Corrupt("a node"))? = m;
        }
        self.finish(sec)?;

        let mut sec = self.section_of(kind::EDGES)?;
        for _ in 0..s.edges {
            let mut bytes = [0u8; EDGE_LEN];
            self.take(&mut sec, &mut bytes)?;
            graph
                .add_edge(get_edge(&bytes)?)
                .map_err(|_| MapFileError::Corrupt("an edge's nodes or values"))?;
        }
        self.finish(sec)?;

        let nodes = meta.get(..s.nodes as usize).unwrap_or_default();
        let per = s.grid.cells();
        let mut sec = self.section_of(kind::SUBMAPS)?;
        for _ in 0..s.submaps {
            let mut bytes = [0u8; SUBMAP_HEAD_LEN];
            self.take(&mut sec, &mut bytes)?;
            let (slot, m) = get_submap_head(&bytes)?;
            if u32::from(slot) >= s.submap_slots {
                return Err(MapFileError::Corrupt("a submap's slot"));
            }
            let slot = slot as usize;
            let dest = submaps
                .get_mut(slot)
                .ok_or(MapFileError::Corrupt("a submap's slot"))?;
            if dest.in_use {
                return Err(MapFileError::Corrupt("a submap slot stored twice"));
            }
            if node_index(nodes, m.anchor_serial).is_none() {
                return Err(MapFileError::Corrupt("a submap's anchor is not a node"));
            }
            *dest = m;
            let grid = cells
                .get_mut(slot * per..(slot + 1) * per)
                .ok_or(MapFileError::Corrupt("a submap slot"))?;
            for chunk in grid.chunks_mut(256) {
                let mut raw = [0u8; 256];
                let raw = raw.get_mut(..chunk.len()).unwrap_or_default();
                self.take(&mut sec, raw)?;
                for (c, &b) in chunk.iter_mut().zip(raw.iter()) {
                    *c = b as i8;
                    if *c < s.grid.min || *c > s.grid.max {
                        return Err(MapFileError::Corrupt("a cell outside the grid's clamps"));
                    }
                }
            }
        }
        self.finish(sec)?;
        // Sections after the last required one are skipped, their CRCs checked.
        while self.next < self.sections {
            let s = self.open_next();
            self.skip(s)?;
        }
        Ok(())
    }

    /// The section lengths agree with the map section's counts (checked before anything is
    /// sized from them).
    fn check_lengths(&self) -> Result<(), MapFileError> {
        let s = &self.summary;
        if s.grid.side == 0 || !(s.grid.resolution > 0.0 && s.grid.resolution.is_finite()) {
            return Err(MapFileError::Corrupt("submap grid"));
        }
        if s.submaps > s.submap_slots {
            return Err(MapFileError::Corrupt("more submaps than slots"));
        }
        let per_submap = (SUBMAP_HEAD_LEN + s.grid.cells()) as u64;
        for e in self.table.iter().take(self.sections) {
            let want = match e.kind {
                kind::NODES => u64::from(s.nodes) * NODE_LEN as u64,
                kind::EDGES => u64::from(s.edges) * EDGE_LEN as u64,
                kind::SUBMAPS => u64::from(s.submaps) * per_submap,
                _ => continue,
            };
            if u64::from(e.len) != want {
                return Err(MapFileError::Corrupt(
                    "a section's length disagrees with its count",
                ));
            }
        }
        Ok(())
    }

    /// Skips (checking) sections of other kinds up to the next one of kind `k`.
    fn section_of(&mut self, k: u16) -> Result<Section, MapFileError> {
        while self.next < self.sections {
            let s = self.open_next();
            if s.entry.kind == k {
                return Ok(s);
            }
            self.skip(s)?;
        }
        Err(MapFileError::Corrupt("a required section is missing"))
    }

    fn open_next(&mut self) -> Section {
        let entry = self.table.get(self.next).copied().unwrap_or_default();
        self.next += 1;
        Section {
            entry,
            left: entry.len,
            crc: crc32fast::Hasher::new(),
        }
    }

    /// Reads `buf.len()` bytes of section `s`.
    fn take(&mut self, s: &mut Section, buf: &mut [u8]) -> Result<(), MapFileError> {
        let n = u32::try_from(buf.len()).map_err(|_| MapFileError::Corrupt("a record"))?;
        s.left = s
            .left
            .checked_sub(n)
            .ok_or(MapFileError::Corrupt("a section shorter than its records"))?;
        self.input.read_exact(buf)?;
        s.crc.update(buf);
        Ok(())
    }

    /// Ends section `s`: all its bytes read and its CRC right.
    fn finish(&mut self, s: Section) -> Result<(), MapFileError> {
        if s.left != 0 {
            return Err(MapFileError::Corrupt("a section longer than its records"));
        }
        if s.crc.finalize() != s.entry.crc {
            return Err(MapFileError::Checksum(s.entry.kind));
        }
        Ok(())
    }

    /// Reads past section `s`, checking its CRC.
    fn skip(&mut self, mut s: Section) -> Result<(), MapFileError> {
        let mut buf = [0u8; 256];
        while s.left > 0 {
            let n = (s.left as usize).min(buf.len());
            let chunk = buf.get_mut(..n).unwrap_or_default();
            self.take(&mut s, chunk)?;
        }
        self.finish(s)
    }
}

/// `need` fits in `have`.
fn fits(what: &'static str, need: u32, have: usize) -> Result<(), MapFileError> {
    if need as usize > have {
        return Err(MapFileError::TooLarge(what, need, have as u32));
    }
    Ok(())
}
