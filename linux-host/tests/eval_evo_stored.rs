//! `cloi eval ate|rpe` against the results evo stored in `trajectories/evo_results/*.zip`
//! (KITTI 00, ORB-SLAM vs ground truth): APE after SE(3) Umeyama alignment, RPE over 10 m of
//! path. Needs only the system `python3` (its zipfile module)
//! to open the archives.

use std::path::Path;
use std::process::Command;

use cloi_host::dataset::shared_file;
use cloi_host::eval::metrics::{ate, rpe, DeltaUnit};
use cloi_host::eval::traj::{Alignment, Trajectory};
use serde_json::Value;

fn stats_of(zip: &Path) -> Value {
    let out = Command::new("python3")
        .args([
            "-c",
            "import sys, zipfile; print(zipfile.ZipFile(sys.argv[1]).read('stats.json').decode())",
        ])
        .arg(zip)
        .output()
        .expect("python3 is needed to open the evo result archives");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

fn close(ours: f64, theirs: &Value, what: &str) {
    let t = theirs.as_f64().unwrap();
    assert!(
        (ours - t).abs() <= 1e-6 * t.abs(),
        "{what}: cloi {ours} vs evo {t}"
    );
}

#[test]
fn kitti_00_matches_stored_evo_results() {
    let (Some(gt), Some(orb), Some(ape_zip), Some(rpe_zip), Some(each_zip)) = (
        shared_file("trajectories/KITTI_00_gt.txt"),
        shared_file("trajectories/KITTI_00_ORB.txt"),
        shared_file("trajectories/evo_results/orb_ape.zip"),
        shared_file("trajectories/evo_results/orb_rpe.zip"),
        shared_file("trajectories/evo_results/orb_rpe-for-each.zip"),
    ) else {
        return;
    };
    let reference = Trajectory::load(&gt).unwrap();
    let est = Trajectory::load(&orb).unwrap();

    let stored = stats_of(&ape_zip);
    let a = ate(&est, &reference, Alignment::Se3, 0.01).unwrap();
    for (k, v) in [
        ("rmse", a.translation_m.rmse),
        ("mean", a.translation_m.mean),
        ("median", a.translation_m.median),
        ("std", a.translation_m.std),
        ("min", a.translation_m.min),
        ("max", a.translation_m.max),
        ("sse", a.translation_m.sse),
    ] {
        close(v, &stored[k], &format!("APE {k}"));
    }

    // The stored RPE was made by an evo that started path-based pairs `delta` metres along.
    let stored = stats_of(&rpe_zip);
    let r = rpe(&est, &reference, 10.0, DeltaUnit::Meters, 0.01, true).unwrap();
    assert_eq!(r.pairs, 353);
    for (k, v) in [
        ("rmse", r.translation_m.rmse),
        ("mean", r.translation_m.mean),
        ("median", r.translation_m.median),
        ("std", r.translation_m.std),
        ("min", r.translation_m.min),
        ("max", r.translation_m.max),
        ("sse", r.translation_m.sse),
    ] {
        close(v, &stored[k], &format!("RPE {k}"));
    }

    // `orb_rpe-for-each.zip` (mean RPE for 10..50 m) is not compared: its values (about 11 %
    // of the step) are not reproduced by current evo on these files with any pair or relation
    // option either (about 1.7 %), so they come from other inputs. Check only that it loads.
    let stored = stats_of(&each_zip);
    assert!(stored["10.0"].as_f64().is_some());
}

#[test]
fn cli_prints_the_same_ate() {
    let (Some(gt), Some(orb)) = (
        shared_file("trajectories/KITTI_00_gt.txt"),
        shared_file("trajectories/KITTI_00_ORB.txt"),
    ) else {
        return;
    };
    let out = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(["eval", "ate", "--align", "se3", "--trajectory"])
        .arg(&orb)
        .arg("--reference")
        .arg(&gt)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    close(
        v["translation_m"]["rmse"].as_f64().unwrap(),
        &Value::from(1.3034497145650266),
        "CLI APE rmse",
    );
}
