//! Cross-checks against independent tools, run from the venv of `scripts/venv.sh`:
//! * `cloi convert` output decodes with rosbags and with the mcap reader;
//! * a bag written by rosbags from a CARMEN log reads back in cloi with the same scans and
//!   odometry;
//! * `cloi eval ate|rpe` agree with evo to 1e-6 relative.
//!
//! Under `CI` a missing venv or dataset fails the test; elsewhere it skips with a message.

mod common;

use std::path::Path;

use cloi_host::dataset::shared_file;
use cloi_host::eval::metrics::{ate, rpe, DeltaUnit};
use cloi_host::eval::traj::{Alignment, ErrorStats, Trajectory};
use cloi_host::io::bag_read::{BagReadOptions, BagReader, SensorMsg};
use cloi_host::io::carmen::{CarmenReader, CarmenRecord, LaserSource};
use serde_json::Value;

fn assert_rel(ours: f64, theirs: f64, what: &str) {
    let tol = 1e-6 * theirs.abs().max(1e-12);
    assert!(
        (ours - theirs).abs() <= tol,
        "{what}: cloi {ours} vs evo {theirs} (relative {})",
        (ours - theirs).abs() / theirs.abs()
    );
}

fn assert_stats(ours: &ErrorStats, theirs: &Value, what: &str) {
    for (key, value) in [
        ("rmse", ours.rmse),
        ("mean", ours.mean),
        ("median", ours.median),
        ("std", ours.std),
        ("min", ours.min),
        ("max", ours.max),
        ("sse", ours.sse),
    ] {
        assert_rel(
            value,
            theirs[key].as_f64().unwrap(),
            &format!("{what} {key}"),
        );
    }
}

#[test]
fn cloi_convert_output_decodes_with_rosbags_and_mcap() {
    let Some(python) = common::venv_python() else {
        return;
    };
    let Some(log) = shared_file("carmen/mit-csail.clf") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let bag = dir.path().join("mit.mcap");
    let out = common::cloi()
        .args(["convert".as_ref(), log.as_os_str(), bag.as_os_str()])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["scans"], 1988);

    let decoded: Value = serde_json::from_str(&common::run_python(
        &python,
        "decode_bag.py",
        &[bag.as_os_str()],
    ))
    .unwrap();
    assert_eq!(decoded["/scan"]["type"], "sensor_msgs/msg/LaserScan");
    assert_eq!(decoded["/scan"]["count"], 1988);
    // mit-csail has no ODOM lines: odometry comes from the laser lines, one per scan.
    assert_eq!(decoded["/odom"]["count"], 1988);
    assert_eq!(decoded["/tf"]["count"], 1988);
    assert_eq!(decoded["/tf_static"]["count"], 1);

    // Values: compare with the log read directly.
    let lasers: Vec<_> = CarmenReader::open(&log, true)
        .unwrap()
        .filter_map(|r| match r.unwrap() {
            CarmenRecord::Laser(l) if l.source == LaserSource::Front => Some(l),
            _ => None,
        })
        .collect();
    for k in [0usize, 1000, 1987] {
        let v = &decoded["/scan"]["values"][k];
        let l = &lasers[k];
        assert_eq!(v["n"], l.ranges.len());
        assert_eq!(v["header_ns"], l.stamp_ns);
        assert_eq!(decoded["/scan"]["stamps"][k], l.stamp_ns);
        let sum: f64 = l
            .ranges
            .iter()
            .filter(|r| r.is_finite())
            .map(|&r| f64::from(r))
            .sum();
        assert!((v["ranges_sum"].as_f64().unwrap() - sum).abs() < 1e-9 * sum.max(1.0));
        let odom = &decoded["/odom"]["values"][k];
        let (x, y, _) = l.odom_pose.unwrap();
        assert_eq!(odom["x"].as_f64().unwrap(), x);
        assert_eq!(odom["y"].as_f64().unwrap(), y);
    }
}

#[test]
fn rosbags_bag_from_carmen_reads_back_the_same() {
    let Some(python) = common::venv_python() else {
        return;
    };
    let Some(log) = shared_file("carmen/intel.clf") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let bag_dir = dir.path().join("intel_rosbags");
    let max_scans = 300;
    let printed = common::run_python(
        &python,
        "carmen_to_rosbag.py",
        &[
            log.as_os_str(),
            bag_dir.as_os_str(),
            max_scans.to_string().as_ref(),
        ],
    );
    let mut parts = printed.split_whitespace();
    let mcap_path = parts.next().unwrap().to_owned();
    let (n_scans, n_odoms): (usize, usize) = (
        parts.next().unwrap().parse().unwrap(),
        parts.next().unwrap().parse().unwrap(),
    );
    assert_eq!(n_scans, max_scans);

    // The same records, read by cloi's CARMEN reader, up to the same point.
    let mut lasers = Vec::new();
    let mut odoms = Vec::new();
    for r in CarmenReader::open(&log, true).unwrap() {
        match r.unwrap() {
            CarmenRecord::Laser(l) => {
                if lasers.len() == max_scans {
                    break;
                }
                lasers.push(l);
            }
            CarmenRecord::Odom(o) => odoms.push(o),
            CarmenRecord::Param { .. } => {}
        }
    }
    assert_eq!(odoms.len(), n_odoms);
    // intel.clf has time stamps that step back (about 600 of each type, by up to ~0.3 s);
    // the bag reader delivers in log-time order, ties in file order: a stable sort.
    lasers.sort_by_key(|l| l.stamp_ns);
    odoms.sort_by_key(|o| o.stamp_ns);

    let mut reader = BagReader::open(
        Path::new(&mcap_path),
        BagReadOptions {
            strict: true,
            ..Default::default()
        },
    )
    .unwrap();
    let (mut si, mut oi) = (0, 0);
    for m in reader.by_ref() {
        let m = m.unwrap();
        match &m.msg {
            SensorMsg::Scan(s) => {
                let l = &lasers[si];
                assert_eq!(s.header.stamp.to_nanos(), l.stamp_ns);
                assert_eq!(m.log_time_ns as i64, l.stamp_ns);
                assert_eq!(s.ranges, l.ranges, "scan {si}");
                assert!((s.angle_min - l.angle_min).abs() < 1e-7);
                assert!((s.angle_increment - l.angle_increment).abs() < 1e-7);
                si += 1;
            }
            SensorMsg::Odom(o) => {
                let c = &odoms[oi];
                assert_eq!(o.header.stamp.to_nanos(), c.stamp_ns);
                let (x, y, th) = o.pose.pose.to_planar();
                assert_eq!((x, y), (c.pose.0, c.pose.1));
                assert!(
                    (th - c.pose.2).abs() < 1e-12,
                    "odom {oi}: {th} vs {}",
                    c.pose.2
                );
                assert_eq!(o.twist.twist.linear.x, c.tv);
                assert_eq!(o.twist.twist.angular.z, c.rv);
                oi += 1;
            }
            other => panic!("unexpected message {other:?}"),
        }
    }
    assert_eq!((si, oi), (n_scans, n_odoms));
    assert_eq!(reader.stats().out_of_order, 0);
}

