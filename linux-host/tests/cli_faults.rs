//! `cloi map` and `cloi convert` when the output cannot be written: a full disk (a file-size
//! limit, `ulimit -f`, which makes every write past it fail with EFBIG like a full disk does
//! with ENOSPC) and a read-only output folder. Each must exit non-zero with an error that names
//! what could not be written, leave no partial output and no temporary file, and keep a
//! previous run's outputs as they were.
//!
//! Tests often run as root, where permission bits do not stop writes: the read-only folder is
//! then a read-only tmpfs mounted over it in a private mount namespace (`unshare -m`).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const CLOI: &str = env!("CARGO_BIN_EXE_cloi");

/// Runs `cloi ARGS` under `sh` with writes limited to `blocks` of 512 bytes (dash's unit) and
/// SIGXFSZ ignored, so that an oversized write fails with EFBIG instead of killing the process.
fn cloi_with_file_limit(blocks: u32, args: &[&str]) -> Output {
    Command::new("sh")
        .arg("-c")
        .arg(format!(
            "trap '' XFSZ; ulimit -f {blocks} && exec \"$0\" \"$@\""
        ))
        .arg(CLOI)
        .args(args)
        .output()
        .expect("sh runs")
}

fn cloi(args: &[&str]) -> Output {
    Command::new(CLOI).args(args).output().expect("cloi runs")
}

/// Names in `dir`, sorted.
fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .expect("list the folder")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
}

/// Runs `cloi ARGS` with `dir` read-only: by permissions for an ordinary user, by a read-only
/// tmpfs over it (in a private mount namespace) for root. `None` when neither can be set up.
fn cloi_with_read_only(dir: &Path, args: &[&str]) -> Option<Output> {
    if !is_root() {
        use std::os::unix::fs::PermissionsExt;
        let set = |mode| std::fs::set_permissions(dir, std::fs::Permissions::from_mode(mode));
        set(0o555).expect("chmod");
        let out = cloi(args);
        set(0o755).expect("chmod");
        return Some(out);
    }
    let out = Command::new("unshare")
        .args(["-m", "sh", "-c"])
        .arg(
            "mount -t tmpfs -o ro tmpfs \"$0\" || exit 97; echo read-only-mounted >&2; \
             exec \"$@\"",
        )
        .arg(dir)
        .arg(CLOI)
        .args(args)
        .output()
        .ok()?;
    stderr(&out).starts_with("read-only-mounted").then_some(out)
}

fn map_args(out: &Path) -> Vec<String> {
    [
        "map",
        "--deterministic",
        "--quiet",
        "--sim-duration",
        "10",
        "--out",
    ]
    .iter()
    .map(|s| (*s).to_owned())
    .chain([out.to_string_lossy().into_owned()])
    .collect()
}

fn as_strs(v: &[String]) -> Vec<&str> {
    v.iter().map(String::as_str).collect()
}

#[test]
fn map_on_a_full_disk_fails_and_keeps_the_previous_outputs() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("out");
    let args = map_args(&out);
    let first = cloi(&as_strs(&args));
    assert!(first.status.success(), "{}", stderr(&first));
    let before = names(&out);
    assert!(before.contains(&"report.json".to_owned()), "{before:?}");
    let report = std::fs::read(out.join("report.json")).expect("report");

    // 16 blocks = 8 KiB: the map image alone is larger.
    let second = cloi_with_file_limit(16, &as_strs(&args));
    let err = stderr(&second);
    assert!(!second.status.success(), "a full disk must fail: {err}");
    assert!(err.contains("File too large"), "{err}");
    assert!(
        err.contains(&out.to_string_lossy().into_owned()),
        "the error names the output: {err}"
    );
    assert_eq!(
        names(&out),
        before,
        "no partial file, no temporary file, nothing removed"
    );
    assert_eq!(
        std::fs::read(out.join("report.json")).expect("report"),
        report
    );
}

/// A small CARMEN log for `cloi convert`.
fn carmen_log(dir: &Path) -> PathBuf {
    let mut text = String::from("PARAM robot_frontlaser_offset 0.1 h 0\n");
    for i in 0..200 {
        let t = 100.0 + f64::from(i) * 0.1;
        let x = f64::from(i) * 0.01;
        text.push_str(&format!("ODOM {x} 0.0 0.0 0.5 0.0 0.0 {t} h 0\n"));
        text.push_str(&format!(
            "FLASER 3 1.0 2.0 3.0 {x} 0 0 {x} 0 0 {:.3} h 0\n",
            t + 0.05
        ));
    }
    let path = dir.join("tiny.clf");
    std::fs::write(&path, text).expect("write the log");
    path
}

#[test]
fn convert_on_a_full_disk_fails_without_output_or_temporary_file() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let log = carmen_log(tmp.path());
    let out_dir = tmp.path().join("out");
    std::fs::create_dir(&out_dir).expect("mkdir");
    for name in ["tiny.mcap", "tiny.cloilog", "tiny.tum"] {
        let target = out_dir.join(name);
        let args = [
            "convert",
            log.to_str().expect("utf-8"),
            target.to_str().expect("utf-8"),
        ];
        // 2 blocks = 1 KiB; every output of 200 scans is larger.
        let run = cloi_with_file_limit(2, &args);
        let err = stderr(&run);
        assert!(
            !run.status.success(),
            "{name}: a full disk must fail: {err}"
        );
        assert!(err.contains("File too large"), "{name}: {err}");
        assert!(
            err.contains(target.to_str().expect("utf-8")),
            "{name}: the error names the output file: {err}"
        );
        assert!(names(&out_dir).is_empty(), "{name}: {:?}", names(&out_dir));
        // Without the limit the same conversion works: the failure was the disk's.
        let ok = cloi(&args);
        assert!(ok.status.success(), "{name}: {}", stderr(&ok));
        assert_eq!(names(&out_dir), [name]);
        std::fs::remove_file(&target).expect("remove");
    }
}

#[test]
fn map_and_convert_into_a_read_only_folder_fail_naming_it() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let log = carmen_log(tmp.path());
    let ro = tmp.path().join("ro");
    std::fs::create_dir(&ro).expect("mkdir");
    let target = ro.join("tiny.mcap");
    let convert = [
        "convert",
        log.to_str().expect("utf-8"),
        target.to_str().expect("utf-8"),
    ];
    let Some(run) = cloi_with_read_only(&ro, &convert) else {
        eprintln!(
            "skipped: running as root without `unshare -m` and tmpfs mounts, a folder cannot \
             be made read-only"
        );
        return;
    };
    let err = stderr(&run);
    assert!(!run.status.success(), "{err}");
    assert!(
        err.contains(target.to_str().expect("utf-8")),
        "the error names the output file: {err}"
    );
    assert!(
        err.contains("Read-only file system") || err.contains("Permission denied"),
        "{err}"
    );

    let args = map_args(&ro);
    let run = cloi_with_read_only(&ro, &as_strs(&args)).expect("set up as above");
    let err = stderr(&run);
    assert!(!run.status.success(), "{err}");
    assert!(
        err.contains(ro.to_str().expect("utf-8")),
        "the error names the output folder: {err}"
    );
    assert!(names(&ro).is_empty(), "{:?}", names(&ro));
}
