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
    /// Boxes (furniture, pillars, glass booths), axis-aligned unless turned.
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
    /// How the world changes from one mapping session to the next (`cloi sim --session N`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub changes: Vec<toml::Spanned<ChangeSpec>>,
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
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct WallSpec {
    /// A name that changes can address it by (unique among walls and boxes).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
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

/// A box made of four segments: the rectangle `min`..`max`, turned by `angle` about its centre.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct BoxSpec {
    /// A name that changes can address it by (unique among walls and boxes).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// Lower-left corner (before the turn).
    pub min: P2,
    /// Upper-right corner (before the turn).
    pub max: P2,
    /// Counter-clockwise turn about the centre, radians (a moved chair rarely stays square to
    /// the walls).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub angle: f64,
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

// By reference: serde's `skip_serializing_if` passes one.
fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

/// A box or a wall that a change acts on: its `name`, or its 0-based position among the
/// `[[box]]` (or `[[wall]]`) tables as written.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(
    untagged,
    expecting = "a box or wall given by its name (a string) or its 0-based position in the \
                 file (an integer >= 0)"
)]
pub enum ItemRef {
    /// Position among the tables of its kind as written, from 0.
    Index(usize),
    /// The item's `name`.
    Name(String),
}

/// One change of the world between mapping sessions. It holds from its `session` on: the world
/// of session N has every change whose session is 1..=N applied, in session order and, within
/// a session, in file order.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "snake_case", tag = "kind")]
pub enum ChangeSpec {
    /// Furniture moved: a box or a wall shifted by `dx`, `dy` and turned by `angle` (about a
    /// box's centre, or the mean of a wall's points).
    Move {
        /// First session with the change (>= 1).
        session: u32,
        /// The box moved (give `box` or `wall`).
        #[serde(rename = "box", default, skip_serializing_if = "Option::is_none")]
        box_ref: Option<ItemRef>,
        /// The wall moved.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        wall: Option<ItemRef>,
        /// Shift along x, metres.
        #[serde(default)]
        dx: f64,
        /// Shift along y, metres.
        #[serde(default)]
        dy: f64,
        /// Counter-clockwise turn, radians.
        #[serde(default, skip_serializing_if = "is_zero")]
        angle: f64,
    },
    /// Something taken away: furniture carried out, or a door segment (the door is opened).
    Remove {
        /// First session with the change (>= 1).
        session: u32,
        /// The box removed (give `box` or `wall`).
        #[serde(rename = "box", default, skip_serializing_if = "Option::is_none")]
        box_ref: Option<ItemRef>,
        /// The wall removed.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        wall: Option<ItemRef>,
    },
    /// Something new: a box (clutter) or a wall (a closed door).
    Add {
        /// First session with the change (>= 1).
        session: u32,
        /// The box added (give `box` or `wall`).
        #[serde(rename = "box", default, skip_serializing_if = "Option::is_none")]
        box_spec: Option<BoxSpec>,
        /// The wall added.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        wall: Option<WallSpec>,
    },
}

impl ChangeSpec {
    /// The first session that has this change.
    pub fn session(&self) -> u32 {
        match self {
            ChangeSpec::Move { session, .. }
            | ChangeSpec::Remove { session, .. }
            | ChangeSpec::Add { session, .. } => *session,
        }
    }

    fn verb(&self) -> &'static str {
        match self {
            ChangeSpec::Move { .. } => "move",
            ChangeSpec::Remove { .. } => "remove",
            ChangeSpec::Add { .. } => "add",
        }
    }
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
            check_wall(w.get_ref()).map_err(|m| (Some(w.span()), m))?;
        }
        for b in &self.boxes {
            check_box(b.get_ref()).map_err(|m| (Some(b.span()), m))?;
        }
        let mut names = std::collections::HashSet::new();
        let named = self.walls.iter().map(|w| (w.span(), &w.get_ref().name));
        let named = named.chain(self.boxes.iter().map(|b| (b.span(), &b.get_ref().name)));
        for (span, name) in named {
            if let Some(name) = name {
                if !names.insert(name.as_str()) {
                    return Err((Some(span), format!("the name {name:?} is used twice")));
                }
            }
        }
        // Applying every change checks each one against the world it meets.
        self.layout(u32::MAX)?;
        let rect_ok =
            |min: &P2, max: &P2| fin(min) && fin(max) && min[0] < max[0] && min[1] < max[1];
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

