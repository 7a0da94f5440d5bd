//! Synthetic rooms for the window: a ceiling 2.4 m up and two walls, seen by the cleaner's
//! ceiling-tilted KB4 camera from a short arc of keyframes, with the true pixels known.

extern crate std;

use std::boxed::Box;
use std::vec::Vec;

use proptest::prelude::*;

use super::*;
use crate::frontend::visual::camera::Pinhole;
use crate::frontend::visual::synth::{cleaner_camera, Rng};
use crate::frontend::visual::triangulate::{
    triangulate, CameraPose, Observation, TriangulateConfig,
};

type Window = BundleWindow<8, 400, 3000>;

const WIDTH: f64 = 320.0;
const HEIGHT: f64 = 240.0;

struct Room {
    model: CameraModel,
    mount: CameraExtrinsic,
    poses: Vec<Se2>,
    points: Vec<Vector3<f64>>,
    /// Exact pixels, each landmark seen at least twice.
    obs: Vec<PixelObservation>,
}

fn gauss(rng: &mut Rng) -> f64 {
    // Box-Muller on two uniforms in (0, 1].
    let u1 = ((rng.next_u64() >> 11) as f64 + 1.0) / (1u64 << 53) as f64;
    let u2 = (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
    libm::sqrt(-2.0 * libm::log(u1)) * libm::cos(2.0 * core::f64::consts::PI * u2)
}

fn uniform(rng: &mut Rng, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64
}

fn pixel_of(room: &Room, pose: &Se2, p: &Vector3<f64>) -> Option<Vector2<f64>> {
    let cam = CameraPose::of_robot(pose, &room.mount);
    let pc = cam.world_to_camera(p);
    let px = room.model.project(&pc)?;
    let inside = pc.z > 0.1 && px.x >= 0.0 && px.x < WIDTH && px.y >= 0.0 && px.y < HEIGHT;
    inside.then_some(px)
}

/// `keyframes` poses along a left-turning arc, 25 cm and 5 degrees apart, and the points of
/// the ceiling and walls that at least two of them see by the cleaner's camera.
fn room(keyframes: usize) -> Room {
    let (model, mount) = cleaner_camera();
    room_seen_by(keyframes, model, mount)
}

fn room_seen_by(keyframes: usize, model: CameraModel, mount: CameraExtrinsic) -> Room {
    let mut poses = Vec::new();
    let mut pose = Se2::new(0.0, 0.0, 0.0);
    for _ in 0..keyframes {
        poses.push(pose);
        pose = pose.compose(&Se2::new(0.25, 0.0, 5f64.to_radians()));
    }
    let mut candidates = Vec::new();
    for i in 0..16 {
        for j in 0..14 {
            let (x, y) = (-0.5 + 0.33 * i as f64, -2.0 + 0.33 * j as f64);
            candidates.push(Vector3::new(x, y, 2.4));
        }
    }
    for i in 0..14 {
        for j in 0..6 {
            let (y, z) = (-2.0 + 0.33 * i as f64, 0.6 + 0.3 * j as f64);
            candidates.push(Vector3::new(4.5, y, z));
            candidates.push(Vector3::new(-0.5 + 0.35 * i as f64, 2.6, z));
        }
    }
    let mut room = Room {
        model,
        mount,
        poses,
        points: Vec::new(),
        obs: Vec::new(),
    };
    for p in candidates {
        let seen: Vec<(usize, Vector2<f64>)> = room
            .poses
            .iter()
            .enumerate()
            .filter_map(|(k, pose)| Some((k, pixel_of(&room, pose, &p)?)))
            .collect();
        if seen.len() < 2 {
            continue;
        }
        let landmark = room.points.len();
        room.points.push(p);
        for (keyframe, px) in seen {
            room.obs.push(PixelObservation {
                keyframe,
                landmark,
                px,
                sigma_px: 0.5,
            });
        }
    }
    room
}

/// Information of wheel+gyro motion with the given standard deviations.
fn odometry_information(sigma_xy: f64, sigma_theta: f64) -> Matrix3<f64> {
    let (a, b) = (
        1.0 / (sigma_xy * sigma_xy),
        1.0 / (sigma_theta * sigma_theta),
    );
    Matrix3::new(a, 0.0, 0.0, 0.0, a, 0.0, 0.0, 0.0, b)
}

fn fill(
    w: &mut Window,
    poses: &[Se2],
    points: &[Vector3<f64>],
    obs: &[PixelObservation],
    priors: &[MotionPrior],
) {
    w.clear();
    for p in poses {
        w.push_pose(*p).unwrap();
    }
    for p in points {
        w.push_landmark(*p).unwrap();
    }
    for o in obs {
        w.push_observation(*o).unwrap();
    }
    for p in priors {
        w.push_motion_prior(*p).unwrap();
    }
}

/// The true motions between consecutive keyframes as priors.
fn exact_priors(room: &Room, info: Matrix3<f64>) -> Vec<MotionPrior> {
    room.poses
        .windows(2)
        .enumerate()
        .map(|(k, pair)| MotionPrior {
            from: k,
            to: k + 1,
            motion: pair[0].between(&pair[1]),
            information: info,
        })
        .collect()
}

/// Largest position (metres) and heading (degrees) error of the window's poses.
fn pose_errors(w: &Window, truth: &[Se2]) -> (f64, f64) {
    let mut worst = (0.0f64, 0.0f64);
    for (k, t) in truth.iter().enumerate() {
        let p = w.pose(k).unwrap();
        worst.0 = worst.0.max(libm::hypot(p.x - t.x, p.y - t.y));
        worst.1 = worst
            .1
            .max(wrap_angle(p.theta - t.theta).abs().to_degrees());
    }
    worst
}

/// Root mean square position error of a trajectory, metres.
fn rms_position(poses: &[Se2], truth: &[Se2]) -> f64 {
    let sum: f64 = poses
        .iter()
        .zip(truth)
        .map(|(p, t)| (p.x - t.x).powi(2) + (p.y - t.y).powi(2))
        .sum();
    libm::sqrt(sum / poses.len() as f64)
}

/// The trajectory's scale about the first pose that best fits the truth, and the RMS position
/// error left after that scale is applied: one camera cannot see the scale (the window takes
/// it from the odometry), so this separates what the images fixed from what they could not.
fn scale_and_shape(poses: &[Se2], truth: &[Se2]) -> (f64, f64) {
    let d: Vec<Vector2<f64>> = poses
        .iter()
        .map(|p| p.translation() - poses[0].translation())
        .collect();
    let e: Vec<Vector2<f64>> = truth
        .iter()
        .map(|t| t.translation() - truth[0].translation())
        .collect();
    let num: f64 = d.iter().zip(&e).map(|(d, e)| d.dot(e)).sum();
    let den: f64 = d.iter().map(|d| d.norm_squared()).sum();
    let s = num / den;
    let sum: f64 = d
        .iter()
        .zip(&e)
        .map(|(d, e)| (d * s - e).norm_squared())
        .sum();
    (s, libm::sqrt(sum / poses.len() as f64))
}

fn perturbed_poses(room: &Room, rng: &mut Rng, xy: f64, deg: f64) -> Vec<Se2> {
    room.poses
        .iter()
        .enumerate()
        .map(|(k, p)| {
            if k == 0 {
                return *p;
            }
            Se2::new(
                p.x + uniform(rng, -xy, xy),
                p.y + uniform(rng, -xy, xy),
                p.theta + uniform(rng, -deg, deg).to_radians(),
            )
        })
        .collect()
}

fn perturbed_points(room: &Room, rng: &mut Rng, d: f64) -> Vec<Vector3<f64>> {
    room.points
        .iter()
        .map(|p| {
            p + Vector3::new(
                uniform(rng, -d, d),
                uniform(rng, -d, d),
                uniform(rng, -d, d),
            )
        })
        .collect()
}

#[test]
fn reprojection_jacobians_match_central_differences() {
    let (model, mount) = cleaner_camera();
    let pose = Se2::new(0.4, -0.2, 0.7);
    let point = Vector3::new(1.9, 0.8, 2.4);
    let trig = (libm::cos(pose.theta), libm::sin(pose.theta));
    let z = Vector2::new(100.0, 80.0);
    let (r, jx, jl) = reprojection(&model, &mount, &pose, trig, &point, &z).unwrap();
    // The residual is the same projection the triangulation tests use.
    let cam = CameraPose::of_robot(&pose, &mount);
    let direct = model.project(&cam.world_to_camera(&point)).unwrap() - z;
    assert!((r - direct).norm() < 1e-9);
    let h = 1e-6;
    let at = |p: Se2, q: Vector3<f64>| {
        let t = (libm::cos(p.theta), libm::sin(p.theta));
        reprojection(&model, &mount, &p, t, &q, &z).unwrap().0
    };
    for c in 0..3 {
        let mut dp = Vector3::zeros();
        dp[c] = h;
        let plus = Se2::from_vector(&(pose.to_vector() + dp));
        let minus = Se2::from_vector(&(pose.to_vector() - dp));
        let num = (at(plus, point) - at(minus, point)) / (2.0 * h);
        assert!(
            (jx.column(c) - num).norm() < 1e-4,
            "pose {c}: {jx} vs {num}"
        );
        let num = (at(pose, point + dp) - at(pose, point - dp)) / (2.0 * h);
        assert!(
            (jl.column(c) - num).norm() < 1e-4,
            "point {c}: {jl} vs {num}"
        );
    }
}

/// Test 1: exact pixels and exact odometry from a start a few centimetres and degrees off.
#[test]
fn exact_data_is_recovered_from_perturbed_poses_and_points() {
    let room = room(6);
    assert!(room.points.len() > 100, "{} landmarks", room.points.len());
    let mut rng = Rng::new(7);
    let poses = perturbed_poses(&room, &mut rng, 0.04, 3.0);
    let points = perturbed_points(&room, &mut rng, 0.05);
    let priors = exact_priors(&room, odometry_information(0.01, 0.5f64.to_radians()));
    let mut w = Box::new(Window::new());
    fill(&mut w, &poses, &points, &room.obs, &priors);
    let summary = w
        .solve(&room.model, &room.mount, &WindowConfig::default())
        .unwrap();
    std::eprintln!("exact: {summary:?}");
    assert_eq!(summary.termination, Termination::Converged);
    assert!(summary.final_cost < 1e-12 && summary.initial_cost > 1e3);
    assert_eq!(summary.active_landmarks, room.points.len());
    assert_eq!(summary.outliers, 0);
    let (pos, deg) = pose_errors(&w, &room.poses);
    assert!(pos < 1e-3 && deg < 0.01, "{pos} m, {deg} deg");
    // In fact to round-off.
    assert!(pos < 1e-8 && deg < 1e-7, "{pos} m, {deg} deg");
    for (l, truth) in room.points.iter().enumerate() {
        let got = w.landmark(l).unwrap();
        assert!(
            (got - truth).norm() < 1e-3,
            "landmark {l}: {got} vs {truth}"
        );
        assert!(w.landmark_report(l).unwrap().is_inlier());
    }
}

/// Test 1 with a pinhole lens of the same focal length.
#[test]
fn exact_data_is_recovered_through_a_pinhole_lens_too() {
    let (kb4, mount) = cleaner_camera();
    let pinhole = CameraModel::Pinhole(Pinhole::new_checked(kb4.intrinsics()).unwrap());
    let room = room_seen_by(5, pinhole, mount);
    assert!(room.points.len() > 50, "{} landmarks", room.points.len());
    let mut rng = Rng::new(17);
    let poses = perturbed_poses(&room, &mut rng, 0.04, 3.0);
    let points = perturbed_points(&room, &mut rng, 0.05);
    let priors = exact_priors(&room, odometry_information(0.01, 0.01));
    let mut w = Box::new(Window::new());
    fill(&mut w, &poses, &points, &room.obs, &priors);
    let summary = w
        .solve(&room.model, &room.mount, &WindowConfig::default())
        .unwrap();
    std::eprintln!("pinhole: {summary:?}");
    assert_eq!(summary.termination, Termination::Converged);
    let (pos, deg) = pose_errors(&w, &room.poses);
    assert!(pos < 1e-6 && deg < 1e-5, "{pos} m, {deg} deg");
    for (l, truth) in room.points.iter().enumerate() {
        assert!((w.landmark(l).unwrap() - truth).norm() < 1e-6);
    }
}

/// Errors of a trajectory against the truth.
#[derive(Debug)]
struct Errors {
    /// RMS position error, metres.
    rms: f64,
    /// Largest heading error, degrees.
    heading_deg: f64,
    /// Scale about the first pose (1 is right).
    scale: f64,
    /// RMS position error once that scale is taken out, metres.
    shape: f64,
}

fn errors(poses: &[Se2], truth: &[Se2]) -> Errors {
    let heading_deg = poses
        .iter()
        .zip(truth)
        .map(|(p, t)| wrap_angle(p.theta - t.theta).abs().to_degrees())
        .fold(0.0, f64::max);
    let (scale, shape) = scale_and_shape(poses, truth);
    Errors {
        rms: rms_position(poses, truth),
        heading_deg,
        scale,
        shape,
    }
}

/// A noisy window: odometry with 5 mm and 1 degree of noise per 25 cm step, chained from the
/// first pose as the start; pixels with 0.5 px of noise, a share of them replaced by random
/// pixels; landmarks triangulated along the odometry chain. Returns the errors of the
/// odometry chain and of the window, the window, and which observations were made wrong.
fn noisy_run(seed: u64, outlier_share: f64) -> (Errors, Errors, Box<Window>, Vec<bool>) {
    let room = room(7);
    let mut rng = Rng::new(seed);
    let (sigma_xy, sigma_theta) = (0.005, 1f64.to_radians());
    let info = odometry_information(sigma_xy, sigma_theta);
    // Odometry: each true step with noise; dead reckoning chains them from the first pose.
    let mut priors = Vec::new();
    let mut chain = std::vec![room.poses[0]];
    for (k, pair) in room.poses.windows(2).enumerate() {
        let t = pair[0].between(&pair[1]);
        let z = Se2::new(
            t.x + sigma_xy * gauss(&mut rng),
            t.y + sigma_xy * gauss(&mut rng),
            t.theta + sigma_theta * gauss(&mut rng),
        );
        priors.push(MotionPrior {
            from: k,
            to: k + 1,
            motion: z,
            information: info,
        });
        let last = chain[k];
        chain.push(last.compose(&z));
    }
    // Pixels with 0.5 px of noise; a share of them replaced by random pixels.
    let mut outlier = Vec::new();
    let obs: Vec<PixelObservation> = room
        .obs
        .iter()
        .map(|o| {
            let wrong = uniform(&mut rng, 0.0, 1.0) < outlier_share;
            let px = if wrong {
                Vector2::new(
                    uniform(&mut rng, 0.0, WIDTH),
                    uniform(&mut rng, 0.0, HEIGHT),
                )
            } else {
                o.px + Vector2::new(0.5 * gauss(&mut rng), 0.5 * gauss(&mut rng))
            };
            // A random pixel near the true one is not wrong.
            outlier.push(wrong && (px - o.px).norm() > 5.0);
            PixelObservation { px, ..*o }
        })
        .collect();
    // Landmarks triangulated from the first and last views along the odometry chain.
    let loose = TriangulateConfig {
        max_relative_depth_error: 0.5,
        gap_sigmas: 1e6,
    };
    let points: Vec<Vector3<f64>> = (0..room.points.len())
        .map(|l| {
            let seen: Vec<&PixelObservation> = obs.iter().filter(|o| o.landmark == l).collect();
            let (a, b) = (seen[0], seen[seen.len() - 1]);
            let view = |o: &PixelObservation| {
                let pose = CameraPose::of_robot(&chain[o.keyframe], &room.mount);
                let ob = Observation {
                    px: o.px,
                    sigma_px: o.sigma_px,
                };
                (pose, ob)
            };
            let ((pa, oa), (pb, ob)) = (view(a), view(b));
            match triangulate(&room.model, &pa, &oa, &pb, &ob, &loose) {
                Ok(p) if (p.position - room.points[l]).norm() < 1.0 => p.position,
                // No usable pair (an outlier among them): a guess half a metre off.
                _ => room.points[l] + Vector3::new(0.3, -0.3, 0.3),
            }
        })
        .collect();
    let mut w = Box::new(Window::new());
    fill(&mut w, &chain, &points, &obs, &priors);
    let summary = w
        .solve(&room.model, &room.mount, &WindowConfig::default())
        .unwrap();
    std::eprintln!("seed {seed}, outliers {outlier_share}: {summary:?}");
    let solved: Vec<Se2> = (0..room.poses.len()).map(|k| w.pose(k).unwrap()).collect();
    let (odometry, window) = (errors(&chain, &room.poses), errors(&solved, &room.poses));
    std::eprintln!("seed {seed}: odometry {odometry:?}\n        window {window:?}");
    (odometry, window, w, outlier)
}

/// Test 2: 0.5 px of pixel noise; odometry with 5 mm and 1 degree per 25 cm step. The
/// heading is where the images help most; the position error left is nearly all scale, which
/// one camera cannot see and the window takes from the odometry.
#[test]
fn noisy_pixels_and_odometry_beat_the_odometry_alone() {
    let (mut odo_rms, mut win_rms, mut win_shape) = (0.0, 0.0, 0.0);
    for seed in 1..=4 {
        let (odo, win, _, _) = noisy_run(seed, 0.0);
        assert!(win.heading_deg < 0.1 && win.heading_deg < 0.05 * odo.heading_deg);
        assert!(win.rms < 0.5 * odo.rms, "seed {seed}");
        assert!(
            win.shape < 3e-3 && win.shape < 0.5 * odo.shape,
            "seed {seed}"
        );
        assert!((win.scale - 1.0).abs() < 0.01, "seed {seed}");
        odo_rms += odo.rms / 4.0;
        win_rms += win.rms / 4.0;
        win_shape += win.shape / 4.0;
    }
    std::eprintln!(
        "mean RMS: odometry {odo_rms:.4} m, window {win_rms:.4} m, shape {win_shape:.5} m"
    );
    assert!(win_rms < 0.4 * odo_rms);
}

/// Test 4: one observation in ten replaced by a random pixel.
#[test]
fn random_pixels_are_flagged_and_do_not_pull_the_poses_away() {
    for seed in 11..=13 {
        let (odo, win, w, wrong) = noisy_run(seed, 0.1);
        assert!(win.heading_deg < 0.15 && win.heading_deg < 0.1 * odo.heading_deg);
        assert!(win.rms < 0.6 * odo.rms, "seed {seed}");
        assert!(
            win.shape < 3e-3 && (win.scale - 1.0).abs() < 0.015,
            "seed {seed}"
        );
        let (mut caught, mut missed, mut false_alarms, mut good) = (0, 0, 0, 0);
        for (i, &is_wrong) in wrong.iter().enumerate() {
            let r = w.observation_report(i).unwrap();
            let flagged = r.status != ObservationStatus::Inlier;
            match (is_wrong, flagged) {
                (true, true) => caught += 1,
                (true, false) => missed += 1,
                (false, true) => false_alarms += 1,
                (false, false) => good += 1,
            }
        }
        std::eprintln!(
            "seed {seed}: {caught} outliers flagged, {missed} missed, {false_alarms} good ones \
             flagged, {good} good ones kept"
        );
        assert!(caught > 50 && missed * 20 <= caught, "{caught} / {missed}");
        // A 95 % gate flags about one right observation in twenty by design.
        let right = false_alarms + good;
        assert!(false_alarms * 100 <= 7 * right, "{false_alarms} / {right}");
    }
}

/// Test 3: the step through the Schur complement equals the step of the full normal
/// equations, with robust weights below one and priors included.
#[test]
fn schur_step_equals_the_dense_normal_equations_step() {
    let room = room(3);
    let mut rng = Rng::new(3);
    let poses = perturbed_poses(&room, &mut rng, 0.03, 2.0);
    let mut points = perturbed_points(&room, &mut rng, 0.05);
    points.truncate(20);
    let mut obs: Vec<PixelObservation> = room
        .obs
        .iter()
        .filter(|o| o.landmark < 20)
        .copied()
        .collect();
    // Two gross errors, so that some weights fall below one.
    obs[0].px.x += 30.0;
    obs[5].px.y -= 25.0;
    let priors = exact_priors(&room, odometry_information(0.02, 0.02));
    let mut w = Box::new(Window::new());
    fill(&mut w, &poses, &points, &obs, &priors);
    let cfg = WindowConfig::default();
    let fixed = 1;
    assert_eq!(w.prepare(&room.model, &room.mount, &cfg), obs.len());
    w.linearize(&room.model, &room.mount, fixed, cfg.huber);
    w.compute_step(fixed, 0.0).unwrap();

    // The full system: free poses first, then the landmarks.
    let np = poses.len() - fixed;
    let dim = 3 * np + 3 * points.len();
    let mut h = std::vec![std::vec![0.0f64; dim]; dim];
    let mut b = std::vec![0.0f64; dim];
    for o in &obs {
        let pose = poses[o.keyframe];
        let t = (libm::cos(pose.theta), libm::sin(pose.theta));
        let (r, jx, jl) = reprojection(
            &room.model,
            &room.mount,
            &pose,
            t,
            &points[o.landmark],
            &o.px,
        )
        .unwrap();
        let (r, jx, jl) = (r / o.sigma_px, jx / o.sigma_px, jl / o.sigma_px);
        let (wt, _) = huber(r.norm_squared(), cfg.huber);
        // One row of the Jacobian per pixel coordinate, scattered into the full width.
        for row in 0..2 {
            let mut j = std::vec![0.0f64; dim];
            if o.keyframe >= fixed {
                for c in 0..3 {
                    j[3 * (o.keyframe - fixed) + c] = jx[(row, c)];
                }
            }
            for c in 0..3 {
                j[3 * np + 3 * o.landmark + c] = jl[(row, c)];
            }
            for a in 0..dim {
                b[a] -= wt * j[a] * r[row];
                for c in 0..dim {
                    h[a][c] += wt * j[a] * j[c];
                }
            }
        }
    }
    for p in &priors {
        let (e, ja, jb) = prior_residual(p, &poses[p.from], &poses[p.to]);
        for row in 0..3 {
            let mut j = std::vec![0.0f64; dim];
            for c in 0..3 {
                if p.from >= fixed {
                    j[3 * (p.from - fixed) + c] = ja[(row, c)];
                }
                if p.to >= fixed {
                    j[3 * (p.to - fixed) + c] = jb[(row, c)];
                }
            }
            // Omega is diagonal here: row by row with its own weight.
            let info = p.information[(row, row)];
            for a in 0..dim {
                b[a] -= info * j[a] * e[row];
                for c in 0..dim {
                    h[a][c] += info * j[a] * j[c];
                }
            }
        }
    }
    let x = gauss_solve(h, b);
    let mut largest: f64 = 0.0;
    for f in 0..np {
        let step = w.poses[f + fixed].step;
        for c in 0..3 {
            largest = largest.max(step[c].abs());
            assert!(
                (step[c] - x[3 * f + c]).abs() < 1e-9,
                "pose {f}: {step} vs dense"
            );
        }
    }
    for l in 0..points.len() {
        let step = w.landmarks[l].step;
        for c in 0..3 {
            let d = x[3 * np + 3 * l + c];
            assert!((step[c] - d).abs() < 1e-9, "landmark {l}: {step} vs {d}");
        }
    }
    // A real step, not two zeros agreeing.
    assert!(largest > 1e-3, "{largest}");
}

/// Gaussian elimination with partial pivoting, for the dense reference.
fn gauss_solve(mut a: Vec<Vec<f64>>, mut b: Vec<f64>) -> Vec<f64> {
    let n = b.len();
    for c in 0..n {
        let p = (c..n)
            .max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))
            .unwrap();
        a.swap(c, p);
        b.swap(c, p);
        let pivot = a[c].clone();
        for r in (c + 1)..n {
            let f = a[r][c] / pivot[c];
            for (x, p) in a[r][c..].iter_mut().zip(&pivot[c..]) {
                *x -= f * p;
            }
            b[r] -= f * b[c];
        }
    }
    let mut x = std::vec![0.0; n];
    for r in (0..n).rev() {
        let s: f64 = ((r + 1)..n).map(|k| a[r][k] * x[k]).sum();
        x[r] = (b[r] - s) / a[r][r];
    }
    x
}

