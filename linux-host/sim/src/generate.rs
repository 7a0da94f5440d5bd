//! Generated buildings (`cloi sim --world gen:SEED[:SIZE][:nogyro]`): a random floor plan from
//! a seed, assembled from the parts that break 2D SLAM (issue 15): corridor rings, round and
//! oval halls, long plain corridors, rows of identical offices behind door recesses, halls
//! wider than the LiDAR's range with a glass side, slippery floors; a route with several loops
//! and late revisits; and a cheap robot's odometry (fixed wheel scale errors up to 2 %, heading
//! drift, slip), with or without a gyro. Ground truth stays exact.
//!
//! Layout: a straight spine corridor along x; every part stands on one side of it and opens
//! onto it through gaps in the spine's wall. Each part is built in its own frame (`u` along the
//! spine, `v` away from it) and placed north or south by a mirror, so a part never overlaps the
//! spine or its neighbours. The route drives the spine east with an excursion into every part
//! (a lap of each ring and hall), then back west revisiting the two westernmost rings or halls
//! (late revisits), and ends where it started, so repeating it closes the loop again.
//!
//! Determinism: one ChaCha8 stream per seed and attempt, and only `+ - * /` and `sqrt` (exactly
//! rounded in IEEE 754) on the numbers: the ellipse's trigonometry is a local power series, so
//! the world's bytes do not depend on the platform's math library.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use toml::Spanned;

use crate::builtin::{boxed, plain_wall, sp, wall_with_doors, waypoints};
use crate::path::route_points;
use crate::world::{
    point_seg, CeilingSpec, FaultKind, FaultSpec, Material, OdometrySpec, RegionKind, RegionSpec,
    RobotKind, RouteSpec, WallSpec, World, WorldFile, P2,
};

/// A size class: the floor area (bounding box, m^2) of the building.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SizeClass {
    /// 200 to 800 m^2: a small floor (cleaning robot).
    Small,
    /// 800 to 3,000 m^2 (cleaning robot).
    Medium,
    /// 3,000 to 8,000 m^2 (cleaning robot).
    Large,
    /// 8,000 to 20,000 m^2 (guide robot with a 30 m LiDAR).
    Huge,
}

impl SizeClass {
    /// All classes, smallest first.
    pub const ALL: [SizeClass; 4] = [
        SizeClass::Small,
        SizeClass::Medium,
        SizeClass::Large,
        SizeClass::Huge,
    ];

    /// The class's name in a `gen:` spec.
    pub fn name(self) -> &'static str {
        match self {
            SizeClass::Small => "s",
            SizeClass::Medium => "m",
            SizeClass::Large => "l",
            SizeClass::Huge => "xl",
        }
    }

    /// Floor area bounds, m^2 (inclusive).
    pub fn area(self) -> (f64, f64) {
        match self {
            SizeClass::Small => (200.0, 800.0),
            SizeClass::Medium => (800.0, 3_000.0),
            SizeClass::Large => (3_000.0, 8_000.0),
            SizeClass::Huge => (8_000.0, 20_000.0),
        }
    }

    /// Perimeter bounds of the corridor ring (its centre line), metres.
    fn ring_perimeter(self) -> (f64, f64) {
        match self {
            SizeClass::Small => (40.0, 48.0),
            SizeClass::Medium => (56.0, 90.0),
            SizeClass::Large => (90.0, 160.0),
            SizeClass::Huge => (150.0, 260.0),
        }
    }
}

/// A parsed `gen:` world spec.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GenSpec {
    /// Seed of the building, its route and its robot's odometry errors.
    pub seed: u64,
    /// Requested size class (drawn from the seed when absent).
    pub size: SizeClass,
    /// Whether the robot carries a gyro.
    pub gyro: bool,
}

/// The prefix of generated-world specs.
pub const PREFIX: &str = "gen:";

