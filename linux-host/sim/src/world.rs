//! The simulated world: floor-plan segments with heights and materials, a textured ceiling with
//! features, wall posters, floor regions that disturb wheel odometry, the robot's route and the
//! fault schedule. Built from a [`WorldFile`] (the TOML format documented in
//! `docs/sim/world-format.md`) and indexed by a uniform grid so rays are cast quickly.

use std::fmt;
use std::path::Path;

use serde::{Deserialize, Serialize};

/// A point or vector in the floor plane, metres.
pub type P2 = [f64; 2];

/// What a vertical segment is made of; decides how the sensors see it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Material {
    /// Opaque, textured wall from the floor to its height.
    #[default]
    Wall,
    /// Glass: mostly invisible to the LiDAR (missing returns) and see-through for cameras.
    Glass,
    /// Low furniture (sofa, bed, cabinet); hit by the LiDAR if taller than the scan plane.
    Furniture,
    /// A pillar face.
    Pillar,
}

/// The robot type; decides speeds, sensor ranges and camera tilt defaults.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum RobotKind {
    /// A home/office cleaning robot: slow, 10 m LiDAR, camera tilted 60 deg.
    #[default]
    Cleaner,
    /// An airport guide robot: faster, 30 m LiDAR, cameras tilted 45 deg.
    Guide,
}

/// The kind of a ceiling feature.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FeatureKind {
    /// A bright, emissive light panel.
    Light,
    /// An air vent: a grille of dark slots.
    Vent,
    /// A structural beam: a darker band with edges.
    Beam,
    /// A small round fixture (sprinkler, smoke detector, spot light).
    Spot,
}

// ---------------------------------------------------------------------------------------------
// File format
// ---------------------------------------------------------------------------------------------

/// The serialised world (TOML). Every list is optional; see `docs/sim/world-format.md`.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorldFile {
    /// A human-readable name.
    pub name: String,
    /// Ceiling height above the floor, metres.
    pub ceiling_height: f64,
    /// Which robot drives in this world.
    #[serde(default)]
    pub robot: RobotKind,
    /// Ceiling appearance.
    #[serde(default)]
    pub ceiling: CeilingSpec,
    /// Wall polylines.
    #[serde(default, rename = "wall")]
    pub walls: Vec<toml::Spanned<WallSpec>>,
    /// Axis-aligned boxes (furniture, pillars, glass booths).
    #[serde(default, rename = "box")]
    pub boxes: Vec<toml::Spanned<BoxSpec>>,
    /// Ceiling features.
    #[serde(default, rename = "feature")]
    pub features: Vec<toml::Spanned<FeatureSpec>>,
    /// Posters on walls.
    #[serde(default, rename = "poster")]
    pub posters: Vec<toml::Spanned<PosterSpec>>,
    /// Floor regions that disturb wheel odometry.
    #[serde(default, rename = "region")]
    pub regions: Vec<toml::Spanned<RegionSpec>>,
    /// The route the robot drives (repeated until the duration is reached).
    pub route: toml::Spanned<RouteSpec>,
    /// Time-scheduled faults.
    #[serde(default, rename = "fault")]
    pub faults: Vec<toml::Spanned<FaultSpec>>,
    /// The robot's odometry sensors, when they differ from the nominal rig.
    #[serde(default, skip_serializing_if = "OdometrySpec::is_nominal")]
    pub odometry: OdometrySpec,
}

/// How the robot's wheels and gyro differ from the nominal rig: a cheap robot's fixed wheel
/// scale errors (a worn or mis-sized tyre; unequal errors make the heading drift), extra wheel
/// noise, a constant gyro bias, or no gyro at all.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct OdometrySpec {
    /// Fixed scale error of the left and right wheel, added to the per-run random draw
    /// (0.01: the wheel reports 1 % more travel than it rolled).
    pub wheel_scale_error: [f64; 2],
    /// Extra wheel noise, fraction of the travel per square-root metre (added in quadrature).
    pub wheel_noise: f64,
    /// Constant gyro bias added to the random one, rad/s.
    pub gyro_bias: f64,
    /// Whether the robot carries a gyro; without one the stream has no IMU messages.
    pub gyro: bool,
}

impl Default for OdometrySpec {
    fn default() -> Self {
        OdometrySpec {
            wheel_scale_error: [0.0; 2],
            wheel_noise: 0.0,
            gyro_bias: 0.0,
            gyro: true,
        }
    }
}

impl OdometrySpec {
    /// Whether this is the nominal rig (then it is left out of a dumped world file).
    pub fn is_nominal(&self) -> bool {
        *self == OdometrySpec::default()
    }
}

