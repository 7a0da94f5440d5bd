//! The built-in worlds: a 352 m^2 home, a 1000 m^2 office floor with repeated cubicle
//! partitions and a 12,800 m^2 airport hall. `cloi sim --world NAME --dump-world FILE` writes
//! any of them as a TOML world file to start your own from.

use toml::Spanned;

use crate::world::{
    BoxSpec, CeilingSpec, FaultKind, FaultSpec, FeatureKind, FeatureSpec, LegSpec, Material,
    OdometrySpec, PosterSpec, RegionKind, RegionSpec, RobotKind, RouteSpec, WallSpec, WorldFile,
    P2,
};

/// Names of the built-in worlds.
pub const NAMES: [&str; 3] = ["home", "office", "airport"];

pub(crate) fn sp<T>(v: T) -> Spanned<T> {
    Spanned::new(0..0, v)
}

/// A straight wall from `a` to `b` (axis-aligned) with door gaps given as intervals along it.
pub(crate) fn wall_with_doors(
    walls: &mut Vec<Spanned<WallSpec>>,
    a: P2,
    b: P2,
    doors: &[(f64, f64)],
) {
    let axis = if (a[0] - b[0]).abs() > (a[1] - b[1]).abs() {
        0
    } else {
        1
    };
    let mut pos = a[axis];
    let end = b[axis];
    let at = |v: f64| {
        let mut p = a;
        p[axis] = v;
        p
    };
    for &(d0, d1) in doors {
        if d0 > pos {
            walls.push(sp(plain_wall(vec![at(pos), at(d0)], Material::Wall)));
        }
        pos = d1;
    }
    if end > pos {
        walls.push(sp(plain_wall(vec![at(pos), at(end)], Material::Wall)));
    }
}

pub(crate) fn plain_wall(points: Vec<P2>, material: Material) -> WallSpec {
    WallSpec {
        name: None,
        points,
        closed: false,
        material,
        height: None,
    }
}

pub(crate) fn boxed(min: P2, max: P2, material: Material, height: f64) -> Spanned<BoxSpec> {
    sp(BoxSpec {
        name: None,
        min,
        max,
        angle: 0.0,
        material,
        height: Some(height),
    })
}

pub(crate) fn feature(kind: FeatureKind, c: P2, size: P2) -> Spanned<FeatureSpec> {
    sp(FeatureSpec {
        kind,
        min: [c[0] - size[0] / 2.0, c[1] - size[1] / 2.0],
        max: [c[0] + size[0] / 2.0, c[1] + size[1] / 2.0],
    })
}

pub(crate) fn poster(a: P2, b: P2) -> Spanned<PosterSpec> {
    sp(PosterSpec {
        a,
        b,
        bottom: 1.1,
        top: 1.9,
    })
}

pub(crate) fn zigzag(min: P2, max: P2, spacing: f64, vertical: bool) -> LegSpec {
    LegSpec::Zigzag {
        min,
        max,
        spacing,
        vertical,
    }
}

pub(crate) fn waypoints(points: &[P2]) -> LegSpec {
    LegSpec::Waypoints {
        points: points.to_vec(),
    }
}

/// The default fault schedule, placed at fractions of the run.
pub fn default_faults(duration: f64) -> Vec<Spanned<FaultSpec>> {
    let at = |a: f64, b: f64, kind: FaultKind| {
        sp(FaultSpec {
            start: a * duration,
            end: b * duration,
            kind,
        })
    };
    vec![
        at(
            0.30,
            0.40,
            FaultKind::DirtyLens {
                camera: Some(0),
                blur: 3.0,
                drop: 0.2,
            },
        ),
        at(0.50, 0.55, FaultKind::LidarOutage),
        at(
            0.60,
            0.65,
            FaultKind::Slip {
                scale: 1.08,
                noise: 0.03,
            },
        ),
        at(0.70, 0.80, FaultKind::OptimizerDelay { delay: 2.0 }),
    ]
}

/// A built-in world by name, with its fault schedule fitted to `duration` seconds.
pub fn builtin(name: &str, duration: f64) -> Option<WorldFile> {
    let mut w = match name {
        "home" => home(),
        "office" => office(),
        "airport" => airport(),
        _ => return None,
    };
    w.faults = default_faults(duration);
    Some(w)
}

