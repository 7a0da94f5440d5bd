//! `cloi convert` and `cloi eval` from the command line, on small made-up inputs.

use std::io::Write;
use std::process::Command;

use serde_json::Value;

fn cloi(args: &[&std::ffi::OsStr]) -> (bool, Value, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(args)
        .output()
        .unwrap();
    let stdout: Value = serde_json::from_slice(&out.stdout).unwrap_or(Value::Null);
    (
        out.status.success(),
        stdout,
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

const LOG: &str = "PARAM robot_frontlaser_offset 0.1 h 0\n\
ODOM 0.0 0.0 0.0 0.0 0.0 0.0 100.0 h 0\n\
FLASER 3 1.0 2.0 3.0 0.1 0 0 0 0 0 100.05 h 0\n\
ODOM 1.0 0.0 0.0 0.5 0.0 0.0 100.1 h 0\n\
WEIRD 1 2 3\n\
FLASER 3 1.0 2.0 3.0 1.1 0 0 1 0 0 100.15 h 0\n\
ODOM 2.0 0.0 0.0 0.5 0.0 0.0 100.2 h 0\n";

#[test]
fn convert_bz2_log_to_bag_and_bag_to_tum() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("tiny.clf.bz2");
    let mut enc = bzip2::write::BzEncoder::new(
        std::fs::File::create(&log).unwrap(),
        bzip2::Compression::fast(),
    );
    enc.write_all(LOG.as_bytes()).unwrap();
    enc.finish().unwrap();
    let bag = dir.path().join("tiny.mcap");
    let (ok, v, stderr) = cloi(&["convert".as_ref(), log.as_os_str(), bag.as_os_str()]);
    assert!(ok, "{stderr}");
    assert_eq!(v["scans"], 2);
    // Three ODOM lines and the odometry pose of each of the two scans.
    assert_eq!(v["odometry"], 5);
    assert_eq!(v["unknown_lines"]["WEIRD"], 1);
    // Unknown line types are reported once.
    assert_eq!(stderr.matches("WEIRD").count(), 1, "{stderr}");

    let tum = dir.path().join("odom.tum");
    let (ok, v, stderr) = cloi(&["convert".as_ref(), bag.as_os_str(), tum.as_os_str()]);
    assert!(ok, "{stderr}");
    assert_eq!(v["odometry"]["poses"], 5);
    assert_eq!(v["odometry"]["path_length_m"], 2.0);
    assert_eq!(v["scans"], 2);
    let text = std::fs::read_to_string(&tum).unwrap();
    assert_eq!(text.lines().count(), 6);
    assert!(text
        .lines()
        .nth(5)
        .unwrap()
        .starts_with("100.200000000 2.000000000 0.0"));

    let (ok, _, stderr) = cloi(&["convert".as_ref(), tum.as_os_str(), bag.as_os_str()]);
    assert!(!ok);
    assert!(stderr.contains("cannot convert .tum to .mcap"), "{stderr}");
}

/// A simulator's bag holds ground truth as `nav_msgs/Odometry` in the `map` frame beside the
/// wheel odometry: the TUM file gets the wheel odometry alone, unless the other is named.
#[test]
fn bag_to_tum_takes_one_odometry_topic_and_not_a_global_one() {
    use cloi_host::io::ros2::{Header, Odometry, Pose, Time};
    let dir = tempfile::tempdir().unwrap();
    let bag_path = dir.path().join("sim.mcap");
    let mut bag = cloi_host::io::BagWriter::create(&bag_path).unwrap();
    for k in 1..=3i64 {
        for (topic, frame, x) in [("/ground_truth", "map", 10.0), ("/odom", "odom", 1.0)] {
            let mut odom = Odometry {
                header: Header::new(Time::from_nanos(k * 1_000_000_000), frame),
                child_frame_id: "base_link".into(),
                ..Default::default()
            };
            odom.pose.pose = Pose::planar(x * k as f64, 0.0, 0.0);
            bag.write(topic, k * 1_000_000_000, &odom).unwrap();
        }
    }
    bag.finish().unwrap();
    let xs = |tum: &std::path::Path| -> Vec<f64> {
        std::fs::read_to_string(tum)
            .unwrap()
            .lines()
            .filter(|l| !l.starts_with('#'))
            .map(|l| l.split_whitespace().nth(1).unwrap().parse().unwrap())
            .collect()
    };
    let tum = dir.path().join("odom.tum");
    let (ok, v, stderr) = cloi(&["convert".as_ref(), bag_path.as_os_str(), tum.as_os_str()]);
    assert!(ok, "{stderr}");
    assert_eq!(v["odometry_topic"], "/odom");
    assert_eq!(xs(&tum), [1.0, 2.0, 3.0]);
    assert!(stderr.contains("several topics"), "{stderr}");
    let gt = dir.path().join("gt.tum");
    let (ok, _, stderr) = cloi(&[
        "convert".as_ref(),
        bag_path.as_os_str(),
        gt.as_os_str(),
        "--odom-topic".as_ref(),
        "/ground_truth".as_ref(),
    ]);
    assert!(ok, "{stderr}");
    assert_eq!(xs(&gt), [10.0, 20.0, 30.0]);
}

#[test]
fn truncated_log_warns_or_fails_with_strict() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("cut.clf");
    std::fs::write(&log, &LOG[..LOG.len() - 10]).unwrap();
    let bag = dir.path().join("cut.mcap");
    let (ok, v, stderr) = cloi(&["convert".as_ref(), log.as_os_str(), bag.as_os_str()]);
    assert!(ok, "{stderr}");
    assert_eq!(v["truncated"], true);
    // Two ODOM lines and the two scans' odometry poses.
    assert_eq!(v["odometry"], 4);
    assert!(stderr.contains("cut.clf:7:"), "{stderr}");
    let (ok, _, stderr) = cloi(&[
        "convert".as_ref(),
        "--strict".as_ref(),
        log.as_os_str(),
        bag.as_os_str(),
    ]);
    assert!(!ok);
    assert!(stderr.contains("cut.clf:7:"), "{stderr}");
}