fn check_name(name: &Option<String>) -> Result<(), String> {
    match name {
        Some(n) if n.trim().is_empty() => Err("a name must not be empty".into()),
        _ => Ok(()),
    }
}

fn check_wall(w: &WallSpec) -> Result<(), String> {
    check_name(&w.name)?;
    let fin = |p: &P2| p[0].is_finite() && p[1].is_finite();
    let min_pts = if w.closed { 3 } else { 2 };
    if w.points.len() < min_pts {
        return Err(format!("wall needs at least {min_pts} points"));
    }
    for pair in w.points.windows(2) {
        if !fin(&pair[0]) || !fin(&pair[1]) || dist(pair[0], pair[1]) < 1e-6 {
            return Err("wall has a zero-length or non-finite segment".into());
        }
    }
    if let Some(h) = w.height {
        if !(h > 0.0 && h.is_finite()) {
            return Err("wall height must be > 0".into());
        }
    }
    Ok(())
}

fn check_box(b: &BoxSpec) -> Result<(), String> {
    check_name(&b.name)?;
    let fin = |p: &P2| p[0].is_finite() && p[1].is_finite();
    if !(fin(&b.min) && fin(&b.max) && b.min[0] < b.max[0] && b.min[1] < b.max[1]) {
        return Err("box needs min < max".into());
    }
    if !b.angle.is_finite() {
        return Err("box angle must be finite".into());
    }
    if let Some(h) = b.height {
        if !(h > 0.0 && h.is_finite()) {
            return Err("box height must be > 0".into());
        }
    }
    Ok(())
}

/// Number of segments a wall polyline is drawn with.
fn wall_segments(w: &WallSpec) -> u32 {
    let open = w.points.len().saturating_sub(1);
    (open + usize::from(w.closed && !w.points.is_empty())) as u32
}

/// `p` turned by `angle` about `pivot`.
fn turn(p: P2, pivot: P2, angle: f64) -> P2 {
    let (s, c) = angle.sin_cos();
    let (x, y) = (p[0] - pivot[0], p[1] - pivot[1]);
    [pivot[0] + c * x - s * y, pivot[1] + s * x + c * y]
}

/// A wall or box standing in a session, with the texture number of its first segment. The
/// numbers are those of the world as written, and added items count on after its last
/// segment, so furniture that a session leaves alone looks the same in every session.
#[derive(Clone, Debug)]
struct Placed<T> {
    spec: T,
    texture: u32,
}

/// The walls and boxes of one session. Removed items stay as `None` so that positions in the
/// file keep addressing the same item whatever earlier sessions removed.
#[derive(Clone, Debug)]
struct Layout {
    walls: Vec<Option<Placed<WallSpec>>>,
    boxes: Vec<Option<Placed<BoxSpec>>>,
    /// How many walls and boxes the file lists (positions beyond are added items).
    written: [usize; 2],
    /// The next texture number for an added item.
    next_texture: u32,
}

#[derive(Clone, Copy, PartialEq)]
enum ItemKind {
    // The discriminants index `Layout::written`.
    Wall,
    Box,
}

impl ItemKind {
    fn noun(self) -> &'static str {
        match self {
            ItemKind::Wall => "wall",
            ItemKind::Box => "box",
        }
    }
}

fn name_of<T>(item: &Option<Placed<T>>, name: impl Fn(&T) -> &Option<String>) -> Option<&str> {
    item.as_ref().and_then(|p| name(&p.spec).as_deref())
}