/// Ceiling appearance.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CeilingSpec {
    /// Base albedo in `[0, 1]`.
    pub brightness: f64,
    /// Amplitude of the fine random texture (stains, paint), `[0, 1]`; near 0 is featureless.
    pub texture: f64,
    /// Pitch of a suspended-ceiling tile grid in metres; 0 for a plain ceiling.
    pub tile: f64,
}

impl Default for CeilingSpec {
    fn default() -> Self {
        CeilingSpec {
            brightness: 0.6,
            texture: 0.15,
            tile: 0.0,
        }
    }
}

/// A wall polyline.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WallSpec {
    /// Vertices, metres.
    pub points: Vec<P2>,
    /// Join the last vertex back to the first.
    #[serde(default)]
    pub closed: bool,
    /// Material (default `wall`).
    #[serde(default)]
    pub material: Material,
    /// Height in metres (default: the ceiling height).
    #[serde(default)]
    pub height: Option<f64>,
}

/// An axis-aligned box made of four segments.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoxSpec {
    /// Lower-left corner.
    pub min: P2,
    /// Upper-right corner.
    pub max: P2,
    /// Material (default `furniture`).
    #[serde(default = "default_box_material")]
    pub material: Material,
    /// Height in metres (default 0.8; pillars and glass default to the ceiling).
    #[serde(default)]
    pub height: Option<f64>,
}

fn default_box_material() -> Material {
    Material::Furniture
}

/// A rectangular ceiling feature.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FeatureSpec {
    /// Kind of feature.
    pub kind: FeatureKind,
    /// Lower-left corner on the ceiling.
    pub min: P2,
    /// Upper-right corner on the ceiling.
    pub max: P2,
}

/// A poster on a wall: the stretch `a`..`b` of a wall between heights `bottom` and `top`.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PosterSpec {
    /// One end on the wall line.
    pub a: P2,
    /// Other end on the wall line.
    pub b: P2,
    /// Lower edge height, metres.
    pub bottom: f64,
    /// Upper edge height, metres.
    pub top: f64,
}

/// A floor region that disturbs wheel odometry.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegionSpec {
    /// What happens in the region.
    pub kind: RegionKind,
    /// Lower-left corner.
    pub min: P2,
    /// Upper-right corner.
    pub max: P2,
    /// Walkway belt velocity in world coordinates, m/s (walkways only).
    #[serde(default)]
    pub velocity: P2,
    /// Wheel travel multiplier (slip zones only; > 1 means the wheels spin more than the robot
    /// moves).
    #[serde(default = "one")]
    pub scale: f64,
    /// Extra wheel noise, fraction of the travel per sqrt(metre) (slip zones only).
    #[serde(default)]
    pub noise: f64,
}

fn one() -> f64 {
    1.0
}

/// The kind of a floor region.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RegionKind {
    /// A moving walkway: the floor moves, wheels measure motion relative to the belt.
    Walkway,
    /// A slippery floor (wet, carpet edge): wheel travel is scaled and noisier.
    Slip,
}

/// The route: a sequence of legs, driven as straight lines with pure rotations in between and
/// repeated (as a loop) until the simulation ends.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RouteSpec {
    /// Start position; the first heading points at the first target.
    pub start: P2,
    /// Legs in order.
    pub legs: Vec<LegSpec>,
}

/// One leg of a route.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "snake_case", tag = "type")]
pub enum LegSpec {
    /// Drive through the listed points in order.
    Waypoints {
        /// Points to visit.
        points: Vec<P2>,
    },
    /// Boustrophedon (zigzag) coverage of a free rectangle with lanes along x or y.
    Zigzag {
        /// Lower-left corner of the free area.
        min: P2,
        /// Upper-right corner of the free area.
        max: P2,
        /// Lane spacing, metres.
        spacing: f64,
        /// Lanes run along y instead of x.
        #[serde(default)]
        vertical: bool,
    },
}

/// A scheduled fault.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct FaultSpec {
    /// Start, seconds from the beginning.
    pub start: f64,
    /// End, seconds from the beginning.
    pub end: f64,
    /// What goes wrong.
    #[serde(flatten)]
    pub kind: FaultKind,
}