#[test]
fn convert_log_to_cloilog_with_to_out_and_max_scans() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("tiny.clf");
    std::fs::write(&log, LOG).unwrap();
    let out = dir.path().join("tiny.bin");
    let (ok, v, stderr) = cloi(&[
        "convert".as_ref(),
        log.as_os_str(),
        "--to".as_ref(),
        "cloilog".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
        "--max-scans".as_ref(),
        "1".as_ref(),
    ]);
    assert!(ok, "{stderr}");
    assert_eq!(v["format"], "cloilog");
    assert_eq!(
        (v["scans"].as_u64(), v["odometry"].as_u64()),
        (Some(1), Some(1))
    );
    assert_eq!(v["cut_at_max_scans"], true);
    let bytes = std::fs::read(&out).unwrap();
    assert_eq!(v["bytes"].as_u64(), Some(bytes.len() as u64));
    assert!(bytes.starts_with(b"CLOILOG"));

    // By extension, the whole log.
    let out = dir.path().join("tiny.cloilog");
    let (ok, v, stderr) = cloi(&["convert".as_ref(), log.as_os_str(), out.as_os_str()]);
    assert!(ok, "{stderr}");
    assert_eq!(
        (v["scans"].as_u64(), v["odometry"].as_u64()),
        (Some(2), Some(3))
    );

    let bag = dir.path().join("tiny.mcap");
    let (ok, _, stderr) = cloi(&[
        "convert".as_ref(),
        log.as_os_str(),
        bag.as_os_str(),
        "--max-scans".as_ref(),
        "1".as_ref(),
    ]);
    assert!(!ok && stderr.contains("--max-scans"), "{stderr}");
}

