//! The core's image front-end (pyramid, FAST, rotated BRIEF, guided and brute-force matching)
//! on frames rendered by the simulator, checked against its exact ground truth (issue 16).
//!
//! A short run of a built-in world with one fisheye camera tilted 60 degrees towards the
//! ceiling (the cleaner's rig, 320 x 240, 10 Hz) goes through the simulator's own stream, as
//! `cloi sim --sensors C` would write it. Features of frame A are matched to frame B, either
//! the next frame or one 0.5 s later. A match is correct when the world point that A's pixel
//! sees (its ray from the ground-truth camera pose, the robot pose composed with the
//! extrinsic, cut by the first wall or the ceiling plane exactly as the renderer cuts it)
//! reprojects into B within `visual_sim::TOL_PX` pixels of the level the features were found on.
//!
//! Guided matching predicts where A's points fall in B from the wheel odometry the simulator
//! produces (A's point as a landmark, moved by the odometry's relative motion), which is what
//! the visual odometry will do with its landmarks.
//!
//! `cargo test -p cloi-host --test camera_frontend_sim -- --nocapture` prints the figures.

mod visual_sim;

use cloi_core::frontend::visual::{FastConfig, MatchConfig};
use cloi_sim::builtin;
use cloi_sim::engine::SensorSet;
use cloi_sim::world::{FaultKind, FaultSpec, LegSpec, RouteSpec, WorldFile};
use cloi_sim::{SimConfig, Simulation, World};
use visual_sim::{brute_force, extract, guided, Features, Geometry, Recording, GUIDE_RADIUS};

/// Simulated seconds: 40 frames at 10 Hz.
const DURATION: f64 = 4.0;
/// Frames between the two views of the wide pairs (0.5 s at 10 Hz).
const WIDE: usize = 5;

/// Matching figures over all pairs of one kind.
#[derive(Clone, Copy, Debug, Default)]
struct Tally {
    pairs: usize,
    matches: usize,
    inliers: usize,
}

impl Tally {
    fn ratio(&self) -> f64 {
        self.inliers as f64 / self.matches.max(1) as f64
    }

    fn per_pair(&self) -> f64 {
        self.matches as f64 / self.pairs.max(1) as f64
    }

    fn inliers_per_pair(&self) -> f64 {
        self.inliers as f64 / self.pairs.max(1) as f64
    }
}

/// What one run gave.
#[derive(Debug, Default)]
struct Report {
    frames: usize,
    features_min: usize,
    features_median: usize,
    relaxed_cells: usize,
    cells: usize,
    /// The largest ground-truth translation (m) and turn (rad) between the frames of a wide
    /// pair.
    wide_motion: [f64; 2],
    brute: [Tally; 2],
    guided: [Tally; 2],
}

/// Simulates [`DURATION`] seconds of `world` with one camera, applying `world`'s faults.
fn simulate(world: World) -> (Simulation, Recording) {
    let cfg = SimConfig {
        duration: DURATION,
        seed: 3,
        sensors: SensorSet::Camera,
        ..SimConfig::default()
    };
    let sim = Simulation::new(world, cfg);
    let rec = Recording::of(&sim);
    (sim, rec)
}

/// `file` with no scheduled fault, driven along a route that both translates and turns
/// within [`DURATION`]: 0.4 m along the corridor, a 90-degree turn, then on.
fn short_route(file: &WorldFile) -> World {
    let mut world = World::from_file(file);
    world.faults.clear();
    world.route = RouteSpec {
        start: [2.0, 8.0],
        legs: vec![LegSpec::Waypoints {
            points: vec![[2.4, 8.0], [2.4, 9.0]],
        }],
    };
    world
}

/// The home world on the short route.
fn home() -> World {
    short_route(&builtin::builtin("home", DURATION).expect("home"))
}

