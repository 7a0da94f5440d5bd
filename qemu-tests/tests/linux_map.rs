//! `cloi map` built for the robot computer's Linux (armv7-unknown-linux-gnueabihf) and run
//! under `qemu-arm -cpu cortex-a9` on the first scans of intel.clf gives the same files as the
//! x86-64 build: the trajectory of every scan, the real-time poses, the graph and the map,
//! byte for byte.
//!
//! Both builds are release builds of the same source; the core uses `libm` for every float
//! function and Rust never fuses multiply-adds, so the two are expected to agree to the bit and
//! the test compares the files exactly (the report differs only in timings and heap figures,
//! so its counters are compared instead).

use std::path::Path;
use std::process::{Command, Stdio};

use cloi_qemu_tests::{build_cloi, workspace_root, LINUX_TARGET};

/// Scans of intel.clf mapped (office profile, the default for files): enough for loop
/// closures (216) and many back-end optimizations (99); about a minute under qemu-arm.
const SCANS: &str = "3500";

fn map(cmd: &mut Command, clf: &Path, out: &Path) {
    let status = cmd
        .arg("map")
        .arg(clf)
        .args(["--deterministic", "--quiet", "--max-scans", SCANS, "--out"])
        .arg(out)
        .stdout(Stdio::null())
        .status()
        .expect("cloi runs");
    assert!(status.success(), "{cmd:?} failed: {status}");
}

fn report(dir: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(dir.join("report.json")).expect("report.json");
    serde_json::from_str(&text).expect("report.json parses")
}

#[test]
fn cloi_map_on_armv7_linux_equals_x86() {
    let Some(clf) = cloi_host::dataset::shared_file("carmen/intel.clf") else {
        return;
    };
    let x86 = build_cloi(None).expect("x86-64 build");
    let arm = build_cloi(Some(LINUX_TARGET)).expect("armv7 build");
    let dir = workspace_root().join("target").join("qemu-linux-map");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let (out_x86, out_arm) = (dir.join("x86_64"), dir.join("armv7"));

    map(&mut Command::new(&x86), &clf, &out_x86);
    let mut qemu = Command::new("qemu-arm");
    qemu.args(["-cpu", "cortex-a9", "-L", "/usr/arm-linux-gnueabihf"])
        .arg(&arm);
    map(&mut qemu, &clf, &out_arm);

    for file in [
        "trajectory.tum",
        "gpe.tum",
        "graph.g2o",
        "map.pgm",
        "map.yaml",
    ] {
        let a = std::fs::read(out_x86.join(file)).expect(file);
        let b = std::fs::read(out_arm.join(file)).expect(file);
        assert!(!a.is_empty(), "{file} is empty");
        if a != b {
            let first = a
                .iter()
                .zip(&b)
                .position(|(x, y)| x != y)
                .unwrap_or(a.len().min(b.len()));
            panic!(
                "{file} differs between x86-64 and armv7 from byte {first} ({} vs {} bytes)",
                a.len(),
                b.len()
            );
        }
    }
    let (rx, ra) = (report(&out_x86), report(&out_arm));
    for key in [
        "scans",
        "scans_rejected",
        "keyframes",
        "nodes",
        "edges",
        "loop_closures",
        "gpe_max_jump_m",
        "stamps_repaired",
        "mapper",
    ] {
        assert!(!rx[key].is_null(), "report has no {key}");
        assert_eq!(rx[key], ra[key], "report field {key}");
    }
    assert_eq!(rx["scans"], 3500);
    assert!(rx["loop_closures"].as_u64().unwrap() > 0, "{rx}");
    assert!(rx["mapper"]["optimizations"].as_u64().unwrap() > 1, "{rx}");
    let lines = std::fs::read_to_string(out_x86.join("trajectory.tum")).unwrap();
    println!(
        "cloi map on {SCANS} intel scans: {} trajectory lines, {} keyframes, {} loop closures, \
         identical on x86-64 and armv7 (qemu-arm)",
        lines.lines().count(),
        rx["keyframes"],
        rx["loop_closures"]
    );
}