/// A 22 m x 16 m flat (352 m^2): living room, kitchen, bathroom, utility room, three bedrooms
/// off a corridor; furniture against the walls, a carpet that makes the wheels slip.
pub fn home() -> WorldFile {
    let mut walls = vec![sp(WallSpec {
        name: None,
        points: vec![[0.0, 0.0], [22.0, 0.0], [22.0, 16.0], [0.0, 16.0]],
        closed: true,
        material: Material::Wall,
        height: None,
    })];
    wall_with_doors(
        &mut walls,
        [0.0, 7.0],
        [22.0, 7.0],
        &[(3.0, 7.0), (12.0, 13.0), (17.0, 18.0), (20.0, 21.0)],
    );
    wall_with_doors(
        &mut walls,
        [0.0, 9.0],
        [22.0, 9.0],
        &[(5.0, 6.0), (10.0, 11.0), (17.0, 18.0)],
    );
    for x in [10.0, 16.0, 19.0] {
        walls.push(sp(plain_wall(vec![[x, 0.0], [x, 7.0]], Material::Wall)));
    }
    for x in [7.0, 14.0] {
        walls.push(sp(plain_wall(vec![[x, 9.0], [x, 16.0]], Material::Wall)));
    }
    let f = Material::Furniture;
    let mut boxes = vec![
        // Living room: sofa, TV cabinet, armchair, side table legs.
        boxed([0.3, 0.3], [3.5, 1.2], f, 0.45),
        boxed([9.4, 1.5], [9.8, 5.0], f, 0.5),
        boxed([0.3, 4.5], [1.2, 5.5], f, 0.45),
        // Kitchen: counter, fridge.
        boxed([10.05, 0.05], [15.95, 0.65], f, 0.9),
        boxed([15.2, 5.8], [15.95, 6.95], f, 1.8),
        // Bathroom: tub, toilet, sink cabinet.
        boxed([16.05, 0.05], [18.95, 0.8], f, 0.55),
        boxed([18.3, 3.0], [18.95, 3.6], f, 0.4),
        boxed([16.05, 4.0], [16.6, 5.0], f, 0.85),
        // Utility: washing machine, shelves.
        boxed([21.3, 0.05], [21.95, 0.7], f, 0.85),
        boxed([19.05, 0.05], [19.5, 3.0], f, 1.8),
        // Bedroom 3: bed, wardrobe, night stands.
        boxed([18.0, 13.0], [20.0, 15.95], f, 0.5),
        boxed([14.05, 14.5], [16.0, 15.95], f, 2.0),
        boxed([17.4, 15.4], [17.9, 15.95], f, 0.5),
        boxed([20.1, 15.4], [20.6, 15.95], f, 0.5),
        // Bedroom 2: bed, desk.
        boxed([8.0, 12.5], [10.0, 15.95], f, 0.5),
        boxed([12.5, 14.8], [13.95, 15.95], f, 0.75),
        // Bedroom 1: bed, wardrobe.
        boxed([1.0, 12.5], [3.0, 15.95], f, 0.5),
        boxed([0.05, 9.05], [0.7, 11.5], f, 2.0),
    ];
    // Side table: four legs.
    for (x, y) in [(0.4, 2.2), (1.1, 2.2), (0.4, 3.5), (1.1, 3.5)] {
        boxes.push(boxed([x, y], [x + 0.05, y + 0.05], f, 0.6));
    }
    let light = |c: P2| feature(FeatureKind::Light, c, [0.45, 0.45]);
    let spot = |c: P2| feature(FeatureKind::Spot, c, [0.12, 0.12]);
    let features = vec![
        light([5.0, 3.5]),
        light([3.0, 3.5]),
        light([13.0, 3.5]),
        light([17.5, 3.5]),
        light([20.5, 3.5]),
        light([3.5, 12.5]),
        light([10.5, 12.5]),
        light([18.0, 12.0]),
        feature(FeatureKind::Light, [11.0, 8.0], [1.2, 0.25]),
        feature(FeatureKind::Light, [4.0, 8.0], [0.3, 0.3]),
        feature(FeatureKind::Light, [18.0, 8.0], [0.3, 0.3]),
        feature(FeatureKind::Beam, [7.0, 3.5], [0.3, 7.0]),
        feature(FeatureKind::Vent, [14.5, 1.5], [0.6, 0.3]),
        feature(FeatureKind::Vent, [18.0, 6.0], [0.3, 0.3]),
        feature(FeatureKind::Vent, [20.5, 1.0], [0.4, 0.25]),
        spot([8.0, 5.5]),
        spot([12.0, 5.0]),
        spot([5.5, 14.0]),
        spot([12.0, 11.0]),
        spot([16.0, 11.0]),
        spot([15.0, 8.0]),
    ];
    let posters = vec![
        poster([0.0, 6.0], [0.0, 6.9]),
        poster([4.0, 0.0], [5.5, 0.0]),
        poster([10.0, 2.0], [10.0, 3.2]),
        poster([22.0, 11.0], [22.0, 12.0]),
        poster([7.0, 10.0], [7.0, 11.2]),
        poster([0.0, 13.0], [0.0, 14.0]),
        poster([8.0, 9.0], [9.2, 9.0]),
        poster([14.0, 10.0], [14.0, 11.0]),
    ];
    let regions = vec![sp(RegionSpec {
        kind: RegionKind::Slip,
        min: [2.0, 2.0],
        max: [6.0, 5.0],
        velocity: [0.0, 0.0],
        scale: 1.03,
        noise: 0.02,
    })];
    let s = 0.45;
    let legs = vec![
        waypoints(&[[5.0, 8.0], [5.0, 6.6]]),
        zigzag([1.6, 1.6], [9.0, 6.6], s, false),
        waypoints(&[[5.0, 6.6], [5.0, 8.0], [12.5, 8.0], [12.5, 6.6]]),
        zigzag([10.4, 1.05], [14.8, 6.6], s, false),
        waypoints(&[[12.5, 6.6], [12.5, 8.0], [17.5, 8.0], [17.5, 6.6]]),
        zigzag([16.95, 1.15], [17.95, 6.6], s, true),
        waypoints(&[[17.5, 6.6], [17.5, 8.0], [20.5, 8.0], [20.5, 6.6]]),
        zigzag([19.85, 1.05], [21.6, 6.6], s, true),
        waypoints(&[[20.5, 6.6], [20.5, 8.0], [17.5, 8.0], [17.5, 9.45]]),
        zigzag([14.5, 9.45], [21.6, 12.6], s, false),
        waypoints(&[[17.5, 9.45], [17.5, 8.0], [10.5, 8.0], [10.5, 9.45]]),
        zigzag([7.45, 9.45], [13.55, 12.15], s, false),
        waypoints(&[[10.5, 9.45], [10.5, 8.0], [5.5, 8.0], [5.5, 9.45]]),
        zigzag([1.05, 9.45], [6.55, 12.15], s, false),
        waypoints(&[[5.5, 9.45], [5.5, 8.0], [21.5, 8.0]]),
    ];
    WorldFile {
        name: "home".into(),
        ceiling_height: 2.4,
        robot: RobotKind::Cleaner,
        ceiling: CeilingSpec {
            brightness: 0.7,
            texture: 0.12,
            tile: 0.0,
        },
        walls,
        boxes,
        features,
        posters,
        regions,
        route: sp(RouteSpec {
            start: [2.0, 8.0],
            legs,
        }),
        faults: Vec::new(),
        odometry: OdometrySpec::default(),
        changes: Vec::new(),
    }
}