/// What a scheduled fault does.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum FaultKind {
    /// A contaminated lens: blurred, low-contrast, smudged images and dropped frames.
    DirtyLens {
        /// Camera index (0 or 1); all cameras when absent.
        #[serde(default)]
        camera: Option<u8>,
        /// Blur radius in pixels at 320x240 (scaled with the resolution).
        #[serde(default = "default_blur")]
        blur: f64,
        /// Probability that a frame is dropped.
        #[serde(default)]
        drop: f64,
    },
    /// The LiDAR delivers no scans.
    LidarOutage,
    /// Wheel slip independent of place: wheel travel scaled and noisier.
    Slip {
        /// Wheel travel multiplier.
        scale: f64,
        /// Extra noise, fraction per sqrt(metre).
        #[serde(default)]
        noise: f64,
    },
    /// The mapper's background optimisation thread is delayed by this many seconds per step
    /// while the window lasts. Not a sensor effect: recorded for the mapper to honour.
    OptimizerDelay {
        /// Delay in seconds.
        delay: f64,
    },
}

fn default_blur() -> f64 {
    3.0
}

// ---------------------------------------------------------------------------------------------
// Errors
// ---------------------------------------------------------------------------------------------

/// A world file that could not be read, parsed or validated.
#[derive(Debug)]
pub struct WorldError {
    /// The file (or built-in name).
    pub file: String,
    /// 1-based line, when known.
    pub line: Option<usize>,
    /// What was wrong.
    pub message: String,
}

impl fmt::Display for WorldError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.line {
            Some(line) => write!(f, "{}:{}: {}", self.file, line, self.message),
            None => write!(f, "{}: {}", self.file, self.message),
        }
    }
}

impl std::error::Error for WorldError {}

/// `a > b`, false for NaN (reads better than a negated comparison).
fn greater(a: f64, b: f64) -> bool {
    a > b
}

fn line_of(text: &str, offset: usize) -> usize {
    text.as_bytes()
        .iter()
        .take(offset)
        .filter(|&&b| b == b'\n')
        .count()
        + 1
}

impl WorldFile {
    /// Parses TOML text; `file` names the source in error messages.
    ///
    /// # Errors
    /// Syntax or schema errors, and semantic errors (degenerate walls, empty routes, ...),
    /// each naming the file and the line.
    pub fn parse(text: &str, file: &str) -> Result<WorldFile, WorldError> {
        let parsed: WorldFile = toml::from_str(text).map_err(|e| WorldError {
            file: file.to_string(),
            line: e.span().map(|s| line_of(text, s.start)),
            message: e.message().trim().to_string(),
        })?;
        parsed.validate().map_err(|(span, message)| WorldError {
            file: file.to_string(),
            line: span.map(|s| line_of(text, s.start)),
            message,
        })?;
        Ok(parsed)
    }

