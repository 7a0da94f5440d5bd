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
/// of 52 bytes (track, pixel, level, measure (a)'s flag and descriptor) and two poses; per landmark a track id, a point and a descriptor; per
/// observation slot the keyframe and feature it came from; two frames of track ids; and the
/// re-finding's working space (per landmark a track id, a descriptor and a pixel, per feature
/// an index, a descriptor, a pixel, a track id and a match).
#[test]
fn sizes() {
    type Small = VisualOdometry<3, 16, 64>;
    let window = size_of::<BundleWindow<3, 16, 64>>();
    assert_eq!(size_of::<KeyFeature>(), 52);
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

// The low-feature measures, on a window set up by hand: keyframes with their features, and
// landmarks, as the odometry would have left them.

fn descriptor(rng: &mut Rng) -> Descriptor {
    let mut d = [0u32; 8];
    d.iter_mut().for_each(|w| *w = rng.next_u64() as u32);
    Descriptor(d)
}

/// `d` with its lowest `bits` bits (at most 32) flipped: the same corner seen again.
fn flipped(d: Descriptor, bits: u32) -> Descriptor {
    let mut out = d;
    out.0[0] ^= u32::MAX >> (32 - bits);
    out
}

fn feature(track: u32, px: [f32; 2], descriptor: Option<Descriptor>) -> KeyFeature {
    KeyFeature {
        track,
        px,
        level: 0,
        backfilled: false,
        descriptor,
    }
}

/// Appends a keyframe at `pose` with `features` (sorted here).
fn put_keyframe<const N: usize, const M: usize, const K: usize>(
    vo: &mut VisualOdometry<N, M, K>,
    pose: Se2,
    features: &[KeyFeature],
) {
    let kf = &mut vo.keyframes[vo.keyframe_count];
    kf.pose = pose;
    kf.odometry = pose;
    kf.features[..features.len()].copy_from_slice(features);
    kf.len = features.len();
    kf.compact();
    vo.keyframe_count += 1;
}

fn put_landmarks<const N: usize, const M: usize, const K: usize>(
    vo: &mut VisualOdometry<N, M, K>,
    landmarks: &[(u32, Vector3<f64>, Descriptor)],
) {
    for (slot, &(track, position, d)) in vo.landmarks.iter_mut().zip(landmarks) {
        *slot = Landmark {
            track,
            position,
            descriptor: Some(d),
        };
    }
    vo.landmark_count = landmarks.len();
    crate::sort::sort_by_key(&mut vo.landmarks[..landmarks.len()], |l| l.track);
}

fn landmark<const N: usize, const M: usize, const K: usize>(
    vo: &VisualOdometry<N, M, K>,
    track: u32,
) -> Option<Landmark> {
    vo.landmarks[..vo.landmark_count]
        .iter()
        .find(|l| l.track == track)
        .copied()
}

/// Measure (b): the same corner triangulated twice, from two keyframes that each saw one of
/// its tracks, becomes one landmark at the mean of the two, with both sightings; a close
/// point with another descriptor, a far point with the same one, and two points seen side by
/// side in one image stay apart.
#[test]
fn duplicate_landmarks_become_one_at_their_mean() {
    let mut rng = Rng::new(3);
    let (corner, other, lamp) = (
        descriptor(&mut rng),
        descriptor(&mut rng),
        descriptor(&mut rng),
    );
    let mut vo = Box::new(VisualOdometry::<4, 16, 64>::new());
    let f = |t| feature(t, [100.0, 100.0], None);
    put_keyframe(&mut vo, Se2::IDENTITY, &[f(1), f(3), f(5)]);
    put_keyframe(
        &mut vo,
        Se2::new(0.25, 0.0, 0.0),
        &[f(2), f(3), f(4), f(5), f(6)],
    );
    put_landmarks(
        &mut vo,
        &[
            (1, Vector3::new(1.00, 0.00, 2.4), corner),
            (2, Vector3::new(1.04, 0.02, 2.4), flipped(corner, 6)),
            (3, Vector3::new(1.03, 0.00, 2.4), other),
            (4, Vector3::new(1.50, 0.00, 2.4), corner),
            (5, Vector3::new(3.00, 0.00, 2.4), lamp),
            (6, Vector3::new(3.01, 0.00, 2.4), lamp),
        ],
    );
    // Track 2 is still followed in the newest frame.
    vo.current[0] = 2;
    vo.previous[0] = 2;
    vo.previous_len = 1;
    let merged = vo.merge_duplicates(&VoConfig::default());
    assert_eq!(merged, 1);
    assert_eq!(vo.stats().merged, 1);
    assert_eq!(vo.landmark_count(), 5);
    assert!(landmark(&vo, 2).is_none());
    let kept = landmark(&vo, 1).expect("the first track kept");
    assert!((kept.position - Vector3::new(1.02, 0.01, 2.4)).norm() < 1e-12);
    // Both keyframes now see the one landmark, and the live track continues it.
    assert!(vo.keyframes[0].find(1).is_some());
    assert!(vo.keyframes[1].find(1).is_some());
    assert!(vo.keyframes[1].find(2).is_none());
    assert_eq!(vo.sightings(1), 2);
    assert_eq!((vo.current[0], vo.previous[0]), (1, 1));
    for t in [3, 4, 5, 6] {
        assert!(landmark(&vo, t).is_some(), "landmark {t}");
    }
    // Off, nothing merges.
    let off = VoConfig {
        low_feature: LowFeatureConfig {
            merge_distance: 0.0,
            ..LowFeatureConfig::default()
        },
        ..VoConfig::default()
    };
    assert_eq!(vo.merge_duplicates(&off), 0);
}

/// Measure (b): the landmark seen more often stays, and the mean leans towards it.
#[test]
fn a_merge_keeps_the_better_seen_landmark() {
    let mut rng = Rng::new(4);
    let corner = descriptor(&mut rng);
    let mut vo = Box::new(VisualOdometry::<4, 16, 64>::new());
    let f = |t| feature(t, [100.0, 100.0], None);
    put_keyframe(&mut vo, Se2::IDENTITY, &[f(7)]);
    put_keyframe(&mut vo, Se2::new(0.25, 0.0, 0.0), &[f(7)]);
    put_keyframe(&mut vo, Se2::new(0.5, 0.0, 0.0), &[f(8)]);
    put_landmarks(
        &mut vo,
        &[
            (7, Vector3::new(1.0, 0.0, 2.4), corner),
            (8, Vector3::new(1.0, 0.06, 2.4), corner),
        ],
    );
    assert_eq!(vo.merge_duplicates(&VoConfig::default()), 1);
    let kept = landmark(&vo, 7).expect("the better seen kept");
    assert!((kept.position - Vector3::new(1.0, 0.02, 2.4)).norm() < 1e-12);
    assert_eq!(vo.sightings(7), 3);
}

/// Measure (c): when the oldest keyframe is about to leave, the landmarks it sees that fewer
/// than four keyframes saw leave with their sightings; those seen often enough, and those
/// the oldest keyframe does not see (they may still be seen again), stay.
#[test]
fn short_lived_landmarks_are_dropped() {
    let mut vo = Box::new(VisualOdometry::<5, 16, 64>::new());
    let f = |t| feature(t, [100.0, 100.0], None);
    put_keyframe(&mut vo, Se2::IDENTITY, &[f(1), f(2)]);
    put_keyframe(&mut vo, Se2::new(0.25, 0.0, 0.0), &[f(1), f(2), f(3)]);
    put_keyframe(&mut vo, Se2::new(0.5, 0.0, 0.0), &[f(2), f(3)]);
    put_keyframe(&mut vo, Se2::new(0.75, 0.0, 0.0), &[f(2)]);
    put_keyframe(&mut vo, Se2::new(1.0, 0.0, 0.0), &[f(4)]);
    let d = Descriptor([0; 8]);
    let p = Vector3::new(1.0, 0.0, 2.4);
    put_landmarks(&mut vo, &[(1, p, d), (2, p, d), (3, p, d), (4, p, d)]);
    let off = VoConfig {
        low_feature: LowFeatureConfig {
            min_sightings: 0,
            ..LowFeatureConfig::default()
        },
        ..VoConfig::default()
    };
    assert_eq!(vo.drop_short_lived(&off), 0);
    assert_eq!(vo.landmark_count(), 4);

    assert_eq!(vo.drop_short_lived(&VoConfig::default()), 1);
    assert_eq!(vo.stats().short_lived_dropped, 1);
    assert!(landmark(&vo, 1).is_none());
    assert!(vo.keyframes[..5].iter().all(|k| k.find(1).is_none()));
    assert_eq!(vo.keyframes[1].len, 2);
    for t in [2, 3, 4] {
        assert!(landmark(&vo, t).is_some(), "landmark {t}");
    }
    // The window then slides as before: the survivors are still seen.
    vo.slide();
    assert_eq!(vo.landmark_count(), 3);
}

/// Measure (a): a landmark triangulated in the two newest keyframes is found in the oldest,
/// whose feature of the same corner had started a track that ended there; a look-alike
/// feature farther than the radius, a close feature of another corner, and a feature whose
/// track is still followed are not taken. The window then has one more observation.
#[test]
fn an_older_keyframe_gains_the_sightings_of_a_later_landmark() {
    let (model, mount) = cleaner_camera();
    let mut rng = Rng::new(5);
    let (corner, other, lamp) = (
        descriptor(&mut rng),
        descriptor(&mut rng),
        descriptor(&mut rng),
    );
    let poses = [
        Se2::IDENTITY,
        Se2::new(0.25, 0.0, 0.05),
        Se2::new(0.5, 0.0, 0.1),
    ];
    let (p, q) = (Vector3::new(1.2, 0.3, 2.4), Vector3::new(1.0, -0.4, 2.4));
    let px = |pose: &Se2, point: &Vector3<f64>| {
        let c = CameraPose::of_robot(pose, &mount);
        let px = model.project(&c.world_to_camera(point)).expect("in view");
        [px.x as f32, px.y as f32]
    };
    let p0 = px(&poses[0], &p);
    let q0 = px(&poses[0], &q);
    let mut vo = Box::new(VisualOdometry::<4, 16, 64>::new());
    put_keyframe(
        &mut vo,
        poses[0],
        &[
            // The corner, under an ended track (10), and a look-alike 20 px away.
            feature(10, [p0[0] + 0.4, p0[1] - 0.3], Some(flipped(corner, 5))),
            feature(11, [p0[0] + 20.0, p0[1]], Some(corner)),
            feature(12, [p0[0] - 2.0, p0[1] + 1.0], Some(other)),
            // The lamp under track 40, still followed in the newest keyframe.
            feature(40, q0, Some(lamp)),
        ],
    );
    for pose in &poses[1..] {
        put_keyframe(
            &mut vo,
            *pose,
            &[
                feature(20, px(pose, &p), Some(corner)),
                feature(30, px(pose, &q), Some(lamp)),
                feature(40, [5.0, 5.0], Some(other)),
            ],
        );
    }
    put_landmarks(&mut vo, &[(20, p, corner), (30, q, lamp)]);
    let cfg = VoConfig::default();
    vo.fill(&cfg).expect("room");
    assert_eq!(vo.window.observation_count(), 4);

    assert_eq!(vo.backfill(&model, &mount, &cfg), 1);
    assert_eq!(vo.stats().backfilled, 1);
    let oldest = &vo.keyframes[0];
    let (_, found) = oldest
        .find(20)
        .expect("the corner found in the oldest keyframe");
    assert_eq!(found.px, [p0[0] + 0.4, p0[1] - 0.3]);
    assert!(oldest.find(10).is_none());
    assert!(oldest.find(11).is_some() && oldest.find(12).is_some());
    assert!(oldest.find(30).is_none() && oldest.find(40).is_some());
    assert_eq!(vo.sightings(20), 3);
    vo.fill(&cfg).expect("room");
    assert_eq!(vo.window.observation_count(), 5);
    // Found already: a second pass adds nothing.
    assert_eq!(vo.backfill(&model, &mount, &cfg), 0);
}

/// The three measures on the drive with missed features: sightings are found in older
/// keyframes, and none of them is an outlier (each descriptor is unique, the poses exact).
#[test]
fn the_low_feature_measures_on_a_drive_with_misses() {
    let off = VoConfig {
        low_feature: LowFeatureConfig {
            backfill_radius_px: 0.0,
            merge_distance: 0.0,
            min_sightings: 0,
            ..LowFeatureConfig::default()
        },
        ..VoConfig::default()
    };
    let (kf_off, seen_off, stats_off) = with_stack(move || run_with_misses(&off));
    let (kf_on, seen_on, stats_on) = with_stack(|| run_with_misses(&VoConfig::default()));
    std::println!("measures off: {kf_off} keyframes, {seen_off} landmarks seen, {stats_off:?}");
    std::println!("measures on: {kf_on} keyframes, {seen_on} landmarks seen, {stats_on:?}");
    assert_eq!(
        (
            stats_off.backfilled,
            stats_off.merged,
            stats_off.short_lived_dropped
        ),
        (0, 0, 0)
    );
    assert!(stats_on.backfilled > 0, "{stats_on:?}");
    assert_eq!(stats_on.outliers_dropped, 0, "{stats_on:?}");
}