#[test]
fn eval_relations_and_ref_print_json() {
    let dir = tempfile::tempdir().unwrap();
    let tum = dir.path().join("t.tum");
    std::fs::write(
        &tum,
        "1.5 0 0 0 0 0 0 1\n2.5 1 0 0 0 0 0 1\n3.5 2 0.1 0 0 0 0 1\n",
    )
    .unwrap();
    let rel = dir.path().join("r.relations");
    std::fs::write(
        &rel,
        "1.5 2.5 1 0 0 0 0 0\n2.5 3.5 1 0 0 0 0 0\n9 10 1 0 0 0 0 0\n",
    )
    .unwrap();
    let (ok, v, stderr) = cloi(&[
        "eval".as_ref(),
        "relations".as_ref(),
        "--trajectory".as_ref(),
        tum.as_os_str(),
        "--relations".as_ref(),
        rel.as_os_str(),
    ]);
    assert!(ok, "{stderr}");
    assert_eq!(v["pairs_used"], 2);
    assert_eq!(v["pairs_missing"], 1);
    assert!((v["trans_mean_m"].as_f64().unwrap() - 0.05).abs() < 1e-12);
    for key in ["trans_std_m", "rot_mean_deg", "rot_std_deg"] {
        assert!(v[key].is_number(), "{key}");
    }

    let reference = dir.path().join("x.gfs_reference_poses.txt");
    std::fs::write(
        &reference,
        "# t idx x y theta\n1.5 0 0 0 0\n2.5 1 1 0 0\n3.5 2 2 0 0\n",
    )
    .unwrap();
    let (ok, v, stderr) = cloi(&[
        "eval".as_ref(),
        "ref".as_ref(),
        "--trajectory".as_ref(),
        tum.as_os_str(),
        "--reference".as_ref(),
        reference.as_os_str(),
        "--max-distance".as_ref(),
        "1.5".as_ref(),
    ]);
    assert!(ok, "{stderr}");
    assert_eq!(v["relations"], 2);
    assert_eq!(v["pairs_used"], 2);
    assert!((v["trans_mean_m"].as_f64().unwrap() - 0.05).abs() < 1e-12);

    // A quarter turn on the spot; the reference holds the poses of a laser 0.04 m behind the
    // robot's centre: 0.04 * sqrt(2) m of error unless the trajectory is moved to the laser.
    let half = std::f64::consts::FRAC_1_SQRT_2;
    std::fs::write(
        &tum,
        format!(
            "1.5 0 0 0 0 0 0 1
2.5 0 0 0 0 0 {half} {half}
"
        ),
    )
    .unwrap();
    std::fs::write(
        &reference,
        format!(
            "1.5 0 -0.04 0 0
2.5 1 0 -0.04 {}
",
            std::f64::consts::FRAC_PI_2
        ),
    )
    .unwrap();
    for (offset, expected) in [(None, 0.04 * 2f64.sqrt()), (Some("-0.04,0,0"), 0.0)] {
        let mut args: Vec<&std::ffi::OsStr> = vec![
            "eval".as_ref(),
            "ref".as_ref(),
            "--trajectory".as_ref(),
            tum.as_os_str(),
            "--reference".as_ref(),
            reference.as_os_str(),
        ];
        if let Some(o) = offset {
            args.push("--sensor-offset".as_ref());
            args.push(o.as_ref());
        }
        let (ok, v, stderr) = cloi(&args);
        assert!(ok, "{stderr}");
        assert_eq!(v["pairs_used"], 1);
        let err = v["trans_mean_m"].as_f64().unwrap();
        assert!((err - expected).abs() < 1e-9, "{offset:?}: {v}");
    }
}

#[test]
fn garbage_converts_to_an_error_not_an_empty_bag() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("garbage.clf");
    std::fs::write(&log, "hello world\n\x01\x02 3 4\nFLASER x\n").unwrap();
    let bag = dir.path().join("garbage.mcap");
    let (ok, _, stderr) = cloi(&["convert".as_ref(), log.as_os_str(), bag.as_os_str()]);
    assert!(!ok);
    assert!(stderr.contains("not a CARMEN log"), "{stderr}");
    assert!(!bag.exists());
}
