//! Writing a map file: each section is encoded twice, first into a tally for the table's
//! lengths and CRCs, then to the sink, so the table can lead the file and a reader can check
//! each section as it streams past, with no buffer for the whole map on either side.

use super::codec::{put_edge, put_grid, put_node, put_submap_head, Tally};
use super::{kind, MapFileError, MapRef, MAGIC, VERSION};

/// The required sections, in file order.
const SECTIONS: [u16; 4] = [kind::MAP, kind::NODES, kind::EDGES, kind::SUBMAPS];

/// Writes `map` to `out` as a version-[`VERSION`] map file; returns the bytes written.
///
/// # Errors
/// [`MapFileError::Io`] from the sink; [`MapFileError::Corrupt`] when `map`'s parts do not fit
/// together (fewer metadata entries than nodes, cells missing for a slot in use, a section
/// above 4 GiB).
pub fn write_map<W: embedded_io::Write>(
    map: &MapRef<'_>,
    out: &mut W,
) -> Result<u64, MapFileError> {
    check(map)?;
    let mut table = [(0u32, 0u32); SECTIONS.len()];
    for (entry, &k) in table.iter_mut().zip(&SECTIONS) {
        let mut tally = Tally::<W>::new(None);
        section(k, map, &mut tally)?;
        let len =
            u32::try_from(tally.len).map_err(|_| MapFileError::Corrupt("a section above 4 GiB"))?;
        *entry = (len, tally.crc.finalize());
    }
    let mut head = Tally::new(Some(&mut *out));
    head.put(&MAGIC)?;
    head.u16(VERSION)?;
    head.u16(SECTIONS.len() as u16)?;
    head.u32(0)?;
    for (&k, &(len, crc)) in SECTIONS.iter().zip(&table) {
        head.u16(k)?;
        head.u16(0)?;
        head.u32(len)?;
        head.u32(crc)?;
        head.u32(0)?;
    }
    let header_crc = head.crc.clone().finalize();
    head.u32(header_crc)?;
    let mut total = head.len;
    for &k in &SECTIONS {
        let mut body = Tally::new(Some(&mut *out));
        section(k, map, &mut body)?;
        total += body.len;
    }
    out.flush()
        .map_err(|e| MapFileError::Io(embedded_io::Error::kind(&e)))?;
    Ok(total)
}

/// The parts of `map` agree with each other.
fn check(map: &MapRef<'_>) -> Result<(), MapFileError> {
    if map.meta.len() < map.nodes.len() {
        return Err(MapFileError::Corrupt("fewer node metadata than nodes"));
    }
    let per = map.grid.cells();
    let in_use = map.submaps.iter().enumerate().filter(|(_, m)| m.in_use);
    for (slot, _) in in_use {
        if slot > u16::MAX as usize || map.cells.len() < (slot + 1) * per {
            return Err(MapFileError::Corrupt("a submap slot without cells"));
        }
    }
    Ok(())
}

/// Encodes section `k` of `map` into `t`.
fn section<W: embedded_io::Write>(
    k: u16,
    map: &MapRef<'_>,
    t: &mut Tally<'_, W>,
) -> Result<(), MapFileError> {
    let per = map.grid.cells();
    let stored = || map.submaps.iter().enumerate().filter(|(_, m)| m.in_use);
    match k {
        kind::MAP => {
            put_grid(t, &map.grid)?;
            t.u32(map.nodes.len() as u32)?;
            t.u32(map.edges.len() as u32)?;
            t.u32(map.submaps.len() as u32)?;
            t.u32(stored().count() as u32)?;
            t.u32(map.next_serial)
        }
        kind::NODES => {
            for (n, m) in map.nodes.iter().zip(map.meta) {
                put_node(t, n, m)?;
            }
            Ok(())
        }
        kind::EDGES => {
            for e in map.edges {
                put_edge(t, e)?;
            }
            Ok(())
        }
        _ => {
            for (slot, m) in stored() {
                put_submap_head(t, slot as u16, m)?;
                let cells = map
                    .cells
                    .get(slot * per..(slot + 1) * per)
                    .unwrap_or_default();
                for chunk in cells.chunks(256) {
                    let mut bytes = [0u8; 256];
                    for (b, &c) in bytes.iter_mut().zip(chunk) {
                        *b = c as u8;
                    }
                    t.put(bytes.get(..chunk.len()).unwrap_or_default())?;
                }
            }
            Ok(())
        }
    }
}