/// Parses `gen:SEED[:SIZE][:nogyro]` (SIZE one of `s`, `m`, `l`, `xl`). `Ok(None)` when the
/// spec does not start with `gen:`.
///
/// # Errors
/// A seed that is not a non-negative integer, an unknown size or option.
pub fn parse_spec(spec: &str) -> Result<Option<GenSpec>, String> {
    let Some(rest) = spec.strip_prefix(PREFIX) else {
        return Ok(None);
    };
    let mut parts = rest.split(':');
    let seed_text = parts.next().unwrap_or("");
    let seed: u64 = seed_text.parse().map_err(|_| {
        format!(
            "--world {spec:?}: the seed {seed_text:?} must be an integer 0..{}",
            u64::MAX
        )
    })?;
    let mut size = None;
    let mut gyro = true;
    for p in parts {
        if let Some(c) = SizeClass::ALL.iter().find(|c| c.name() == p) {
            if size.replace(*c).is_some() {
                return Err(format!("--world {spec:?}: the size is given twice"));
            }
        } else if p == "nogyro" {
            gyro = false;
        } else {
            let names: Vec<String> = SizeClass::ALL
                .iter()
                .map(|c| {
                    let (lo, hi) = c.area();
                    format!("{} ({lo:.0}-{hi:.0} m^2)", c.name())
                })
                .collect();
            return Err(format!(
                "--world {spec:?}: unknown part {p:?}; expected gen:SEED[:SIZE][:nogyro] with \
                 SIZE one of {}",
                names.join(", ")
            ));
        }
    }
    let size = size.unwrap_or(SizeClass::ALL[(seed % 4) as usize]);
    Ok(Some(GenSpec { seed, size, gyro }))
}

/// Sine and cosine by range reduction and a power series: only `+ - * /`, so the same bits on
/// every platform (the world's walls must not depend on the C library).
fn sin_cos(x: f64) -> (f64, f64) {
    const TAU: f64 = std::f64::consts::TAU;
    let k = (x / TAU).round();
    let r = x - k * TAU;
    let (mut s, mut c) = (0.0, 0.0);
    let (mut ts, mut tc) = (r, 1.0);
    for n in 0..14 {
        s += ts;
        c += tc;
        let n = f64::from(n);
        ts *= -r * r / ((2.0 * n + 2.0) * (2.0 * n + 3.0));
        tc *= -r * r / ((2.0 * n + 1.0) * (2.0 * n + 2.0));
    }
    (s, c)
}

/// Uniform in `[a, b)`.
fn uni(rng: &mut ChaCha8Rng, a: f64, b: f64) -> f64 {
    a + (b - a) * rng.random::<f64>()
}

/// Rounds to centimetres, so the dumped world reads well and stays exact.
fn cm(v: f64) -> f64 {
    (v * 100.0).round() / 100.0
}

/// The dimensions every part shares.
#[derive(Clone, Copy, Debug)]
struct Dims {
    /// Spine (and ring) corridor width.
    corridor: f64,
    /// Office door width.
    door: f64,
    /// LiDAR range of the robot.
    range: f64,
}

/// A part in its own frame: `u` along the spine from the part's start, `v` away from it.
#[derive(Default)]
struct Part {
    /// Extent along the spine.
    width: f64,
    /// Extent away from the spine.
    depth: f64,
    /// Wall polylines (with material).
    walls: Vec<(Vec<P2>, Material)>,
    /// Boxes (min, max, material, height).
    boxes: Vec<(P2, P2, Material, f64)>,
    /// Gaps in the spine's wall, `u` intervals.
    doors: Vec<(f64, f64)>,
    /// Excursions: each starts and ends on the spine's centre line at its first point's `u`
    /// (given as points inside the part; the spine points are added when placed).
    excursions: Vec<Vec<P2>>,
    /// Slippery floor rectangles.
    slips: Vec<(P2, P2)>,
}