/// Extracts every frame of `rec` and matches the pairs `(k, k + 1)` and `(k, k + WIDE)` for
/// every frame of the run.
fn measure(sim: &Simulation, rec: &Recording) -> Report {
    let cam = sim.rig.cameras[0];
    let g = Geometry {
        world: &sim.world,
        model: cam.core_model().expect("a valid lens"),
        extrinsic: cam.core_extrinsic(),
    };
    let fast = FastConfig::default();
    let mcfg = MatchConfig::default();
    let shots: Vec<_> = rec.shots.iter().collect();
    let feats: Vec<Features> = shots.iter().map(|s| extract(&s.frame, &fast).0).collect();
    let mut counts: Vec<usize> = feats.iter().map(|f| f.descriptors.len()).collect();
    counts.sort_unstable();
    let mut r = Report {
        frames: feats.len(),
        features_min: counts.first().copied().unwrap_or(0),
        features_median: counts.get(counts.len() / 2).copied().unwrap_or(0),
        relaxed_cells: feats.iter().map(|f| f.stats.relaxed_cells).sum(),
        cells: feats.iter().map(|f| f.stats.cells).sum(),
        ..Report::default()
    };
    for (kind, step) in [1, WIDE].into_iter().enumerate() {
        for i in 0..feats.len().saturating_sub(step) {
            let (sa, sb) = (shots[i], shots[i + step]);
            let (a, b) = (&feats[i], &feats[i + step]);
            let pa = sim.state(sa.t).pose;
            let pb = sim.state(sb.t).pose;
            let odo = rec
                .odometry_at(sa.t)
                .zip(rec.odometry_at(sb.t))
                .map(|(oa, ob)| oa.between(&ob))
                .expect("odometry over the run");
            let predicted_b = pa.compose(&odo);
            if kind == 1 {
                let d = pa.between(&pb);
                r.wide_motion[0] = r.wide_motion[0].max(d.x.hypot(d.y));
                r.wide_motion[1] = r.wide_motion[1].max(d.theta.abs());
            }
            let predicted = g.predict(&pa, &predicted_b, a);
            for (tally, matches) in [
                (&mut r.brute[kind], brute_force(a, b, &mcfg)),
                (
                    &mut r.guided[kind],
                    guided(a, &predicted, b, GUIDE_RADIUS, &mcfg),
                ),
            ] {
                tally.pairs += 1;
                tally.matches += matches.len();
                tally.inliers += matches
                    .iter()
                    .filter(|m| g.is_correct(&pa, &pb, a, b, m))
                    .count();
            }
        }
    }
    eprintln!(
        "{} frames, features min {} median {}, relaxed cells {}/{}, wide pairs up to {:.2} m \
         and {:.2} rad apart",
        r.frames,
        r.features_min,
        r.features_median,
        r.relaxed_cells,
        r.cells,
        r.wide_motion[0],
        r.wide_motion[1]
    );
    for (name, t) in [
        ("brute, consecutive", r.brute[0]),
        ("brute, 0.5 s apart", r.brute[1]),
        ("guided, consecutive", r.guided[0]),
        ("guided, 0.5 s apart", r.guided[1]),
    ] {
        eprintln!(
            "  {name}: {:.1} matches/pair, {:.1} inliers/pair, inlier ratio {:.3} ({} pairs)",
            t.per_pair(),
            t.inliers_per_pair(),
            t.ratio(),
            t.pairs
        );
    }
    r
}

#[test]
fn home_ceiling_features_match_with_ground_truth() {
    let (sim, rec) = simulate(home());
    let r = measure(&sim, &rec);
    assert!(r.frames >= 38, "{r:?}");
    // The wide pairs span real motion: the cleaner cruises at 0.3 m/s and turns at 1 rad/s,
    // so 0.5 s is 0.15 m on the straight and 0.5 rad in the turn.
    assert!(r.wide_motion[0] >= 0.1 && r.wide_motion[1] >= 0.3, "{r:?}");
    // The paper's ORB-SLAM3 fails at 20 features or fewer (its plain airport ceiling); a
    // textured home ceiling must give at least twice that in every frame.
    assert!(r.features_min >= 40, "{r:?}");
    // Guided matching between consecutive frames: the prediction is good to a pixel or two,
    // so a wrong match needs a look-alike corner within 16 px that also passes the ratio
    // test; on a textured home ceiling that is rare.
    assert!(r.guided[0].ratio() >= 0.8, "{r:?}");
    assert!(r.guided[0].inliers_per_pair() >= 30.0, "{r:?}");
    assert!(r.guided[1].ratio() >= 0.8, "{r:?}");
    // Brute force has no prediction: mutual best plus the ratio test must still be right
    // most of the time, or it cannot restart tracking.
    assert!(r.brute[0].ratio() >= 0.7, "{r:?}");
}

/// The paper's low-feature case: a plain, dim ceiling (no texture, no lights, no vents;
/// the walls and furniture the tilted camera also sees keep their texture, so a frame must
/// still hold more than the 20 features at which the paper's ORB-SLAM3 fails).
#[test]
fn a_plain_dim_ceiling_keeps_features_and_right_guided_matches() {
    let mut file = builtin::builtin("home", DURATION).expect("home");
    file.features.clear();
    file.ceiling.texture = 0.0;
    file.ceiling.brightness = 0.3;
    let (sim, rec) = simulate(short_route(&file));
    let r = measure(&sim, &rec);
    assert!(r.frames >= 38, "{r:?}");
    // Where the ceiling is blank, cells fall back to the lower threshold.
    assert!(r.relaxed_cells > 0, "{r:?}");
    assert!(r.features_min > 20, "{r:?}");
    assert!(r.guided[0].ratio() >= 0.8, "{r:?}");
    assert!(r.guided[1].ratio() >= 0.8, "{r:?}");
}

