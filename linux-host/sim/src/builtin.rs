//! The built-in worlds: a 352 m^2 home, a 1000 m^2 office floor with repeated cubicle
//! partitions and a 12,800 m^2 airport hall. `cloi sim --world NAME --dump-world FILE` writes
//! any of them as a TOML world file to start your own from.

use toml::Spanned;

use crate::world::{
    BoxSpec, CeilingSpec, ChangeSpec, FaultKind, FaultSpec, FeatureKind, FeatureSpec, ItemRef,
    LegSpec, Material, OdometrySpec, PosterSpec, RegionKind, RegionSpec, RobotKind, RouteSpec,
    WallSpec, WorldFile, P2,
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

/// A named piece of furniture: changes between sessions address it by name.
fn furniture(name: &str, min: P2, max: P2, height: f64) -> Spanned<BoxSpec> {
    let mut b = boxed(min, max, Material::Furniture, height);
    b.get_mut().name = Some(name.into());
    b
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
    let mut boxes = vec![
        // Living room: sofa, TV cabinet, armchair, side table legs.
        furniture("sofa", [0.3, 0.3], [3.5, 1.2], 0.45),
        furniture("tv-cabinet", [9.4, 1.5], [9.8, 5.0], 0.5),
        furniture("armchair", [0.3, 4.5], [1.2, 5.5], 0.45),
        // Kitchen: counter, fridge.
        furniture("kitchen-counter", [10.05, 0.05], [15.95, 0.65], 0.9),
        furniture("fridge", [15.2, 5.8], [15.95, 6.95], 1.8),
        // Bathroom: tub, toilet, sink cabinet.
        furniture("bathtub", [16.05, 0.05], [18.95, 0.8], 0.55),
        furniture("toilet", [18.3, 3.0], [18.95, 3.6], 0.4),
        furniture("sink-cabinet", [16.05, 4.0], [16.6, 5.0], 0.85),
        // Utility: washing machine, shelves.
        furniture("washing-machine", [21.3, 0.05], [21.95, 0.7], 0.85),
        furniture("utility-shelves", [19.05, 0.05], [19.5, 3.0], 1.8),
        // Bedroom 3: bed, wardrobe, night stands.
        furniture("bed-3", [18.0, 13.0], [20.0, 15.95], 0.5),
        furniture("wardrobe-3", [14.05, 14.5], [16.0, 15.95], 2.0),
        furniture("nightstand-3-west", [17.4, 15.4], [17.9, 15.95], 0.5),
        furniture("nightstand-3-east", [20.1, 15.4], [20.6, 15.95], 0.5),
        // Bedroom 2: bed, desk.
        furniture("bed-2", [8.0, 12.5], [10.0, 15.95], 0.5),
        furniture("desk-2", [12.5, 14.8], [13.95, 15.95], 0.75),
        // Bedroom 1: bed, wardrobe.
        furniture("bed-1", [1.0, 12.5], [3.0, 15.95], 0.5),
        furniture("wardrobe-1", [0.05, 9.05], [0.7, 11.5], 2.0),
    ];
    // Side table: four legs.
    let f = Material::Furniture;
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
        changes: home_changes(),
    }
}