/// A 40 m x 25 m office floor: three rows of six identical cubicle blocks (1.4 m partitions),
/// a suspended ceiling with a 0.6 m tile grid and a regular lattice of light panels (the
/// repetition is the point), an open area and a glass meeting room.
pub fn office() -> WorldFile {
    let mut walls = vec![sp(WallSpec {
        name: None,
        points: vec![[0.0, 0.0], [40.0, 0.0], [40.0, 25.0], [0.0, 25.0]],
        closed: true,
        material: Material::Wall,
        height: None,
    })];
    for r in 0..3 {
        let y0 = 2.0 + 5.5 * f64::from(r);
        for c in 0..6 {
            let x0 = 2.0 + 4.0 * f64::from(c);
            let part = |pts: Vec<P2>| {
                sp(WallSpec {
                    name: None,
                    points: pts,
                    closed: false,
                    material: Material::Furniture,
                    height: Some(1.4),
                })
            };
            walls.push(part(vec![[x0, y0 + 1.5], [x0 + 3.5, y0 + 1.5]]));
            walls.push(part(vec![[x0, y0], [x0, y0 + 3.0]]));
            walls.push(part(vec![[x0 + 3.5, y0], [x0 + 3.5, y0 + 3.0]]));
            walls.push(part(vec![[x0 + 1.75, y0 + 0.2], [x0 + 1.75, y0 + 2.8]]));
        }
    }
    // Glass meeting room with a door on its west side.
    walls.push(sp(WallSpec {
        name: None,
        points: vec![
            [30.0, 17.0],
            [30.0, 15.0],
            [38.0, 15.0],
            [38.0, 23.0],
            [30.0, 23.0],
            [30.0, 18.0],
        ],
        closed: false,
        material: Material::Glass,
        height: None,
    }));
    let boxes = vec![
        boxed([32.0, 18.0], [36.0, 20.0], Material::Furniture, 0.75),
        boxed([39.3, 2.0], [39.95, 8.0], Material::Furniture, 1.9),
        boxed([33.7, 11.7], [34.3, 12.3], Material::Pillar, 3.0),
    ];
    let mut features = Vec::new();
    let mut x = 1.5;
    while x < 40.0 {
        let mut y = 1.5;
        while y < 25.0 {
            features.push(feature(FeatureKind::Light, [x, y], [1.2, 0.6]));
            if (x / 2.4) as i64 % 3 == 1 {
                features.push(feature(FeatureKind::Vent, [x, y + 1.5], [0.6, 0.6]));
            }
            y += 3.0;
        }
        x += 2.4;
    }
    let posters = vec![
        poster([0.0, 3.0], [0.0, 4.5]),
        poster([40.0, 12.0], [40.0, 13.5]),
        poster([10.0, 25.0], [11.5, 25.0]),
        poster([25.0, 0.0], [26.5, 0.0]),
    ];
    let legs = vec![
        waypoints(&[
            [26.5, 1.0],
            [26.5, 6.25],
            [1.0, 6.25],
            [1.0, 11.75],
            [26.5, 11.75],
            [26.5, 17.5],
            [1.0, 17.5],
            [1.0, 22.0],
            [28.0, 22.0],
        ]),
        zigzag([27.0, 1.0], [33.0, 10.5], 0.5, false),
        waypoints(&[[26.5, 1.0]]),
    ];
    WorldFile {
        name: "office".into(),
        ceiling_height: 2.8,
        robot: RobotKind::Cleaner,
        ceiling: CeilingSpec {
            brightness: 0.75,
            texture: 0.05,
            tile: 0.6,
        },
        walls,
        boxes,
        features,
        posters,
        regions: Vec::new(),
        route: sp(RouteSpec {
            start: [1.0, 1.0],
            legs,
        }),
        faults: Vec::new(),
        odometry: OdometrySpec::default(),
        changes: Vec::new(),
    }
}