/// Test 5: inputs that fix nothing are refused or flagged, never a panic.
#[test]
fn degenerate_inputs_are_refused_or_flagged() {
    let room = room(4);
    let cfg = WindowConfig::default();
    let mut w = Box::new(Window::new());
    // An empty window.
    assert_eq!(
        w.solve(&room.model, &room.mount, &cfg),
        Err(WindowError::Empty)
    );
    // Keyframes and landmarks but nothing that relates them.
    w.push_pose(Se2::IDENTITY).unwrap();
    w.push_pose(Se2::new(0.3, 0.0, 0.0)).unwrap();
    w.push_landmark(Vector3::new(1.0, 0.0, 2.4)).unwrap();
    assert_eq!(
        w.solve(&room.model, &room.mount, &cfg),
        Err(WindowError::NoMeasurements)
    );
    // Non-finite inputs and unknown indices are refused at the door.
    let good = PixelObservation {
        keyframe: 0,
        landmark: 0,
        px: Vector2::new(100.0, 100.0),
        sigma_px: 0.5,
    };
    for bad in [
        PixelObservation {
            px: Vector2::new(f64::NAN, 1.0),
            ..good
        },
        PixelObservation {
            px: Vector2::new(1.0, f64::INFINITY),
            ..good
        },
        PixelObservation {
            sigma_px: 0.0,
            ..good
        },
        PixelObservation {
            sigma_px: f64::NAN,
            ..good
        },
    ] {
        assert_eq!(w.push_observation(bad), Err(WindowError::NotFinite));
    }
    for bad in [
        PixelObservation {
            px: Vector2::new(1e300, 1.0),
            ..good
        },
        PixelObservation {
            sigma_px: 1e-300,
            ..good
        },
        PixelObservation {
            sigma_px: 1e300,
            ..good
        },
    ] {
        assert_eq!(w.push_observation(bad), Err(WindowError::OutOfRange));
    }
    assert_eq!(
        w.push_landmark(Vector3::new(0.0, 0.0, -1e300)),
        Err(WindowError::OutOfRange)
    );
    assert_eq!(
        w.push_pose(Se2::new(1e7, 0.0, 0.0)),
        Err(WindowError::OutOfRange)
    );
    assert_eq!(
        w.push_observation(PixelObservation {
            keyframe: 2,
            ..good
        }),
        Err(WindowError::UnknownKeyframe)
    );
    assert_eq!(
        w.push_observation(PixelObservation {
            landmark: 1,
            ..good
        }),
        Err(WindowError::UnknownLandmark)
    );
    assert_eq!(
        w.push_pose(Se2 {
            x: f64::NAN,
            y: 0.0,
            theta: 0.0
        }),
        Err(WindowError::NotFinite)
    );
    assert_eq!(
        w.push_landmark(Vector3::new(0.0, f64::NEG_INFINITY, 0.0)),
        Err(WindowError::NotFinite)
    );
    let prior = MotionPrior {
        from: 0,
        to: 1,
        motion: Se2::new(0.3, 0.0, 0.0),
        information: Matrix3::identity(),
    };
    assert_eq!(
        w.push_motion_prior(MotionPrior { to: 0, ..prior }),
        Err(WindowError::UnknownKeyframe)
    );
    assert_eq!(
        w.push_motion_prior(MotionPrior {
            information: Matrix3::identity() * f64::NAN,
            ..prior
        }),
        Err(WindowError::NotFinite)
    );
    assert_eq!(w.observation_count(), 0);
    // A prior that carries no information constrains nothing: no gradient, no step, no
    // factorisation of a zero matrix going wrong.
    w.push_motion_prior(MotionPrior {
        information: Matrix3::zeros(),
        motion: Se2::new(0.5, 0.1, 0.2),
        ..prior
    })
    .unwrap();
    let summary = w.solve(&room.model, &room.mount, &cfg).unwrap();
    assert_eq!((summary.iterations, summary.final_cost), (0, 0.0));
    assert_eq!(w.pose(1), Some(Se2::new(0.3, 0.0, 0.0)));
    assert_eq!(
        w.landmark_report(0).unwrap().status,
        LandmarkStatus::TooFewViews
    );

    // A real scene with four kinds of bad landmark added: seen once, seen along the same
    // ray twice (from two keyframes at one place), behind the camera, and 200 km away (no
    // parallax from 25 cm).
    let mut poses = room.poses.clone();
    let same_place = poses.len();
    poses.push(room.poses[0]);
    let mut points = room.points.clone();
    let mut obs = room.obs.clone();
    let once = points.len();
    points.push(room.points[0]);
    obs.push(PixelObservation {
        landmark: once,
        ..room.obs[0]
    });
    let same_ray = points.len();
    let p = Vector3::new(2.0, 0.2, 2.4);
    points.push(p);
    for k in [0, same_place] {
        let px = pixel_of(&room, &poses[k], &p).unwrap();
        obs.push(PixelObservation {
            keyframe: k,
            landmark: same_ray,
            px,
            sigma_px: 0.5,
        });
    }
    let behind = points.len();
    points.push(Vector3::new(-3.0, 0.0, 0.5));
    let far = points.len();
    let far_point = Vector3::new(1.0e5, 0.0, 1.7e5);
    points.push(far_point);
    for (k, pose) in poses.iter().enumerate().take(2) {
        obs.push(PixelObservation {
            keyframe: k,
            landmark: behind,
            px: Vector2::new(160.0, 120.0),
            sigma_px: 0.5,
        });
        let px = pixel_of(&room, pose, &far_point).unwrap();
        obs.push(PixelObservation {
            keyframe: k,
            landmark: far,
            px,
            sigma_px: 0.5,
        });
    }
    let mut priors = exact_priors(&room, odometry_information(0.01, 0.01));
    priors.push(MotionPrior {
        from: 0,
        to: same_place,
        motion: Se2::IDENTITY,
        information: odometry_information(0.001, 0.001),
    });
    let mut rng = Rng::new(5);
    let mut start = perturbed_poses(&room, &mut rng, 0.02, 1.0);
    start.push(room.poses[0]);
    fill(&mut w, &start, &points, &obs, &priors);
    let summary = w.solve(&room.model, &room.mount, &cfg).unwrap();
    std::eprintln!("degenerate: {summary:?}");
    let status = |l: usize| w.landmark_report(l).unwrap().status;
    assert_eq!(status(once), LandmarkStatus::TooFewViews);
    assert_eq!(status(same_ray), LandmarkStatus::NoParallax);
    assert_eq!(status(behind), LandmarkStatus::TooFewViews);
    assert_eq!(status(far), LandmarkStatus::NoParallax);
    assert_eq!(summary.skipped_landmarks, 4);
    assert!(!w.landmark_report(far).unwrap().is_inlier());
    // Set-aside landmarks stay where they were; the rest of the window is still solved.
    assert_eq!(w.landmark(far), Some(far_point));
    let (pos, deg) = pose_errors(&w, &room.poses);
    assert!(pos < 1e-6 && deg < 1e-5, "{pos} m {deg} deg");
    let behind_obs = obs.iter().position(|o| o.landmark == behind).unwrap();
    assert_eq!(
        w.observation_report(behind_obs).unwrap().status,
        ObservationStatus::NotProjectable
    );
    assert_eq!(
        w.observation_report(obs.len() - 1).unwrap().status,
        ObservationStatus::Skipped
    );
    assert_eq!(w.observation_report(obs.len()), None);
    assert_eq!(w.landmark_report(points.len()), None);
    assert_eq!(w.pose(poses.len()), None);
}

