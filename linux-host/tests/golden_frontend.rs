//! Golden test of the LiDAR front-end on the first 3,000 scans of `intel.clf`: scan-to-submap
//! ICP seeded by wheel odometry (no loop closure, no back-end) must never fail, and its
//! relative motion between consecutive GMapping reference poses must beat the raw odometry
//! clearly. Release mode: `cargo test --release -p cloi-host --features golden --test golden_frontend`.

use std::collections::HashMap;

use cloi_core::frontend::{
    align, preprocess, BeamGeometry, IcpConfig, KeyframeConfig, KeyframeSelector, PointMap,
    PreprocessConfig, ScanPoints,
};
use cloi_core::Se2;

/// Laser pose (raw odometry) and ranges of each FLASER line.
fn read_flaser(text: &str, max: usize) -> Vec<(Vec<f32>, Se2)> {
    let mut out = Vec::new();
    for line in text.lines() {
        let mut f = line.split_ascii_whitespace();
        if f.next() != Some("FLASER") {
            continue;
        }
        let n: usize = f.next().unwrap().parse().unwrap();
        let v: Vec<f64> = f.take(n + 3).map(|s| s.parse().unwrap()).collect();
        out.push((
            v[..n].iter().map(|&r| r as f32).collect(),
            Se2::new(v[n], v[n + 1], v[n + 2]),
        ));
        if out.len() == max {
            break;
        }
    }
    out
}

#[test]
fn intel_lidar_odometry_beats_wheel_odometry() {
    let Some(log) = cloi_host::dataset::shared_file("carmen/intel.clf") else {
        return;
    };
    let Some(refs) = cloi_host::dataset::shared_file("carmen/intel.gfs_reference_poses.txt") else {
        return;
    };
    let scans = read_flaser(&std::fs::read_to_string(log).unwrap(), 3000);
    assert_eq!(scans.len(), 3000);
    let geometry = BeamGeometry {
        angle_min: -core::f32::consts::FRAC_PI_2,
        angle_increment: core::f32::consts::PI / 180.0,
        range_min: 0.05,
        range_max: 40.0,
        time_increment: 0.0,
    };
    let pre = PreprocessConfig {
        voxel_size: 0.05,
        ..PreprocessConfig::default()
    };
    let icp = IcpConfig {
        allow_degenerate: true,
        ..IcpConfig::default()
    };
    let mut points = Box::new(PointMap::<4096>::new(0.05));
    let mut keyframes = KeyframeSelector::new(KeyframeConfig::default());
    let mut query: ScanPoints = ScanPoints::new();
    let (mut pose, mut origin) = (Se2::IDENTITY, Se2::IDENTITY);
    let mut est = Vec::new();
    let mut failures = 0;
    for (i, (ranges, odom)) in scans.iter().enumerate() {
        preprocess(ranges, &geometry, &pre, &mut query).unwrap();
        if i > 0 {
            pose = pose.compose(&scans[i - 1].1.between(odom));
            match align(&query, &points.tree(), &pose, &icp) {
                Ok(r) if r.fitness > 0.5 => pose = r.pose,
                _ => failures += 1,
            }
        }
        est.push(pose);
        if keyframes.offer(&pose) {
            if (pose.x - origin.x).hypot(pose.y - origin.y) > 3.0 {
                points.clear();
                origin = pose;
            }
            points.insert(&pose, &query, 8.0);
        }
    }
    assert_eq!(failures, 0);

    let refs: HashMap<usize, Se2> = std::fs::read_to_string(refs)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let v: Vec<f64> = l
                .split_whitespace()
                .filter_map(|x| x.parse().ok())
                .collect();
            (v.len() == 5).then(|| (v[1] as usize, Se2::new(v[2], v[3], v[4])))
        })
        .collect();
    let mut idx: Vec<usize> = refs.keys().copied().filter(|&i| i < est.len()).collect();
    idx.sort();
    let (mut lidar, mut wheel) = (0.0, 0.0);
    for w in idx.windows(2) {
        let truth = refs[&w[0]].between(&refs[&w[1]]);
        let d = truth.between(&est[w[0]].between(&est[w[1]]));
        lidar += d.x.hypot(d.y);
        let d = truth.between(&scans[w[0]].1.between(&scans[w[1]].1));
        wheel += d.x.hypot(d.y);
    }
    let n = (idx.len() - 1) as f64;
    let (lidar, wheel) = (lidar / n, wheel / n);
    println!("{n} pairs: LiDAR odometry {lidar:.4} m, wheel odometry {wheel:.4} m");
    assert!(n > 150.0);
    // Measured: 0.0313 m against 0.0543 m.
    assert!(lidar < 0.036 && lidar < 0.7 * wheel, "{lidar} vs {wheel}");
}