/// Three sessions of everyday change in the home, none of them in the robot's way: session 1
/// turns the armchair and slides a door across the west half of the living-room opening;
/// session 2 shifts the sofa and leaves a laundry basket in bedroom 1 and a moving box in
/// the corridor; session 3 opens the sliding door again, clears the moving box, moves the
/// desk and drops a toy box in bedroom 2.
fn home_changes() -> Vec<Spanned<ChangeSpec>> {
    let name = |n: &str| Some(ItemRef::Name(n.into()));
    let move_box = |session: u32, n: &str, dx: f64, dy: f64, angle: f64| {
        sp(ChangeSpec::Move {
            session,
            box_ref: name(n),
            wall: None,
            dx,
            dy,
            angle,
        })
    };
    let add_box = |session: u32, n: &str, min: P2, max: P2, height: f64| {
        sp(ChangeSpec::Add {
            session,
            box_spec: Some(furniture(n, min, max, height).into_inner()),
            wall: None,
        })
    };
    let sliding_door = WallSpec {
        name: Some("sliding-door".into()),
        ..plain_wall(vec![[3.0, 7.0], [4.5, 7.0]], Material::Wall)
    };
    vec![
        move_box(1, "armchair", 0.0, 0.8, 0.3),
        sp(ChangeSpec::Add {
            session: 1,
            box_spec: None,
            wall: Some(sliding_door),
        }),
        move_box(2, "sofa", 1.0, 0.0, 0.0),
        add_box(2, "laundry-basket", [4.2, 13.0], [4.7, 13.5], 0.5),
        add_box(2, "moving-box", [14.6, 8.35], [15.2, 8.85], 0.4),
        sp(ChangeSpec::Remove {
            session: 3,
            box_ref: None,
            wall: name("sliding-door"),
        }),
        sp(ChangeSpec::Remove {
            session: 3,
            box_ref: name("moving-box"),
            wall: None,
        }),
        move_box(3, "desk-2", -0.6, 0.0, 0.0),
        add_box(3, "toy-box", [10.4, 13.2], [11.0, 13.7], 0.3),
    ]
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

    fn fnv(h: &mut u64, bytes: &[u8]) {
        for &b in bytes {
            *h ^= u64::from(b);
            *h = h.wrapping_mul(0x0100_0000_01b3);
        }
    }

    fn segment_hash(world: &World) -> u64 {
        let mut h = 0xcbf2_9ce4_8422_2325;
        for s in &world.segments {
            for v in [s.a[0], s.a[1], s.b[0], s.b[1], s.height] {
                fnv(&mut h, &v.to_bits().to_le_bytes());
            }
            fnv(&mut h, &[s.material as u8]);
            fnv(&mut h, &s.texture.to_le_bytes());
        }
        h
    }

    /// Pins session 0 to the worlds as they were before worlds could change between sessions:
    /// recordings and results made earlier stay reproducible. Update a figure only when a
    /// world is changed on purpose.
    #[test]
    fn session_zero_of_the_builtin_worlds_is_unchanged() {
        for (name, segments, hash) in [
            ("home", 106, 0xcf69_b31f_068e_4a6c_u64),
            ("office", 93, 0xd7be_6e64_5c1b_8ff3),
            ("airport", 76, 0xfd83_1475_76e4_1080),
        ] {
            let file = builtin(name, 100.0).expect("exists");
            for world in [
                World::from_file(&file),
                World::at_session(&file, 0).expect("session 0"),
            ] {
                assert_eq!(world.segments.len(), segments, "{name}");
                assert_eq!(segment_hash(&world), hash, "{name}");
            }
        }
        // Worlds without changes dump to the same bytes as before.
        for (name, hash) in [
            ("office", 0x8212_a80a_d845_c818_u64),
            ("airport", 0x337f_74fb_eee3_5d79),
        ] {
            let text = builtin(name, 100.0)
                .expect("exists")
                .to_toml()
                .expect("toml");
            let mut h = 0xcbf2_9ce4_8422_2325;
            fnv(&mut h, text.as_bytes());
            assert_eq!(h, hash, "{name}:\n{text}");
        }
    }

    fn sorted_ends(world: &World) -> Vec<[u64; 4]> {
        let mut v: Vec<[u64; 4]> = world
            .segments
            .iter()
            .map(|s| [s.a[0], s.a[1], s.b[0], s.b[1]].map(f64::to_bits))
            .collect();
        v.sort_unstable();
        v
    }

    /// How many segments of `a` are not in `b` (as a multiset).
    fn missing(a: &[[u64; 4]], b: &[[u64; 4]]) -> usize {
        let mut b = b.to_vec();
        a.iter()
            .filter(|s| match b.iter().position(|t| t == *s) {
                Some(i) => {
                    b.swap_remove(i);
                    false
                }
                None => true,
            })
            .count()
    }

    #[test]
    fn home_sessions_change_the_expected_segments_and_keep_the_route_clear() {
        let file = builtin("home", 100.0).expect("exists");
        // Parsing the dump validates every change against the world it meets.
        let text = file.to_toml().expect("serialisable");
        let back = WorldFile::parse(&text, "home").expect("round trip");
        assert_eq!(back.last_session(), 3);
        let worlds: Vec<World> = (0..=4)
            .map(|n| World::at_session(&back, n).expect("applies"))
            .collect();
        for (n, w) in worlds.iter().enumerate() {
            let direct = World::at_session(&file, n as u32).expect("applies");
            assert_eq!(direct.segments, w.segments, "session {n}");
        }
        // (segments gone, segments new) from one session to the next: session 1 turns the
        // armchair and closes the sliding door; session 2 moves the sofa and adds two boxes;
        // session 3 opens the door, takes one box away, moves the desk and adds a toy box;
        // session 4 is session 3 again.
        let expected = [(4, 5), (4, 12), (9, 8), (0, 0)];
        for (n, (gone, new)) in expected.iter().enumerate() {
            let (a, b) = (sorted_ends(&worlds[n]), sorted_ends(&worlds[n + 1]));
            assert_eq!(
                (missing(&a, &b), missing(&b, &a)),
                (*gone, *new),
                "session {} -> {}",
                n,
                n + 1
            );
        }
        let door = |w: &World| {
            w.segments
                .iter()
                .any(|s| s.a == [3.0, 7.0] && s.b == [4.5, 7.0])
        };
        let doors: Vec<bool> = worlds.iter().map(door).collect();
        assert_eq!(doors, [false, true, true, false, false]);
        for (n, world) in worlds.iter().enumerate() {
            for pair in route_points(&world.route).windows(2) {
                assert!(
                    world.path_is_clear(pair[0], pair[1], 0.15),
                    "home session {n}: drive {:?} -> {:?} hits {:?}",
                    pair[0],
                    pair[1],
                    world
                        .path_blocker(pair[0], pair[1], 0.15)
                        .and_then(|s| back.describe_segment(n as u32, s))
                );
            }
            crate::command::session_world(&back, n as u32, &mut Vec::new())
                .expect("the route stays clear");
        }
    }
}
