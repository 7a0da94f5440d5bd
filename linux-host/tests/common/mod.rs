//! Shared helpers of the interop tests: the Python venv with the independent tools.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

/// The repository root.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The venv's python (made by `bash scripts/venv.sh`), or `None` with a message when it is
/// missing on a developer machine.
///
/// # Panics
/// Under CI (`CI` set) when the venv is missing: the interop checks must never silently skip.
pub fn venv_python() -> Option<PathBuf> {
    let python = repo_root().join(".venv").join("bin").join("python");
    if python.is_file() {
        return Some(python);
    }
    if std::env::var_os("CI").is_some() {
        panic!(
            "the Python venv {} is missing: run `bash scripts/venv.sh` before the tests",
            python.display()
        );
    }
    eprintln!(
        "SKIPPED: no venv at {} (run `bash scripts/venv.sh`)",
        python.display()
    );
    None
}

/// Runs `scripts/interop/<script>` with the venv python and returns its stdout.
///
/// # Panics
/// When the script fails.
pub fn run_python(python: &Path, script: &str, args: &[&std::ffi::OsStr]) -> String {
    let script = repo_root().join("scripts").join("interop").join(script);
    let out = Command::new(python)
        .arg(&script)
        .args(args)
        .output()
        .expect("starting python");
    assert!(
        out.status.success(),
        "{} failed:\nstdout:\n{}\nstderr:\n{}",
        script.display(),
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("utf-8 output")
}

/// The `cloi` binary of this build.
pub fn cloi() -> Command {
    Command::new(env!("CARGO_BIN_EXE_cloi"))
}
