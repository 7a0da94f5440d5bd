//! Times the LiDAR front-end of `cloi-core` on a real CARMEN log: scan-to-submap ICP per scan
//! (LiDAR odometry seeded by wheel odometry) and correlative loop-closure searches, and checks
//! the odometry against the GMapping reference poses over consecutive reference pairs.
//!
//! `cargo run --release -p cloi-host --example frontend_timing -- [LOG.clf] [MAX_SCANS]`
//! (default `../shared/data/carmen/intel.clf`, 3,000 scans; `SUBMAP=home` for 4.1 m
//! submaps). Scans come through the host's CARMEN reader, as for `cloi map`.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use cloi_core::frontend::csm::{search, CsmConfig, Pyramid};
use cloi_core::frontend::{
    align, preprocess, BeamGeometry, GridParams, IcpConfig, KeyframeConfig, KeyframeSelector,
    PointMap, PreprocessConfig, ScanPoints, Submap,
};
use cloi_core::Se2;
use cloi_host::io::carmen::{CarmenReader, CarmenRecord, LaserSource};

struct Scan {
    ranges: Vec<f32>,
    odom: Se2,
}

/// The first `max` front-laser scans of a CARMEN log that carry odometry, read by the host's
/// CARMEN reader, and their beam geometry.
fn read_front_scans(path: &std::path::Path, max: usize) -> Result<(Vec<Scan>, BeamGeometry)> {
    let mut scans = Vec::new();
    let mut geometry = None;
    for rec in CarmenReader::open(path, false)? {
        let CarmenRecord::Laser(l) = rec? else {
            continue;
        };
        let (LaserSource::Front, Some((x, y, theta))) = (l.source, l.odom_pose) else {
            continue;
        };
        geometry.get_or_insert(BeamGeometry {
            angle_min: l.angle_min,
            angle_increment: l.angle_increment,
            range_min: 0.05,
            range_max: 40.0,
            time_increment: 0.0,
        });
        scans.push(Scan {
            ranges: l.ranges,
            odom: Se2::new(x, y, theta),
        });
        if scans.len() == max {
            break;
        }
    }
    let geometry = geometry.with_context(|| format!("{}: no FLASER line", path.display()))?;
    Ok((scans, geometry))
}

