//! Helpers shared by the fuzz targets.

use std::path::PathBuf;

/// Writes `data` to a file private to this process and returns its path, for the parsers
/// that only take a path (trajectories, relations). The file is overwritten on every run.
pub fn scratch_file(name: &str, data: &[u8]) -> PathBuf {
    let path = std::env::temp_dir().join(format!("cloi-fuzz-{}-{name}", std::process::id()));
    std::fs::write(&path, data).expect("scratch file writable");
    path
}
