//! Golden tests of `cloi map` on real logs, against the GMapping reference with the metric of
//! `cloi eval ref` (in the laser's frame, as the reference poses are):
//! * the whole `mit-csail.clf` (1,988 scans, 7 minutes): the relation error of the final
//!   trajectory beats GMapping's published 0.049 m, and two deterministic runs are identical;
//! * the whole `fr079.clf` (4,934 scans, 18 minutes): beats GMapping's published 0.061 m;
//! * a cut of `intel.clf` (the first 4,000 scans, 13 minutes, with its first big loops): the
//!   error stays under its golden bound, and the two-thread schedule and a deliberately
//!   delayed back-end keep the real-time pose free of jumps;
//! * the whole `intel.clf` (13,631 scans, 45 minutes), with the preset and with more loop
//!   candidates per keyframe (a perturbation that used to bend the map to 0.73 m): both stay
//!   under the error intel had before the loop-search window was taken from the submap's
//!   anchor (0.0515 m).
//!
//! Release mode: `cargo test --release -p cloi-host --features golden --test golden_map`.

use std::path::Path;
use std::process::Command;

use cloi_core::Se2;
use cloi_host::eval::relations::{relations_from_reference, score, PlanarTrajectory};

fn map(log: &Path, out: &Path, extra: &[&str]) -> serde_json::Value {
    let mut args = vec![
        "map",
        log.to_str().expect("utf-8"),
        "--quiet",
        "--out",
        out.to_str().expect("utf-8"),
    ];
    args.extend_from_slice(extra);
    let o = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(&args)
        .output()
        .expect("cloi runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = std::fs::read_to_string(out.join("report.json")).expect("report");
    serde_json::from_str(&text).expect("json")
}

/// The relation error of `dir/trajectory.tum` in the laser's frame (the reference holds the
/// laser's poses; the mounting is the one `cloi map` reports).
fn relation_error(
    dir: &Path,
    report: &serde_json::Value,
    reference: &Path,
    min_pairs: usize,
) -> f64 {
    let o = &report["input"]["laser_offset"];
    let laser = Se2::new(
        o[0].as_f64().expect("laser x"),
        o[1].as_f64().expect("laser y"),
        o[2].as_f64().expect("laser theta"),
    );
    let traj = PlanarTrajectory::load_tum(&dir.join("trajectory.tum"))
        .expect("trajectory")
        .in_sensor_frame(&laser);
    let reference = PlanarTrajectory::load_reference(reference).expect("reference");
    let rels = relations_from_reference(&reference, 1.0);
    let s = score(&traj, &rels, 0.0).expect("score");
    assert!(s.pairs_used > min_pairs, "{s:?}");
    s.trans_mean_m
}

#[test]
fn csail_beats_gmapping_and_repeats_exactly() {
    let Some(log) = cloi_host::dataset::shared_file("carmen/mit-csail.clf") else {
        return;
    };
    let Some(reference) =
        cloi_host::dataset::shared_file("carmen/mit-csail.gfs_reference_poses.txt")
    else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    let ra = map(&log, &a, &["--deterministic"]);
    map(&log, &b, &["--deterministic"]);
    for f in ["trajectory.tum", "gpe.tum", "graph.g2o", "map.pgm"] {
        assert_eq!(
            std::fs::read(a.join(f)).expect("a"),
            std::fs::read(b.join(f)).expect("b"),
            "{f} differs between two deterministic runs"
        );
    }
    let err = relation_error(&a, &ra, &reference, 500);
    println!("mit-csail: relation error {err:.4} m, report {ra}");
    // Measured 0.0422 m (2026-11-29); GMapping's published figure is the bound.
    assert!(err < 0.049, "relation error {err} m");
    assert!(ra["gpe_max_jump_m"].as_f64().expect("jump") < 0.05, "{ra}");
}

#[test]
fn fr079_beats_gmapping() {
    let Some(log) = cloi_host::dataset::shared_file("carmen/fr079.clf") else {
        return;
    };
    let Some(reference) = cloi_host::dataset::shared_file("carmen/fr079.gfs_reference_poses.txt")
    else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let a = tmp.path().join("a");
    let ra = map(&log, &a, &["--deterministic"]);
    // The one log of the three whose laser is off the robot's centre (0.04 m behind it).
    assert_eq!(ra["input"]["laser_offset"][0].as_f64(), Some(-0.04), "{ra}");
    let err = relation_error(&a, &ra, &reference, 500);
    println!("fr079: relation error {err:.4} m, report {ra}");
    // Measured 0.0371 m (2026-11-29); GMapping's published figure is the bound.
    assert!(err < 0.061, "relation error {err} m");
    assert!(ra["gpe_max_jump_m"].as_f64().expect("jump") < 0.05, "{ra}");
}

#[test]
fn intel_cut_stays_within_its_bound_and_has_no_jumps() {
    let Some(log) = cloi_host::dataset::shared_file("carmen/intel.clf") else {
        return;
    };
    let Some(reference) = cloi_host::dataset::shared_file("carmen/intel.gfs_reference_poses.txt")
    else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let a = tmp.path().join("a");
    let cut = ["--max-scans", "4000"];
    let ra = map(&log, &a, &[&cut[..], &["--deterministic"]].concat());
    let err = relation_error(&a, &ra, &reference, 500);
    println!("intel first 4000 scans: relation error {err:.4} m, report {ra}");
    // Measured 0.0437 m (2026-11-29; 0.605 m while the loop-search window shrank after every
    // local loop closure and the first big loops of the cut were missed); 5 % margin.
    assert!(err < 0.046, "relation error {err} m");
    assert_eq!(ra["stamps_repaired"].as_u64(), Some(494), "{ra}");
    assert!(ra["gpe_max_jump_m"].as_f64().expect("jump") < 0.05, "{ra}");

    // Two threads, and a back-end held back by 30 s of data: no jumps either.
    for (i, extra) in [&[][..], &["--backend-delay", "30"][..]].iter().enumerate() {
        let dir = tmp.path().join(format!("t{i}"));
        let r = map(&log, &dir, &[&cut[..], extra].concat());
        assert!(r["gpe_max_jump_m"].as_f64().expect("jump") < 0.05, "{r}");
        assert_eq!(r["scans"], ra["scans"]);
    }
}

#[test]
fn intel_stays_consistent_when_loop_search_changes() {
    let Some(log) = cloi_host::dataset::shared_file("carmen/intel.clf") else {
        return;
    };
    let Some(reference) = cloi_host::dataset::shared_file("carmen/intel.gfs_reference_poses.txt")
    else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let five = tmp.path().join("five.toml");
    std::fs::write(&five, "[loop_closure]\nmax_candidates = 5\n").expect("config");
    for (name, extra) in [
        ("preset", vec!["--deterministic"]),
        (
            "5 candidates",
            vec!["--deterministic", "--config", five.to_str().expect("utf-8")],
        ),
    ] {
        let dir = tmp.path().join(name.replace(' ', "-"));
        let r = map(&log, &dir, &extra);
        let err = relation_error(&dir, &r, &reference, 5000);
        println!("intel ({name}): relation error {err:.4} m, report {r}");
        // Measured 0.0415 m (preset) and 0.0400 m (5 candidates) (2026-11-29); before the
        // window change 0.0515 m and 0.73 m. The old preset figure is the bound.
        assert!(err < 0.0515, "{name}: relation error {err} m");
        assert!(r["gpe_max_jump_m"].as_f64().expect("jump") < 0.05, "{r}");
    }
}