/// A window filled to every capacity solves; one more of anything is refused.
#[test]
fn a_full_window_solves_and_refuses_more() {
    let room = room(3);
    let mut w = Box::new(BundleWindow::<3, 12, 30>::new());
    for p in &room.poses {
        w.push_pose(*p).unwrap();
    }
    assert_eq!(w.push_pose(Se2::IDENTITY), Err(WindowError::Full));
    for p in room.points.iter().take(12) {
        w.push_landmark(*p + Vector3::new(0.02, -0.01, 0.03))
            .unwrap();
    }
    assert_eq!(w.push_landmark(room.points[0]), Err(WindowError::Full));
    for o in room.obs.iter().filter(|o| o.landmark < 12).take(30) {
        w.push_observation(*o).unwrap();
    }
    assert_eq!(w.observation_count(), 30);
    assert_eq!(w.push_observation(room.obs[0]), Err(WindowError::Full));
    for p in exact_priors(&room, odometry_information(0.01, 0.01)) {
        w.push_motion_prior(p).unwrap();
    }
    let extra = MotionPrior {
        from: 0,
        to: 2,
        motion: room.poses[0].between(&room.poses[2]),
        information: odometry_information(0.01, 0.01),
    };
    w.push_motion_prior(extra).unwrap();
    assert_eq!(w.push_motion_prior(extra), Err(WindowError::Full));
    // No iteration allowed, however many rounds: the start is kept and still reported on.
    let frozen = WindowConfig {
        max_iterations: 0,
        rejection_rounds: u32::MAX,
        ..WindowConfig::default()
    };
    let summary = w.solve(&room.model, &room.mount, &frozen).unwrap();
    assert_eq!(summary.termination, Termination::IterationLimit);
    assert_eq!(summary.iterations, 0);
    assert_eq!(summary.initial_cost, summary.final_cost);
    assert_eq!(
        w.landmark(0),
        Some(room.points[0] + Vector3::new(0.02, -0.01, 0.03))
    );
    let skipped = (0..30)
        .filter(|&i| w.observation_report(i).unwrap().status == ObservationStatus::Skipped)
        .count();
    assert_eq!(summary.inliers + summary.outliers + skipped, 30);
    let summary = w
        .solve(&room.model, &room.mount, &WindowConfig::default())
        .unwrap();
    assert_eq!(summary.termination, Termination::Converged);
    assert!(summary.final_cost < 1e-12);
    // Holding every pose fixed leaves only the landmarks to solve.
    let cfg = WindowConfig {
        fixed_poses: 10,
        ..WindowConfig::default()
    };
    let again = w.solve(&room.model, &room.mount, &cfg).unwrap();
    assert!(again.final_cost < 1e-12);
}