    /// Reads and parses a world file.
    ///
    /// # Errors
    /// IO errors and everything [`WorldFile::parse`] reports.
    pub fn load(path: &Path) -> Result<WorldFile, WorldError> {
        let name = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| WorldError {
            file: name.clone(),
            line: None,
            message: format!("cannot read: {e}"),
        })?;
        WorldFile::parse(&text, &name)
    }

    /// Serialises to TOML (the built-in worlds can be dumped as examples).
    ///
    /// # Errors
    /// Only if a value cannot be represented in TOML.
    pub fn to_toml(&self) -> Result<String, toml::ser::Error> {
        toml::to_string(self)
    }

    /// Checks the values a parser cannot: returns the span of the offending item.
    pub(crate) fn validate(&self) -> Result<(), (Option<std::ops::Range<usize>>, String)> {
        let fin = |p: &P2| p[0].is_finite() && p[1].is_finite();
        if !(self.ceiling_height.is_finite() && self.ceiling_height > 0.5) {
            return Err((None, "ceiling_height must be > 0.5 m".into()));
        }
        for w in &self.walls {
            let min_pts = if w.get_ref().closed { 3 } else { 2 };
            if w.get_ref().points.len() < min_pts {
                return Err((
                    Some(w.span()),
                    format!("wall needs at least {min_pts} points"),
                ));
            }
            for pair in w.get_ref().points.windows(2) {
                if !fin(&pair[0]) || !fin(&pair[1]) || dist(pair[0], pair[1]) < 1e-6 {
                    return Err((
                        Some(w.span()),
                        "wall has a zero-length or non-finite segment".into(),
                    ));
                }
            }
            if let Some(h) = w.get_ref().height {
                if !(h > 0.0 && h.is_finite()) {
                    return Err((Some(w.span()), "wall height must be > 0".into()));
                }
            }
        }
        let rect_ok =
            |min: &P2, max: &P2| fin(min) && fin(max) && min[0] < max[0] && min[1] < max[1];
        for b in &self.boxes {
            if !rect_ok(&b.get_ref().min, &b.get_ref().max) {
                return Err((Some(b.span()), "box needs min < max".into()));
            }
        }
        for f in &self.features {
            if !rect_ok(&f.get_ref().min, &f.get_ref().max) {
                return Err((Some(f.span()), "feature needs min < max".into()));
            }
        }
        for r in &self.regions {
            let spec = r.get_ref();
            if !rect_ok(&spec.min, &spec.max)
                || !greater(spec.scale, 0.0)
                || spec.noise.is_nan()
                || spec.noise < 0.0
            {
                return Err((
                    Some(r.span()),
                    "region needs min < max, scale > 0, noise >= 0".into(),
                ));
            }
        }
        for p in &self.posters {
            let spec = p.get_ref();
            if dist(spec.a, spec.b) < 1e-3 || !greater(spec.top, spec.bottom) {
                return Err((
                    Some(p.span()),
                    "poster needs a != b and top > bottom".into(),
                ));
            }
        }
        for f in &self.faults {
            let spec = f.get_ref();
            if !(spec.start >= 0.0 && spec.end > spec.start) {
                return Err((Some(f.span()), "fault needs 0 <= start < end".into()));
            }
        }
        let o = &self.odometry;
        if !(o.wheel_scale_error.iter().all(|e| e.abs() < 0.2)
            && (0.0..0.5).contains(&o.wheel_noise)
            && o.gyro_bias.abs() < 0.1)
        {
            return Err((
                None,
                "odometry needs |wheel_scale_error| < 0.2, 0 <= wheel_noise < 0.5 and \
                 |gyro_bias| < 0.1 rad/s"
                    .into(),
            ));
        }
        let route = self.route.get_ref();
        if route.legs.is_empty() {
            return Err((Some(self.route.span()), "route has no legs".into()));
        }
        for leg in &route.legs {
            match leg {
                LegSpec::Waypoints { points } if points.is_empty() => {
                    return Err((Some(self.route.span()), "waypoints leg is empty".into()));
                }
                LegSpec::Zigzag {
                    min, max, spacing, ..
                } if !rect_ok(min, max) || !greater(*spacing, 0.05) => {
                    return Err((
                        Some(self.route.span()),
                        "zigzag needs min < max and spacing > 0.05 m".into(),
                    ));
                }
                _ => {}
            }
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------------
// Indexed world
// ---------------------------------------------------------------------------------------------

/// A vertical wall segment.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Segment {
    /// One end.
    pub a: P2,
    /// Other end.
    pub b: P2,
    /// Material.
    pub material: Material,
    /// Top edge height, metres.
    pub height: f64,
    /// Texture seed (distinct per segment).
    pub texture: u32,
}

/// A ceiling feature, indexed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Feature {
    /// Kind.
    pub kind: FeatureKind,
    /// Lower-left corner.
    pub min: P2,
    /// Upper-right corner.
    pub max: P2,
    /// Pattern seed.
    pub seed: u32,
}

/// A poster attached to a segment.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Poster {
    /// Index of the segment it hangs on.
    pub segment: usize,
    /// Start and end as fractions along the segment (`u0 < u1`).
    pub u: [f64; 2],
    /// Bottom and top heights.
    pub z: [f64; 2],
    /// Pattern seed.
    pub seed: u32,
}

/// A floor region, indexed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Region {
    /// Kind.
    pub kind: RegionKind,
    /// Lower-left corner.
    pub min: P2,
    /// Upper-right corner.
    pub max: P2,
    /// Belt velocity (walkways).
    pub velocity: P2,
    /// Wheel travel multiplier (slip).
    pub scale: f64,
    /// Extra noise (slip).
    pub noise: f64,
}

impl Region {
    /// Whether the point lies inside.
    pub fn contains(&self, p: P2) -> bool {
        p[0] >= self.min[0] && p[0] <= self.max[0] && p[1] >= self.min[1] && p[1] <= self.max[1]
    }
}

/// A uniform grid over the floor plan holding, per cell, the indices of the items overlapping
/// it (compressed rows: `start[cell]..start[cell + 1]` into `items`).
#[derive(Clone, Debug)]
pub struct Grid {
    origin: P2,
    cell: f64,
    nx: usize,
    ny: usize,
    start: Vec<u32>,
    items: Vec<u32>,
}