/// A corridor ring around a solid block, entered from the spine through a wide gap.
fn ring(rng: &mut ChaCha8Rng, d: &Dims, perimeter: f64) -> Part {
    let w = d.corridor;
    // Centre-line lengths: a + b = perimeter / 2, aspect between 1 and 3.
    let half = perimeter / 2.0;
    let a = cm(half * uni(rng, 0.5, 0.75));
    let b = cm(half - a);
    let (rw, rd) = (a + w, b + w);
    let mut p = Part {
        width: rw,
        depth: rd,
        ..Part::default()
    };
    p.walls.push((
        vec![[0.0, 0.0], [0.0, rd], [rw, rd], [rw, 0.0]],
        Material::Wall,
    ));
    p.walls.push((
        vec![[w, w], [rw - w, w], [rw - w, rd - w], [w, rd - w], [w, w]],
        Material::Wall,
    ));
    let um = cm(rw / 2.0);
    p.doors.push((um - w / 2.0, um + w / 2.0));
    let c = w / 2.0;
    let ex = vec![
        [um, c],
        [rw - c, c],
        [rw - c, rd - c],
        [c, rd - c],
        [c, c],
        [um, c],
    ];
    p.excursions.push(ex);
    p
}

/// A row of identical offices, each behind a recess in the corridor wall with its door at the
/// back; the desks are alike too. Optionally glass office fronts.
fn offices(rng: &mut ChaCha8Rng, d: &Dims, count: usize, glass: bool) -> Part {
    let ow = cm(uni(rng, 3.2, 4.5).max(d.door + 1.6));
    let od = cm(uni(rng, 3.2, 5.0));
    let rec = 0.5;
    let rw = d.door + 0.6;
    let front = if glass {
        Material::Glass
    } else {
        Material::Wall
    };
    let n = count as f64;
    let visit = 1 + ((count - 1) as f64 * rng.random::<f64>()) as usize;
    let mut p = Part {
        width: ow * n,
        depth: rec + od,
        ..Part::default()
    };
    let back = rec + od;
    p.walls.push((
        vec![[0.0, 0.0], [0.0, back], [ow * n, back], [ow * n, 0.0]],
        Material::Wall,
    ));
    let mut front_doors = Vec::new();
    for k in 0..count {
        let u0 = ow * k as f64;
        let uc = u0 + ow / 2.0;
        p.doors.push((uc - rw / 2.0, uc + rw / 2.0));
        front_doors.push((uc - d.door / 2.0, uc + d.door / 2.0));
        for side in [-1.0, 1.0] {
            p.walls.push((
                vec![[uc + side * rw / 2.0, 0.0], [uc + side * rw / 2.0, rec]],
                Material::Wall,
            ));
        }
        if k > 0 {
            p.walls.push((vec![[u0, rec], [u0, back]], Material::Wall));
        }
        // A desk against the back wall, beside the office's centre line.
        p.boxes.push((
            [u0 + 0.2, back - 0.75],
            [uc - 0.4, back - 0.05],
            Material::Furniture,
            0.75,
        ));
        // The robot enters the first office and one other: two identical rooms in one run.
        if k == 0 || k == visit {
            p.excursions.push(vec![[uc, rec + od * 0.45]]);
        }
    }
    // The office fronts at the back of the recesses, with the doors.
    let mut front_walls = Vec::new();
    wall_with_doors(&mut front_walls, [0.0, rec], [ow * n, rec], &front_doors);
    for w in front_walls {
        let w = w.into_inner();
        p.walls.push((w.points, front));
    }
    p
}

/// The points of the ellipse `c + (a cos t, b sin t)` for `t` from `t0` to `t1` in `n` steps.
fn arc(c: P2, a: f64, b: f64, t0: f64, t1: f64, n: usize) -> Vec<P2> {
    (0..=n)
        .map(|i| {
            let t = t0 + (t1 - t0) * i as f64 / n as f64;
            let (s, co) = sin_cos(t);
            [c[0] + a * co, c[1] + b * s]
        })
        .collect()
}

