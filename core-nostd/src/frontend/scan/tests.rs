//! Tests of scan preprocessing, and the synthetic scans other front-end tests build on.

use super::*;

/// A tiny ray caster over closed polygons, for synthetic scans in tests.
pub(crate) fn ray_cast(origin: [f64; 2], angle: f64, walls: &[[f64; 4]]) -> f64 {
    let (dx, dy) = (libm::cos(angle), libm::sin(angle));
    let mut best = f64::INFINITY;
    for w in walls {
        let (ex, ey) = (w[2] - w[0], w[3] - w[1]);
        let den = dx * ey - dy * ex;
        if den.abs() < 1e-12 {
            continue;
        }
        let (ox, oy) = (w[0] - origin[0], w[1] - origin[1]);
        let t = (ox * ey - oy * ex) / den;
        let u = (ox * dy - oy * dx) / den;
        if t > 1e-9 && (0.0..=1.0).contains(&u) && t < best {
            best = t;
        }
    }
    best
}

/// Walls of a polygon given by its corners.
pub(crate) fn polygon(corners: &[[f64; 2]], out: &mut heapless::Vec<[f64; 4], 32>) {
    for i in 0..corners.len() {
        let a = corners[i];
        let b = corners[(i + 1) % corners.len()];
        out.push([a[0], a[1], b[0], b[1]]).unwrap();
    }
}

/// An L-shaped room with a pillar: rich enough geometry for matching.
pub(crate) fn room() -> heapless::Vec<[f64; 4], 32> {
    let mut w = heapless::Vec::new();
    polygon(
        &[
            [-2.0, -1.5],
            [3.0, -1.5],
            [3.0, 0.5],
            [1.5, 0.5],
            [1.5, 2.5],
            [-2.0, 2.5],
        ],
        &mut w,
    );
    polygon(
        &[[-0.8, 0.8], [-0.4, 0.8], [-0.4, 1.2], [-0.8, 1.2]],
        &mut w,
    );
    w
}

/// Ranges of a full-circle scanner with `n` beams at `pose` (sensor = robot frame).
pub(crate) fn scan_at(pose: Se2, n: usize, walls: &[[f64; 4]], out: &mut [f32]) -> BeamGeometry {
    let inc = 2.0 * core::f64::consts::PI / n as f64;
    let amin = -core::f64::consts::PI;
    for (i, r) in out.iter_mut().enumerate().take(n) {
        let a = pose.theta + amin + inc * i as f64;
        *r = ray_cast([pose.x, pose.y], a, walls) as f32;
    }
    BeamGeometry {
        angle_min: amin as f32,
        angle_increment: inc as f32,
        range_min: 0.05,
        range_max: 20.0,
        time_increment: 0.0,
    }
}

#[test]
fn bad_beams_are_counted_and_dropped() {
    let ranges = [
        1.0,
        f32::NAN,
        f32::INFINITY,
        -1.0,
        0.01,
        50.0,
        2.0,
        f32::NEG_INFINITY,
    ];
    let g = BeamGeometry {
        angle_min: 0.0,
        angle_increment: 0.1,
        range_min: 0.1,
        range_max: 30.0,
        time_increment: 0.0,
    };
    let mut out: ScanPoints<16> = heapless::Vec::new();
    let s = preprocess(&ranges, &g, &PreprocessConfig::default(), &mut out).unwrap();
    assert_eq!(s.beams, 8);
    assert_eq!(s.nan, 1);
    assert_eq!(s.infinite, 2);
    assert_eq!(s.too_short, 2);
    assert_eq!(s.too_long, 1);
    assert_eq!(s.points, 2);
    assert_eq!(out.len(), 2);
    assert!((out[0].p[0] - 1.0).abs() < 1e-6 && out[0].p[1].abs() < 1e-6);
    let a = 0.6f32;
    assert!((out[1].p[0] - 2.0 * a.cos()).abs() < 1e-5);
    // An empty scan is fine.
    let s = preprocess(&[], &g, &PreprocessConfig::default(), &mut out).unwrap();
    assert_eq!(s.points, 0);
}