impl Grid {
    fn build(origin: P2, size: P2, cell: f64, boxes: &[(P2, P2)]) -> Grid {
        let nx = ((size[0] / cell).ceil() as usize).max(1);
        let ny = ((size[1] / cell).ceil() as usize).max(1);
        let mut lists: Vec<Vec<u32>> = vec![Vec::new(); nx * ny];
        for (i, (lo, hi)) in boxes.iter().enumerate() {
            let (x0, y0) = cell_of(origin, cell, nx, ny, *lo);
            let (x1, y1) = cell_of(origin, cell, nx, ny, *hi);
            for y in y0..=y1 {
                for x in x0..=x1 {
                    lists[y * nx + x].push(i as u32);
                }
            }
        }
        let mut start = Vec::with_capacity(nx * ny + 1);
        let mut items = Vec::new();
        start.push(0);
        for l in lists {
            items.extend_from_slice(&l);
            start.push(items.len() as u32);
        }
        Grid {
            origin,
            cell,
            nx,
            ny,
            start,
            items,
        }
    }

    /// Items overlapping the cell that contains `p` (empty outside the grid).
    pub fn at(&self, p: P2) -> &[u32] {
        let fx = (p[0] - self.origin[0]) / self.cell;
        let fy = (p[1] - self.origin[1]) / self.cell;
        if !(fx >= 0.0 && fy >= 0.0) {
            return &[];
        }
        let (x, y) = (fx as usize, fy as usize);
        if x >= self.nx || y >= self.ny {
            return &[];
        }
        self.cell_items(y * self.nx + x)
    }

    fn cell_items(&self, idx: usize) -> &[u32] {
        let s = self.start[idx] as usize;
        let e = self.start[idx + 1] as usize;
        &self.items[s..e]
    }
}

fn cell_of(origin: P2, cell: f64, nx: usize, ny: usize, p: P2) -> (usize, usize) {
    let x = ((p[0] - origin[0]) / cell)
        .floor()
        .clamp(0.0, (nx - 1) as f64) as usize;
    let y = ((p[1] - origin[1]) / cell)
        .floor()
        .clamp(0.0, (ny - 1) as f64) as usize;
    (x, y)
}

/// A ray hit on a segment.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Horizontal distance along the ray, metres.
    pub s: f64,
    /// Index of the segment.
    pub segment: usize,
    /// Fraction along the segment from `a` to `b`.
    pub u: f64,
}

/// The simulated world, validated and indexed.
#[derive(Clone, Debug)]
pub struct World {
    /// Name.
    pub name: String,
    /// Ceiling height.
    pub ceiling_height: f64,
    /// Robot kind.
    pub robot: RobotKind,
    /// Ceiling appearance.
    pub ceiling: CeilingSpec,
    /// Vertical segments.
    pub segments: Vec<Segment>,
    /// Ceiling features.
    pub features: Vec<Feature>,
    /// Posters (sorted by segment).
    pub posters: Vec<Poster>,
    /// Floor regions.
    pub regions: Vec<Region>,
    /// Route.
    pub route: RouteSpec,
    /// Fault schedule.
    pub faults: Vec<FaultSpec>,
    /// How the odometry sensors differ from the nominal rig.
    pub odometry: OdometrySpec,
    /// Bounding box lower-left corner.
    pub bounds_min: P2,
    /// Bounding box upper-right corner.
    pub bounds_max: P2,
    segment_grid: Grid,
    feature_grid: Grid,
    /// For each segment, `poster_start[i]..poster_start[i+1]` indexes `posters`.
    poster_start: Vec<u32>,
}

fn dist(a: P2, b: P2) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
}

