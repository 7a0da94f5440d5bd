//! `cloi prune` and `cloi eval arps` end to end on a small generated graph, and their errors.

use std::fmt::Write as _;
use std::process::Command;

fn cloi(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(args)
        .output()
        .expect("cloi runs")
}

/// A 10 m x 10 m square walked twice in 0.25 m steps with noisy odometry and loop closures
/// on the second lap, as g2o text.
fn square_graph() -> String {
    let mut s = String::new();
    let mut poses = Vec::new();
    let (mut x, mut y, mut t) = (0.0f64, 0.0f64, 0.0f64);
    for i in 0..320 {
        poses.push((x, y, t));
        let turn = if i % 40 == 39 {
            std::f64::consts::FRAC_PI_2
        } else {
            0.0
        };
        x += 0.25 * t.cos();
        y += 0.25 * t.sin();
        t += turn;
    }
    for (i, p) in poses.iter().enumerate() {
        writeln!(s, "VERTEX_SE2 {i} {} {} {}", p.0, p.1, p.2).unwrap();
    }
    let rel = |a: (f64, f64, f64), b: (f64, f64, f64)| {
        let (dx, dy) = (b.0 - a.0, b.1 - a.1);
        let (c, sn) = (a.2.cos(), a.2.sin());
        let dt = (b.2 - a.2 + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI)
            - std::f64::consts::PI;
        (c * dx + sn * dy, -sn * dx + c * dy, dt)
    };
    for i in 0..poses.len() - 1 {
        let (a, b, c) = rel(poses[i], poses[i + 1]);
        let n = 0.01 * ((i as f64) * 1.3).sin();
        writeln!(
            s,
            "EDGE_SE2 {i} {} {} {} {} 400 0 0 400 0 2500",
            i + 1,
            a + n,
            b - n,
            c + 0.2 * n
        )
        .unwrap();
    }
    for i in (160..320).step_by(8) {
        let j = i - 160;
        let (a, b, c) = rel(poses[j], poses[i]);
        writeln!(s, "EDGE_SE2 {j} {i} {a} {b} {c} 100 0 0 100 0 1000").unwrap();
    }
    s
}

#[test]
fn prune_then_eval_arps_agree() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("square.g2o");
    std::fs::write(&input, square_graph()).unwrap();
    let pruned = dir.path().join("pruned.g2o");
    let out = cloi(&[
        "prune",
        input.to_str().unwrap(),
        "--cell",
        "1.0",
        "--out",
        pruned.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let kept = report["nodes_after"].as_u64().unwrap();
    assert!(
        kept < 320 / 2,
        "pruning must remove most of the doubled lap: {report}"
    );
    assert!(
        report["nodes_per_cell_max"].as_u64().unwrap() <= 2,
        "{report}"
    );
    let out = cloi(&[
        "eval",
        "arps",
        "--original",
        input.to_str().unwrap(),
        "--pruned",
        pruned.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let eval: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(eval["nodes_matched"].as_u64().unwrap(), kept);
    let (a, b) = (
        report["arps_percent"].as_f64().unwrap(),
        eval["arps_percent"].as_f64().unwrap(),
    );
    assert!((a - b).abs() < 1e-9, "prune says {a} %, eval says {b} %");
}

#[test]
fn bad_prune_input_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("square.g2o");
    std::fs::write(&input, square_graph()).unwrap();
    for (args, needle) in [
        (
            vec!["prune", input.to_str().unwrap(), "--cell", "0"],
            "--cell",
        ),
        (
            vec!["prune", input.to_str().unwrap(), "--cell", "1", "--s", "2"],
            "--s",
        ),
        (
            vec!["prune", "/nonexistent.g2o", "--cell", "1"],
            "/nonexistent.g2o",
        ),
        (
            vec![
                "prune",
                input.to_str().unwrap(),
                "--cell",
                "1",
                "--online",
                "--pool",
                "10",
                "--window",
                "50",
            ],
            "pool",
        ),
    ] {
        let out = cloi(&args);
        assert!(!out.status.success(), "{args:?} should fail");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            err.starts_with("error: ") && err.contains(needle),
            "{args:?}: {err}"
        );
    }
}

#[test]
fn online_mode_stays_within_its_pool() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("square.g2o");
    std::fs::write(&input, square_graph()).unwrap();
    let out = cloi(&[
        "prune",
        input.to_str().unwrap(),
        "--cell",
        "1.0",
        "--online",
        "--pool",
        "100",
        "--window",
        "20",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(r["peak_nodes"].as_u64().unwrap() <= 100, "{r}");
    assert!(r["prunes"].as_u64().unwrap() >= 1, "{r}");
    assert!(r["arps_vs_batch_percent"].as_f64().unwrap() < 5.0, "{r}");
}
