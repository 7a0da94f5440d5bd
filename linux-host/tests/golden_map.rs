//! Golden test of `cloi map` on a cut of a real log (the first 4,000 scans of `intel.clf`,
//! about 13 minutes of data): the relation error against the GMapping reference (the metric of
//! `cloi eval ref`) stays under its golden bound, deterministic runs are bit-identical, the
//! two-thread schedule and a deliberately delayed back-end keep the real-time pose free of
//! jumps. Release mode: `cargo test --release -p cloi-host --features golden --test golden_map`.

use std::path::Path;
use std::process::Command;

use cloi_host::eval::relations::{relations_from_reference, score, PlanarTrajectory};

fn map(log: &Path, out: &Path, extra: &[&str]) -> serde_json::Value {
    let mut args = vec![
        "map",
        log.to_str().expect("utf-8"),
        "--max-scans",
        "4000",
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

fn relation_error(dir: &Path, reference: &Path) -> f64 {
    let traj = PlanarTrajectory::load_tum(&dir.join("trajectory.tum")).expect("trajectory");
    let reference = PlanarTrajectory::load_reference(reference).expect("reference");
    let rels = relations_from_reference(&reference, 1.0);
    let s = score(&traj, &rels, 0.0).expect("score");
    assert!(s.pairs_used > 500, "{s:?}");
    s.trans_mean_m
}

#[test]
fn intel_cut_maps_within_the_golden_error_and_repeats_exactly() {
    let Some(log) = cloi_host::dataset::shared_file("carmen/intel.clf") else {
        return;
    };
    let Some(reference) = cloi_host::dataset::shared_file("carmen/intel.gfs_reference_poses.txt")
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
    let err = relation_error(&a, &reference);
    println!("intel first 4000 scans: relation error {err:.4} m, report {ra}");
    // Measured 0.846 m (2026-11-22, f90fc1e); the bound leaves 5 %.
    assert!(err < 0.89, "relation error {err} m");
    assert_eq!(ra["mapper"]["icp_failures"].as_u64(), Some(0), "{ra}");
    assert!(ra["gpe_max_jump_m"].as_f64().expect("jump") < 0.05, "{ra}");

    // Two threads, and a back-end held back by 30 s of data: no jumps either.
    for extra in [&[][..], &["--backend-delay", "30"][..]] {
        let dir = tmp.path().join(format!("t{}", extra.len()));
        let r = map(&log, &dir, extra);
        assert!(r["gpe_max_jump_m"].as_f64().expect("jump") < 0.05, "{r}");
        assert_eq!(r["scans"], ra["scans"]);
    }
}