/// A round (`a == b`) or oval hall, reached through a short passage; the robot circles inside.
fn hall(d: &Dims, a: f64, b: f64) -> Part {
    let pw = (d.door * 1.6).max(1.6);
    let gap = 1.0;
    let c = [a + 0.5, gap + b];
    let mut p = Part {
        width: 2.0 * a + 1.0,
        depth: gap + 2.0 * b,
        ..Part::default()
    };
    // The wall leaves the ellipse open where |u - c| < pw / 2 at the bottom.
    let sphi = pw / 2.0 / a;
    // Angle phi from its sine (series of asin; sphi <= 0.2).
    let phi = sphi + sphi.powi(3) / 6.0 + 3.0 * sphi.powi(5) / 40.0 + 5.0 * sphi.powi(7) / 112.0;
    let half_pi = std::f64::consts::FRAC_PI_2;
    let rim = arc(c, a, b, -half_pi + phi, 3.0 * half_pi - phi, 72);
    // The passage's side walls run from the spine's wall straight to the rim's two ends.
    let mut pts = vec![[rim[0][0], 0.0]];
    pts.extend_from_slice(&rim);
    pts.push([rim[rim.len() - 1][0], 0.0]);
    p.walls.push((pts, Material::Wall));
    p.doors.push((c[0] - pw / 2.0, c[0] + pw / 2.0));
    let mut ex = vec![[c[0], c[1] - b * 0.55]];
    ex.extend(arc(c, a * 0.55, b * 0.55, -half_pi, 3.0 * half_pi, 10));
    ex.push(c);
    ex.push([c[0], c[1] - b * 0.55]);
    p.excursions.push(ex);
    p
}

/// A hall wider than the LiDAR's range both ways, with a glass far side (when `glass`), a few
/// pillars and a slippery stretch; the robot drives round it and across its middle.
fn big_hall(rng: &mut ChaCha8Rng, d: &Dims, glass: bool) -> Part {
    let hw = cm(2.0 * d.range + uni(rng, 4.0, 14.0));
    let hd = cm(2.0 * d.range + uni(rng, 2.0, 8.0));
    let m = 3.0;
    let door = (2.0 * d.door).max(2.0);
    let uc = cm(hw / 2.0);
    let mut p = Part {
        width: hw,
        depth: hd,
        ..Part::default()
    };
    p.walls.push((vec![[hw, hd], [hw, 0.0]], Material::Wall));
    p.walls.push((vec![[0.0, 0.0], [0.0, hd]], Material::Wall));
    p.walls.push((
        vec![[0.0, hd], [hw, hd]],
        if glass {
            Material::Glass
        } else {
            Material::Wall
        },
    ));
    p.doors.push((uc - door / 2.0, uc + door / 2.0));
    let ex = vec![
        [uc, m],
        [hw - m, m],
        [hw - m, hd - m],
        [m, hd - m],
        [m, m],
        [uc, m],
        [uc, hd * 0.5],
        [uc, m],
    ];
    // Pillars where they keep 1 m from the route.
    for _ in 0..6 {
        let q = [cm(uni(rng, m, hw - m)), cm(uni(rng, m, hd - m))];
        let r = 0.3;
        let clear = ex
            .windows(2)
            .all(|s| point_seg(q, s[0], s[1]) > r * 1.5 + 1.0);
        if clear {
            p.boxes.push((
                [q[0] - r, q[1] - r],
                [q[0] + r, q[1] + r],
                Material::Pillar,
                0.0,
            ));
        }
    }
    p.slips.push(([m - 1.0, m - 1.0], [hw * 0.5, m + 1.0]));
    p.excursions.push(ex);
    p
}

/// A long plain dead-end corridor: nothing along it to fix the position in its direction.
fn plain_corridor(rng: &mut ChaCha8Rng, d: &Dims, max_len: f64) -> Part {
    let w = d.corridor;
    let len = cm(uni(rng, 15.0, 40.0).min(max_len));
    let mut p = Part {
        width: w,
        depth: len,
        ..Part::default()
    };
    p.walls.push((
        vec![[0.0, 0.0], [0.0, len], [w, len], [w, 0.0]],
        Material::Wall,
    ));
    p.doors.push((0.0, w));
    p.excursions.push(vec![[w / 2.0, len - 1.0]]);
    p
}

