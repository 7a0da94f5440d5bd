//! The core's visual odometry (`cloi_core::frontend::visual::odometry`) on the simulator's
//! rendered camera frames of the home world, against its exact ground truth (issue 16).
//!
//! The first [`DURATION`] seconds of the home's own route are simulated (three seeds) with the cleaner's
//! single ceiling-tilted fisheye (320 x 240, 10 Hz). Every frame goes through the product's
//! path: `CameraTrack` extracts its features and matches them to the previous frame, and the
//! odometry takes those matches with the simulator's wheel+gyro pose at the frame's time. At
//! each keyframe the chain of the odometry's relative poses, and the wheel+gyro pose, are
//! compared with the true pose, all expressed in the first keyframe's frame.
//!
//! `cargo test -p cloi-host --test visual_odometry_sim -- --nocapture` prints the figures
//! (under a minute in a debug build).

mod visual_sim;

use cloi_core::frontend::visual::frame::{scratch_bytes, MAX_FEATURES};
use cloi_core::frontend::visual::{
    CameraTrack, Keypoint, Match, TrackConfig, TrackScratch, VisualOdometry, VoConfig, VoFrame,
};
use cloi_core::sensor::{ImageView, PixelFormat, Timestamp};
use cloi_core::Se2;
use cloi_sim::builtin;
use cloi_sim::engine::SensorSet;
use cloi_sim::{SimConfig, Simulation, World};
use visual_sim::Recording;

/// Simulated seconds of the route.
const DURATION: f64 = 25.0;

type Vo = VisualOdometry<8, 600, 5000>;

/// Heading and position errors of a trajectory against the truth, at the keyframes.
#[derive(Debug, Default)]
struct Errors {
    heading_final: f64,
    heading_mean: f64,
    heading_max: f64,
    position_final: f64,
    position_mean: f64,
    position_max: f64,
}

fn errors(estimate: &[Se2], truth: &[Se2]) -> Errors {
    let mut e = Errors::default();
    for (a, t) in estimate.iter().zip(truth) {
        let d = t.between(a);
        e.heading_final = d.theta.abs();
        e.position_final = (a.x - t.x).hypot(a.y - t.y);
        e.heading_max = e.heading_max.max(e.heading_final);
        e.position_max = e.position_max.max(e.position_final);
        e.heading_mean += e.heading_final;
        e.position_mean += e.position_final;
    }
    let n = estimate.len().min(truth.len()).max(1) as f64;
    e.heading_mean /= n;
    e.position_mean /= n;
    e
}

#[derive(Debug, Default)]
struct Run {
    vo: Errors,
    odometry: Errors,
    frames: usize,
    keyframes: usize,
    landmarks_seen: usize,
    outliers: usize,
    landmarks_dropped: usize,
    failed_solves: usize,
    distance: f64,
    turned: f64,
}