impl World {
    /// Builds and indexes a world from its (validated) file form.
    pub fn from_file(file: &WorldFile) -> World {
        let h = file.ceiling_height;
        let mut segments = Vec::new();
        let mut push = |a: P2, b: P2, material: Material, height: f64| {
            let texture = (segments.len() as u32).wrapping_mul(2_654_435_761) ^ 0x5bd1_e995;
            segments.push(Segment {
                a,
                b,
                material,
                height,
                texture,
            });
        };
        for w in &file.walls {
            let w = w.get_ref();
            let height = w.height.unwrap_or(h);
            for pair in w.points.windows(2) {
                push(pair[0], pair[1], w.material, height);
            }
            if w.closed {
                if let (Some(&last), Some(&first)) = (w.points.last(), w.points.first()) {
                    push(last, first, w.material, height);
                }
            }
        }
        for b in &file.boxes {
            let b = b.get_ref();
            let height = b.height.unwrap_or(match b.material {
                Material::Furniture => 0.8,
                _ => h,
            });
            let c = [b.min, [b.max[0], b.min[1]], b.max, [b.min[0], b.max[1]]];
            for i in 0..4 {
                push(c[i], c[(i + 1) % 4], b.material, height);
            }
        }
        let features: Vec<Feature> = file
            .features
            .iter()
            .enumerate()
            .map(|(i, f)| Feature {
                kind: f.get_ref().kind,
                min: f.get_ref().min,
                max: f.get_ref().max,
                seed: (i as u32).wrapping_mul(0x9e37_79b9) ^ 0x1234_5678,
            })
            .collect();
        // Posters attach to the nearest collinear segment.
        let mut posters = Vec::new();
        for (i, p) in file.posters.iter().enumerate() {
            let p = p.get_ref();
            let mut best: Option<(f64, usize)> = None;
            for (k, s) in segments.iter().enumerate() {
                let d = point_segment_distance(p.a, s) + point_segment_distance(p.b, s);
                if d < 0.1 && best.is_none_or(|(bd, _)| d < bd) {
                    best = Some((d, k));
                }
            }
            if let Some((_, k)) = best {
                let s = &segments[k];
                let ua = project_fraction(p.a, s);
                let ub = project_fraction(p.b, s);
                posters.push(Poster {
                    segment: k,
                    u: [ua.min(ub), ua.max(ub)],
                    z: [p.bottom, p.top],
                    seed: (i as u32).wrapping_mul(0x85eb_ca6b) ^ 0xc2b2_ae35,
                });
            }
        }
        posters.sort_by_key(|p| p.segment);
        let mut poster_start = vec![0u32; segments.len() + 1];
        for p in &posters {
            poster_start[p.segment + 1] += 1;
        }
        for i in 0..segments.len() {
            poster_start[i + 1] += poster_start[i];
        }
        let regions = file
            .regions
            .iter()
            .map(|r| {
                let r = r.get_ref();
                Region {
                    kind: r.kind,
                    min: r.min,
                    max: r.max,
                    velocity: r.velocity,
                    scale: r.scale,
                    noise: r.noise,
                }
            })
            .collect();

        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        for s in &segments {
            for p in [s.a, s.b] {
                lo = [lo[0].min(p[0]), lo[1].min(p[1])];
                hi = [hi[0].max(p[0]), hi[1].max(p[1])];
            }
        }
        if !lo[0].is_finite() {
            lo = [0.0, 0.0];
            hi = [1.0, 1.0];
        }
        lo = [lo[0] - 1.0, lo[1] - 1.0];
        hi = [hi[0] + 1.0, hi[1] + 1.0];
        let size = [hi[0] - lo[0], hi[1] - lo[1]];
        // About one segment per two cells on average, bounded to a sane range.
        let area = size[0] * size[1];
        let cell = (area / (2.0 * segments.len().max(1) as f64))
            .sqrt()
            .clamp(0.5, 4.0);
        let seg_boxes: Vec<(P2, P2)> = segments
            .iter()
            .map(|s| {
                (
                    [s.a[0].min(s.b[0]), s.a[1].min(s.b[1])],
                    [s.a[0].max(s.b[0]), s.a[1].max(s.b[1])],
                )
            })
            .collect();
        let segment_grid = Grid::build(lo, size, cell, &seg_boxes);
        let feat_boxes: Vec<(P2, P2)> = features.iter().map(|f| (f.min, f.max)).collect();
        let feature_grid = Grid::build(lo, size, 1.0, &feat_boxes);
        World {
            name: file.name.clone(),
            ceiling_height: h,
            robot: file.robot,
            ceiling: file.ceiling.clone(),
            segments,
            features,
            posters,
            regions,
            route: file.route.get_ref().clone(),
            faults: file.faults.iter().map(|f| f.get_ref().clone()).collect(),
            odometry: file.odometry.clone(),
            bounds_min: lo,
            bounds_max: hi,
            segment_grid,
            feature_grid,
            poster_start,
        }
    }

    /// Features whose grid cell contains `p` (candidates; test containment yourself).
    pub fn features_near(&self, p: P2) -> impl Iterator<Item = &Feature> {
        self.feature_grid
            .at(p)
            .iter()
            .map(move |&i| &self.features[i as usize])
    }

    /// Posters hanging on segment `seg`.
    pub fn posters_on(&self, seg: usize) -> &[Poster] {
        let s = self.poster_start[seg] as usize;
        let e = self.poster_start[seg + 1] as usize;
        &self.posters[s..e]
    }

    /// Floor area inside the bounding box, square metres (a rough size figure).
    pub fn bounding_area(&self) -> f64 {
        (self.bounds_max[0] - self.bounds_min[0] - 2.0)
            * (self.bounds_max[1] - self.bounds_min[1] - 2.0)
    }