/// A part placed on a side of the spine, starting at `x0`.
struct Placed {
    part: Part,
    x0: f64,
    north: bool,
}

impl Placed {
    /// The part's point `q` in world coordinates (the spine spans `0 <= y <= corridor`).
    fn at(&self, q: P2, corridor: f64) -> P2 {
        if self.north {
            [self.x0 + q[0], corridor + q[1]]
        } else {
            [self.x0 + q[0], -q[1]]
        }
    }
}

/// The robot and corridor dimensions of a class.
fn dims(rng: &mut ChaCha8Rng, size: SizeClass) -> (Dims, RobotKind) {
    if size == SizeClass::Huge {
        let d = Dims {
            corridor: cm(uni(rng, 2.6, 3.4)),
            door: 1.4,
            range: 30.0,
        };
        (d, RobotKind::Guide)
    } else {
        let d = Dims {
            corridor: cm(uni(rng, 1.8, 2.6)),
            door: 1.0,
            range: 10.0,
        };
        (d, RobotKind::Cleaner)
    }
}

/// One attempt at a building of class `size`; `None` when the draw missed the class's area.
fn attempt(spec: &GenSpec, rng: &mut ChaCha8Rng) -> Option<WorldFile> {
    let size = spec.size;
    let (d, robot) = dims(rng, size);
    let (area_lo, area_hi) = size.area();
    let target = uni(rng, area_lo * 1.05, area_hi * 0.95);
    let (per_lo, per_hi) = size.ring_perimeter();
    let glass_offices = rng.random::<f64>() < 0.3;
    // The parts every building of the class has, in a random order.
    let perimeter = cm(uni(rng, per_lo, per_hi));
    let mut parts = vec![ring(rng, &d, perimeter)];
    let office_count = match size {
        SizeClass::Small => 3,
        SizeClass::Medium => 5,
        _ => 8,
    };
    parts.push(offices(rng, &d, office_count, glass_offices));
    let small = size == SizeClass::Small;
    let r = cm(uni(
        rng,
        if small { 2.5 } else { 3.0 },
        if small { 3.5 } else { 8.0 },
    ));
    parts.push(hall(&d, r, r));
    if !small {
        let a = cm(uni(
            rng,
            5.0,
            if size == SizeClass::Medium { 7.0 } else { 10.0 },
        ));
        parts.push(hall(&d, a, cm(a * uni(rng, 0.5, 0.75))));
        let glass = rng.random::<f64>() < 0.7;
        parts.push(big_hall(rng, &d, glass));
        let max_len = if size == SizeClass::Medium {
            20.0
        } else {
            40.0
        };
        parts.push(plain_corridor(rng, &d, max_len));
    }
    if matches!(size, SizeClass::Large | SizeClass::Huge) {
        parts.push(offices(rng, &d, office_count, !glass_offices));
    }
    for i in (1..parts.len()).rev() {
        let j = (rng.random::<f64>() * (i + 1) as f64) as usize;
        parts.swap(i, j.min(i));
    }
    // Place them along the spine, each on the side that is shorter so far.
    let mut ends = [2.0, 2.0]; // south, north
    let mut placed = Vec::new();
    for part in parts {
        let north = ends[1] <= ends[0];
        let side = usize::from(north);
        let x0 = cm(ends[side] + uni(rng, 1.0, if small { 3.0 } else { 6.0 }));
        ends[side] = x0 + part.width;
        placed.push(Placed { part, x0, north });
    }
    let mut depth = [0.0f64; 2];
    for p in &placed {
        let side = usize::from(p.north);
        depth[side] = depth[side].max(p.part.depth);
    }
    let span = depth[0] + d.corridor + depth[1];
    let mut length = ends[0].max(ends[1]) + 2.0;
    // Grow to the target with more identical offices and a plainer spine.
    while (length + 1.0) * span < target {
        let side = usize::from(ends[1] <= ends[0]);
        let row = offices(rng, &d, 4, glass_offices);
        let x0 = cm(ends[side] + uni(rng, 2.0, 12.0));
        let fits = row.depth <= depth[side] && (x0 + row.width + 2.0) * span <= target;
        if !fits {
            length = cm(target / span);
            break;
        }
        ends[side] = x0 + row.width;
        placed.push(Placed {
            part: row,
            x0,
            north: side == 1,
        });
        length = ends[0].max(ends[1]) + 2.0;
    }
    let length = cm(length);
    let area = length * span;
    if !(area_lo..=area_hi).contains(&area) {
        return None;
    }
    Some(assemble(spec, &d, robot, placed, length, rng))
}

