//! Tests of the far search on a small simulated room.

use super::*;
use crate::frontend::csm::{search, CsmConfig};
use crate::frontend::grid::GridParams;
use crate::frontend::scan::tests::{room, scan_at};
use crate::frontend::scan::{preprocess, PreprocessConfig, ScanPoints};

const SIDE: usize = 120;

fn scan(pose: Se2, voxel: f32, out: &mut ScanPoints) {
    let mut ranges = [0.0f32; 720];
    let g = scan_at(pose, 720, &room(), &mut ranges);
    let cfg = PreprocessConfig {
        voxel_size: voxel,
        ..PreprocessConfig::default()
    };
    preprocess(&ranges, &g, &cfg, out).unwrap();
}

fn params() -> GridParams {
    GridParams {
        side: SIDE as u16,
        ..GridParams::HOME
    }
}

fn build_map(cells: &mut [i8]) -> Submap<&mut [i8]> {
    let mut map = Submap::new(Se2::new(0.5, 0.5, 0.0), params(), cells).unwrap();
    let mut s: ScanPoints = heapless::Vec::new();
    for pose in [
        Se2::IDENTITY,
        Se2::new(-0.5, 0.8, -0.3),
        Se2::new(2.0, -0.7, 1.0),
    ] {
        scan(pose, 0.0, &mut s);
        map.insert_scan(&pose, &Se2::IDENTITY, &s).unwrap();
    }
    map
}

/// The test room's submap and pyramid storage.
struct Room {
    cells: [i8; SIDE * SIDE],
    storage: [u8; SIDE * SIDE * 5],
}

impl Room {
    fn new() -> Self {
        Room {
            cells: [0; SIDE * SIDE],
            storage: [0; SIDE * SIDE * 5],
        }
    }

    /// The room mapped from three poses, and its 5-level pyramid.
    fn map_and_pyramid(&mut self) -> (Submap<&mut [i8]>, Pyramid<'_>) {
        let map = build_map(&mut self.cells);
        let pyr = Pyramid::build(&map, 5, &mut self.storage).unwrap();
        (map, pyr)
    }
}

/// A query scan of the room from `pose`, voxelised at 5 cm.
fn query_at(pose: Se2) -> ScanPoints {
    let mut query: ScanPoints = heapless::Vec::new();
    scan(pose, 0.05, &mut query);
    query
}

fn run(
    far: &mut FarSearch,
    map: &Submap<&mut [i8]>,
    pyr: &Pyramid<'_>,
    budget: u32,
) -> (Option<FarMatch>, u32) {
    let mut calls = 0;
    loop {
        calls += 1;
        match far.step(map, pyr, budget).unwrap() {
            FarStep::Working => continue,
            FarStep::Done(m) => return (m, calls),
        }
    }
}

#[test]
fn finds_a_pose_two_metres_and_a_half_turn_away_and_the_fine_search_confirms_it() {
    let mut room = Room::new();
    let (map, pyr) = room.map_and_pyramid();
    let truth = Se2::new(0.9, 0.1, 2.5);
    let query = query_at(truth);
    // Far outside any windowed search: 2.1 m and 170 degrees off.
    let seed = Se2::new(-0.8, 1.3, 2.5 - 170f64.to_radians());
    let mut far = FarSearch::new();
    far.start(&query, &seed, 3.0, &FarCsmConfig::default())
        .unwrap();
    let (m, calls) = run(&mut far, &map, &pyr, 2_000);
    let m = m.expect("a coarse match");
    assert!(calls > 1, "the budget splits the search: {calls} call(s)");
    let d = m.pose.between(&truth);
    assert!(
        libm::hypot(d.x, d.y) < 2.0 * m.cell && libm::fabs(d.theta) < 3.0 * m.angular_step,
        "{m:?}"
    );
    // The windowed fine search around the coarse pose lands on the truth.
    let cfg = CsmConfig {
        window_xy: 2.0 * m.cell,
        window_theta: 3.0 * m.angular_step,
        ..CsmConfig::default()
    };
    let fine = search(&query, &map, &pyr, &m.pose, &cfg).unwrap();
    let d = fine.pose.between(&truth);
    assert!(
        libm::hypot(d.x, d.y) < 0.06 && libm::fabs(d.theta) < 0.02,
        "{fine:?}"
    );
}