    /// Casts a horizontal ray from `o` along the unit direction `d` up to distance `max_s`, and
    /// returns the nearest segment hit that `accept` takes (`accept(segment, s)`). Walks the
    /// uniform grid cell by cell (Amanatides-Woo), testing only the segments in visited cells.
    pub fn cast(
        &self,
        o: P2,
        d: P2,
        max_s: f64,
        mut accept: impl FnMut(&Segment, f64) -> bool,
    ) -> Option<Hit> {
        let g = &self.segment_grid;
        // Clip the ray to the grid box.
        let mut t0: f64 = 0.0;
        let mut t1 = max_s;
        for k in 0..2 {
            let lo = g.origin[k];
            let hi = g.origin[k] + g.cell * [g.nx, g.ny][k] as f64;
            if d[k].abs() < 1e-12 {
                if o[k] < lo || o[k] > hi {
                    return None;
                }
            } else {
                let ta = (lo - o[k]) / d[k];
                let tb = (hi - o[k]) / d[k];
                t0 = t0.max(ta.min(tb));
                t1 = t1.min(ta.max(tb));
            }
        }
        if t0 > t1 {
            return None;
        }
        let p = [o[0] + d[0] * t0, o[1] + d[1] * t0];
        let (mut cx, mut cy) = cell_of(g.origin, g.cell, g.nx, g.ny, p);
        let step_x: isize = if d[0] > 0.0 { 1 } else { -1 };
        let step_y: isize = if d[1] > 0.0 { 1 } else { -1 };
        let next_boundary = |c: usize, k: usize, step: isize| {
            let edge = if step > 0 { c + 1 } else { c } as f64;
            g.origin[k] + edge * g.cell
        };
        let mut t_max_x = if d[0].abs() < 1e-12 {
            f64::INFINITY
        } else {
            (next_boundary(cx, 0, step_x) - o[0]) / d[0]
        };
        let mut t_max_y = if d[1].abs() < 1e-12 {
            f64::INFINITY
        } else {
            (next_boundary(cy, 1, step_y) - o[1]) / d[1]
        };
        let t_dx = if d[0].abs() < 1e-12 {
            f64::INFINITY
        } else {
            g.cell / d[0].abs()
        };
        let t_dy = if d[1].abs() < 1e-12 {
            f64::INFINITY
        } else {
            g.cell / d[1].abs()
        };
        let mut best: Option<Hit> = None;
        loop {
            for &i in g.cell_items(cy * g.nx + cx) {
                let seg = &self.segments[i as usize];
                if let Some((s, u)) = ray_segment(o, d, seg.a, seg.b) {
                    if s <= max_s && best.is_none_or(|b| s < b.s) && accept(seg, s) {
                        best = Some(Hit {
                            s,
                            segment: i as usize,
                            u,
                        });
                    }
                }
            }
            let t_exit = t_max_x.min(t_max_y);
            if let Some(b) = best {
                if b.s <= t_exit {
                    return best;
                }
            }
            if t_exit > t1 {
                return best;
            }
            if t_max_x < t_max_y {
                let nx = cx as isize + step_x;
                if nx < 0 || nx >= g.nx as isize {
                    return best;
                }
                cx = nx as usize;
                t_max_x += t_dx;
            } else {
                let ny = cy as isize + step_y;
                if ny < 0 || ny >= g.ny as isize {
                    return best;
                }
                cy = ny as usize;
                t_max_y += t_dy;
            }
        }
    }

    /// Whether the straight path from `a` to `b` keeps `clearance` from every segment taller
    /// than 5 cm (used to check routes).
    pub fn path_is_clear(&self, a: P2, b: P2, clearance: f64) -> bool {
        self.segments
            .iter()
            .filter(|s| s.height > 0.05)
            .all(|s| segment_segment_distance(a, b, s.a, s.b) >= clearance)
    }
}

/// Intersection of the ray `o + s d` (s >= 0) with the segment `a`-`b`: `(s, u)`.
#[inline]
pub fn ray_segment(o: P2, d: P2, a: P2, b: P2) -> Option<(f64, f64)> {
    let e = [b[0] - a[0], b[1] - a[1]];
    let denom = d[0] * e[1] - d[1] * e[0];
    if denom.abs() < 1e-12 {
        return None;
    }
    let w = [a[0] - o[0], a[1] - o[1]];
    let s_num = w[0] * e[1] - w[1] * e[0];
    let u_num = w[0] * d[1] - w[1] * d[0];
    // Test the signs before dividing: most candidates miss.
    let (s_num, u_num, den) = if denom > 0.0 {
        (s_num, u_num, denom)
    } else {
        (-s_num, -u_num, -denom)
    };
    if s_num < 0.0 || u_num < 0.0 || u_num > den {
        return None;
    }
    let inv = 1.0 / den;
    Some((s_num * inv, u_num * inv))
}