/// Walls, route and odometry of the placed parts.
fn assemble(
    spec: &GenSpec,
    d: &Dims,
    robot: RobotKind,
    mut placed: Vec<Placed>,
    length: f64,
    rng: &mut ChaCha8Rng,
) -> WorldFile {
    placed.sort_by(|a, b| a.x0.total_cmp(&b.x0));
    let w = d.corridor;
    let mut walls: Vec<Spanned<WallSpec>> = Vec::new();
    let mut boxes = Vec::new();
    let mut regions = Vec::new();
    // The spine's walls with every part's gaps, and its two ends.
    for north in [false, true] {
        let mut gaps: Vec<(f64, f64)> = placed
            .iter()
            .filter(|p| p.north == north)
            .flat_map(|p| p.part.doors.iter().map(|&(a, b)| (p.x0 + a, p.x0 + b)))
            .collect();
        gaps.sort_by(|a, b| a.0.total_cmp(&b.0));
        let y = if north { w } else { 0.0 };
        wall_with_doors(&mut walls, [0.0, y], [length, y], &gaps);
    }
    walls.push(sp(plain_wall(vec![[0.0, 0.0], [0.0, w]], Material::Wall)));
    walls.push(sp(plain_wall(
        vec![[length, 0.0], [length, w]],
        Material::Wall,
    )));
    for p in &placed {
        for (pts, material) in &p.part.walls {
            let pts = pts.iter().map(|&q| p.at(q, w)).collect();
            walls.push(sp(plain_wall(pts, *material)));
        }
        for &(a, b, material, height) in &p.part.boxes {
            let (a, b) = (p.at(a, w), p.at(b, w));
            let lo = [a[0].min(b[0]), a[1].min(b[1])];
            let hi = [a[0].max(b[0]), a[1].max(b[1])];
            boxes.push(boxed(
                lo,
                hi,
                material,
                if height > 0.0 { height } else { 3.0 },
            ));
        }
        for &(a, b) in &p.part.slips {
            let (a, b) = (p.at(a, w), p.at(b, w));
            regions.push(sp(RegionSpec {
                kind: RegionKind::Slip,
                min: [a[0].min(b[0]), a[1].min(b[1])],
                max: [a[0].max(b[0]), a[1].max(b[1])],
                velocity: [0.0, 0.0],
                scale: cm(uni(rng, 1.02, 1.06)),
                noise: cm(uni(rng, 0.01, 0.04)),
            }));
        }
    }
    // A slippery stretch of the spine too.
    let sx = cm(uni(rng, 2.0, (length - 8.0).max(3.0)));
    regions.push(sp(RegionSpec {
        kind: RegionKind::Slip,
        min: [sx, 0.05],
        max: [sx + 5.0, w - 0.05],
        velocity: [0.0, 0.0],
        scale: cm(uni(rng, 1.02, 1.05)),
        noise: cm(uni(rng, 0.01, 0.03)),
    }));
    // The route: east with every excursion, then west revisiting the first parts.
    let yc = w / 2.0;
    let start = [1.0, yc];
    let mut pts = Vec::new();
    let excursion = |p: &Placed, ex: &Vec<P2>, pts: &mut Vec<P2>| {
        let first = p.at(ex[0], w);
        pts.push([first[0], yc]);
        pts.extend(ex.iter().map(|&q| p.at(q, w)));
        pts.push(first);
        pts.push([first[0], yc]);
    };
    for p in &placed {
        for ex in &p.part.excursions {
            excursion(p, ex, &mut pts);
        }
    }
    pts.push([length - 1.0, yc]);
    // Late revisits: on the way back, the two westernmost halls or rings again.
    let loops: Vec<&Placed> = placed
        .iter()
        .filter(|p| p.part.excursions.len() == 1 && p.part.excursions[0].len() > 2)
        .take(2)
        .collect();
    for p in loops.iter().rev() {
        excursion(p, &p.part.excursions[0], &mut pts);
    }
    pts.push(start);
    pts.dedup();
    // Cheap odometry: a common wheel scale error up to 2 % and a small difference between the
    // wheels (heading drift), extra noise, an uncalibrated gyro.
    let common = uni(rng, -0.019, 0.019);
    let diff = uni(rng, -0.001, 0.001);
    let odometry = OdometrySpec {
        wheel_scale_error: [common - diff / 2.0, common + diff / 2.0],
        wheel_noise: uni(rng, 0.005, 0.02),
        gyro_bias: uni(rng, -0.004, 0.004),
        gyro: spec.gyro,
    };
    WorldFile {
        name: format!(
            "gen:{}:{}{}",
            spec.seed,
            spec.size.name(),
            if spec.gyro { "" } else { ":nogyro" }
        ),
        ceiling_height: if robot == RobotKind::Guide { 8.0 } else { 2.8 },
        robot,
        ceiling: CeilingSpec::default(),
        walls,
        boxes,
        features: Vec::new(),
        posters: Vec::new(),
        regions,
        route: sp(RouteSpec {
            start,
            legs: vec![waypoints(&pts)],
        }),
        faults: Vec::new(),
        odometry,
        changes: Vec::new(),
    }
}