impl Layout {
    fn as_written(file: &WorldFile) -> Layout {
        let mut texture = 0u32;
        let mut walls = Vec::with_capacity(file.walls.len());
        for w in &file.walls {
            walls.push(Some(Placed {
                spec: w.get_ref().clone(),
                texture,
            }));
            texture = texture.wrapping_add(wall_segments(w.get_ref()));
        }
        let mut boxes = Vec::with_capacity(file.boxes.len());
        for b in &file.boxes {
            boxes.push(Some(Placed {
                spec: b.get_ref().clone(),
                texture,
            }));
            texture = texture.wrapping_add(4);
        }
        Layout {
            written: [walls.len(), boxes.len()],
            walls,
            boxes,
            next_texture: texture,
        }
    }

    fn wall_name(&self, i: usize) -> Option<&str> {
        name_of(&self.walls[i], |w: &WallSpec| &w.name)
    }

    fn box_name(&self, i: usize) -> Option<&str> {
        name_of(&self.boxes[i], |b: &BoxSpec| &b.name)
    }

    fn position_of_name(&self, kind: ItemKind, name: &str) -> Option<usize> {
        match kind {
            ItemKind::Wall => (0..self.walls.len()).find(|&i| self.wall_name(i) == Some(name)),
            ItemKind::Box => (0..self.boxes.len()).find(|&i| self.box_name(i) == Some(name)),
        }
    }

    /// Where the item `r` of `kind` stands in this session.
    fn find(&self, kind: ItemKind, r: &ItemRef) -> Result<usize, String> {
        let noun = kind.noun();
        match r {
            ItemRef::Index(i) => {
                let written = self.written[kind as usize];
                let standing = match kind {
                    ItemKind::Wall => self.walls.get(*i).is_some_and(Option::is_some),
                    ItemKind::Box => self.boxes.get(*i).is_some_and(Option::is_some),
                };
                if *i >= written {
                    Err(format!(
                        "{noun} {i}: the file has {written} {noun} table(s), counted from 0 \
                         (an added {noun} is addressed by its name)"
                    ))
                } else if !standing {
                    Err(format!("{noun} {i} was removed by an earlier change"))
                } else {
                    Ok(*i)
                }
            }
            ItemRef::Name(name) => {
                if let Some(i) = self.position_of_name(kind, name) {
                    return Ok(i);
                }
                let other = if kind == ItemKind::Wall {
                    ItemKind::Box
                } else {
                    ItemKind::Wall
                };
                if self.position_of_name(other, name).is_some() {
                    Err(format!("{name:?} names a {}, not a {noun}", other.noun()))
                } else {
                    Err(format!(
                        "no {noun} named {name:?} stands here (misspelt, removed earlier or \
                         added only later)"
                    ))
                }
            }
        }
    }

    fn check_free(&self, name: &Option<String>) -> Result<(), String> {
        if let Some(name) = name {
            for kind in [ItemKind::Wall, ItemKind::Box] {
                if self.position_of_name(kind, name).is_some() {
                    return Err(format!("a {} named {name:?} stands already", kind.noun()));
                }
            }
        }
        Ok(())
    }