fn run_home(seed: u64) -> Run {
    let mut world = World::from_file(&builtin::builtin("home", DURATION).expect("home"));
    world.faults.clear();
    let sim = Simulation::new(
        world,
        SimConfig {
            duration: DURATION,
            seed,
            sensors: SensorSet::Camera,
            ..SimConfig::default()
        },
    );
    let rec = Recording::of(&sim);
    let cam = sim.rig.cameras[0];
    let (model, mount) = (
        cam.core_model().expect("a valid lens"),
        cam.core_extrinsic(),
    );
    let cfg = VoConfig::default();
    let tcfg = TrackConfig::default();
    let (w, h) = rec
        .shots
        .first()
        .map(|s| (s.frame.width as usize, s.frame.height as usize))
        .expect("frames");
    let mut bytes = vec![0u8; scratch_bytes(w, h)];
    let mut corners = vec![Keypoint::default(); MAX_FEATURES];
    let mut matches = vec![Match::default(); MAX_FEATURES];
    let mut track = Box::new(CameraTrack::new());
    let mut vo = Box::new(Vo::new());
    let mut r = Run::default();
    let (mut chain, mut first) = (Se2::IDENTITY, None::<(Se2, Se2)>);
    let (mut est, mut odo, mut truth) = (Vec::new(), Vec::new(), Vec::new());
    let mut last_truth: Option<Se2> = None;
    for shot in &rec.shots {
        let stamp = (shot.t * 1e9).round() as i64;
        let true_pose = sim.state(shot.t).pose;
        if let Some(p) = last_truth {
            let d = p.between(&true_pose);
            r.distance += d.x.hypot(d.y);
            r.turned += d.theta.abs();
        }
        last_truth = Some(true_pose);
        let Some(wheel) = rec.odometry_at(shot.t) else {
            continue;
        };
        let view = ImageView::new_checked(
            Timestamp::from_nanos(stamp),
            w,
            h,
            w,
            PixelFormat::Mono8,
            &shot.frame.pixels,
        )
        .expect("a valid frame");
        let mut scratch = TrackScratch {
            bytes: &mut bytes,
            corners: &mut corners,
            matches: &mut matches,
        };
        let Ok(step) = track.track(stamp, &view, &tcfg, &mut scratch) else {
            continue;
        };
        let newest = track.newest();
        let keypoints = newest.map(|f| f.keypoints()).unwrap_or_default();
        let descriptors = newest.map(|f| f.descriptors()).unwrap_or_default();
        let frame = VoFrame {
            stamp,
            odometry: wheel,
            keypoints,
            matches: &matches[..step.tracked],
            descriptors,
        };
        r.frames += 1;
        let Ok(out) = vo.process(&frame, &model, &mount, &cfg) else {
            continue;
        };
        let Some(k) = out.keyframe else { continue };
        let (odo0, truth0) = *first.get_or_insert((wheel, true_pose));
        chain = chain.compose(&k.relative.unwrap_or(Se2::IDENTITY));
        est.push(chain);
        odo.push(odo0.between(&wheel));
        truth.push(truth0.between(&true_pose));
        r.keyframes += 1;
        r.landmarks_seen += k.landmarks_seen;
        r.outliers += k.outliers_dropped;
        r.landmarks_dropped += k.landmarks_dropped;
        r.failed_solves += usize::from(k.relative.is_some() && k.solve.is_err());
    }
    r.vo = errors(&est, &truth);
    r.odometry = errors(&odo, &truth);
    eprintln!(
        "home, seed {seed}, first {DURATION} s: {} frames, {:.2} m driven, {:.1} deg turned; {} keyframes, \
         {:.1} landmarks seen per keyframe, {} outlying observations and {} landmarks dropped, \
         {} failed solves",
        r.frames,
        r.distance,
        r.turned.to_degrees(),
        r.keyframes,
        r.landmarks_seen as f64 / r.keyframes.max(1) as f64,
        r.outliers,
        r.landmarks_dropped,
        r.failed_solves,
    );
    for (name, e) in [("VO", &r.vo), ("wheel+gyro", &r.odometry)] {
        eprintln!(
            "  {name}: heading error final {:.2} deg (mean {:.2}, max {:.2}), position error \
             final {:.3} m (mean {:.3}, max {:.3})",
            e.heading_final.to_degrees(),
            e.heading_mean.to_degrees(),
            e.heading_max.to_degrees(),
            e.position_final,
            e.position_mean,
            e.position_max
        );
    }
    eprintln!("  {:?}", vo.stats());
    r
}

/// Three seeds of the simulator (its sensor noise), each asserted on its own for the figures
/// the visual odometry clearly improves, and together for the mean heading error, where its
/// gain is smaller: about a dozen landmarks per keyframe (tracks continued by re-finding the
/// window's landmarks, but most new tracks still too short for triangulation) do not outweigh
/// the wheel+gyro prior by much.
#[test]
fn home_visual_odometry_is_not_worse_than_the_wheels() {
    let runs = std::thread::Builder::new()
        .stack_size(64 << 20)
        .spawn(|| (1..=3).map(run_home).collect::<Vec<_>>())
        .expect("thread")
        .join()
        .expect("no panic");
    for r in &runs {
        assert!(r.keyframes >= 10, "{r:?}");
        assert!(r.distance >= 2.0, "{r:?}");
        // Re-finding the window's landmarks in each keyframe keeps about a dozen in sight.
        assert!(r.landmarks_seen >= 8 * r.keyframes, "{r:?}");
        assert!(r.vo.heading_max <= r.odometry.heading_max, "{r:?}");
        assert!(r.vo.position_mean <= r.odometry.position_mean, "{r:?}");
        assert!(r.vo.position_max <= r.odometry.position_max + 0.02, "{r:?}");
    }
    let mean = |f: fn(&Run) -> f64| runs.iter().map(f).sum::<f64>() / runs.len() as f64;
    let (vo, odo) = (
        mean(|r| r.vo.heading_mean),
        mean(|r| r.odometry.heading_mean),
    );
    eprintln!(
        "mean heading error over the seeds: VO {:.2} deg, wheel+gyro {:.2} deg",
        vo.to_degrees(),
        odo.to_degrees()
    );
    assert!(vo <= odo, "{runs:?}");
}