/// Clearance the route keeps from walls: the robot's radius plus a margin.
pub fn clearance(robot: RobotKind) -> f64 {
    match robot {
        RobotKind::Cleaner => 0.15,
        RobotKind::Guide => 0.3,
    }
}

/// The building of `spec`, its wheel-slip fault fitted to `duration` seconds.
///
/// # Errors
/// Only if no attempt lands in the class or a route would touch a wall (a generator bug,
/// reported rather than simulated).
pub fn generate(spec: &GenSpec, duration: f64) -> Result<WorldFile, String> {
    for attempt_no in 0..64u64 {
        let mut rng = ChaCha8Rng::seed_from_u64(
            spec.seed
                .wrapping_mul(0x9E37_79B9_7F4A_7C15)
                .wrapping_add(attempt_no.wrapping_mul(0xD1B5_4A32_D192_ED03))
                ^ (spec.size as u64),
        );
        let Some(mut file) = attempt(spec, &mut rng) else {
            continue;
        };
        file.validate()
            .map_err(|(_, m)| format!("generated world {}: {m}", file.name))?;
        let world = World::from_file(&file);
        let c = clearance(file.robot);
        let pts = route_points(&world.route);
        if let Some(pair) = pts.windows(2).find(|p| !world.path_is_clear(p[0], p[1], c)) {
            return Err(format!(
                "generated world {}: the route {:?} -> {:?} passes closer than {c} m to a wall",
                file.name, pair[0], pair[1]
            ));
        }
        // A stretch of wheel slip wherever the robot is, past the middle of the run.
        file.faults = vec![sp(FaultSpec {
            start: 0.55 * duration,
            end: 0.6 * duration,
            kind: FaultKind::Slip {
                scale: 1.06,
                noise: 0.03,
            },
        })];
        return Ok(file);
    }
    Err(format!(
        "gen:{}:{}: no layout in {} attempts fits the size class",
        spec.seed,
        spec.size.name(),
        64
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn series_sine_and_cosine_match_the_library() {
        for i in -40..=40 {
            let x = f64::from(i) * 0.37;
            let (s, c) = sin_cos(x);
            assert!(
                (s - x.sin()).abs() < 1e-12 && (c - x.cos()).abs() < 1e-12,
                "{x}"
            );
        }
    }

    #[test]
    fn specs_parse_and_bad_ones_are_refused_with_the_reason() {
        let g = parse_spec("gen:17:m:nogyro").expect("ok").expect("gen");
        assert_eq!((g.seed, g.size, g.gyro), (17, SizeClass::Medium, false));
        let g = parse_spec("gen:5").expect("ok").expect("gen");
        assert_eq!((g.size, g.gyro), (SizeClass::ALL[1], true));
        assert_eq!(parse_spec("office"), Ok(None));
        for (bad, why) in [
            ("gen:", "seed"),
            ("gen:-3", "seed"),
            ("gen:1.5", "seed"),
            ("gen:99999999999999999999999", "seed"),
            ("gen:3:huge", "unknown part"),
            ("gen:3:s:m", "twice"),
        ] {
            let e = parse_spec(bad).expect_err(bad);
            assert!(e.contains(why), "{bad}: {e}");
        }
    }

    #[test]
    fn a_seed_gives_the_same_world_and_route_and_another_seed_another() {
        let spec = |seed| {
            parse_spec(&format!("gen:{seed}:m"))
                .expect("ok")
                .expect("gen")
        };
        let a = generate(&spec(7), 600.0)
            .expect("a")
            .to_toml()
            .expect("toml");
        let b = generate(&spec(7), 600.0)
            .expect("b")
            .to_toml()
            .expect("toml");
        let c = generate(&spec(8), 600.0)
            .expect("c")
            .to_toml()
            .expect("toml");
        assert_eq!(a, b);
        assert_ne!(a, c);
        // The dumped world reads back as the same world.
        let back = WorldFile::parse(&a, "gen").expect("parses");
        assert_eq!(back.to_toml().expect("toml"), a);
    }

    #[test]
    fn twenty_seeds_give_worlds_in_their_class_with_clear_routes_inside_the_bounds() {
        for seed in 0..20u64 {
            for size in SizeClass::ALL {
                for gyro in [true, false] {
                    let spec = GenSpec { seed, size, gyro };
                    let file = generate(&spec, 900.0)
                        .unwrap_or_else(|e| panic!("seed {seed} {size:?}: {e}"));
                    let world = World::from_file(&file);
                    let area = world.bounding_area();
                    let (lo, hi) = size.area();
                    assert!(
                        (lo..=hi).contains(&area),
                        "seed {seed} {size:?}: area {area}"
                    );
                    let pts = route_points(&world.route);
                    assert!(
                        pts.len() > 10,
                        "seed {seed}: a route of {} points",
                        pts.len()
                    );
                    let c = clearance(world.robot);
                    for pair in pts.windows(2) {
                        assert!(
                            world.path_is_clear(pair[0], pair[1], c),
                            "seed {seed} {size:?}: {:?} -> {:?}",
                            pair[0],
                            pair[1]
                        );
                    }
                    for p in &pts {
                        let inside = (0..2).all(|k| {
                            p[k] > world.bounds_min[k] + 1.0 && p[k] < world.bounds_max[k] - 1.0
                        });
                        assert!(inside, "seed {seed} {size:?}: {p:?} outside the building");
                    }
                    assert_eq!(world.odometry.gyro, gyro);
                    let e = world.odometry.wheel_scale_error;
                    assert!(e.iter().all(|v| v.abs() <= 0.02), "{e:?}");
                    assert!(e[0] != e[1], "the wheels differ, so the heading drifts");
                    assert!(world.regions.iter().any(|r| r.kind == RegionKind::Slip));
                }
            }
        }
    }
}