    /// Applies one change.
    fn apply(&mut self, change: &ChangeSpec) -> Result<(), String> {
        let target = |b: &Option<ItemRef>, w: &Option<ItemRef>| match (b, w) {
            (Some(b), None) => Ok((ItemKind::Box, b.clone())),
            (None, Some(w)) => Ok((ItemKind::Wall, w.clone())),
            _ => Err("give either `box` or `wall`".to_string()),
        };
        match change {
            ChangeSpec::Move {
                box_ref,
                wall,
                dx,
                dy,
                angle,
                ..
            } => {
                let (kind, r) = target(box_ref, wall)?;
                if !(dx.is_finite() && dy.is_finite() && angle.is_finite()) {
                    return Err("dx, dy and angle must be finite numbers".into());
                }
                if *dx == 0.0 && *dy == 0.0 && *angle == 0.0 {
                    return Err("a move needs a non-zero dx, dy or angle".into());
                }
                let i = self.find(kind, &r)?;
                match kind {
                    ItemKind::Box => {
                        let Some(placed) = self.boxes[i].as_mut() else {
                            return Err("box is gone".into());
                        };
                        let b = &mut placed.spec;
                        b.min = [b.min[0] + dx, b.min[1] + dy];
                        b.max = [b.max[0] + dx, b.max[1] + dy];
                        b.angle += angle;
                        check_box(b).map_err(|m| format!("the moved box: {m}"))?;
                    }
                    ItemKind::Wall => {
                        let Some(placed) = self.walls[i].as_mut() else {
                            return Err("wall is gone".into());
                        };
                        let w = &mut placed.spec;
                        let n = w.points.len().max(1) as f64;
                        let pivot = w
                            .points
                            .iter()
                            .fold([0.0, 0.0], |s, p| [s[0] + p[0] / n, s[1] + p[1] / n]);
                        for p in &mut w.points {
                            let q = if *angle == 0.0 {
                                *p
                            } else {
                                turn(*p, pivot, *angle)
                            };
                            *p = [q[0] + dx, q[1] + dy];
                        }
                        check_wall(w).map_err(|m| format!("the moved wall: {m}"))?;
                    }
                }
            }
            ChangeSpec::Remove { box_ref, wall, .. } => {
                let (kind, r) = target(box_ref, wall)?;
                let i = self.find(kind, &r)?;
                match kind {
                    ItemKind::Box => self.boxes[i] = None,
                    ItemKind::Wall => self.walls[i] = None,
                }
            }
            ChangeSpec::Add { box_spec, wall, .. } => match (box_spec, wall) {
                (Some(b), None) => {
                    check_box(b).map_err(|m| format!("the added box: {m}"))?;
                    self.check_free(&b.name)?;
                    self.boxes.push(Some(Placed {
                        spec: b.clone(),
                        texture: self.next_texture,
                    }));
                    self.next_texture = self.next_texture.wrapping_add(4);
                }
                (None, Some(w)) => {
                    check_wall(w).map_err(|m| format!("the added wall: {m}"))?;
                    self.check_free(&w.name)?;
                    self.walls.push(Some(Placed {
                        spec: w.clone(),
                        texture: self.next_texture,
                    }));
                    self.next_texture = self.next_texture.wrapping_add(wall_segments(w));
                }
                _ => return Err("give either `box` or `wall`".into()),
            },
        }
        Ok(())
    }
}

impl WorldFile {
    /// The last session that changes the world (0 for a world without changes); later
    /// sessions look like this one.
    pub fn last_session(&self) -> u32 {
        self.changes
            .iter()
            .map(|c| c.get_ref().session())
            .max()
            .unwrap_or(0)
    }

    /// The walls and boxes of `session`: every change of sessions 1..=`session` applied.
    fn layout(&self, session: u32) -> Result<Layout, (Option<std::ops::Range<usize>>, String)> {
        let mut layout = Layout::as_written(self);
        let mut order: Vec<&toml::Spanned<ChangeSpec>> = self.changes.iter().collect();
        // Stable: changes of one session apply in file order.
        order.sort_by_key(|c| c.get_ref().session());
        for c in order {
            let change = c.get_ref();
            let s = change.session();
            if s == 0 {
                return Err((
                    Some(c.span()),
                    "a change needs session >= 1 (session 0 is the world as written)".into(),
                ));
            }
            if s > session {
                break;
            }
            layout.apply(change).map_err(|m| {
                (
                    Some(c.span()),
                    format!("session {s} {}: {m}", change.verb()),
                )
            })?;
        }
        Ok(layout)
    }

