//! Development harness for the mapper on a CARMEN log: runs `cloi_core::mapper::Mapper` with
//! the back-end stepped after every scan and scores the final, real-time (GPE) and front-end
//! trajectories against the GMapping reference relations, in process.
//!
//! `cargo run --release -p cloi-host --example mapper_eval -- LOG.clf [MAX_SCANS]`

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use cloi_core::frontend::BeamGeometry;
use cloi_core::mapper::{MapperConfig, ScanInput};
use cloi_core::profile::{HomeResources, OfficeResources};
use cloi_core::Se2;
use cloi_host::eval::relations::{relations_from_reference, score, PlanarTrajectory};
use cloi_host::io::carmen::{CarmenReader, CarmenRecord};

struct Stderr;
impl log::Log for Stderr {
    fn enabled(&self, _: &log::Metadata<'_>) -> bool {
        true
    }
    fn log(&self, r: &log::Record<'_>) {
        eprintln!("{}", r.args());
    }
    fn flush(&self) {}
}

fn main() -> Result<()> {
    if std::env::var_os("DEBUG").is_some() {
        log::set_logger(&Stderr).ok();
        log::set_max_level(log::LevelFilter::Debug);
    }
    let stack = size_of::<OfficeResources>() * 3 + (64 << 20);
    std::thread::Builder::new()
        .stack_size(stack)
        .spawn(run)?
        .join()
        .map_err(|_| anyhow::anyhow!("mapper thread panicked"))?
}

