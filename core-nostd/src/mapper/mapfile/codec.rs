//! The records of a map file as bytes: little-endian fields written through a sink that keeps
//! the length and CRC of what passed, and read back from fixed record buffers.

use super::MapFileError;
use crate::frontend::lidar::Travel;
use crate::frontend::GridParams;
use crate::geom::{Info3, Se2};
use crate::graph::{EdgeKind, MixtureComponent, PoseEdge, RobustKernel, MAX_MIXTURE_COMPONENTS};
use crate::mapper::frames::NodeMeta;
use crate::mapper::submaps::SubmapMeta;
use crate::storage::NodeId;

/// Bytes of the map section.
pub(super) const MAP_LEN: usize = 30;
/// Bytes of one node record.
pub(super) const NODE_LEN: usize = 79;
/// Bytes of one edge record.
pub(super) const EDGE_LEN: usize = 115;
/// Bytes of a submap record before its cells.
pub(super) const SUBMAP_HEAD_LEN: usize = 51;

/// A sink of section bytes: forwards them to `inner` (if any) and keeps their count and CRC.
pub(super) struct Tally<'w, W> {
    pub(super) inner: Option<&'w mut W>,
    pub(super) len: u64,
    pub(super) crc: crc32fast::Hasher,
}

impl<'w, W: embedded_io::Write> Tally<'w, W> {
    pub(super) fn new(inner: Option<&'w mut W>) -> Self {
        Tally {
            inner,
            len: 0,
            crc: crc32fast::Hasher::new(),
        }
    }

    pub(super) fn put(&mut self, bytes: &[u8]) -> Result<(), MapFileError> {
        self.crc.update(bytes);
        self.len += bytes.len() as u64;
        if let Some(w) = self.inner.as_deref_mut() {
            w.write_all(bytes)
                .map_err(|e| MapFileError::Io(embedded_io::Error::kind(&e)))?;
        }
        Ok(())
    }

    pub(super) fn u8(&mut self, v: u8) -> Result<(), MapFileError> {
        self.put(&[v])
    }
    pub(super) fn u16(&mut self, v: u16) -> Result<(), MapFileError> {
        self.put(&v.to_le_bytes())
    }
    pub(super) fn u32(&mut self, v: u32) -> Result<(), MapFileError> {
        self.put(&v.to_le_bytes())
    }
    pub(super) fn i64(&mut self, v: i64) -> Result<(), MapFileError> {
        self.put(&v.to_le_bytes())
    }
    pub(super) fn f32(&mut self, v: f32) -> Result<(), MapFileError> {
        self.put(&v.to_bits().to_le_bytes())
    }
    pub(super) fn f64(&mut self, v: f64) -> Result<(), MapFileError> {
        self.put(&v.to_bits().to_le_bytes())
    }
    pub(super) fn se2(&mut self, p: &Se2) -> Result<(), MapFileError> {
        self.f64(p.x)?;
        self.f64(p.y)?;
        self.f64(p.theta)
    }
    pub(super) fn travel(&mut self, t: &Travel) -> Result<(), MapFileError> {
        self.f64(t.path)?;
        self.f64(t.rotation)
    }
}

/// Fields read in order from one record's bytes; a short record reads zeros, which the record
/// lengths (checked before) rule out.
pub(super) struct Fields<'b> {
    bytes: &'b [u8],
}

impl<'b> Fields<'b> {
    pub(super) fn new(bytes: &'b [u8]) -> Self {
        Fields { bytes }
    }

    fn take<const N: usize>(&mut self) -> [u8; N] {
        let mut out = [0u8; N];
        if let (Some(head), Some(rest)) = (self.bytes.get(..N), self.bytes.get(N..)) {
            out.copy_from_slice(head);
            self.bytes = rest;
        }
        out
    }