/// What each element costs, for the memory budget: the window is `N^2` reduced blocks plus
/// these per keyframe, landmark and observation.
#[test]
fn slot_sizes() {
    // Indices are `usize`: the ARMv7 target's slots are smaller than x86-64's.
    let word = size_of::<usize>();
    let (pose, landmark, observation, prior) = if word == 8 {
        (184, 256, 136, 184)
    } else {
        (184, 248, 120, 176)
    };
    assert_eq!(size_of::<PoseSlot>(), pose);
    assert_eq!(size_of::<LandmarkSlot>(), landmark);
    assert_eq!(size_of::<ObservationSlot>(), observation);
    assert_eq!(size_of::<PriorSlot>(), prior);
    // Per keyframe: its slot, a prior, a row of reduced blocks and a right-hand side; then
    // the landmarks, the observations and four counts.
    let expected =
        8 * (pose + prior + 8 * 72 + 24) + 400 * landmark + 3000 * observation + 4 * word;
    assert_eq!(size_of::<Window>(), expected);
    // The constructor runs at compile time, so the firmware can keep a window in a static.
    static SMALL: BundleWindow<2, 4, 8> = BundleWindow::new();
    assert_eq!(SMALL.pose_count() + SMALL.landmark_count(), 0);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(12))]

    /// Small random rooms (a random subset of landmarks, a random start) converge to the truth.
    #[test]
    fn small_random_windows_converge(
        seed in 0u64..1000,
        keep in 0.2f64..1.0,
        xy in 0.0f64..0.03,
        deg in 0.0f64..2.0,
    ) {
        let room = room(4);
        let mut rng = Rng::new(seed);
        let poses = perturbed_poses(&room, &mut rng, xy, deg);
        let kept: Vec<usize> = (0..room.points.len())
            .filter(|_| uniform(&mut rng, 0.0, 1.0) < keep)
            .collect();
        let points: Vec<Vector3<f64>> = perturbed_points(&room, &mut rng, 0.03)
            .into_iter()
            .enumerate()
            .filter(|(l, _)| kept.contains(l))
            .map(|(_, p)| p)
            .collect();
        let obs: Vec<PixelObservation> = room
            .obs
            .iter()
            .filter_map(|o| {
                let landmark = kept.iter().position(|&l| l == o.landmark)?;
                Some(PixelObservation { landmark, ..*o })
            })
            .collect();
        let priors = exact_priors(&room, odometry_information(0.01, 0.01));
        let mut w = Box::new(Window::new());
        fill(&mut w, &poses, &points, &obs, &priors);
        let summary = w.solve(&room.model, &room.mount, &WindowConfig::default()).unwrap();
        prop_assert_eq!(summary.termination, Termination::Converged);
        let (pos, deg) = pose_errors(&w, &room.poses);
        prop_assert!(pos < 1e-6 && deg < 1e-5, "{} m {} deg {:?}", pos, deg, summary);
    }
}
