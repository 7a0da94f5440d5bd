//! Tests of the FAST detector: the arc test, corners of synthetic shapes, repeatability
//! under rotation, bucketing and orientation.

extern crate std;

use super::super::synth::{Scene, View};
use super::*;

const W: usize = 256;
const H: usize = 192;

fn detect_all(data: &[u8], cfg: &FastConfig) -> (DetectStats, [Keypoint; 400]) {
    let img = GrayImage::new_checked(W, H, W, data).unwrap();
    let mut out = [Keypoint::default(); 400];
    (detect(&img, 0, cfg, &mut out), out)
}

#[test]
fn the_arc_test_needs_nine_contiguous_pixels() {
    assert!(has_arc(0b0000_0001_1111_1111));
    assert!(has_arc(0b1111_0000_0001_1111)); // wraps around
    assert!(!has_arc(0b0000_0001_1111_0111));
    assert!(!has_arc(0b0101_0101_0101_0101));
    assert!(has_arc(u16::MAX));
}

#[test]
fn a_bright_square_gives_its_four_corners_pointing_inwards() {
    let scene = Scene::single([128.5, 96.5], [40.0, 30.0], 200.0, 60.0);
    let data = scene.render(&View::new(W, H, 0.0, [0.0, 0.0]));
    let cfg = FastConfig {
        per_cell: 1,
        ..FastConfig::default()
    };
    let (stats, out) = detect_all(&data, &cfg);
    let kps = &out[..stats.kept];
    assert_eq!(kps.len(), 4, "{kps:?}");
    // The square spans [88.5, 168.5] x [66.5, 126.5]; inside pixels are 89..=168.
    let want = [
        ([89.0, 67.0], core::f32::consts::FRAC_PI_4),
        ([168.0, 67.0], 3.0 * core::f32::consts::FRAC_PI_4),
        ([89.0, 126.0], -core::f32::consts::FRAC_PI_4),
        ([168.0, 126.0], -3.0 * core::f32::consts::FRAC_PI_4),
    ];
    for (p, angle) in want {
        let k = kps
            .iter()
            .find(|k| (k.x - p[0]).abs() <= 1.5 && (k.y - p[1]).abs() <= 1.5);
        let k = k.unwrap_or_else(|| panic!("no corner near {p:?}: {kps:?}"));
        assert!((k.angle - angle).abs() < 0.1, "{k:?} vs {angle}");
    }
    // Level 0 is not rescanned at the lower threshold: the other cells stay empty.
    assert_eq!(
        (stats.relaxed_cells, stats.empty_cells),
        (0, stats.cells - 4)
    );
}

#[test]
fn plain_and_tiny_images_give_nothing_and_do_not_panic() {
    let flat = [90u8; W * H];
    let (stats, _) = detect_all(&flat, &FastConfig::default());
    assert_eq!(stats.kept, 0);
    assert_eq!(stats.empty_cells, stats.cells);
    let tiny = [0u8, 255, 0, 255];
    let img = GrayImage::new_checked(2, 2, 2, &tiny).unwrap();
    let mut out = [Keypoint::default(); 4];
    assert_eq!(detect(&img, 0, &FastConfig::default(), &mut out).kept, 0);
    assert_eq!(corner_score(&img, -5, 1, 10), None);
    assert_eq!(corner_score(&img, i32::MAX, i32::MIN, 10), None);
    assert_eq!(orientation(&img, 1, 1), None);
}

#[test]
fn a_weak_corner_is_found_by_the_fallback_threshold() {
    // Contrast 12: below the threshold of 20, above the fallback of 7.
    let scene = Scene::single([128.5, 96.5], [40.0, 30.0], 72.0, 60.0);
    let data = scene.render(&View::new(W, H, 0.0, [0.0, 0.0]));
    let img = GrayImage::new_checked(W, H, W, &data).unwrap();
    let mut out = [Keypoint::default(); 400];
    let stats = detect(&img, 1, &FastConfig::default(), &mut out);
    assert_eq!(stats.kept, 4);
    assert_eq!(stats.relaxed_cells, stats.cells);
    let strict = FastConfig {
        min_threshold: 20,
        ..FastConfig::default()
    };
    assert_eq!(detect(&img, 1, &strict, &mut out).kept, 0);
    // Level 0, with the sensor's full noise, is not relaxed unless asked.
    assert_eq!(detect_all(&data, &FastConfig::default()).0.kept, 0);
    let everywhere = FastConfig {
        relax_from_level: 0,
        ..FastConfig::default()
    };
    assert_eq!(detect_all(&data, &everywhere).0.kept, 4);
}

