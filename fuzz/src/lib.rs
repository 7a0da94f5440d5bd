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