    /// What segment `index` of the world of `session` belongs to, for messages
    /// (`box "armchair"`, `wall 3`, `added box "toy-box"`).
    pub fn describe_segment(&self, session: u32, index: usize) -> Option<String> {
        let layout = self.layout(session).ok()?;
        let mut first = 0usize;
        let label = |kind: ItemKind, i: usize, name: Option<&str>| {
            let added = if i >= layout.written[kind as usize] {
                "added "
            } else {
                ""
            };
            match name {
                Some(n) => format!("{added}{} {n:?}", kind.noun()),
                None => format!("{added}{} {i}", kind.noun()),
            }
        };
        for (i, w) in layout.walls.iter().enumerate() {
            if let Some(w) = w {
                let n = wall_segments(&w.spec) as usize;
                if index < first + n {
                    return Some(label(ItemKind::Wall, i, layout.wall_name(i)));
                }
                first += n;
            }
        }
        for (i, b) in layout.boxes.iter().enumerate() {
            if b.is_some() {
                if index < first + 4 {
                    return Some(label(ItemKind::Box, i, layout.box_name(i)));
                }
                first += 4;
            }
        }
        None
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
    /// The mapping session this world shows (0: as written).
    pub session: u32,
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
    /// Builds and indexes a world from its (validated) file form, as written (session 0).
    pub fn from_file(file: &WorldFile) -> World {
        World::build(file, &Layout::as_written(file), 0)
    }

    /// Builds the world of mapping session `session`: every change of sessions 1..=`session`
    /// applied (0: the world as written; past the last session: the last session's world).
    /// Posters and ceiling features stay where they are written.
    ///
    /// # Errors
    /// A change that does not apply (unknown name, degenerate result, ...): only for a file
    /// that was not validated, since parsing applies every change.
    pub fn at_session(file: &WorldFile, session: u32) -> Result<World, WorldError> {
        let layout = file.layout(session).map_err(|(_, message)| WorldError {
            file: file.name.clone(),
            line: None,
            message,
        })?;
        Ok(World::build(file, &layout, session))
    }

    fn build(file: &WorldFile, layout: &Layout, session: u32) -> World {
        let h = file.ceiling_height;
        let mut segments = Vec::new();
        let mut push = |a: P2, b: P2, material: Material, height: f64, number: u32| {
            let texture = number.wrapping_mul(2_654_435_761) ^ 0x5bd1_e995;
            segments.push(Segment {
                a,
                b,
                material,
                height,
                texture,
            });
        };
        for w in layout.walls.iter().flatten() {
            let number = w.texture;
            let w = &w.spec;
            let height = w.height.unwrap_or(h);
            let mut k = number;
            for pair in w.points.windows(2) {
                push(pair[0], pair[1], w.material, height, k);
                k = k.wrapping_add(1);
            }
            if w.closed {
                if let (Some(&last), Some(&first)) = (w.points.last(), w.points.first()) {
                    push(last, first, w.material, height, k);
                }
            }
        }
        for b in layout.boxes.iter().flatten() {
            let number = b.texture;
            let b = &b.spec;
            let height = b.height.unwrap_or(match b.material {
                Material::Furniture => 0.8,
                _ => h,
            });
            let mut c = [b.min, [b.max[0], b.min[1]], b.max, [b.min[0], b.max[1]]];
            if b.angle != 0.0 {
                let centre = [(b.min[0] + b.max[0]) / 2.0, (b.min[1] + b.max[1]) / 2.0];
                c = c.map(|p| turn(p, centre, b.angle));
            }
            for i in 0..4 {
                push(
                    c[i],
                    c[(i + 1) % 4],
                    b.material,
                    height,
                    number.wrapping_add(i as u32),
                );
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
            session,
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
        self.path_blocker(a, b, clearance).is_none()
    }

    /// The first segment taller than 5 cm that the straight path from `a` to `b` passes closer
    /// than `clearance` to.
    pub fn path_blocker(&self, a: P2, b: P2, clearance: f64) -> Option<usize> {
        self.segments
            .iter()
            .position(|s| s.height > 0.05 && segment_segment_distance(a, b, s.a, s.b) < clearance)
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

    /// SQUARE with two named boxes, an unnamed one and a change list.
    fn with_changes(changes: &str) -> String {
        format!(
            "{SQUARE}
[[box]]
name = \"chair\"
min = [2, 2]
max = [3, 3]

[[box]]
min = [6, 6]
max = [7, 7]

[[wall]]
name = \"door\"
points = [[4, 0], [4, 2]]
{changes}"
        )
    }

    const CHANGES: &str = r#"
[[changes]]
session = 2
kind = "remove"
wall = "door"

[[changes]]
session = 1
kind = "move"
box = "chair"
dx = 1
dy = -0.5

[[changes]]
session = 1
kind = "add"
box = { name = "crate", min = [8, 2], max = [8.5, 2.5], height = 0.3 }

[[changes]]
session = 3
kind = "move"
box = 1
dx = -1
angle = 0.5

[[changes]]
session = 3
kind = "remove"
box = "crate"
"#;

    fn ends(world: &World) -> Vec<[f64; 4]> {
        world
            .segments
            .iter()
            .map(|s| [s.a[0], s.a[1], s.b[0], s.b[1]])
            .collect()
    }

    fn has(world: &World, a: P2, b: P2) -> bool {
        world.segments.iter().any(|s| s.a == a && s.b == b)
    }

    #[test]
    fn changes_accumulate_over_sessions() {
        let file = WorldFile::parse(&with_changes(CHANGES), "c.toml").expect("valid");
        assert_eq!(file.last_session(), 3);
        let at = |n| World::at_session(&file, n).expect("applies");
        let s0 = at(0);
        assert_eq!(ends(&s0), ends(&World::from_file(&file)));
        // 4 square walls, the door, two boxes.
        assert_eq!(s0.segments.len(), 4 + 1 + 8);
        assert!(has(&s0, [2.0, 2.0], [3.0, 2.0]) && has(&s0, [4.0, 0.0], [4.0, 2.0]));

        // Session 1: the chair moved and a crate added; the door still stands.
        let s1 = at(1);
        assert_eq!(s1.session, 1);
        assert_eq!(s1.segments.len(), 4 + 1 + 12);
        assert!(!has(&s1, [2.0, 2.0], [3.0, 2.0]));
        assert!(has(&s1, [3.0, 1.5], [4.0, 1.5]));
        assert!(has(&s1, [8.0, 2.0], [8.5, 2.0]));
        let crate_seg = s1.segments.iter().find(|s| s.a == [8.0, 2.0]).unwrap();
        assert!((crate_seg.height - 0.3).abs() < 1e-12);

        // Session 2 adds the door's opening to session 1's changes.
        let s2 = at(2);
        assert_eq!(s2.segments.len(), 4 + 12);
        assert!(!has(&s2, [4.0, 0.0], [4.0, 2.0]) && has(&s2, [3.0, 1.5], [4.0, 1.5]));

        // Session 3: the unnamed box (by position) moved and turned, the crate gone.
        let s3 = at(3);
        assert_eq!(s3.segments.len(), 4 + 8);
        assert!(!has(&s3, [8.0, 2.0], [8.5, 2.0]));
        let turned: Vec<&Segment> = s3.segments[s3.segments.len() - 4..].iter().collect();
        for s in &turned {
            // A 1 m square about (5.5, 6.5): corners at 0.707 m from the centre, none axis-aligned.
            let r = dist(s.a, [5.5, 6.5]);
            assert!((r - 0.5f64.sqrt()).abs() < 1e-12, "{r}");
            assert!((dist(s.a, s.b) - 1.0).abs() < 1e-12);
            assert!((s.a[0] - s.b[0]).abs() > 0.1 && (s.a[1] - s.b[1]).abs() > 0.1);
        }
        // Past the last session the world stays as in the last one.
        assert_eq!(ends(&at(9)), ends(&s3));
        assert_eq!(ends(&at(u32::MAX)), ends(&s3));
    }

    #[test]
    fn unchanged_items_keep_their_texture_across_sessions() {
        let file = WorldFile::parse(&with_changes(CHANGES), "c.toml").expect("valid");
        let s0 = World::from_file(&file);
        for n in 1..=3 {
            let sn = World::at_session(&file, n).expect("applies");
            for s in &sn.segments {
                if let Some(same) = s0.segments.iter().find(|o| o.a == s.a && o.b == s.b) {
                    assert_eq!(same.texture, s.texture, "session {n}: {s:?}");
                }
            }
        }
        // Moved items keep their texture too; added ones get their own.
        let s1 = World::at_session(&file, 1).expect("applies");
        let chair = |w: &World, a: P2| w.segments.iter().find(|s| s.a == a).unwrap().texture;
        assert_eq!(chair(&s0, [2.0, 2.0]), chair(&s1, [3.0, 1.5]));
        let mut all: Vec<u32> = s1.segments.iter().map(|s| s.texture).collect();
        all.sort_unstable();
        all.dedup();
        assert_eq!(all.len(), s1.segments.len());
    }

    #[test]
    fn a_world_without_changes_is_the_same_in_every_session() {
        let file = WorldFile::parse(SQUARE, "square.toml").expect("valid");
        assert_eq!(file.last_session(), 0);
        let s0 = World::from_file(&file);
        assert_eq!(s0.segments, World::at_session(&file, 5).unwrap().segments);
        let text = file.to_toml().expect("serialisable");
        assert!(
            !text.contains("[[changes]]") && !text.contains("angle"),
            "{text}"
        );
    }

    #[test]
    fn changes_survive_a_round_trip() {
        let file = WorldFile::parse(&with_changes(CHANGES), "c.toml").expect("valid");
        let text = file.to_toml().expect("serialisable");
        let back = WorldFile::parse(&text, "back.toml").expect("round trip");
        for n in 0..=3 {
            let a = World::at_session(&file, n).unwrap();
            let b = World::at_session(&back, n).unwrap();
            assert_eq!(a.segments, b.segments, "session {n}");
        }
    }

    /// The error of the world with `changes`, which must name `c.toml` and the line of the
    /// `[[changes]]` table that starts at `line`.
    fn change_error(changes: &str) -> WorldError {
        WorldFile::parse(&with_changes(changes), "c.toml").expect_err("invalid change")
    }

    #[test]
    fn bad_changes_are_errors_naming_the_line() {
        // Line of the first `[[changes]]` header after the base world.
        let first = with_changes("").lines().count() + 2;
        for (changes, expected) in [
            (
                "\n[[changes]]\nsession = 1\nkind = \"move\"\nbox = \"chiar\"\ndx = 1\n",
                "session 1 move: no box named \"chiar\"",
            ),
            (
                "\n[[changes]]\nsession = 0\nkind = \"remove\"\nbox = \"chair\"\n",
                "a change needs session >= 1",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"move\"\nbox = \"chair\"\ndx = nan\n",
                "must be finite",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"move\"\nbox = \"chair\"\ndy = inf\n",
                "must be finite",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"move\"\nbox = \"chair\"\nangle = -inf\n",
                "must be finite",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"move\"\nbox = \"chair\"\n",
                "non-zero dx, dy or angle",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"remove\"\nbox = \"chair\"\nwall = \"door\"\n",
                "either `box` or `wall`",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"remove\"\n",
                "either `box` or `wall`",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"remove\"\nbox = \"door\"\n",
                "\"door\" names a wall, not a box",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"remove\"\nbox = 2\n",
                "box 2: the file has 2 box table(s)",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"remove\"\nbox = \"chair\"\n\n\
                 [[changes]]\nsession = 1\nkind = \"move\"\nbox = \"chair\"\ndx = 1\n",
                "no box named \"chair\"",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"remove\"\nbox = 1\n\n\
                 [[changes]]\nsession = 2\nkind = \"remove\"\nbox = 1\n",
                "box 1 was removed by an earlier change",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"add\"\nbox = { min = [3, 3], max = [2, 4] }\n",
                "the added box: box needs min < max",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"add\"\n\
                 wall = { name = \"chair\", points = [[1, 5], [2, 5]] }\n",
                "a box named \"chair\" stands already",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"add\"\nwall = { points = [[1, 5], [1, 5]] }\n",
                "zero-length",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"move\"\nbox = \"chair\"\ndx = 1e308\n",
                "the moved box: box needs min < max",
            ),
        ] {
            let err = change_error(changes);
            let msg = err.to_string();
            assert!(msg.starts_with("c.toml:"), "{msg}");
            assert!(msg.contains(expected), "{changes}\n=> {msg}");
            let line = err.line.expect("a line");
            assert!(line >= first, "{msg}: line {line} before the changes");
        }
        // Schema errors: the parser's own messages, still with file and line.
        for (changes, expected) in [
            (
                "\n[[changes]]\nsession = 1\nkind = \"shuffle\"\nbox = \"chair\"\n",
                "shuffle",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"move\"\nbox = \"chair\"\ndz = 1\n",
                "dz",
            ),
            (
                "\n[[changes]]\nsession = -1\nkind = \"remove\"\nbox = \"chair\"\n",
                "-1",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"remove\"\nbox = 1.5\n",
                "its name (a string) or its 0-based position",
            ),
            (
                "\n[[changes]]\nsession = 1\nkind = \"remove\"\nbox = -1\n",
                "its name (a string) or its 0-based position",
            ),
        ] {
            let msg = change_error(changes).to_string();
            assert!(msg.starts_with("c.toml:"), "{msg}");
            assert!(msg.contains(expected), "{changes}\n=> {msg}");
        }
    }

    #[test]
    fn names_must_be_unique_and_not_empty() {
        let twice = format!("{SQUARE}\n[[box]]\nname = \"a\"\nmin = [1, 1]\nmax = [2, 2]\n\n[[wall]]\nname = \"a\"\npoints = [[5, 5], [6, 5]]\n");
        let msg = WorldFile::parse(&twice, "n.toml")
            .expect_err("twice")
            .to_string();
        assert!(msg.contains("the name \"a\" is used twice"), "{msg}");
        let empty = format!("{SQUARE}\n[[box]]\nname = \" \"\nmin = [1, 1]\nmax = [2, 2]\n");
        let msg = WorldFile::parse(&empty, "n.toml")
            .expect_err("empty")
            .to_string();
        assert!(msg.contains("must not be empty"), "{msg}");
        // A removed item's name is free again: a door can be taken out and put back.
        let again = with_changes(
            "\n[[changes]]\nsession = 1\nkind = \"remove\"\nwall = \"door\"\n\n\
             [[changes]]\nsession = 2\nkind = \"add\"\nwall = { name = \"door\", points = [[4, 0], [4, 2]] }\n",
        );
        let file = WorldFile::parse(&again, "n.toml").expect("valid");
        let s2 = World::at_session(&file, 2).unwrap();
        assert!(has(&s2, [4.0, 0.0], [4.0, 2.0]));
        assert!(!has(
            &World::at_session(&file, 1).unwrap(),
            [4.0, 0.0],
            [4.0, 2.0]
        ));
    }

    #[test]
    fn describes_the_item_a_segment_belongs_to() {
        let file = WorldFile::parse(&with_changes(CHANGES), "c.toml").expect("valid");
        let world = World::at_session(&file, 1).unwrap();
        let find = |a: P2| world.segments.iter().position(|s| s.a == a).unwrap();
        let describe = |a: P2| file.describe_segment(1, find(a)).unwrap();
        assert_eq!(describe([0.0, 0.0]), "wall 0");
        assert_eq!(describe([4.0, 0.0]), "wall \"door\"");
        assert_eq!(describe([3.0, 1.5]), "box \"chair\"");
        assert_eq!(describe([6.0, 6.0]), "box 1");
        assert_eq!(describe([8.0, 2.0]), "added box \"crate\"");
        assert_eq!(file.describe_segment(1, world.segments.len()), None);
    }
}