/// A dirty lens over the whole run (the simulator's fault: blur, lower contrast, smudges).
/// Few features survive it (under 10 per frame, the paper's low-feature failure level of a
/// single camera); what the front-end still matches must be right, so the visual odometry can
/// weigh a few good points against the wheel prior instead of being pulled off by bad ones.
#[test]
fn a_dirty_lens_keeps_guided_matches_right() {
    let mut world = home();
    world.faults.push(FaultSpec {
        start: 0.0,
        end: DURATION + 1.0,
        kind: FaultKind::DirtyLens {
            camera: Some(0),
            blur: 3.0,
            drop: 0.0,
        },
    });
    let (sim, rec) = simulate(world);
    let r = measure(&sim, &rec);
    assert!(r.frames >= 38, "{r:?}");
    assert!(r.guided[0].ratio() >= 0.8, "{r:?}");
}

/// Frames between the two views of a triangulation: 1.2 s, about 0.35 m at the cleaner's
/// cruise speed, the baseline a ceiling 2.4 m up needs for a depth within a tenth from
/// whole-pixel corners (0.5 s gives about 3 degrees of parallax, too little).
const BASELINE_FRAMES: usize = 12;

/// What triangulating the right matches of every pair [`BASELINE_FRAMES`] apart gave.
#[derive(Debug, Default)]
struct Triangulated {
    right: usize,
    low_parallax: usize,
    refused: usize,
    /// Error over the depth of each triangulated point, sorted.
    relative_errors: Vec<f64>,
    /// Largest error of the second view's pose the pairs were given: metres, radians.
    worst_pose_error: [f64; 2],
}

impl Triangulated {
    fn quantile(&self, q: f64) -> f64 {
        let n = self.relative_errors.len();
        self.relative_errors[((n - 1) as f64 * q).round() as usize]
    }

    fn within(&self, fraction: f64) -> usize {
        self.relative_errors
            .iter()
            .filter(|&&e| e < fraction)
            .count()
    }
}

/// Where the second view of a triangulated pair is taken to be.
#[derive(Clone, Copy, Debug, PartialEq)]
enum SecondPose {
    /// Its true pose.
    Exact,
    /// The first's true pose moved by the wheel odometry.
    Odometry,
    /// That, with the heading change and direction of travel refined from all the pair's
    /// brute-force matches (`two_view::refine_planar_motion`).
    Refined,
}