fn run() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let path = PathBuf::from(args.get(1).context("usage: mapper_eval LOG.clf [MAX]")?);
    let max: usize = args.get(2).map_or(Ok(usize::MAX), |s| s.parse())?;
    let home = std::env::var("PROFILE").as_deref() == Ok("home");
    let mut cfg = if home {
        MapperConfig::home()
    } else {
        MapperConfig::default()
    };
    if let Ok(over) = std::env::var("CFG") {
        apply_overrides(&mut cfg, &over)?;
    }
    let mut home_res;
    let mut office_res;
    let mapper = if home {
        home_res = Box::new(HomeResources::new());
        home_res.mapper(cfg)
    } else {
        office_res = Box::new(OfficeResources::new());
        office_res.mapper(cfg)
    };
    let mut mapper = mapper.map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut offset_x = 0.0;
    let mut records: Vec<(i64, u32, Se2, Se2, Se2)> = Vec::new();
    let keep_order = std::env::var_os("STAMP_AS_IS").is_none();
    let mut fed = i64::MIN;
    let t0 = Instant::now();
    let (mut first, mut last) = (None, 0i64);
    for rec in CarmenReader::open(&path, false)? {
        match rec? {
            CarmenRecord::Param { name, value } if name == "robot_frontlaser_offset" => {
                offset_x = value.parse().unwrap_or(0.0);
            }
            CarmenRecord::Laser(l) => {
                if records.len() >= max {
                    break;
                }
                // Old CARMEN logs (intel) have IPC time stamps that jitter backwards while
                // the file order is the true order (the odometry in the lines is monotonic):
                // the mapper gets a stamp made increasing, the evaluation the original one.
                let stamp = if keep_order {
                    l.stamp_ns.max(fed + 1_000)
                } else {
                    l.stamp_ns
                };
                fed = fed.max(stamp);
                if let Some((x, y, t)) = l.odom_pose {
                    let _ = mapper.push_odometry(stamp, Se2::new(x, y, t));
                }
                let scan = ScanInput {
                    stamp,
                    ranges: &l.ranges,
                    geometry: BeamGeometry {
                        angle_min: l.angle_min,
                        angle_increment: match std::env::var("FOV_DEG") {
                            // Development check of the beam-angle convention of old logs.
                            Ok(v) => {
                                v.parse::<f32>().unwrap_or(180.0).to_radians()
                                    / (l.ranges.len().max(2) - 1) as f32
                            }
                            Err(_) => l.angle_increment,
                        },
                        range_min: 0.05,
                        range_max: l.max_range.unwrap_or(80.0),
                    },
                    mounting: Se2::new(offset_x, 0.0, 0.0),
                };
                if let Ok(mut out) = mapper.push_scan(&scan, false) {
                    out.stamp = l.stamp_ns;
                    first.get_or_insert(l.stamp_ns);
                    last = l.stamp_ns;
                    let ref_f = mapper
                        .node_of(out.reference_serial)
                        .and_then(|i| mapper.nodes().get(i))
                        .map(|m| m.frontend)
                        .unwrap_or(Se2::IDENTITY);
                    records.push((
                        out.stamp,
                        out.reference_serial,
                        ref_f.between(&out.frontend),
                        out.pose,
                        out.frontend,
                    ));
                }
                mapper.step_backend(5);
            }
            _ => {}
        }
    }
    let t_stream = t0.elapsed().as_secs_f64();
    while mapper.step_backend(10) != cloi_core::mapper::BackendStep::Idle {}
    // Final optimization regardless of pending work.
    let wall = t0.elapsed().as_secs_f64();
    let stats = mapper.stats();
    println!("{stats:#?}");
    println!(
        "nodes {} edges {} data {:.1} s wall {:.2} s (stream {:.2} s) ratio {:.0}x",
        mapper.graph().node_count(),
        mapper.graph().edge_count(),
        (last - first.unwrap_or(0)) as f64 * 1e-9,
        wall,
        t_stream,
        (last - first.unwrap_or(0)) as f64 * 1e-9 / wall
    );
    let fin = PlanarTrajectory {
        poses: records
            .iter()
            .filter_map(|r| Some((r.0, mapper.keyframe_pose(r.1)?.compose(&r.2))))
            .collect(),
    };
    let gpe = PlanarTrajectory {
        poses: records.iter().map(|r| (r.0, r.3)).collect(),
    };
    let fe = PlanarTrajectory {
        poses: records.iter().map(|r| (r.0, r.4)).collect(),
    };
    // The relation lookup needs increasing stamps.
    let mut fin = fin;
    let mut gpe = gpe;
    let mut fe = fe;
    for t in [&mut fin, &mut gpe, &mut fe] {
        t.poses.sort_by_key(|p| p.0);
    }
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
    let refp = path.with_file_name(name.replace(".clf", ".gfs_reference_poses.txt"));
    let reference = PlanarTrajectory::load_reference(&refp).ok();
    if let Some(reference) = reference.as_ref() {
        let rels = relations_from_reference(reference, 1.0);
        // The reference holds the laser's poses: compare in the laser's frame.
        let laser = Se2::new(offset_x, 0.0, 0.0);
        for (n, t) in [("final", &fin), ("gpe", &gpe), ("frontend", &fe)] {
            let s = score(&t.in_sensor_frame(&laser), &rels, 0.0)?;
            println!(
                "{n}: trans {:.4} +- {:.4} m rot {:.3} deg pairs {} missing {}",
                s.trans_mean_m, s.trans_std_m, s.rot_mean_deg, s.pairs_used, s.pairs_missing
            );
        }
    }
    if let Ok(dump) = std::env::var("DUMP") {
        // Development dump: stamp, front-end pose, final pose.
        use std::io::Write;
        let mut f = std::io::BufWriter::new(std::fs::File::create(dump)?);
        let mut rows: Vec<_> = records
            .iter()
            .filter_map(|r| Some((r, mapper.keyframe_pose(r.1)?.compose(&r.2))))
            .collect();
        rows.sort_by_key(|(r, _)| r.0);
        for (r, p) in rows {
            writeln!(
                f,
                "{:.6} {:.5} {:.5} {:.6} {:.5} {:.5} {:.6}",
                r.0 as f64 * 1e-9,
                r.4.x,
                r.4.y,
                r.4.theta,
                p.x,
                p.y,
                p.theta
            )?;
        }
    }
    if std::env::var_os("NODES").is_some() {
        for m in mapper.nodes() {
            eprintln!(
                "NODE {} {} {} {} {}",
                m.serial, m.stamp, m.frontend.x, m.frontend.y, m.frontend.theta
            );
        }
    }
    if std::env::var_os("LOOPS").is_some() {
        let g = mapper.graph();
        for e in g
            .edges()
            .iter()
            .filter(|e| e.kind == cloi_core::graph::EdgeKind::Loop)
        {
            let (a, b) = (
                g.nodes()[e.from.0 as usize].pose,
                g.nodes()[e.to.0 as usize].pose,
            );
            let r = e.residual(&a, &b);
            // Error of the measurement against the reference (laser poses moved to the base).
            let (ma, mb) = (
                &mapper.nodes()[e.from.0 as usize],
                &mapper.nodes()[e.to.0 as usize],
            );
            let laser = Se2::new(offset_x, 0.0, 0.0);
            // Reference pose of a node: the nearest reference pose carried to the node by the
            // front-end's own motion (the reference holds one pose in ~15 scans).
            let truth_of = |m: &cloi_core::mapper::NodeMeta| -> Option<Se2> {
                let rf = reference.as_ref()?;
                let i = rf.poses.partition_point(|p| p.0 < m.stamp);
                let (tr, pr) = [i.checked_sub(1), Some(i)]
                    .iter()
                    .flatten()
                    .filter_map(|&k| rf.poses.get(k))
                    .min_by_key(|p| (p.0 - m.stamp).abs())?;
                let j = fe.poses.partition_point(|p| p.0 < *tr);
                let (tf, pf) = fe.poses.get(j)?;
                if (tf - tr).abs() > 1_000_000 || (tr - m.stamp).abs() > 3_000_000_000 {
                    return None;
                }
                Some(
                    pr.compose(&laser.inverse())
                        .compose(&pf.between(&m.frontend)),
                )
            };
            let truth = {
                let ra = truth_of(ma);
                let rb = truth_of(mb);
                (|| {
                    let (ra, rb) = (ra?, rb?);
                    let t = ra.between(&rb);
                    let d = t.between(&e.measurement);
                    Some((d.x.hypot(d.y), d.theta))
                })()
            };
            let (te, tt) = truth.unwrap_or((f64::NAN, f64::NAN));
            println!(
                "loop {} -> {}: residual {:.3} {:.3} {:.3} chi2 {:.1} truth_err {:.3} {:.4} dt {:.0} s info {:.0} {:.0} {:.0}",
                e.from.0,
                e.to.0,
                r[0],
                r[1],
                r[2],
                e.chi2_of(&r),
                te,
                tt,
                (mb.stamp - ma.stamp) as f64 * 1e-9,
                e.information[(0, 0)],
                e.information[(1, 1)],
                e.information[(2, 2)]
            );
        }
    }
    if let Ok(png) = std::env::var("PNG") {
        let res = cfg.grid.resolution as f64;
        let side = cfg.grid.side as i64;
        let mut pts = Vec::new();
        for (pose, cells) in mapper.submaps() {
            let (c, s) = (pose.theta.cos(), pose.theta.sin());
            for iy in 0..side {
                for ix in 0..side {
                    let l = cells[(iy * side + ix) as usize];
                    if l == 0 {
                        continue;
                    }
                    let lx = (ix as f64 + 0.5 - side as f64 / 2.0) * res;
                    let ly = (iy as f64 + 0.5 - side as f64 / 2.0) * res;
                    pts.push((pose.x + c * lx - s * ly, pose.y + s * lx + c * ly, l));
                }
            }
        }
        let (minx, maxx) = pts
            .iter()
            .fold((f64::MAX, f64::MIN), |a, p| (a.0.min(p.0), a.1.max(p.0)));
        let (miny, maxy) = pts
            .iter()
            .fold((f64::MAX, f64::MIN), |a, p| (a.0.min(p.1), a.1.max(p.1)));
        let w = ((maxx - minx) / res) as u32 + 1;
        let h = ((maxy - miny) / res) as u32 + 1;
        let mut acc = vec![0i32; (w * h) as usize];
        for (x, y, l) in pts {
            let i = ((maxy - y) / res) as u32 * w + ((x - minx) / res) as u32;
            acc[i as usize] += l as i32;
        }
        let img = image::GrayImage::from_fn(w, h, |x, y| {
            let v = acc[(y * w + x) as usize];
            image::Luma([if v > 10 {
                0
            } else if v < -10 {
                255
            } else {
                180
            }])
        });
        img.save(&png)?;
    }
    let mut jump: f64 = 0.0;
    for w in records.windows(2) {
        let g = w[0].3.between(&w[1].3);
        let f = w[0].4.between(&w[1].4);
        jump = jump.max((g.x - f.x).hypot(g.y - f.y));
    }
    println!("gpe max jump {jump:.4} m");
    Ok(())
}