    pub(super) fn u8(&mut self) -> u8 {
        self.take::<1>()[0]
    }
    pub(super) fn i8(&mut self) -> i8 {
        i8::from_le_bytes(self.take::<1>())
    }
    pub(super) fn u16(&mut self) -> u16 {
        u16::from_le_bytes(self.take())
    }
    pub(super) fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }
    pub(super) fn i64(&mut self) -> i64 {
        i64::from_le_bytes(self.take())
    }
    pub(super) fn f32(&mut self) -> f32 {
        f32::from_bits(u32::from_le_bytes(self.take()))
    }
    pub(super) fn f64(&mut self) -> f64 {
        f64::from_bits(u64::from_le_bytes(self.take()))
    }
    pub(super) fn se2(&mut self) -> Se2 {
        let (x, y, theta) = (self.f64(), self.f64(), self.f64());
        Se2 { x, y, theta }
    }
    pub(super) fn travel(&mut self) -> Travel {
        let (path, rotation) = (self.f64(), self.f64());
        Travel { path, rotation }
    }
}

/// The grid parameters as stored (10 bytes).
pub(super) fn put_grid<W: embedded_io::Write>(
    t: &mut Tally<'_, W>,
    g: &GridParams,
) -> Result<(), MapFileError> {
    t.u16(g.side)?;
    t.f32(g.resolution)?;
    for v in [g.hit, g.miss, g.min, g.max] {
        t.u8(v as u8)?;
    }
    Ok(())
}

pub(super) fn get_grid(f: &mut Fields<'_>) -> GridParams {
    GridParams {
        side: f.u16(),
        resolution: f.f32(),
        hit: f.i8(),
        miss: f.i8(),
        min: f.i8(),
        max: f.i8(),
    }
}

pub(super) fn put_node<W: embedded_io::Write>(
    t: &mut Tally<'_, W>,
    node: &crate::graph::PoseNode,
    m: &NodeMeta,
) -> Result<(), MapFileError> {
    t.u32(m.serial)?;
    t.i64(m.stamp)?;
    t.se2(&node.pose)?;
    t.u8(u8::from(node.fixed))?;
    t.se2(&m.frontend)?;
    t.travel(&m.travel)?;
    t.u16(m.submap)
}

/// A node record: the graph node and its metadata.
pub(super) fn get_node(bytes: &[u8]) -> Result<(crate::graph::PoseNode, NodeMeta), MapFileError> {
    let mut f = Fields::new(bytes);
    let serial = f.u32();
    let stamp = f.i64();
    let pose = f.se2();
    let fixed = match f.u8() {
        0 => false,
        1 => true,
        _ => return Err(MapFileError::Corrupt("a node's fixed flag")),
    };
    let meta = NodeMeta {
        serial,
        stamp,
        frontend: f.se2(),
        travel: f.travel(),
        submap: f.u16(),
    };
    if !(pose.is_finite()
        && meta.frontend.is_finite()
        && meta.travel.path.is_finite()
        && meta.travel.rotation.is_finite())
    {
        return Err(MapFileError::Corrupt("a node's pose is not finite"));
    }
    Ok((crate::graph::PoseNode { pose, fixed }, meta))
}

/// The upper triangle of a symmetric 3x3 matrix, row by row.
const UPPER: [(usize, usize); 6] = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)];

pub(super) fn put_edge<W: embedded_io::Write>(
    t: &mut Tally<'_, W>,
    e: &PoseEdge,
) -> Result<(), MapFileError> {
    t.u32(e.from.0)?;
    t.u32(e.to.0)?;
    t.se2(&e.measurement)?;
    for (r, c) in UPPER {
        t.f64(e.information[(r, c)])?;
    }
    t.u8(match e.kind {
        EdgeKind::Odometry => 0,
        EdgeKind::Loop => 1,
        EdgeKind::ZeroConstraint => 2,
        EdgeKind::Prior => 3,
    })?;
    let none = [MixtureComponent::NOMINAL; MAX_MIXTURE_COMPONENTS];
    let (tag, param, count, comps) = match e.robust {
        RobustKernel::None => (0, 0.0, 0, none),
        RobustKernel::Huber { delta } => (1, delta, 0, none),
        RobustKernel::Cauchy { c } => (2, c, 0, none),
        RobustKernel::MaxMixture { components, count } => (3, 0.0, count, components),
    };
    t.u8(tag)?;
    t.f64(param)?;
    t.u8(count)?;
    for c in comps {
        t.f32(c.weight)?;
        t.f32(c.info_scale)?;
    }
    Ok(())
}