/// Triangulates the right brute-force matches of the home's own route (it starts along a
/// straight stretch, where the two views stand apart; the short route of the matching tests
/// mostly turns on the spot) with the first view at its true pose and the second as `second`
/// says, against the world point the first pixel truly sees.
fn triangulate_home(second: SecondPose) -> Triangulated {
    use cloi_core::frontend::visual::triangulate::{
        triangulate, CameraPose, Observation, TriangulateConfig, TriangulateError,
    };
    use cloi_core::frontend::visual::two_view::{refine_planar_motion, BearingPair, TwoViewConfig};
    use cloi_core::frontend::visual::Pyramid;
    use nalgebra::Vector2;

    let mut world = World::from_file(&builtin::builtin("home", DURATION).expect("home"));
    world.faults.clear();
    let (sim, rec) = simulate(world);
    let cam = sim.rig.cameras[0];
    let g = Geometry {
        world: &sim.world,
        model: cam.core_model().expect("a valid lens"),
        extrinsic: cam.core_extrinsic(),
    };
    let (fast, mcfg, tcfg) = (
        FastConfig::default(),
        MatchConfig::default(),
        TriangulateConfig::default(),
    );
    let shots: Vec<_> = rec.shots.iter().collect();
    let feats: Vec<Features> = shots.iter().map(|s| extract(&s.frame, &fast).0).collect();
    let mut r = Triangulated::default();
    for i in 0..feats.len().saturating_sub(BASELINE_FRAMES) {
        let (sa, sb) = (shots[i], shots[i + BASELINE_FRAMES]);
        let (a, b) = (&feats[i], &feats[i + BASELINE_FRAMES]);
        let (truth_a, truth_b) = (sim.state(sa.t).pose, sim.state(sb.t).pose);
        let odo = rec
            .odometry_at(sa.t)
            .zip(rec.odometry_at(sb.t))
            .map(|(oa, ob)| oa.between(&ob))
            .expect("odometry over the run");
        let matches = brute_force(a, b, &mcfg);
        let given_b = match second {
            SecondPose::Exact => truth_b,
            SecondPose::Odometry => truth_a.compose(&odo),
            SecondPose::Refined => {
                let px = |p: [f32; 2]| Vector2::new(f64::from(p[0]), f64::from(p[1]));
                let pairs: Vec<BearingPair> = matches
                    .iter()
                    .filter_map(|m| {
                        BearingPair::of_pixels(
                            &g.model,
                            &px(a.positions[m.query]),
                            &px(b.positions[m.train]),
                        )
                    })
                    .collect();
                let mut scratch = vec![0.0; pairs.len()];
                let motion = refine_planar_motion(
                    &g.extrinsic,
                    &odo,
                    &pairs,
                    &TwoViewConfig::default(),
                    &mut scratch,
                )
                .map_or(odo, |r| r.motion);
                let t = truth_a.between(&truth_b);
                eprintln!(
                    "pair {i}: dist {:.3} n {} odo err th {:.4} refined err th {:.4} dir {:.4}",
                    odo.x.hypot(odo.y),
                    pairs.len(),
                    (odo.theta - t.theta),
                    motion.theta - t.theta,
                    motion.y.atan2(motion.x) - t.y.atan2(t.x)
                );
                truth_a.compose(&motion)
            }
        };
        let e = truth_b.between(&given_b);
        r.worst_pose_error[0] = r.worst_pose_error[0].max(e.x.hypot(e.y));
        r.worst_pose_error[1] = r.worst_pose_error[1].max(e.theta.abs());
        let (pose_a, pose_b) = (
            CameraPose::of_robot(&truth_a, &g.extrinsic),
            CameraPose::of_robot(&given_b, &g.extrinsic),
        );
        for m in matches {
            if !g.is_correct(&truth_a, &truth_b, a, b, &m) {
                continue;
            }
            r.right += 1;
            // FAST positions are whole pixels of their level: half a level pixel of noise.
            let obs = |f: &Features, k: usize| Observation {
                px: Vector2::new(f64::from(f.positions[k][0]), f64::from(f.positions[k][1])),
                sigma_px: 0.5 * f64::from(Pyramid::scale(usize::from(f.keypoints[k].level))),
            };
            let (oa, ob) = (obs(a, m.query), obs(b, m.train));
            match triangulate(&g.model, &pose_a, &oa, &pose_b, &ob, &tcfg) {
                Ok(w) => {
                    let (truth, _) = g
                        .world_point(&truth_a, a.positions[m.query])
                        .expect("a surface");
                    let depth = (truth - pose_a.centre).norm();
                    r.relative_errors.push((w.position - truth).norm() / depth);
                }
                Err(TriangulateError::LowParallax) => r.low_parallax += 1,
                Err(_) => r.refused += 1,
            }
        }
    }
    r.relative_errors.sort_by(f64::total_cmp);
    eprintln!(
        "{second:?}: {} right matches {BASELINE_FRAMES} frames apart (second pose off by up to {:.3} m, \
         {:.4} rad): {} triangulated, {} with too little parallax, {} refused; error / depth \
         median {:.3}, p90 {:.3}, {} within 10 %",
        r.right,
        r.worst_pose_error[0],
        r.worst_pose_error[1],
        r.relative_errors.len(),
        r.low_parallax,
        r.refused,
        r.quantile(0.5),
        r.quantile(0.9),
        r.within(0.1),
    );
    r
}

/// Two-view triangulation (`cloi_core::frontend::visual::triangulate`) from exact poses: a
/// right match with enough parallax lands within its expected error of the true point. From
/// the wheel odometry alone the second pose's heading is off by several hundredths of a radian
/// within a pair, which spoils the points; the two-view refinement of the heading and the
/// direction of travel (`two_view`) from the same matches, wrong ones included, must bring
/// the points back to within twice the exact poses' error.
#[test]
fn right_matches_triangulate_near_the_true_world_points() {
    let exact = triangulate_home(SecondPose::Exact);
    let n = exact.relative_errors.len();
    assert!(
        n >= 20,
        "{n} points triangulated of {} right matches",
        exact.right
    );
    // Whole-pixel corners with at least the parallax for a tenth of the depth.
    assert!(exact.quantile(0.5) < 0.05, "{exact:?}");
    assert!(exact.within(0.1) * 10 >= n * 8, "{exact:?}");
    assert_eq!(exact.refused, 0, "{exact:?}");
    let odometry = triangulate_home(SecondPose::Odometry);
    let refined = triangulate_home(SecondPose::Refined);
    assert!(
        refined.worst_pose_error[1] < odometry.worst_pose_error[1],
        "{refined:?}"
    );
    assert!(refined.relative_errors.len() >= 20, "{refined:?}");
    assert!(
        refined.quantile(0.5) < 2.0 * exact.quantile(0.5).max(0.02),
        "{refined:?}"
    );
}