/// Development overrides of a few parameters: `CFG="name=value,name=value"` (A/B runs
/// without a rebuild; the defaults are what counts).
fn apply_overrides(cfg: &mut MapperConfig, spec: &str) -> Result<()> {
    for kv in spec.split(',').filter(|s| !s.is_empty()) {
        let (k, v) = kv.split_once('=').context("CFG entries are name=value")?;
        let f: f64 = v.parse().with_context(|| format!("bad value in {kv}"))?;
        match k {
            "local_from_submaps" => cfg.local_from_submaps = f != 0.0,
            "local_min_log_odds" => cfg.local_min_log_odds = f as i8,
            "local_reset" => cfg.local_reset = f,
            "local_radius" => cfg.local_radius = f as f32,
            "submap_length" => cfg.submap_length = f,
            "min_fitness" => cfg.min_fitness = f as f32,
            "turn_reseed" => cfg.turn_reseed = f,
            "turn_reseed_rms" => cfg.turn_reseed_rms = f,
            "stall_xy" => cfg.stall_motion.get_or_insert(MapperConfig::STALL_MOTION)[0] = f,
            "stall_theta" => cfg.stall_motion.get_or_insert(MapperConfig::STALL_MOTION)[1] = f,
            "stall_off" => cfg.stall_motion = None,
            "icp_iterations" => cfg.icp.max_iterations = f as u16,
            "kf_distance" => cfg.keyframe.distance = f,
            "kf_angle" => cfg.keyframe.angle = f,
            "icp_huber" => cfg.icp.huber = f,
            "icp_corr" => cfg.icp.max_correspondence = f as f32,
            "icp_degeneracy" => cfg.icp.degeneracy_ratio = f,
            "loop_every" => cfg.loops.every = f as u32,
            "loop_gap" => cfg.loops.min_keyframe_gap = f as u32,
            "loop_sigmas" => cfg.loops.sigmas = f,
            "loop_window_min" => cfg.loops.window_min = f,
            "loop_window_max" => cfg.loops.window_max = f,
            "loop_angle_min" => cfg.loops.angle_min = f,
            "loop_angle_max" => cfg.loops.angle_max = f,
            "loop_min_score" => cfg.loops.min_score = f as f32,
            "loop_min_fitness" => cfg.loops.min_fitness = f as f32,
            "loop_max_rms" => cfg.loops.max_rms = f,
            "loop_agree_xy" => cfg.loops.agree_xy = f,
            "loop_agree_theta" => cfg.loops.agree_theta = f,
            "window_anchor" => cfg.loops.window_from_anchor = f != 0.0,
            "window_lever" => cfg.loops.window_lever = f,
            "null_scale" => cfg.loops.null_scale = f as f32,
            "loop_candidates" => cfg.loops.max_candidates = f as u8,
            "loop_sigma_xy" => cfg.loops.min_sigma[0] = f,
            "loop_sigma_theta" => cfg.loops.min_sigma[1] = f,
            "null_weight" => cfg.loops.null_weight = f as f32,
            "gate_chi2" => cfg.backend.gate_chi2 = f,
            "gpe_huber" => cfg.gpe.huber = f,
            "gpe_process_xy" => cfg.gpe.process_sigma[0] = f,
            "gpe_process_theta" => cfg.gpe.process_sigma[1] = f,
            "backend_every" => cfg.backend.every_keyframes = f as u32,
            "backend_iterations" => cfg.backend.max_iterations = f as u32,
            "var_xy_per_m" => cfg.noise.var_xy_per_m = f,
            "var_theta_per_m" => cfg.noise.var_theta_per_m = f,
            "var_theta_per_rad" => cfg.noise.var_theta_per_rad = f,
            _ => anyhow::bail!("unknown CFG parameter {k}"),
        }
    }
    Ok(())
}
