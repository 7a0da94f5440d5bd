//! Golden pose-graph results on the shared datasets (release build, feature `golden`):
//! `cargo test --release -p cloi-host --features golden --test golden_pgo`.
//!
//! * Final chi2 with Gauss-Newton from the odometry guess must be no worse than the best peer
//!   (g2o and GTSAM, measured on this machine and quoted in issue 3 to two decimals). The
//!   tolerance is half a unit of the quoted last digit (0.005): the quoted figure is a rounded
//!   value of the same minimum, so that is exactly "no worse at the quoted precision". (On
//!   intel our minimum is 45.0047, which the peers print as 45.00.)
//! * Max-mixture on ring and manhattanOlson3500 with 100 and 1,000 seeded false loops
//!   (`cloi corrupt`) must end within 5 % of the outlier-free solution's ground-truth RMSE.
//! * MITb with the default (automatic) solver reaches g2o LM's minimum.

use std::path::{Path, PathBuf};

use clap::Parser;
use cloi_host::cli::{Cli, Command};
use cloi_host::dataset::shared_file;
use cloi_host::optimize::{optimize_file, OptimizeArgs};

fn args(line: &[&str]) -> OptimizeArgs {
    let mut full = vec!["cloi", "optimize"];
    full.extend_from_slice(line);
    match Cli::try_parse_from(full).expect("arguments parse").command {
        Command::Optimize(a) => a,
        other => panic!("not optimize: {other:?}"),
    }
}

fn chi2_of(file: &str) -> Option<f64> {
    let path = shared_file(file)?;
    let r = optimize_file(&args(&[path.to_str()?, "--init", "odometry"]))
        .expect("optimize")
        .report;
    assert!(r.converged, "{file}: {r:?}");
    Some(r.final_chi2)
}

#[test]
fn csail_chi2_no_worse_than_best_peer() {
    if let Some(chi2) = chi2_of("g2o/CSAIL.g2o") {
        assert!(chi2 <= 40.56 + 0.005, "CSAIL chi2 {chi2}");
    }
}

#[test]
fn intel_chi2_no_worse_than_best_peer() {
    if let Some(chi2) = chi2_of("g2o/intel.g2o") {
        assert!(chi2 <= 45.00 + 0.005, "intel chi2 {chi2}");
    }
}

#[test]
fn csail_toro_matches_csail_g2o_structure() {
    if let Some(path) = shared_file("g2o/CSAIL.toro.graph") {
        let r = optimize_file(&args(&[path.to_str().unwrap()]))
            .unwrap()
            .report;
        assert!(r.converged && r.final_chi2 < r.initial_chi2);
        assert_eq!((r.nodes, r.edges), (1045, 1172));
    }
}

fn robust_case(graph: &str, truth: &str, seed: u64) {
    robust_case_with(graph, truth, seed, 100, true);
}

/// `outliers` seeded false loops; `check_plain`: also show that plain least squares suffers
/// (slow with 1,000 false loops, whose factor is dense, so only done with 100).
fn robust_case_with(graph: &str, truth: &str, seed: u64, outliers: usize, check_plain: bool) {
    let (Some(graph), Some(truth)) = (shared_file(graph), shared_file(truth)) else {
        return;
    };
    let stem = graph.file_stem().unwrap().to_string_lossy().into_owned();
    let dir = std::env::temp_dir().join(format!(
        "cloi-golden-{}-{stem}-{seed}-{outliers}",
        std::process::id()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    let corrupted: PathBuf = dir.join("corrupted.g2o");
    let mut g = cloi_host::graph_io::read_graph(&graph, None).unwrap();
    cloi_host::corrupt::add_false_loops(&mut g, outliers, seed, 10.0).unwrap();
    let poses = g.poses.clone();
    std::fs::write(&corrupted, cloi_host::graph_io::write_g2o(&g, &poses)).unwrap();
    let t = truth.to_str().unwrap();
    let clean = optimize_file(&args(&[graph.to_str().unwrap(), "--ground-truth", t]))
        .unwrap()
        .report;
    let run = |robust: &str, p: &Path| {
        optimize_file(&args(&[
            p.to_str().unwrap(),
            "--robust",
            robust,
            "--ground-truth",
            t,
        ]))
        .unwrap_or_else(|e| panic!("{e:#}"))
        .report
    };
    let mm = run("maxmix", &corrupted);
    let (c, m) = (clean.rmse_m.unwrap(), mm.rmse_m.unwrap());
    eprintln!(
        "{} + {outliers} false loops (seed {seed}): clean {c:.4} m, maxmix {m:.4} m in {:.1} ms",
        graph.display(),
        mm.time_ms
    );
    assert!(mm.converged, "{mm:?}");
    assert!(m <= 1.05 * c, "maxmix RMSE {m} vs outlier-free {c}");
    assert!(
        mm.rejected_loops.unwrap_or(0) >= outliers,
        "{:?}",
        mm.rejected_loops
    );
    if check_plain {
        let p = run("none", &corrupted).rmse_m.unwrap();
        eprintln!("  plain least squares {p:.4} m");
        assert!(
            p > 2.0 * c,
            "the outliers do hurt plain least squares ({p} vs {c})"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn maxmix_ring_with_100_false_loops() {
    for seed in [7, 11, 23] {
        robust_case("g2o/ring.g2o", "g2o/ring.groundtruth.g2o", seed);
    }
}

#[test]
fn maxmix_manhattan_with_100_false_loops() {
    for seed in [7, 11, 23] {
        robust_case(
            "g2o/manhattanOlson3500.g2o",
            "g2o/manhattanOlson3500.nodes_groundtruth.dat",
            seed,
        );
    }
}

#[test]
fn mitb_default_solver_reaches_the_lm_minimum() {
    // Gauss-Newton alone stops at 770.66 (as g2o GN does); the default automatic strategy
    // notices the implausible chi2 and reaches g2o LM's 526.33.
    for init in ["file", "odometry"] {
        let Some(path) = shared_file("g2o/MITb.g2o") else {
            return;
        };
        let r = optimize_file(&args(&[path.to_str().unwrap(), "--init", init]))
            .expect("optimize")
            .report;
        assert!(r.converged, "{r:?}");
        assert!(r.final_chi2 <= 526.33 + 0.005, "MITb chi2 {}", r.final_chi2);
    }
}

#[test]
fn maxmix_ring_with_1000_false_loops() {
    for seed in [7, 11, 23] {
        robust_case_with(
            "g2o/ring.g2o",
            "g2o/ring.groundtruth.g2o",
            seed,
            1000,
            false,
        );
    }
}

#[test]
fn maxmix_manhattan_with_1000_false_loops() {
    for seed in [7, 11, 23] {
        robust_case_with(
            "g2o/manhattanOlson3500.g2o",
            "g2o/manhattanOlson3500.nodes_groundtruth.dat",
            seed,
            1000,
            false,
        );
    }
}