#[test]
fn bucketing_bounds_every_cell_and_output_overflow_is_counted() {
    let data = Scene::random(7, W, H, 120).render(&View::new(W, H, 0.0, [0.0, 0.0]));
    let cfg = FastConfig::default();
    let (stats, out) = detect_all(&data, &cfg);
    assert!(stats.kept > 60, "{stats:?}");
    for cell_y in 0..(H - 2 * BORDER).div_ceil(cfg.cell_size) {
        for cell_x in 0..(W - 2 * BORDER).div_ceil(cfg.cell_size) {
            let in_cell = out[..stats.kept]
                .iter()
                .filter(|k| {
                    (k.x as usize - BORDER) / cfg.cell_size == cell_x
                        && (k.y as usize - BORDER) / cfg.cell_size == cell_y
                })
                .count();
            assert!(in_cell <= cfg.per_cell);
        }
    }
    let img = GrayImage::new_checked(W, H, W, &data).unwrap();
    let mut small = [Keypoint::default(); 10];
    let s = detect(&img, 0, &cfg, &mut small);
    assert_eq!((s.kept, s.dropped), (10, stats.kept - 10));
}

#[test]
fn every_level_gets_its_share_and_positions_come_back_to_level_0() {
    use super::super::pyramid::pyramid_bytes;
    // Squares of 24 px: their corners survive halving.
    let scene = Scene::single([128.5, 96.5], [60.0, 45.0], 210.0, 50.0);
    let data = scene.render(&View::new(W, H, 0.0, [0.0, 0.0]));
    let img = GrayImage::new_checked(W, H, W, &data).unwrap();
    let mut store = [0u8; pyramid_bytes(W, H, 2)];
    let pyr = Pyramid::build(img, 2, &mut store).unwrap();
    let mut out = [Keypoint::default(); 20];
    let cfg = FastConfig {
        per_cell: 1,
        ..FastConfig::default()
    };
    let stats = detect_pyramid(&pyr, &cfg, &mut out);
    let kps = &out[..stats.kept];
    // Level 0 gets 4/5 of the output, level 1 the rest.
    assert!(kps.iter().filter(|k| k.level == 0).count() == 4, "{kps:?}");
    let coarse: std::vec::Vec<_> = kps.iter().filter(|k| k.level == 1).collect();
    assert_eq!(coarse.len(), 4, "{kps:?}");
    // The square's inside spans level-0 pixels 69..=188 and 52..=141.
    for k in coarse {
        let p = k.position();
        let near = |v: f32, a: f32, b: f32| (v - a).abs() <= 2.5 || (v - b).abs() <= 2.5;
        assert!(near(p[0], 69.0, 188.0) && near(p[1], 52.0, 141.0), "{p:?}");
    }
}

#[test]
fn corners_repeat_and_turn_with_a_rotated_shifted_view() {
    let scene = Scene::random(11, W, H, 120);
    let a = View::new(W, H, 0.0, [0.0, 0.0]);
    let b = View::new(W, H, 0.5, [7.3, -4.1]);
    let cfg = FastConfig::default();
    let (sa, ka) = detect_all(&scene.render(&a), &cfg);
    let (sb, kb) = detect_all(&scene.render(&b), &cfg);
    let (ka, kb) = (&ka[..sa.kept], &kb[..sb.kept]);
    let (mut visible, mut found, mut angle_ok) = (0, 0, 0);
    for k in ka {
        let p = a.map_to(&b, [k.x, k.y]);
        let m = BORDER as f32 + 2.0;
        if p[0] < m || p[1] < m || p[0] > (W as f32 - m) || p[1] > (H as f32 - m) {
            continue;
        }
        visible += 1;
        let near = kb
            .iter()
            .find(|q| (q.x - p[0]).powi(2) + (q.y - p[1]).powi(2) <= 2.0f32.powi(2));
        if let Some(q) = near {
            found += 1;
            let d = libm::remainderf(q.angle - k.angle - 0.5, 2.0 * core::f32::consts::PI);
            if d.abs() < 0.25 {
                angle_ok += 1;
            }
        }
    }
    // Bucketing keeps only the best few per cell, so a corner of one view can lose its
    // place to another in the other view; most must come back.
    assert!(visible > 40, "{visible}");
    assert!(found * 10 >= visible * 6, "{found} of {visible}");
    assert!(angle_ok * 10 >= found * 8, "{angle_ok} of {found}");
}
