//! Times the image front-end of `cloi-core` per stage on frames rendered by the simulator
//! (one fisheye camera of the cleaner's rig, 320 x 240 by default), and reports features per
//! frame and the ground-truth inlier ratio of its matches between consecutive frames. The
//! pipeline and the checks are those of `tests/camera_frontend_sim.rs`.
//!
//! `cargo run --release -p cloi-host --example camera_frontend_timing -- [WORLD] [FRAMES]`
//! (default `home`, 100 frames at 10 Hz; `WIDTH=640 HEIGHT=480` for another frame size).

#[path = "../tests/visual_sim/mod.rs"]
mod visual_sim;

use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use cloi_core::frontend::visual::{FastConfig, MatchConfig};
use cloi_host::sim::engine::SensorSet;
use cloi_host::sim::{builtin, SimConfig, Simulation, World};
use visual_sim::{brute_force, extract, guided, median, Geometry, Recording, GUIDE_RADIUS};

fn env_or(name: &str, default: u32) -> Result<u32> {
    std::env::var(name).map_or(Ok(default), |v| v.parse().context(name.to_owned()))
}

fn micros(d: Duration) -> f64 {
    d.as_secs_f64() * 1e6
}

fn main() -> Result<()> {
    let mut args = std::env::args().skip(1);
    let name = args.next().unwrap_or_else(|| "home".into());
    let frames: u32 = args.next().map_or(Ok(100), |v| v.parse())?;
    let duration = f64::from(frames) / 10.0;
    let file = builtin::builtin(&name, duration).context("no such built-in world")?;
    let mut world = World::from_file(&file);
    world.faults.clear();
    let cfg = SimConfig {
        duration,
        seed: 3,
        sensors: SensorSet::Camera,
        width: env_or("WIDTH", 320)?,
        height: env_or("HEIGHT", 240)?,
        ..SimConfig::default()
    };
    let sim = Simulation::new(world, cfg);
    let rec = Recording::of(&sim);
    let cam = sim.rig.cameras[0];
    let g = Geometry {
        world: &sim.world,
        model: cam.core_model()?,
        extrinsic: cam.core_extrinsic(),
    };
    let fast = FastConfig::default();
    let mcfg = MatchConfig::default();

    let (mut pyramid, mut detect, mut describe) = (Vec::new(), Vec::new(), Vec::new());
    let (mut brute_t, mut guided_t) = (Vec::new(), Vec::new());
    let mut counts = Vec::new();
    let (mut matches, mut inliers) = ([0usize; 2], [0usize; 2]);
    let mut prev = None;
    for shot in &rec.shots {
        let (f, t) = extract(&shot.frame, &fast);
        pyramid.push(t.pyramid);
        detect.push(t.detect);
        describe.push(t.describe);
        counts.push(f.descriptors.len());
        if let Some((ta, a)) = prev.take() {
            let (pa, pb) = (sim.state(ta).pose, sim.state(shot.t).pose);
            let odo = rec
                .odometry_at(ta)
                .zip(rec.odometry_at(shot.t))
                .map(|(oa, ob)| oa.between(&ob))
                .context("odometry")?;
            let predicted = g.predict(&pa, &pa.compose(&odo), &a);
            let t0 = Instant::now();
            let bm = brute_force(&a, &f, &mcfg);
            brute_t.push(t0.elapsed());
            let t1 = Instant::now();
            let gm = guided(&a, &predicted, &f, GUIDE_RADIUS, &mcfg);
            guided_t.push(t1.elapsed());
            for (k, ms) in [bm, gm].iter().enumerate() {
                matches[k] += ms.len();
                inliers[k] += ms
                    .iter()
                    .filter(|m| g.is_correct(&pa, &pb, &a, &f, m))
                    .count();
            }
        }
        prev = Some((shot.t, f));
    }
    counts.sort_unstable();
    let total: Vec<Duration> = (0..pyramid.len())
        .map(|i| pyramid[i] + detect[i] + describe[i])
        .collect();
    println!(
        "{name}: {} frames of {}x{}, features per frame min {} median {} max {}",
        rec.shots.len(),
        cfg.width,
        cfg.height,
        counts.first().copied().unwrap_or(0),
        counts.get(counts.len() / 2).copied().unwrap_or(0),
        counts.last().copied().unwrap_or(0),
    );
    println!("median per frame (us):");
    for (stage, v) in [
        ("pyramid", &mut pyramid),
        ("FAST + bucketing + orientation", &mut detect),
        ("smoothing + rotated BRIEF", &mut describe),
        ("extraction total", &mut total.clone()),
        ("brute-force matching (pair)", &mut brute_t),
        ("guided matching (pair)", &mut guided_t),
    ] {
        println!("  {stage:32} {:9.0}", micros(median(v)));
    }
    for (k, kind) in ["brute force", "guided"].iter().enumerate() {
        println!(
            "consecutive frames, {kind}: {:.1} matches per pair, inlier ratio {:.3}",
            matches[k] as f64 / rec.shots.len().saturating_sub(1).max(1) as f64,
            inliers[k] as f64 / matches[k].max(1) as f64
        );
    }
    Ok(())
}