fn project_fraction(p: P2, s: &Segment) -> f64 {
    let e = [s.b[0] - s.a[0], s.b[1] - s.a[1]];
    let l2 = e[0] * e[0] + e[1] * e[1];
    (((p[0] - s.a[0]) * e[0] + (p[1] - s.a[1]) * e[1]) / l2).clamp(0.0, 1.0)
}

fn point_segment_distance(p: P2, s: &Segment) -> f64 {
    point_seg(p, s.a, s.b)
}

/// Distance from `p` to the segment `a`-`b`.
pub(crate) fn point_seg(p: P2, a: P2, b: P2) -> f64 {
    let e = [b[0] - a[0], b[1] - a[1]];
    let l2 = e[0] * e[0] + e[1] * e[1];
    let t = if l2 > 0.0 {
        (((p[0] - a[0]) * e[0] + (p[1] - a[1]) * e[1]) / l2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    dist(p, [a[0] + t * e[0], a[1] + t * e[1]])
}

fn segment_segment_distance(a: P2, b: P2, c: P2, d: P2) -> f64 {
    let cross = |o: P2, p: P2, q: P2| (p[0] - o[0]) * (q[1] - o[1]) - (p[1] - o[1]) * (q[0] - o[0]);
    let d1 = cross(c, d, a);
    let d2 = cross(c, d, b);
    let d3 = cross(a, b, c);
    let d4 = cross(a, b, d);
    if ((d1 > 0.0) != (d2 > 0.0)) && ((d3 > 0.0) != (d4 > 0.0)) {
        return 0.0;
    }
    point_seg(a, c, d)
        .min(point_seg(b, c, d))
        .min(point_seg(c, a, b))
        .min(point_seg(d, a, b))
}

#[cfg(test)]
mod tests {
    use super::*;

    const SQUARE: &str = r#"
name = "square"
ceiling_height = 2.5

[[wall]]
points = [[0, 0], [10, 0], [10, 10], [0, 10]]
closed = true

[route]
start = [1, 1]
legs = [{ type = "waypoints", points = [[9, 1], [9, 9]] }]
"#;

    #[test]
    fn parses_and_casts_against_the_nearest_wall() {
        let file = WorldFile::parse(SQUARE, "square.toml").expect("valid");
        let world = World::from_file(&file);
        assert_eq!(world.segments.len(), 4);
        let hit = world
            .cast([1.0, 1.0], [1.0, 0.0], 100.0, |_, _| true)
            .expect("hit");
        assert!((hit.s - 9.0).abs() < 1e-12);
        let d = [0.6f64, 0.8];
        let hit = world.cast([5.0, 5.0], d, 100.0, |_, _| true).expect("hit");
        // Hits y = 10 at s = 5 / 0.8.
        assert!((hit.s - 6.25).abs() < 1e-12, "{}", hit.s);
        assert!(world.cast([5.0, 5.0], d, 6.0, |_, _| true).is_none());
    }

    #[test]
    fn syntax_errors_name_file_and_line() {
        let bad = SQUARE.replace("closed = true", "closed = yes");
        let err = WorldFile::parse(&bad, "flat.toml").expect_err("invalid");
        let msg = err.to_string();
        assert!(msg.starts_with("flat.toml:7:"), "{msg}");
    }

    #[test]
    fn schema_and_semantic_errors_name_file_and_line() {
        let bad = SQUARE.replace("ceiling_height = 2.5", "ceiling_height = 2.5\ncolour = 3");
        let msg = WorldFile::parse(&bad, "a.toml")
            .expect_err("unknown key")
            .to_string();
        assert!(msg.starts_with("a.toml:"), "{msg}");
        assert!(msg.contains("colour"), "{msg}");
        let bad = format!("{SQUARE}\n[[box]]\nmin = [3, 3]\nmax = [2, 4]\n");
        let err = WorldFile::parse(&bad, "b.toml").expect_err("inverted box");
        // The table header `[[box]]` is on line 13.
        assert_eq!(err.line, Some(13), "{err}");
        assert!(
            err.to_string().contains("b.toml:13: box needs min < max"),
            "{err}"
        );
    }
}
