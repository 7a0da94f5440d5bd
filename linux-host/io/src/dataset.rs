//! Where the shared evaluation datasets live.
//!
//! The public datasets stay outside the repository, in `../shared/data` beside the checkout
//! (CI has them there). `CLOI_DATA_DIR` overrides the location.

use std::path::{Path, PathBuf};

/// The shared data folder: `$CLOI_DATA_DIR`, else `<workspace>/../shared/data`.
pub fn shared_data_dir() -> PathBuf {
    if let Some(dir) = std::env::var_os("CLOI_DATA_DIR") {
        return PathBuf::from(dir);
    }
    // This crate is `<workspace>/linux-host/io`.
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("..")
        .join("..")
        .join("shared")
        .join("data")
}

/// The path of a shared dataset file, e.g. `shared_file("g2o/CSAIL.g2o")`, for tests.
///
/// Returns `None` (and says so on stderr) when the file is missing on a developer machine that
/// has no `../shared`, so the test can skip. Under CI (`CI` set) a missing file is a test
/// failure, never a silent skip.
///
/// # Panics
/// When the file is missing and the `CI` environment variable is set.
pub fn shared_file(relative: &str) -> Option<PathBuf> {
    let path = shared_data_dir().join(relative);
    if path.is_file() {
        return Some(path);
    }
    if std::env::var_os("CI").is_some() {
        panic!(
            "shared dataset {} is missing (CI must have ../shared/data)",
            path.display()
        );
    }
    eprintln!(
        "SKIPPED: shared dataset {} not found (set CLOI_DATA_DIR)",
        path.display()
    );
    None
}
