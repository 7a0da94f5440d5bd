//! Helpers shared by the fuzz targets.

use std::path::PathBuf;

/// Writes `data` to a file private to this process and returns its path, for the parsers
/// that only take a path (trajectories, relations). The file is overwritten on every run.
pub fn scratch_file(name: &str, data: &[u8]) -> PathBuf {
    let path = std::env::temp_dir().join(format!("cloi-fuzz-{}-{name}", std::process::id()));
    std::fs::write(&path, data).expect("scratch file writable");
    path
}

/// A copy of a `.cloilog` image with the CRC-32 of every whole record rewritten to match its
/// bytes. Records are found the way the reader finds them: after the header length stored at
/// bytes 10..12, each frame's length from [`frame_len`](cloi_core::sensor::log::frame_len).
pub fn with_cloilog_crcs(data: &[u8]) -> Vec<u8> {
    use cloi_core::sensor::log::{crc32, frame_len};
    let mut out = data.to_vec();
    let Some(&[lo, hi]) = data.get(10..12) else {
        return out;
    };
    let mut at = usize::from(u16::from_le_bytes([lo, hi]));
    while let Some(Ok(Some(total))) = out.get(at..).map(frame_len) {
        // A frame is at least FRAME_OVERHEAD (12) bytes; its last 4 are the CRC.
        let Some(end) = at.checked_add(total) else {
            break;
        };
        let body_end = end.saturating_sub(4);
        let Some(crc) = out.get(at..body_end).map(crc32) else {
            break;
        };
        let Some(field) = out.get_mut(body_end..end) else {
            break;
        };
        field.copy_from_slice(&crc.to_le_bytes());
        at = end;
    }
    out
}

/// `data` with the CRCs of a `.cloimap` recomputed: each section's over the bytes its table
/// entry spans, then the header and table's own; the rest left as it is.
pub fn with_mapfile_crcs(data: &[u8]) -> Vec<u8> {
    use cloi_core::mapper::mapfile::{HEADER_LEN, MAX_SECTIONS, TABLE_ENTRY_LEN};
    let mut out = data.to_vec();
    let Some(&[lo, hi]) = data.get(10..12) else {
        return out;
    };
    let sections = usize::from(u16::from_le_bytes([lo, hi])).min(MAX_SECTIONS);
    let table_end = HEADER_LEN + sections * TABLE_ENTRY_LEN;
    let mut at = table_end + 4;
    for i in 0..sections {
        let entry = HEADER_LEN + i * TABLE_ENTRY_LEN;
        let Some(len) = out.get(entry + 4..entry + 8) else {
            return out;
        };
        let len = u32::from_le_bytes([len[0], len[1], len[2], len[3]]) as usize;
        let Some(body) = at.checked_add(len).and_then(|end| out.get(at..end)) else {
            break;
        };
        let crc = cloi_core::sensor::log::crc32(body);
        out[entry + 8..entry + 12].copy_from_slice(&crc.to_le_bytes());
        at += len;
    }
    if let Some(head) = out.get(..table_end) {
        let crc = cloi_core::sensor::log::crc32(head);
        if let Some(field) = out.get_mut(table_end..table_end + 4) {
            field.copy_from_slice(&crc.to_le_bytes());
        }
    }
    out
}

/// `data` with the trailing CRC-32 of a vocabulary file (its last 4 bytes) rewritten to match
/// every byte before it; inputs shorter than the CRC are left as they are.
pub fn with_vocab_crc(data: &[u8]) -> Vec<u8> {
    use cloi_core::frontend::visual::vocab::file::CRC_LEN;
    let mut out = data.to_vec();
    if let Some(body_len) = out.len().checked_sub(CRC_LEN) {
        let crc = cloi_core::sensor::log::crc32(&out[..body_len]);
        out[body_len..].copy_from_slice(&crc.to_le_bytes());
    }
    out
}