fn stats(name: &str, mut t: Vec<Duration>) {
    if t.is_empty() {
        println!("{name}: none");
        return;
    }
    t.sort();
    let mean = t.iter().sum::<Duration>() / t.len() as u32;
    println!(
        "{name}: n={} mean {:.3} ms, median {:.3} ms, max {:.3} ms",
        t.len(),
        mean.as_secs_f64() * 1e3,
        t[t.len() / 2].as_secs_f64() * 1e3,
        t[t.len() - 1].as_secs_f64() * 1e3
    );
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let path = match args.get(1) {
        Some(p) => std::path::PathBuf::from(p),
        None => cloi_host::dataset::shared_file("carmen/intel.clf").context("intel.clf")?,
    };
    let max: usize = args.get(2).map_or(Ok(3000), |s| s.parse())?;
    let (scans, geometry) = read_front_scans(&path, max)?;
    let beams = scans.first().map_or(0, |s| s.ranges.len());
    let pre = PreprocessConfig {
        voxel_size: 0.05,
        ..PreprocessConfig::default()
    };
    let icp_cfg = IcpConfig {
        allow_degenerate: true,
        ..IcpConfig::default()
    };
    // SUBMAP=home: the 4.1 m submaps (82 x 82) instead of the 10 m ones (200 x 200).
    let home = std::env::var("SUBMAP").is_ok_and(|v| v == "home");
    let params = if home {
        GridParams::HOME
    } else {
        GridParams::LARGE
    };
    let new_submap_after = if home { 1.5 } else { 3.0 };
    let mut cells = vec![0i8; params.cells()];
    let mut pyramid_storage = vec![0u8; Pyramid::storage_len(params.side as usize, 5)];
    let mut points = Box::new(PointMap::<4096>::new(0.05));
    let mut keyframes = KeyframeSelector::new(KeyframeConfig::default());
    let mut query: ScanPoints = ScanPoints::new();

    let mut pose = Se2::IDENTITY;
    let mut submap = Submap::new(pose, params, &mut cells)?;
    let mut prev_odom: Option<Se2> = None;
    let (mut t_pre, mut t_icp, mut t_tree, mut t_csm, mut t_pyr) =
        (vec![], vec![], vec![], vec![], vec![]);
    let (mut failures, mut csm_ok, mut csm_runs, mut degenerate) = (0usize, 0usize, 0usize, 0usize);
    let mut est = Vec::with_capacity(scans.len());
    let mut submaps = 1;
    for (i, s) in scans.iter().enumerate() {
        let t0 = Instant::now();
        preprocess(&s.ranges, &geometry, &pre, &mut query)?;
        t_pre.push(t0.elapsed());
        let seed = match prev_odom {
            Some(p) => pose.compose(&p.between(&s.odom)),
            None => pose,
        };
        prev_odom = Some(s.odom);
        pose = seed;
        if !points.points().is_empty() {
            let t0 = Instant::now();
            let tree = points.tree();
            t_tree.push(t0.elapsed());
            let t0 = Instant::now();
            let r = align(&query, &tree, &seed, &icp_cfg);
            t_icp.push(t0.elapsed());
            match r {
                Ok(r) if r.fitness > 0.5 => {
                    pose = r.pose;
                    degenerate += usize::from(r.degenerate.is_some());
                }
                other => {
                    failures += 1;
                    if std::env::var_os("VERBOSE").is_some() {
                        println!("scan {i}: {other:?}");
                    }
                }
            }
        }
        est.push(pose);
        // Loop-closure search timing: every 50th scan against the current submap, seeded
        // 0.5 m / 10 degrees off the ICP pose.
        if i % 50 == 25 && !points.points().is_empty() {
            let t0 = Instant::now();
            let pyr = Pyramid::build(&submap, 5, &mut pyramid_storage)?;
            t_pyr.push(t0.elapsed());
            let t0 = Instant::now();
            let seed = pose.compose(&Se2::new(0.4, -0.3, 0.17));
            let cfg = CsmConfig {
                window_xy: 1.0,
                window_theta: 20f64.to_radians(),
                min_score: 0.4,
                ..CsmConfig::default()
            };
            let r = search(&query, &submap, &pyr, &seed, &cfg);
            t_csm.push(t0.elapsed());
            csm_runs += 1;
            if std::env::var_os("VERBOSE").is_some() {
                println!("csm {i}: {r:?} icp {pose:?}");
            }
            if let Ok(r) = r {
                let d = r.pose.between(&pose);
                if d.x.hypot(d.y) < 0.1 && d.theta.abs() < 0.05 {
                    csm_ok += 1;
                }
            }
        }
        if keyframes.offer(&pose) {
            let o = submap.origin();
            if (pose.x - o.x).hypot(pose.y - o.y) > new_submap_after {
                // A new submap centred on the robot.
                submap = Submap::new(pose, params, &mut cells)?;
                points.clear();
                submaps += 1;
            }
            submap.insert_scan(&pose, &Se2::IDENTITY, &query)?;
            points.insert(&pose, &query, 8.0);
        }
    }
    println!(
        "{path:?}: {} scans of {beams} beams, {submaps} submaps ({}x{} cells), {failures} ICP failures, {degenerate} degenerate matches (solved without the weak direction)",
        scans.len(), params.side, params.side
    );
    stats("preprocess", t_pre);
    stats("kd-tree build", t_tree);
    stats("ICP scan-to-submap", t_icp);
    stats("CSM pyramid build (5 levels)", t_pyr);
    stats("CSM search (1 m / 20 deg window)", t_csm);
    println!("CSM found the ICP pose (10 cm / 3 deg) in {csm_ok} of {csm_runs} searches");

    // Relative error against the GMapping reference over consecutive reference pairs.
    let ref_path = path.with_file_name(
        path.file_name()
            .and_then(|n| n.to_str())
            .map(|n| n.replace(".clf", ".gfs_reference_poses.txt"))
            .unwrap_or_default(),
    );
    if let Ok(text) = std::fs::read_to_string(&ref_path) {
        let refs: HashMap<usize, Se2> = text
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
        let (mut e_icp, mut e_odo) = (vec![], vec![]);
        for w in idx.windows(2) {
            let (a, b) = (w[0], w[1]);
            let truth = refs[&a].between(&refs[&b]);
            let mine = est[a].between(&est[b]);
            let odo = scans[a].odom.between(&scans[b].odom);
            let d = truth.between(&mine);
            e_icp.push(d.x.hypot(d.y));
            let d = truth.between(&odo);
            e_odo.push(d.x.hypot(d.y));
        }
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        println!(
            "consecutive reference pairs: {}; mean translation error vs GMapping: LiDAR odometry {:.4} m, raw odometry {:.4} m",
            e_icp.len(),
            mean(&e_icp),
            mean(&e_odo)
        );
    }
    Ok(())
}
