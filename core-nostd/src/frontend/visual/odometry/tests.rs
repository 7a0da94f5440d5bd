//! A drive under a synthetic ceiling: features projected from known points by the cleaner's
//! KB4 camera, matched frame to frame by point identity (with some wrong matches), and
//! wheel+gyro odometry with a scale error, a gyro bias and noise.

extern crate std;

use std::boxed::Box;
use std::vec::Vec;

use super::*;
use crate::frontend::visual::synth::{cleaner_camera, Rng};
use crate::geom::wrap_angle;

type Vo = VisualOdometry<6, 512, 4000>;

const WIDTH: f64 = 320.0;
const HEIGHT: f64 = 240.0;

fn gauss(rng: &mut Rng) -> f64 {
    let u1 = ((rng.next_u64() >> 11) as f64 + 1.0) / (1u64 << 53) as f64;
    let u2 = (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
    libm::sqrt(-2.0 * libm::log(u1)) * libm::cos(2.0 * core::f64::consts::PI * u2)
}

fn uniform(rng: &mut Rng, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64
}

/// Runs `f` on a thread with room for the odometry on its stack while it is boxed.
fn with_stack<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> T {
    std::thread::Builder::new()
        .stack_size(64 << 20)
        .spawn(f)
        .expect("thread")
        .join()
        .expect("no panic")
}

/// Per-step body motion of the drive: straight runs and turns on the spot and on arcs,
/// 10 Hz, 0.3 m/s and 45 deg/s.
fn drive() -> Vec<Se2> {
    let mut steps = Vec::new();
    let straight = |steps: &mut Vec<Se2>, metres: f64| {
        for _ in 0..(metres / 0.03) as usize {
            steps.push(Se2::new(0.03, 0.0, 0.0));
        }
    };
    let turn = |steps: &mut Vec<Se2>, degrees: f64, forward: f64| {
        let n = (degrees.abs() / 4.5) as usize;
        for _ in 0..n {
            steps.push(Se2::new(
                forward,
                0.0,
                degrees.signum() * 4.5f64.to_radians(),
            ));
        }
    };
    straight(&mut steps, 2.0);
    turn(&mut steps, 90.0, 0.0);
    straight(&mut steps, 1.5);
    turn(&mut steps, 90.0, 0.02);
    straight(&mut steps, 2.0);
    turn(&mut steps, -90.0, 0.0);
    straight(&mut steps, 1.0);
    turn(&mut steps, -45.0, 0.01);
    straight(&mut steps, 1.0);
    steps
}

struct Errors {
    heading_final: f64,
    heading_mean: f64,
    heading_max: f64,
    position_final: f64,
    position_mean: f64,
    position_max: f64,
}

fn errors(estimate: &[Se2], truth: &[Se2]) -> Errors {
    let mut e = Errors {
        heading_final: 0.0,
        heading_mean: 0.0,
        heading_max: 0.0,
        position_final: 0.0,
        position_mean: 0.0,
        position_max: 0.0,
    };
    for (a, t) in estimate.iter().zip(truth) {
        e.heading_final = libm::fabs(wrap_angle(a.theta - t.theta));
        e.position_final = libm::hypot(a.x - t.x, a.y - t.y);
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
struct Figures {
    keyframes: usize,
    landmarks_seen: usize,
    outliers: usize,
    landmarks_dropped: usize,
    failures: usize,
}

/// Drives under a ceiling of random points and returns the VO's keyframe trajectory (the
/// composed relative poses), the odometry and the truth at the keyframes, and the figures.
fn run(seed: u64, wrong_match_share: f64) -> (Errors, Errors, Figures, VoStats) {
    let (model, mount) = cleaner_camera();
    let mut rng = Rng::new(seed);
    // Ceiling 2.4 m up over the whole drive, with a few lamps lower down.
    let points: Vec<Vector3<f64>> = (0..900)
        .map(|_| {
            let z = if rng.next_u64().is_multiple_of(10) {
                2.0
            } else {
                2.4
            };
            Vector3::new(
                uniform(&mut rng, -3.0, 7.0),
                uniform(&mut rng, -3.0, 6.0),
                z,
            )
        })
        .collect();
    let mut vo = Box::new(Vo::new());
    let cfg = VoConfig::default();
    let (mut truth, mut odo) = (Se2::IDENTITY, Se2::IDENTITY);
    let mut previous_points: Vec<usize> = Vec::new();
    let (mut vo_traj, mut odo_traj, mut true_traj) = (Vec::new(), Vec::new(), Vec::new());
    let mut chained = Se2::IDENTITY;
    let mut figures = Figures::default();
    for (i, step) in core::iter::once(Se2::IDENTITY).chain(drive()).enumerate() {
        truth = truth.compose(&step);
        // Wheels read 3 % long, the gyro drifts 0.6 deg/s, both with noise.
        let measured = Se2::new(
            step.x * 1.03 + 0.002 * gauss(&mut rng),
            0.001 * gauss(&mut rng),
            step.theta + 0.06f64.to_radians() + 0.003 * gauss(&mut rng),
        );
        if i > 0 {
            odo = odo.compose(&measured);
        }
        let cam = CameraPose::of_robot(&truth, &mount);
        let mut keypoints = Vec::new();
        let mut seen = Vec::new();
        for (p, point) in points.iter().enumerate() {
            let pc = cam.world_to_camera(point);
            let Some(px) = model.project(&pc) else {
                continue;
            };
            let (u, v) = (px.x + 0.5 * gauss(&mut rng), px.y + 0.5 * gauss(&mut rng));
            if pc.z > 0.1 && (0.0..WIDTH).contains(&u) && (0.0..HEIGHT).contains(&v) {
                keypoints.push(Keypoint {
                    x: u as f32,
                    y: v as f32,
                    ..Keypoint::default()
                });
                seen.push(p);
            }
            if keypoints.len() == MAX_FEATURES {
                break;
            }
        }
        let mut matches: Vec<Match> = Vec::new();
        for (q, p) in previous_points.iter().enumerate() {
            if let Some(t) = seen.iter().position(|s| s == p) {
                matches.push(Match {
                    query: q,
                    train: t,
                    distance: 10,
                });
            }
        }
        // Wrong matches: some pairs exchange their new features.
        let n = matches.len();
        for k in 0..n {
            if uniform(&mut rng, 0.0, 1.0) < wrong_match_share {
                let j = (rng.next_u64() % n as u64) as usize;
                let (a, b) = (matches[k].train, matches[j].train);
                matches[k].train = b;
                matches[j].train = a;
            }
        }
        previous_points = seen;
        let frame = VoFrame {
            stamp: 100_000_000 * i as i64,
            odometry: odo,
            keypoints: &keypoints,
            matches: &matches,
            descriptors: &[],
        };
        let step = vo.process(&frame, &model, &mount, &cfg).expect("accepted");
        if let Some(k) = step.keyframe {
            chained = chained.compose(&k.relative.unwrap_or(Se2::IDENTITY));
            vo_traj.push(chained);
            odo_traj.push(odo);
            true_traj.push(truth);
            figures.keyframes += 1;
            figures.landmarks_seen += k.landmarks_seen;
            figures.outliers += k.outliers_dropped;
            figures.landmarks_dropped += k.landmarks_dropped;
            if let (Err(e), Some(_)) = (k.solve, k.relative) {
                std::println!("keyframe {}: {e:?}", figures.keyframes);
                figures.failures += 1;
            }
        }
    }
    let stats = vo.stats();
    (
        errors(&vo_traj, &true_traj),
        errors(&odo_traj, &true_traj),
        figures,
        stats,
    )
}

fn report(name: &str, vo: &Errors, odo: &Errors, f: &Figures, s: &VoStats) {
    std::println!(
        "{name}: VO heading final {:.2} deg (mean {:.2}, max {:.2}), position final {:.3} m \
         (mean {:.3}, max {:.3}); odometry heading final {:.2} deg (mean {:.2}, max {:.2}), \
         position final {:.3} m (mean {:.3}, max {:.3}); \
         {} keyframes, {:.1} landmarks seen per keyframe, {} outliers and {} landmarks \
         dropped, {} failed solves; {s:?}",
        vo.heading_final.to_degrees(),
        vo.heading_mean.to_degrees(),
        vo.heading_max.to_degrees(),
        vo.position_final,
        vo.position_mean,
        vo.position_max,
        odo.heading_final.to_degrees(),
        odo.heading_mean.to_degrees(),
        odo.heading_max.to_degrees(),
        odo.position_final,
        odo.position_mean,
        odo.position_max,
        f.keyframes,
        f.landmarks_seen as f64 / f.keyframes.max(1) as f64,
        f.outliers,
        f.landmarks_dropped,
        f.failures,
    );
}

#[test]
fn a_drive_with_turns_drifts_less_than_the_wheel_odometry() {
    let (vo, odo, f, s) = with_stack(|| run(5, 0.0));
    report("clean matches", &vo, &odo, &f, &s);
    assert!(f.keyframes >= 20, "{f:?}");
    assert_eq!(f.failures, 0);
    assert!(f.landmarks_seen >= 30 * f.keyframes, "{f:?}");
    assert!(vo.heading_final < 0.5 * odo.heading_final);
    assert!(vo.heading_max < 0.5 * odo.heading_max);
    assert!(vo.position_final < 0.5 * odo.position_final);
    assert!(vo.position_mean < 0.5 * odo.position_mean);
}

#[test]
fn wrong_matches_are_dropped_and_the_drift_stays_small() {
    let (vo, odo, f, s) = with_stack(|| run(9, 0.02));
    report("2 % wrong matches per frame", &vo, &odo, &f, &s);
    assert!(
        f.outliers > 0 && s.outliers_dropped as usize == f.outliers,
        "{f:?}"
    );
    assert!(vo.heading_final < 0.5 * odo.heading_final);
    assert!(vo.position_final < 0.5 * odo.position_final);
}

fn kp(x: f32, y: f32) -> Keypoint {
    Keypoint {
        x,
        y,
        ..Keypoint::default()
    }
}

#[test]
fn bad_frames_are_refused_and_counted() {
    let (model, mount) = cleaner_camera();
    let cfg = VoConfig::default();
    let mut vo = Box::new(VisualOdometry::<3, 16, 64>::new());
    let points = [kp(10.0, 10.0), kp(50.0, 60.0), kp(100.0, 30.0)];
    let same: Vec<Match> = (0..3)
        .map(|i| Match {
            query: i,
            train: i,
            distance: 0,
        })
        .collect();
    let mut frame = VoFrame {
        stamp: 10,
        odometry: Se2::IDENTITY,
        keypoints: &points,
        matches: &[],
        descriptors: &[],
    };
    let first = vo.process(&frame, &model, &mount, &cfg).expect("first");
    assert_eq!(
        first.keyframe.map(|k| (k.reason, k.relative)),
        Some((KeyframeReason::First, None))
    );
    // The same stamp, then an earlier one.
    frame.matches = &same;
    assert_eq!(
        vo.process(&frame, &model, &mount, &cfg),
        Err(VoError::OutOfOrder)
    );
    frame.stamp = 5;
    assert_eq!(
        vo.process(&frame, &model, &mount, &cfg),
        Err(VoError::OutOfOrder)
    );
    frame.stamp = 20;
    frame.odometry = Se2 {
        x: f64::NAN,
        y: 0.0,
        theta: 0.0,
    };
    assert_eq!(
        vo.process(&frame, &model, &mount, &cfg),
        Err(VoError::BadPose)
    );
    frame.stamp = 30;
    frame.odometry = Se2::IDENTITY;
    frame.keypoints = &[];
    assert_eq!(
        vo.process(&frame, &model, &mount, &cfg),
        Err(VoError::NoFeatures)
    );
    // Matches into the empty frame name features that do not exist; then a frame with
    // features but no match.
    frame.stamp = 40;
    frame.keypoints = &points;
    frame.matches = &[];
    assert_eq!(
        vo.process(&frame, &model, &mount, &cfg),
        Err(VoError::NoMatches)
    );
    // Pixels that are not finite and matches out of range are skipped, not fatal.
    let odd = [kp(f32::NAN, 3.0), kp(50.0, 60.0), kp(100.0, 30.0)];
    let wild = [
        Match {
            query: 7,
            train: 0,
            distance: 0,
        },
        Match {
            query: 1,
            train: 99,
            distance: 0,
        },
        Match {
            query: 2,
            train: 2,
            distance: 0,
        },
    ];
    frame.stamp = 50;
    frame.keypoints = &odd;
    frame.matches = &wild;
    let step = vo
        .process(&frame, &model, &mount, &cfg)
        .expect("one good match");
    assert_eq!(step.tracked, 1);
    let s = vo.stats();
    assert_eq!(
        (
            s.frames,
            s.out_of_order,
            s.bad_pose,
            s.no_features,
            s.no_matches
        ),
        (2, 2, 1, 1, 1)
    );
    assert_eq!((s.bad_matches, s.bad_pixels), (5, 1));
}

proptest::proptest! {
    /// Any sequence of frames (any pixels, matches, poses and stamps) is taken or refused
    /// with a counted error, never a panic.
    #[test]
    fn any_frames_are_taken_or_refused(
        frames in proptest::collection::vec(
            (
                -2i64..6,
                proptest::collection::vec((-50f32..400.0, -50f32..300.0, 0u8..4), 0..12),
                proptest::collection::vec((0usize..14, 0usize..14), 0..12),
                (-1e3f64..1e3, -1e3f64..1e3, -10f64..10.0),
                proptest::bool::ANY,
            ),
            1..12,
        ),
    ) {
        let (model, mount) = cleaner_camera();
        let cfg = VoConfig { keyframe_distance: 0.0, ..VoConfig::default() };
        let mut vo = Box::new(VisualOdometry::<3, 16, 64>::new());
        let mut stamp = 0;
        for (dt, kps, ms, (x, y, t), nan) in &frames {
            stamp += dt;
            let keypoints: Vec<Keypoint> = kps
                .iter()
                .map(|&(x, y, level)| Keypoint { x, y, level, ..Keypoint::default() })
                .collect();
            let matches: Vec<Match> = ms
                .iter()
                .map(|&(query, train)| Match { query, train, distance: 0 })
                .collect();
            let odometry = Se2::new(if *nan { f64::NAN } else { *x }, *y, *t);
            let frame = VoFrame { stamp, odometry, keypoints: &keypoints, matches: &matches, descriptors: &[] };
            if let Ok(step) = vo.process(&frame, &model, &mount, &cfg) {
                proptest::prop_assert!(step.tracked <= keypoints.len());
            }
        }
        let s = vo.stats();
        proptest::prop_assert_eq!(
            (s.frames + s.out_of_order + s.bad_pose + s.no_features + s.no_matches) as usize,
            frames.len()
        );
        proptest::prop_assert!(vo.keyframe_count() <= 3 && vo.landmark_count() <= 16);
    }
}

/// What the odometry costs besides its window: per keyframe slot, [`MAX_FEATURES`] features
/// of 16 bytes and two poses; per landmark a track id, a point and a descriptor; per
/// observation slot the keyframe and feature it came from; two frames of track ids; and the
/// re-finding's working space (per landmark a track id, a descriptor and a pixel, per feature
/// an index, a descriptor, a pixel, a track id and a match).
#[test]
fn sizes() {
    type Small = VisualOdometry<3, 16, 64>;
    let window = size_of::<BundleWindow<3, 16, 64>>();
    assert_eq!(size_of::<KeyFeature>(), 16);
    assert_eq!(size_of::<Landmark>(), 64);
    assert_eq!(size_of::<ObservationSource>(), 4);
    let match_size = size_of::<Match>();
    let refind = 16 * (4 + 32 + 8) + MAX_FEATURES * (2 + 32 + 8 + 4 + match_size);
    assert_eq!(size_of::<RefindScratch<16>>(), refind);
    let own = 3 * size_of::<Keyframe>() + 16 * 64 + 64 * 4 + 2 * MAX_FEATURES * 4 + refind;
    assert!(size_of::<Small>() >= window + own);
    assert!(size_of::<Small>() <= window + own + 128);
}

/// A window with room for nothing refuses nothing and panics on nothing.
#[test]
fn an_empty_window_takes_frames() {
    let (model, mount) = cleaner_camera();
    let mut vo = VisualOdometry::<0, 0, 0>::new();
    let points = [kp(10.0, 10.0), kp(50.0, 60.0)];
    let same = [Match {
        query: 0,
        train: 0,
        distance: 0,
    }];
    for (stamp, x) in [(1, 0.0), (2, 1.0), (3, 2.0)] {
        let frame = VoFrame {
            stamp,
            odometry: Se2::new(x, 0.0, 0.0),
            keypoints: &points,
            matches: &same,
            descriptors: &[],
        };
        let step = vo.process(&frame, &model, &mount, &VoConfig::default());
        let k = step.expect("accepted").keyframe.expect("a keyframe");
        assert_eq!(k.solve, Err(WindowError::Full));
    }
    assert_eq!(vo.keyframe_count(), 0);
}

/// Wheels slipping on a stuck robot: the odometry runs on, the image stands still. The motion
/// rule asks for keyframes, the redundancy test refuses them; then the image moves and the
/// next frame is a keyframe.
#[test]
fn a_frame_that_sees_what_the_keyframe_saw_is_redundant() {
    let (model, mount) = cleaner_camera();
    let cfg = VoConfig::default();
    let mut vo = Box::new(VisualOdometry::<3, 64, 256>::new());
    let still: Vec<Keypoint> = (0..40)
        .map(|i| kp(20.0 + 7.0 * i as f32, 30.0 + 4.0 * i as f32))
        .collect();
    let same: Vec<Match> = (0..40)
        .map(|i| Match {
            query: i,
            train: i,
            distance: 0,
        })
        .collect();
    let mut keyframes = 0;
    for i in 0..10 {
        let frame = VoFrame {
            stamp: i,
            odometry: Se2::new(0.1 * i as f64, 0.0, 0.0),
            keypoints: &still,
            matches: &same,
            descriptors: &[],
        };
        let step = vo.process(&frame, &model, &mount, &cfg).expect("accepted");
        keyframes += usize::from(step.keyframe.is_some());
    }
    assert_eq!(keyframes, 1);
    // From 0.3 m on, seven frames were past the keyframe distance.
    assert_eq!(vo.stats().redundant, 7);
    // Each feature moves 2 px: beyond half-pixel noise, no longer redundant.
    let moved: Vec<Keypoint> = still.iter().map(|k| kp(k.x + 2.0, k.y)).collect();
    let frame = VoFrame {
        stamp: 10,
        odometry: Se2::new(1.0, 0.0, 0.0),
        keypoints: &moved,
        matches: &same,
        descriptors: &[],
    };
    let step = vo.process(&frame, &model, &mount, &cfg).expect("accepted");
    assert_eq!(
        step.keyframe.map(|k| k.reason),
        Some(KeyframeReason::Motion)
    );
}

/// Landmarks seen per keyframe and the counters, on a straight 2 m drive under random
/// ceiling points each missed in a third of the frames (so frame-to-frame tracks break
/// often), every point with its own random descriptor.
fn run_with_misses(cfg: &VoConfig) -> (usize, usize, VoStats) {
    let (model, mount) = cleaner_camera();
    let mut rng = Rng::new(7);
    let points: Vec<(Vector3<f64>, Descriptor)> = (0..600)
        .map(|_| {
            let p = Vector3::new(
                uniform(&mut rng, -2.0, 5.0),
                uniform(&mut rng, -3.0, 3.0),
                2.4,
            );
            let mut d = [0u32; 8];
            d.iter_mut().for_each(|w| *w = rng.next_u64() as u32);
            (p, Descriptor(d))
        })
        .collect();
    let mut vo = Box::new(Vo::new());
    let mut previous: Vec<usize> = Vec::new();
    let (mut keyframes, mut landmarks_seen) = (0, 0);
    let mut pose = Se2::IDENTITY;
    for i in 0..70 {
        if i > 0 {
            pose = pose.compose(&Se2::new(0.03, 0.0, 0.0));
        }
        let cam = CameraPose::of_robot(&pose, &mount);
        let (mut keypoints, mut descriptors, mut seen) = (Vec::new(), Vec::new(), Vec::new());
        for (p, (point, d)) in points.iter().enumerate() {
            let pc = cam.world_to_camera(point);
            let Some(px) = model.project(&pc) else {
                continue;
            };
            let inside =
                pc.z > 0.1 && (0.0..WIDTH).contains(&px.x) && (0.0..HEIGHT).contains(&px.y);
            if !inside || uniform(&mut rng, 0.0, 1.0) < 0.33 || keypoints.len() == MAX_FEATURES {
                continue;
            }
            keypoints.push(kp(px.x as f32, px.y as f32));
            descriptors.push(*d);
            seen.push(p);
        }
        let matches: Vec<Match> = previous
            .iter()
            .enumerate()
            .filter_map(|(q, p)| {
                let t = seen.iter().position(|s| s == p)?;
                Some(Match {
                    query: q,
                    train: t,
                    distance: 0,
                })
            })
            .collect();
        previous = seen;
        let frame = VoFrame {
            stamp: 100_000_000 * i as i64,
            odometry: pose,
            keypoints: &keypoints,
            matches: &matches,
            descriptors: &descriptors,
        };
        let step = vo.process(&frame, &model, &mount, cfg).expect("accepted");
        if let Some(k) = step.keyframe {
            keyframes += 1;
            landmarks_seen += k.landmarks_seen;
        }
    }
    (keyframes, landmarks_seen, vo.stats())
}

/// A feature missed in one frame ends its frame-to-frame track; re-finding the landmark near
/// its predicted pixel by descriptor continues it, so keyframes see more landmarks, and no
/// re-found sighting is an outlier (every descriptor is unique, the prediction exact).
#[test]
fn landmarks_missed_in_a_frame_are_found_again() {
    let off = VoConfig {
        refind_radius_px: 0.0,
        ..VoConfig::default()
    };
    let (kf_off, seen_off, stats_off) = with_stack(move || run_with_misses(&off));
    let (kf_on, seen_on, stats_on) = with_stack(|| run_with_misses(&VoConfig::default()));
    std::println!(
        "without re-finding: {kf_off} keyframes, {seen_off} landmarks seen, {stats_off:?}"
    );
    std::println!("with re-finding: {kf_on} keyframes, {seen_on} landmarks seen, {stats_on:?}");
    assert_eq!(stats_off.refound, 0);
    assert!(stats_on.refound > 0);
    assert!(seen_on > seen_off + seen_off / 2, "{seen_on} vs {seen_off}");
    assert_eq!(stats_on.outliers_dropped, 0);
}