/// An edge record (its node indices and values are checked by the graph when it is added).
pub(super) fn get_edge(bytes: &[u8]) -> Result<PoseEdge, MapFileError> {
    let mut f = Fields::new(bytes);
    let from = NodeId(f.u32());
    let to = NodeId(f.u32());
    let measurement = f.se2();
    let mut information = Info3::zeros();
    for (r, c) in UPPER {
        let v = f.f64();
        information[(r, c)] = v;
        information[(c, r)] = v;
    }
    let kind = match f.u8() {
        0 => EdgeKind::Odometry,
        1 => EdgeKind::Loop,
        2 => EdgeKind::ZeroConstraint,
        3 => EdgeKind::Prior,
        _ => return Err(MapFileError::Corrupt("an edge's kind")),
    };
    let (tag, param, count) = (f.u8(), f.f64(), f.u8());
    let mut components = [MixtureComponent::NOMINAL; MAX_MIXTURE_COMPONENTS];
    for c in &mut components {
        c.weight = f.f32();
        c.info_scale = f.f32();
    }
    let robust = match tag {
        0 => RobustKernel::None,
        1 => RobustKernel::Huber { delta: param },
        2 => RobustKernel::Cauchy { c: param },
        3 if (1..=MAX_MIXTURE_COMPONENTS).contains(&(count as usize))
            && components.iter().all(|c| {
                c.weight > 0.0 && c.weight <= 1.0 && c.info_scale > 0.0 && c.info_scale.is_finite()
            }) =>
        {
            RobustKernel::MaxMixture { components, count }
        }
        _ => return Err(MapFileError::Corrupt("an edge's robust kernel")),
    };
    if matches!(
        robust,
        RobustKernel::Huber { .. } | RobustKernel::Cauchy { .. }
    ) && !(param.is_finite() && param > 0.0)
    {
        return Err(MapFileError::Corrupt("an edge's robust kernel"));
    }
    Ok(PoseEdge {
        from,
        to,
        measurement,
        information,
        kind,
        robust,
    })
}

pub(super) fn put_submap_head<W: embedded_io::Write>(
    t: &mut Tally<'_, W>,
    slot: u16,
    m: &SubmapMeta,
) -> Result<(), MapFileError> {
    t.u16(slot)?;
    t.u8(u8::from(m.active))?;
    t.u32(m.anchor_serial)?;
    t.se2(&m.anchor_frontend)?;
    t.u32(m.keyframes)?;
    t.travel(&m.anchor_travel)
}

/// A submap record's head: its slot and metadata.
pub(super) fn get_submap_head(bytes: &[u8]) -> Result<(u16, SubmapMeta), MapFileError> {
    let mut f = Fields::new(bytes);
    let slot = f.u16();
    let active = match f.u8() {
        0 => false,
        1 => true,
        _ => return Err(MapFileError::Corrupt("a submap's active flag")),
    };
    let m = SubmapMeta {
        in_use: true,
        active,
        anchor_serial: f.u32(),
        anchor_frontend: f.se2(),
        keyframes: f.u32(),
        anchor_travel: f.travel(),
        anchor_estimate: None,
    };
    if !(m.anchor_frontend.is_finite()
        && m.anchor_travel.path.is_finite()
        && m.anchor_travel.rotation.is_finite())
    {
        return Err(MapFileError::Corrupt(
            "a submap's anchor pose is not finite",
        ));
    }
    Ok((slot, m))
}