#[test]
fn the_rotation_window_bounds_the_headings_and_the_runner_up_is_a_distinct_pose() {
    let mut room = Room::new();
    let (map, pyr) = room.map_and_pyramid();
    let truth = Se2::new(0.9, 0.1, 2.5);
    let query = query_at(truth);
    let mut far = FarSearch::new();
    // Every heading: the truth, and a runner-up that scores less.
    let seed = Se2::new(0.0, 0.0, 2.5 - 1.0);
    far.start(&query, &seed, 3.0, &FarCsmConfig::default())
        .unwrap();
    let m = run(&mut far, &map, &pyr, u32::MAX).0.expect("a match");
    let d = m.pose.between(&truth);
    assert!(libm::hypot(d.x, d.y) < 2.0 * m.cell, "{m:?}");
    assert!(m.runner_up < m.score, "{m:?}");
    let every = far.evaluated();
    // Within 0.3 rad of a seed 1 rad off, the true heading is out of reach: whatever is
    // found is not the truth, and the search is cheaper.
    let narrow = FarCsmConfig {
        window_theta: 0.3,
        ..FarCsmConfig::default()
    };
    far.start(&query, &seed, 3.0, &narrow).unwrap();
    if let Some(m) = run(&mut far, &map, &pyr, u32::MAX).0 {
        assert!(libm::fabs(crate::geom::wrap_angle(m.pose.theta - seed.theta)) <= 0.31);
    }
    assert!(far.evaluated() < every, "{} vs {every}", far.evaluated());
}

#[test]
fn result_does_not_depend_on_the_budget_split() {
    let mut room = Room::new();
    let (map, pyr) = room.map_and_pyramid();
    let query = query_at(Se2::new(-0.3, 0.4, -1.0));
    let seed = Se2::new(0.6, -0.2, 1.0);
    let cfg = FarCsmConfig::default();
    let mut far = FarSearch::new();
    far.start(&query, &seed, 2.0, &cfg).unwrap();
    let (whole, one) = run(&mut far, &map, &pyr, u32::MAX);
    let total = far.evaluated();
    far.start(&query, &seed, 2.0, &cfg).unwrap();
    let (split, many) = run(&mut far, &map, &pyr, 300);
    assert_eq!(one, 1);
    assert!(many > 10, "{many}");
    assert_eq!(whole, split);
    assert_eq!(total, far.evaluated());
    assert!(whole.is_some());
}

#[test]
fn rejects_bad_input_and_reports_no_match_above_a_high_threshold() {
    let mut room = Room::new();
    let (map, pyr) = room.map_and_pyramid();
    let mut far = FarSearch::new();
    let cfg = FarCsmConfig::default();
    assert_eq!(
        far.start(&[], &Se2::IDENTITY, 1.0, &cfg),
        Err(CsmError::EmptyScan)
    );
    let query = query_at(Se2::IDENTITY);
    assert_eq!(
        far.start(&query, &Se2::new(f64::NAN, 0.0, 0.0), 1.0, &cfg),
        Err(CsmError::InvalidConfig)
    );
    assert_eq!(
        far.step(&map, &pyr, 10),
        Err(CsmError::InvalidConfig),
        "no search started"
    );
    let strict = FarCsmConfig {
        min_score: 1.0,
        ..cfg
    };
    far.start(&query, &Se2::IDENTITY, 1.0, &strict).unwrap();
    assert_eq!(run(&mut far, &map, &pyr, 5_000).0, None);
    // A base level at the pyramid's top leaves nothing to branch on.
    let top = FarCsmConfig {
        base_level: 4,
        ..cfg
    };
    far.start(&query, &Se2::IDENTITY, 1.0, &top).unwrap();
    assert_eq!(far.step(&map, &pyr, 10), Err(CsmError::InvalidConfig));
    assert!(!far.is_active());
}