proptest::proptest! {
    #[test]
    fn counts_add_up_for_any_ranges(
        ranges in proptest::collection::vec(
            proptest::prop_oneof![
                proptest::num::f32::ANY,
                -1.0f32..40.0,
            ],
            0..400,
        ),
        decimation in 0u16..4,
        voxel in proptest::prop_oneof![proptest::strategy::Just(0.0f32), 0.01f32..0.5],
    ) {
        let g = BeamGeometry {
            angle_min: -2.0,
            angle_increment: 0.01,
            range_min: 0.1,
            range_max: 30.0,
            time_increment: 0.0,
        };
        let cfg = PreprocessConfig {
            decimation,
            voxel_size: voxel,
            ..PreprocessConfig::default()
        };
        let mut out: ScanPoints<256> = heapless::Vec::new();
        let s = preprocess(&ranges, &g, &cfg, &mut out).unwrap();
        let sum = s.nan + s.infinite + s.too_short + s.too_long + s.decimated + s.overflow
            + s.voxel_merged + s.points;
        proptest::prop_assert_eq!(sum, ranges.len() as u32);
        proptest::prop_assert_eq!(s.points as usize, out.len());
        for q in out.iter() {
            proptest::prop_assert!(q.p[0].is_finite() && q.p[1].is_finite());
            let r = libm::sqrtf(q.p[0] * q.p[0] + q.p[1] * q.p[1]);
            proptest::prop_assert!(r <= 30.0 + 1e-3);
            let n = q.n[0] * q.n[0] + q.n[1] * q.n[1];
            proptest::prop_assert!(n == 0.0 || (n - 1.0).abs() < 1e-4);
        }
    }
}

#[test]
fn invalid_geometry_is_an_error() {
    let g = BeamGeometry {
        angle_min: 0.0,
        angle_increment: f32::NAN,
        range_min: 0.1,
        range_max: 30.0,
        time_increment: 0.0,
    };
    let mut out: ScanPoints<4> = heapless::Vec::new();
    assert_eq!(
        preprocess(&[1.0], &g, &PreprocessConfig::default(), &mut out),
        Err(ScanError::InvalidGeometry)
    );
}

/// Distance from `p` (world frame) to the nearest wall.
fn to_nearest_wall(p: [f64; 2], walls: &[[f64; 4]]) -> f64 {
    walls
        .iter()
        .map(|w| {
            let (ex, ey) = (w[2] - w[0], w[3] - w[1]);
            let t =
                (((p[0] - w[0]) * ex + (p[1] - w[1]) * ey) / (ex * ex + ey * ey)).clamp(0.0, 1.0);
            libm::hypot(p[0] - w[0] - t * ex, p[1] - w[1] - t * ey)
        })
        .fold(f64::INFINITY, f64::min)
}