/// A 160 m x 80 m airport hall (12,800 m^2) with a 12 m ceiling: a glass facade to the north,
/// glass shop fronts, pillars, check-in islands, an 80 m moving walkway with hand rails, lights
/// and beams in the west, and a featureless east half. A guide robot tours points of interest
/// and returns to them.
pub fn airport() -> WorldFile {
    let mut walls = vec![
        sp(plain_wall(
            vec![[0.0, 80.0], [0.0, 0.0], [160.0, 0.0], [160.0, 80.0]],
            Material::Wall,
        )),
        sp(plain_wall(
            vec![[160.0, 80.0], [0.0, 80.0]],
            Material::Glass,
        )),
    ];
    // Shops along the south wall with glass fronts.
    for (x0, x1) in [(40.0, 70.0), (100.0, 130.0)] {
        walls.push(sp(plain_wall(vec![[x0, 0.0], [x0, 6.0]], Material::Wall)));
        walls.push(sp(plain_wall(vec![[x1, 0.0], [x1, 6.0]], Material::Wall)));
        walls.push(sp(plain_wall(vec![[x0, 6.0], [x1, 6.0]], Material::Glass)));
    }
    // Hand rails of the moving walkway.
    for y in [37.9, 40.1] {
        walls.push(sp(WallSpec {
            name: None,
            points: vec![[20.0, y], [100.0, y]],
            closed: false,
            material: Material::Furniture,
            height: Some(1.0),
        }));
    }
    let mut boxes = Vec::new();
    for i in 0..7 {
        let x = 35.0 + 20.0 * f64::from(i);
        for y in [25.0, 55.0] {
            boxes.push(boxed(
                [x - 0.5, y - 0.5],
                [x + 0.5, y + 0.5],
                Material::Pillar,
                12.0,
            ));
        }
    }
    for (x0, x1) in [(30.0, 60.0), (90.0, 120.0)] {
        boxes.push(boxed([x0, 68.0], [x1, 70.0], Material::Furniture, 1.1));
    }
    let mut features = Vec::new();
    // West: a lattice of lights.
    let mut x = 4.0;
    while x < 60.0 {
        let mut y = 4.0;
        while y < 80.0 {
            features.push(feature(FeatureKind::Light, [x, y], [1.5, 1.5]));
            y += 9.0;
        }
        x += 8.0;
    }
    // Middle: structural beams every 20 m.
    for i in 0..3 {
        features.push(feature(
            FeatureKind::Beam,
            [65.0 + 15.0 * f64::from(i), 40.0],
            [1.0, 80.0],
        ));
    }
    // Sparse vents over the check-in islands.
    for i in 0..6 {
        features.push(feature(
            FeatureKind::Vent,
            [35.0 + 15.0 * f64::from(i), 69.0],
            [1.2, 0.6],
        ));
    }
    let posters = vec![
        poster([45.0, 6.0], [48.0, 6.0]),
        poster([0.0, 30.0], [0.0, 33.0]),
        poster([160.0, 40.0], [160.0, 43.0]),
        poster([105.0, 6.0], [108.0, 6.0]),
    ];
    let regions = vec![sp(RegionSpec {
        kind: RegionKind::Walkway,
        min: [20.0, 38.0],
        max: [100.0, 40.0],
        velocity: [0.65, 0.0],
        scale: 1.0,
        noise: 0.0,
    })];
    let legs = vec![waypoints(&[
        [19.0, 39.0],
        [101.0, 39.0],
        [130.0, 39.0],
        [130.0, 62.0],
        [80.0, 62.0],
        [40.0, 65.0],
        [10.0, 62.0],
        [10.0, 39.0],
        [10.0, 15.0],
        [80.0, 15.0],
        [150.0, 15.0],
        [150.0, 39.0],
        [130.0, 39.0],
        [130.0, 30.0],
        [10.0, 30.0],
    ])];
    WorldFile {
        name: "airport".into(),
        ceiling_height: 12.0,
        robot: RobotKind::Guide,
        ceiling: CeilingSpec {
            brightness: 0.8,
            texture: 0.03,
            tile: 0.0,
        },
        walls,
        boxes,
        features,
        posters,
        regions,
        route: sp(RouteSpec {
            start: [10.0, 39.0],
            legs,
        }),
        faults: Vec::new(),
        odometry: OdometrySpec::default(),
        changes: Vec::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::path::route_points;
    use crate::world::World;

    #[test]
    fn builtin_worlds_are_large_enough_and_their_routes_are_collision_free() {
        for (name, min_area, clearance) in [
            ("home", 330.0, 0.15),
            ("office", 900.0, 0.15),
            ("airport", 10_000.0, 0.3),
        ] {
            let file = builtin(name, 100.0).expect("exists");
            let text = file.to_toml().expect("serialisable");
            let back = WorldFile::parse(&text, name).expect("round trip");
            let world = World::from_file(&back);
            assert!(
                world.bounding_area() >= min_area,
                "{name}: {}",
                world.bounding_area()
            );
            let pts = route_points(&world.route);
            for pair in pts.windows(2) {
                assert!(
                    world.path_is_clear(pair[0], pair[1], clearance),
                    "{name}: drive {:?} -> {:?} hits a wall",
                    pair[0],
                    pair[1]
                );
            }
        }
    }
}