fn evo(python: &Path, fmt: &str, reference: &Path, est: &Path, delta: &str, unit: &str) -> Value {
    let out = common::run_python(
        python,
        "evo_metrics.py",
        &[
            fmt.as_ref(),
            reference.as_os_str(),
            est.as_os_str(),
            "se3".as_ref(),
            delta.as_ref(),
            unit.as_ref(),
        ],
    );
    serde_json::from_str(&out).unwrap()
}

#[test]
fn ate_and_rpe_agree_with_evo() {
    let Some(python) = common::venv_python() else {
        return;
    };
    let cases = [
        (
            "kitti",
            "trajectories/KITTI_00_gt.txt",
            "trajectories/KITTI_00_ORB.txt",
            10.0,
            DeltaUnit::Meters,
        ),
        (
            "kitti",
            "trajectories/KITTI_00_gt.txt",
            "trajectories/KITTI_00_ORB.txt",
            1.0,
            DeltaUnit::Frames,
        ),
        (
            "tum",
            "trajectories/freiburg1_xyz-groundtruth.txt",
            "trajectories/freiburg1_xyz-rgbdslam.txt",
            1.0,
            DeltaUnit::Frames,
        ),
    ];
    for (fmt, reference, est, delta, unit) in cases {
        let (Some(rp), Some(ep)) = (shared_file(reference), shared_file(est)) else {
            return;
        };
        let unit_arg = if unit == DeltaUnit::Frames { "f" } else { "m" };
        let theirs = evo(&python, fmt, &rp, &ep, &delta.to_string(), unit_arg);
        let r = Trajectory::load(&rp).unwrap();
        let e = Trajectory::load(&ep).unwrap();
        let a = ate(&e, &r, Alignment::Se3, 0.01).unwrap();
        assert_eq!(a.matched as u64, theirs["matched"].as_u64().unwrap());
        assert_stats(&a.translation_m, &theirs["ape"], &format!("{est} APE"));
        let p = rpe(&e, &r, delta, unit, 0.01, false).unwrap();
        assert_eq!(p.pairs as u64, theirs["rpe_pairs"].as_u64().unwrap());
        assert_stats(&p.translation_m, &theirs["rpe"], &format!("{est} RPE"));
        // Rotation angles: evo orthonormalizes through scipy; we through nalgebra.
        for (ours, key) in [
            (&a.rotation_deg, "ape_rot_deg"),
            (&p.rotation_deg, "rpe_rot_deg"),
        ] {
            let t = theirs[key]["mean"].as_f64().unwrap();
            assert!(
                (ours.mean - t).abs() <= 1e-6 * t.abs().max(1e-9),
                "{est} {key}: {} vs {t}",
                ours.mean
            );
        }
    }
}

#[test]
fn nav2_odometry_matches_rosbags_and_mcap() {
    let Some(python) = common::venv_python() else {
        return;
    };
    let Some(bag) = shared_file("mcap/nav2_turtlebot.mcap") else {
        return;
    };
    let theirs: Value = serde_json::from_str(&common::run_python(
        &python,
        "decode_bag.py",
        &[bag.as_os_str()],
    ))
    .unwrap();
    let ours: Vec<_> = BagReader::open(&bag, BagReadOptions::default())
        .unwrap()
        .filter_map(|m| {
            let m = m.unwrap();
            match m.msg {
                SensorMsg::Odom(o) => Some((m.log_time_ns, o)),
                _ => None,
            }
        })
        .collect();
    let odom = &theirs["/odom"];
    assert_eq!(odom["count"].as_u64().unwrap() as usize, ours.len());
    for (k, (t, o)) in ours.iter().enumerate() {
        assert_eq!(odom["stamps"][k].as_u64().unwrap(), *t);
        let v = &odom["values"][k];
        assert_eq!(v["x"].as_f64().unwrap(), o.pose.pose.position.x);
        assert_eq!(v["y"].as_f64().unwrap(), o.pose.pose.position.y);
        assert_eq!(v["qz"].as_f64().unwrap(), o.pose.pose.orientation.z);
        assert_eq!(v["vx"].as_f64().unwrap(), o.twist.twist.linear.x);
        assert_eq!(v["child"], o.child_frame_id.as_str());
    }
    assert_eq!(theirs["/tf"]["count"], 5422);
}