#[test]
fn sweep_motion_puts_the_beams_of_a_turning_scan_back_on_the_walls() {
    // A robot turning at 1.5 rad/s and driving at 0.4 m/s during a 0.2 s sweep of 360
    // beams, each measured from where the robot was at its own time.
    let walls = room();
    let n = 360usize;
    let (v, w, sweep_s) = (0.4, 1.5, 0.2);
    let dt = sweep_s / (n - 1) as f64;
    let pose_at = |t: f64| Se2::new(v * t, 0.0, w * t);
    let inc = 2.0 * core::f64::consts::PI / n as f64;
    let amin = -core::f64::consts::PI;
    let mut ranges = [0.0f32; 360];
    for (i, r) in ranges.iter_mut().enumerate() {
        let p = pose_at(dt * i as f64);
        *r = ray_cast([p.x, p.y], p.theta + amin + inc * i as f64, &walls) as f32;
    }
    let g = BeamGeometry {
        angle_min: amin as f32,
        angle_increment: inc as f32,
        range_min: 0.05,
        range_max: 20.0,
        time_increment: dt as f32,
    };
    assert!((g.sweep_seconds(n) - sweep_s).abs() < 1e-6);
    // Worst distance of the scan's points, placed at the first beam's pose (the origin),
    // from the walls.
    let worst = |sweep: Se2| {
        let cfg = PreprocessConfig {
            sweep,
            ..PreprocessConfig::default()
        };
        let mut out: ScanPoints<512> = heapless::Vec::new();
        preprocess(&ranges, &g, &cfg, &mut out).unwrap();
        out.iter()
            .map(|q| to_nearest_wall([q.p[0] as f64, q.p[1] as f64], &walls))
            .fold(0.0, f64::max)
    };
    let bent = worst(Se2::IDENTITY);
    let corrected = worst(pose_at(sweep_s));
    // Uncorrected, the last beams are off by the 0.3 rad turned during the sweep.
    assert!(bent > 0.3, "{bent}");
    // Corrected at constant velocity along the chord: off by the arc's sagitta at most.
    assert!(corrected < 0.01, "{corrected}");
    // Beams without usable times give no sweep to correct.
    let untimed = BeamGeometry {
        time_increment: 0.0,
        ..g
    };
    assert_eq!(untimed.sweep_seconds(n), 0.0);
    assert_eq!(
        BeamGeometry {
            time_increment: f32::NAN,
            ..g
        }
        .sweep_seconds(n),
        0.0
    );
    assert_eq!(
        BeamGeometry {
            time_increment: 1.0,
            ..g
        }
        .sweep_seconds(n),
        0.0
    );
}

#[test]
fn mounting_offset_decimation_and_overflow() {
    let g = BeamGeometry {
        angle_min: 0.0,
        angle_increment: 0.0,
        range_min: 0.1,
        range_max: 30.0,
        time_increment: 0.0,
    };
    let cfg = PreprocessConfig {
        mounting: Se2::new(0.2, 0.1, core::f64::consts::FRAC_PI_2),
        decimation: 2,
        ..PreprocessConfig::default()
    };
    let mut out: ScanPoints<2> = heapless::Vec::new();
    let s = preprocess(&[1.0; 7], &g, &cfg, &mut out).unwrap();
    assert_eq!(s.decimated, 3);
    assert_eq!(s.overflow, 2);
    assert_eq!(out.len(), 2);
    // Beam along the sensor x axis = robot y axis, from (0.2, 0.1).
    assert!((out[0].p[0] - 0.2).abs() < 1e-6 && (out[0].p[1] - 1.1).abs() < 1e-6);
}

#[test]
fn normals_face_the_sensor_and_voxels_merge() {
    let walls = room();
    let mut ranges = [0.0f32; 720];
    let g = scan_at(Se2::IDENTITY, 720, &walls, &mut ranges);
    let mut out: ScanPoints = heapless::Vec::new();
    let s = preprocess(&ranges, &g, &PreprocessConfig::default(), &mut out).unwrap();
    assert_eq!(s.points, 720);
    assert!(s.with_normal > 650, "{s:?}");
    // Points on the wall y = -1.5 (away from corners) have normal (0, 1).
    let mut checked = 0;
    for q in out
        .iter()
        .filter(|q| (q.p[1] + 1.5).abs() < 1e-3 && q.p[0].abs() < 1.0)
    {
        assert!((q.n[1] - 1.0).abs() < 1e-3 && q.n[0].abs() < 0.05, "{q:?}");
        checked += 1;
    }
    assert!(checked > 20);
    let cfg = PreprocessConfig {
        voxel_size: 0.1,
        ..PreprocessConfig::default()
    };
    let s2 = preprocess(&ranges, &g, &cfg, &mut out).unwrap();
    assert_eq!(s2.points + s2.voxel_merged, 720);
    assert!(s2.points < 300, "{s2:?}");
    // One point per voxel.
    for (i, a) in out.iter().enumerate() {
        for b in &out[i + 1..] {
            assert_ne!(voxel_key(&a.p, 10.0), voxel_key(&b.p, 10.0));
        }
    }
}
