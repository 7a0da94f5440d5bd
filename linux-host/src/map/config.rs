//! The `cloi map` configuration: presets for the `home`, `office` and `airport` profiles, and
//! a TOML file (`--config FILE`) that overrides any part of the preset.
//!
//! A file names only what it changes; every field it leaves out keeps the preset's value
//! (the file is merged key by key onto the preset before it is read). A key the
//! configuration does not have is an error naming the key, the file and the keys that
//! exist. `docs/map-config.toml` documents every field with the `home` values.
//!
//! The values of the presets live in the core (`MapperConfig::home`, `office`, `airport`);
//! these structures are the file's keys, read from a core configuration
//! ([`MapConfig::from_core`]) and written back into one ([`MapConfig::to_core`]), so a key
//! the file documents is a value the mapper uses. `gpe.deadline_us` and `[run]` are the
//! host's own: how the frames are timed and scheduled.

use std::path::Path;

use anyhow::{bail, Context, Result};
use cloi_core::mapper::MapperConfig;
use cloi_core::profile::{ProfileSpec, AIRPORT, HOME, OFFICE};
use serde::{Deserialize, Serialize};

/// A memory and size profile of the mapper.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Profile {
    /// A home (cleaning robot): 4.1 m submaps at 5 cm, 10 m LiDAR.
    #[default]
    Home,
    /// An office floor: 10 m submaps at 5 cm.
    Office,
    /// An airport hall (guide robot): 10 m submaps at 10 cm.
    Airport,
}

impl std::str::FromStr for Profile {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "home" => Ok(Profile::Home),
            "office" => Ok(Profile::Office),
            "airport" => Ok(Profile::Airport),
            _ => Err(format!(
                "unknown profile {s:?}; use home, office or airport"
            )),
        }
    }
}

/// Scan preprocessing.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PreprocessSection {
    /// Beams shorter than this are dropped, metres.
    pub range_min: f32,
    /// Beams longer than this are dropped (also when the sensor reports more), metres.
    pub range_max: f32,
    /// Voxel edge for downsampling the scan points, metres; 0 disables it.
    pub voxel_size: f32,
    /// Keep one beam in this many (1 keeps all).
    pub decimation: u16,
}

/// Scan-to-submap ICP of the front-end.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IcpSection {
    /// Iteration limit.
    pub max_iterations: u16,
    /// Correspondences farther than this are ignored, metres.
    pub max_correspondence: f32,
    /// Huber threshold on point-to-line residuals, metres.
    pub huber: f64,
    /// Fewest points and correspondences a match needs.
    pub min_points: u32,
    /// While turning fast, seeds rotated by the odometry's turn are also tried, but only when
    /// the match from the odometry seed has an RMS residual above this, metres (0: always).
    pub turn_reseed_rms: f64,
    /// Motion the scan matcher measures while the odometry reports exactly none (a stalled
    /// odometry stream) is taken off the odometry's next increment.
    pub stall_compensation: bool,
    /// The reference ICP matches against (the local point map) keeps what two keyframes saw
    /// within this much path, metres; 0 restarts it every 3 m (refilled from the two newest
    /// submaps, or in the airport profile from the current scan alone).
    pub local_map_span: f64,
}

/// When a scan becomes a keyframe.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KeyframeSection {
    /// Distance travelled since the last keyframe, metres.
    pub distance: f64,
    /// Heading change since the last keyframe, radians.
    pub angle: f64,
}

/// Occupancy-grid submaps.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SubmapSection {
    /// Cell edge, metres.
    pub resolution: f32,
    /// Cells per side (the submap is `side * resolution` metres square).
    pub side: u16,
    /// A new submap starts when the robot is this far from the current submap's origin,
    /// metres.
    pub new_submap_distance: f64,
}

impl SubmapSection {
    /// Edge of a submap, metres.
    pub fn size_m(&self) -> f64 {
        f64::from(self.side) * f64::from(self.resolution)
    }
}

/// Loop closure.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LoopClosureSection {
    /// Half-width of the translation search window of the global scan-to-submap search,
    /// metres.
    pub search_window_xy: f64,
    /// Half-width of its rotation window, radians.
    pub search_window_theta: f64,
    /// Smallest accepted match score, in [0, 1].
    pub min_score: f32,
    /// Most candidate submaps searched per keyframe.
    pub max_candidates: u8,
    /// Search beyond the window (every heading, whole submaps) where the drift since a
    /// submap outgrows it; such matches count only when the following keyframes confirm them.
    pub far_search: bool,
}

/// Global pose estimation (the real-time pose of every frame).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GpeSection {
    /// Time budget per frame, microseconds; a frame that misses it gets the worst-case
    /// prediction.
    pub deadline_us: u64,
}

/// The pose-graph back-end.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BackendSection {
    /// Optimize after this many new keyframes.
    pub optimize_every_keyframes: u32,
    /// Gauss-Newton / Levenberg-Marquardt iterations per optimization.
    pub iterations: u32,
    /// Cell edge of the graph pruning (one node kept per cell and heading), metres.
    pub prune_cell_size: f64,
    /// Most work units of one back-end step (about 100 Cortex-A9 instructions each; a solve
    /// spans as many steps as it needs); 0: no limit, each step runs whole solves.
    pub work_budget: u64,
    /// Test each revisit's loop closures against the whole graph after an optimization and
    /// remove the revisit the rest of the graph disagrees with most (a look-alike place
    /// matched from several keyframes in a row).
    pub loop_consistency: bool,
}

/// How the run is scheduled.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunSection {
    /// Run the real-time part and the back-end interleaved with fixed budgets (results are
    /// identical bit for bit between runs) instead of on two threads.
    pub deterministic: bool,
    /// Run the back-end only once per this many seconds of data (tests the real-time pose's
    /// local consistency under a slow back-end); 0: no delay. `--backend-delay` overrides it.
    pub backend_delay_s: f64,
}

/// The whole configuration of `cloi map`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MapConfig {
    /// Scan preprocessing.
    pub preprocess: PreprocessSection,
    /// Front-end ICP.
    pub icp: IcpSection,
    /// Keyframe selection.
    pub keyframes: KeyframeSection,
    /// Submaps.
    pub submaps: SubmapSection,
    /// Loop closure.
    pub loop_closure: LoopClosureSection,
    /// Real-time pose estimation.
    pub gpe: GpeSection,
    /// Back-end.
    pub backend: BackendSection,
    /// Scheduling.
    pub run: RunSection,
}

impl Profile {
    /// The core's configuration of this profile: the one place the presets' values live
    /// (the firmware uses the same functions).
    pub fn core_config(self) -> MapperConfig {
        match self {
            Profile::Home => MapperConfig::home(),
            Profile::Office => MapperConfig::office(),
            Profile::Airport => MapperConfig::airport(),
        }
    }

    /// The capacities of this profile's pools (what `cloi-budget` proves).
    pub fn spec(self) -> ProfileSpec {
        match self {
            Profile::Home => HOME,
            Profile::Office => OFFICE,
            Profile::Airport => AIRPORT,
        }
    }
}

/// The real-time deadline the host gives every frame unless the file says otherwise: well
/// above a frame's typical cost on the robot computer, well below a LiDAR's 100 ms period.
const DEFAULT_DEADLINE_US: u64 = 5_000;

impl MapConfig {
    /// The preset of a profile: the core's configuration seen through the file's keys.
    pub fn preset(profile: Profile) -> Self {
        Self::from_core(
            &profile.core_config(),
            GpeSection {
                deadline_us: DEFAULT_DEADLINE_US,
            },
            RunSection {
                deterministic: false,
                backend_delay_s: 0.0,
            },
        )
    }

    /// The keys of a core configuration, with the host's own sections `gpe` and `run`.
    pub fn from_core(c: &MapperConfig, gpe: GpeSection, run: RunSection) -> Self {
        MapConfig {
            preprocess: PreprocessSection {
                range_min: c.min_range,
                range_max: c.max_range,
                voxel_size: c.preprocess.voxel_size,
                decimation: c.preprocess.decimation,
            },
            icp: IcpSection {
                max_iterations: c.icp.max_iterations,
                max_correspondence: c.icp.max_correspondence,
                huber: c.icp.huber,
                min_points: c.icp.min_points,
                turn_reseed_rms: c.turn_reseed_rms,
                stall_compensation: c.stall_motion.is_some(),
                local_map_span: c.local_span,
            },
            keyframes: KeyframeSection {
                distance: c.keyframe.distance,
                angle: c.keyframe.angle,
            },
            submaps: SubmapSection {
                resolution: c.grid.resolution,
                side: c.grid.side,
                new_submap_distance: c.submap_length,
            },
            loop_closure: LoopClosureSection {
                search_window_xy: c.loops.window_max,
                search_window_theta: c.loops.angle_max,
                min_score: c.loops.min_score,
                max_candidates: c.loops.max_candidates,
                far_search: c.loops.far_search,
            },
            gpe,
            backend: BackendSection {
                optimize_every_keyframes: c.backend.every_keyframes,
                iterations: c.backend.max_iterations,
                prune_cell_size: c.backend.prune_cell,
                work_budget: c.backend.work_budget,
                loop_consistency: c.backend.consistency_test,
            },
            run,
        }
    }

    /// `base` (the profile's core configuration) with every key of this file written into
    /// it; what the file has no key for keeps `base`'s value.
    pub fn to_core(&self, base: &MapperConfig) -> MapperConfig {
        let mut c = *base;
        let p = &self.preprocess;
        c.min_range = p.range_min;
        c.max_range = p.range_max;
        c.preprocess.voxel_size = p.voxel_size;
        c.preprocess.decimation = p.decimation;
        let i = &self.icp;
        c.icp.max_iterations = i.max_iterations;
        c.icp.max_correspondence = i.max_correspondence;
        c.icp.huber = i.huber;
        c.icp.min_points = i.min_points;
        c.turn_reseed_rms = i.turn_reseed_rms;
        c.stall_motion = i
            .stall_compensation
            .then(|| base.stall_motion.unwrap_or(MapperConfig::STALL_MOTION));
        c.local_span = i.local_map_span;
        c.keyframe.distance = self.keyframes.distance;
        c.keyframe.angle = self.keyframes.angle;
        c.grid.resolution = self.submaps.resolution;
        c.grid.side = self.submaps.side;
        c.submap_length = self.submaps.new_submap_distance;
        let l = &self.loop_closure;
        c.loops.window_max = l.search_window_xy;
        c.loops.angle_max = l.search_window_theta;
        c.loops.min_score = l.min_score;
        c.loops.max_candidates = l.max_candidates;
        c.loops.far_search = l.far_search;
        let b = &self.backend;
        c.backend.every_keyframes = b.optimize_every_keyframes;
        c.backend.max_iterations = b.iterations;
        c.backend.prune_cell = b.prune_cell_size;
        c.backend.work_budget = b.work_budget;
        c.backend.consistency_test = b.loop_consistency;
        c
    }

    /// The preset of `profile` with the TOML text `text` merged onto it; `name` names the
    /// text in errors (a file name).
    ///
    /// # Errors
    /// Invalid TOML, a key the configuration does not have, a value of the wrong type, or
    /// values that fail [`MapConfig::validate`].
    pub fn from_toml(profile: Profile, text: &str, name: &str) -> Result<Self> {
        Self::from_patches(profile, &[(text.to_owned(), name.to_owned())])
    }

    /// The preset of `profile`, overridden by the file at `path` if given, then by each
    /// `KEY=VALUE` of `sets` in order (a dotted TOML key and a TOML value, as in
    /// `loop_closure.min_score=0.6`).
    ///
    /// # Errors
    /// See [`MapConfig::from_toml`]; an unreadable file; a `--set` without `=`.
    pub fn load(profile: Profile, path: Option<&Path>, sets: &[String]) -> Result<Self> {
        let mut patches = Vec::new();
        if let Some(p) = path {
            let text =
                std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            patches.push((text, p.display().to_string()));
        }
        for set in sets {
            let Some((key, value)) = set.split_once('=') else {
                bail!("--set {set}: expected KEY=VALUE, e.g. loop_closure.min_score=0.6");
            };
            patches.push((
                format!("{} = {}", key.trim(), value.trim()),
                format!("--set {set}"),
            ));
        }
        Self::from_patches(profile, &patches)
    }

    /// The preset with each `(text, name)` TOML patch merged onto it in order, validated.
    fn from_patches(profile: Profile, patches: &[(String, String)]) -> Result<Self> {
        let mut merged = toml::Table::try_from(Self::preset(profile))
            .context("serialising the preset (a bug)")?;
        let mut names = Vec::new();
        for (text, name) in patches {
            let patch: toml::Table =
                toml::from_str(text).with_context(|| format!("{name}: not valid TOML"))?;
            merged = merge(merged, patch, "", name)?;
            names.push(name.as_str());
        }
        let name = if names.is_empty() {
            "the preset".to_owned()
        } else {
            names.join(", ")
        };
        let cfg: MapConfig = toml::Value::Table(merged)
            .try_into()
            .with_context(|| format!("{name}: invalid configuration"))?;
        cfg.validate().with_context(|| name.clone())?;
        check_core(&cfg.to_core(&profile.core_config())).with_context(|| name.clone())?;
        Ok(cfg)
    }

    /// The configuration as TOML (every field; e.g. to keep with a run's results).
    ///
    /// # Errors
    /// Never for a valid configuration (serialisation of plain numbers).
    pub fn to_toml(&self) -> Result<String> {
        toml::to_string_pretty(self).context("serialising the map configuration")
    }

    /// Checks that values are usable (positive sizes, ordered limits, scores in [0, 1]).
    ///
    /// # Errors
    /// The first offending field, by its TOML path.
    pub fn validate(&self) -> Result<()> {
        let p = &self.preprocess;
        if !(p.range_min >= 0.0 && p.range_max > p.range_min && p.range_max.is_finite()) {
            bail!("preprocess: need 0 <= range_min < range_max (finite)");
        }
        if !(p.voxel_size >= 0.0 && p.voxel_size.is_finite()) {
            bail!("preprocess.voxel_size must be >= 0");
        }
        if p.decimation == 0 {
            bail!("preprocess.decimation must be at least 1");
        }
        let i = &self.icp;
        let positive = |v: f64| v > 0.0 && v.is_finite();
        if i.max_iterations == 0 || !positive(f64::from(i.max_correspondence)) || !positive(i.huber)
        {
            bail!("icp: max_iterations, max_correspondence and huber must be positive");
        }
        if !(i.turn_reseed_rms >= 0.0 && i.turn_reseed_rms.is_finite()) {
            bail!("icp.turn_reseed_rms must be zero or positive");
        }
        if !(i.local_map_span >= 0.0 && i.local_map_span.is_finite()) {
            bail!("icp.local_map_span must be zero or positive");
        }
        let k = &self.keyframes;
        if !(k.distance > 0.0 && k.angle > 0.0) {
            bail!("keyframes: distance and angle must be positive");
        }
        let s = &self.submaps;
        if !(s.resolution > 0.0 && s.resolution.is_finite()) || s.side < 8 {
            bail!("submaps: resolution must be positive and side at least 8 cells");
        }
        if !(s.new_submap_distance > 0.0 && s.new_submap_distance < s.size_m()) {
            bail!(
                "submaps.new_submap_distance must be positive and below the submap size ({} m)",
                s.size_m()
            );
        }
        let l = &self.loop_closure;
        if !(l.search_window_xy >= 0.0 && l.search_window_theta >= 0.0) {
            bail!("loop_closure: search windows must be >= 0");
        }
        if !(0.0..=1.0).contains(&l.min_score) {
            bail!("loop_closure.min_score must be in [0, 1]");
        }
        if !(self.run.backend_delay_s >= 0.0 && self.run.backend_delay_s.is_finite()) {
            bail!("run.backend_delay_s must be a finite number of seconds >= 0");
        }
        if self.gpe.deadline_us == 0 {
            bail!("gpe.deadline_us must be positive");
        }
        let b = &self.backend;
        if b.optimize_every_keyframes == 0 || b.iterations == 0 || !positive(b.prune_cell_size) {
            bail!(
                "backend: optimize_every_keyframes, iterations and prune_cell_size must be positive"
            );
        }
        Ok(())
    }
}

/// Checks the limits a file's keys must keep against the core's own values: a loop search
/// window cannot be narrower than the core's smallest one.
fn check_core(c: &MapperConfig) -> Result<()> {
    let l = &c.loops;
    if l.window_max < l.window_min {
        bail!(
            "loop_closure.search_window_xy must be at least {} m (the smallest window)",
            l.window_min
        );
    }
    if l.angle_max < l.angle_min {
        bail!(
            "loop_closure.search_window_theta must be at least {} rad (the smallest window)",
            l.angle_min
        );
    }
    Ok(())
}

/// Merges `patch` onto `base` key by key; a key of `patch` missing in `base` is an error.
fn merge(mut base: toml::Table, patch: toml::Table, at: &str, name: &str) -> Result<toml::Table> {
    for (key, value) in patch {
        let path = if at.is_empty() {
            key.clone()
        } else {
            format!("{at}.{key}")
        };
        let Some(slot) = base.get_mut(&key) else {
            let known: Vec<&str> = base.keys().map(String::as_str).collect();
            let place = if at.is_empty() {
                "at the top level".to_owned()
            } else {
                format!("in [{at}]")
            };
            bail!(
                "{name}: unknown key `{path}`; the keys {place} are: {}",
                known.join(", ")
            );
        };
        match (slot, value) {
            (toml::Value::Table(b), toml::Value::Table(p)) => {
                let merged = merge(std::mem::take(b), p, &path, name)?;
                *b = merged;
            }
            (toml::Value::Table(_), _) => bail!("{name}: `{path}` must be a table [{path}]"),
            (slot, value) => *slot = value,
        }
    }
    Ok(base)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn example() -> String {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/map-config.toml");
        std::fs::read_to_string(&path).expect("docs/map-config.toml")
    }

    #[test]
    fn presets_are_valid_and_differ_where_documented() {
        for p in [Profile::Home, Profile::Office, Profile::Airport] {
            MapConfig::preset(p).validate().expect("valid preset");
        }
        let home = MapConfig::preset(Profile::Home);
        let office = MapConfig::preset(Profile::Office);
        let airport = MapConfig::preset(Profile::Airport);
        assert!((home.submaps.size_m() - 4.1).abs() < 1e-6);
        assert!((office.submaps.size_m() - 10.0).abs() < 1e-6);
        assert!((airport.submaps.size_m() - 10.0).abs() < 1e-6);
        assert_eq!(airport.submaps.resolution, 0.1);
        // The larger profiles differ from home's ICP only in when the turn seeds are tried
        // and in their local maps, which slide over 30 m of path (home's restarts).
        assert!(home.icp.stall_compensation && home.icp.turn_reseed_rms > 0.0);
        assert_eq!(home.icp.local_map_span, 0.0);
        let larger = IcpSection {
            turn_reseed_rms: 0.0,
            local_map_span: 30.0,
            ..home.icp
        };
        assert_eq!(office.icp, larger);
        assert_eq!(airport.icp, larger);
    }

    #[test]
    fn documented_example_parses_and_equals_the_home_preset() {
        let cfg = MapConfig::from_toml(Profile::Office, &example(), "docs/map-config.toml")
            .expect("example parses");
        // The example spells out every home value, so it turns any preset into home.
        assert_eq!(cfg, MapConfig::preset(Profile::Home));
        // And it names every field: a full parse without merging works too.
        let full: MapConfig = toml::from_str(&example()).expect("complete");
        assert_eq!(full, cfg);
    }

    #[test]
    fn a_file_overrides_only_what_it_names() {
        let text = "[icp]\nhuber = 0.1\n\n[run]\ndeterministic = true\n";
        let cfg = MapConfig::from_toml(Profile::Airport, text, "x.toml").unwrap();
        let mut want = MapConfig::preset(Profile::Airport);
        want.icp.huber = 0.1;
        want.run.deterministic = true;
        assert_eq!(cfg, want);
        assert_eq!(
            MapConfig::from_toml(Profile::Office, "", "empty.toml").unwrap(),
            MapConfig::preset(Profile::Office)
        );
    }

    #[test]
    fn round_trip_through_toml() {
        let cfg = MapConfig::preset(Profile::Airport);
        let text = cfg.to_toml().unwrap();
        assert_eq!(
            MapConfig::from_toml(Profile::Home, &text, "t").unwrap(),
            cfg
        );
    }

    #[test]
    fn unknown_keys_and_bad_values_are_clear_errors() {
        let err =
            MapConfig::from_toml(Profile::Home, "[icp]\nmax_iter = 3\n", "my.toml").unwrap_err();
        let msg = format!("{err:#}");
        assert!(msg.contains("my.toml: unknown key `icp.max_iter`"), "{msg}");
        assert!(msg.contains("max_iterations"), "{msg}");
        let err = MapConfig::from_toml(Profile::Home, "[loops]\nmin_score = 0.5\n", "my.toml")
            .unwrap_err();
        let msg = format!("{err:#}");
        assert!(
            msg.contains("unknown key `loops`") && msg.contains("loop_closure"),
            "{msg}"
        );
        let err = MapConfig::from_toml(Profile::Home, "icp = 3\n", "my.toml").unwrap_err();
        assert!(format!("{err:#}").contains("`icp` must be a table"));
        let err =
            MapConfig::from_toml(Profile::Home, "[icp]\nhuber = \"x\"\n", "my.toml").unwrap_err();
        let msg = format!("{err:#}");
        assert!(msg.contains("my.toml: invalid configuration"), "{msg}");
        let err = MapConfig::from_toml(
            Profile::Home,
            "[loop_closure]\nmin_score = 1.5\n",
            "my.toml",
        )
        .unwrap_err();
        assert!(format!("{err:#}").contains("min_score"));
        let err = MapConfig::from_toml(Profile::Home, "[icp\n", "my.toml").unwrap_err();
        assert!(format!("{err:#}").contains("my.toml: not valid TOML"));
    }

    const PROFILES: [Profile; 3] = [Profile::Home, Profile::Office, Profile::Airport];

    #[test]
    fn presets_are_the_core_configurations() {
        // The firmware, which has no host, uses the core's presets directly and must map as
        // `cloi map --profile P` does.
        for p in PROFILES {
            assert_eq!(
                MapConfig::preset(p).to_core(&p.core_config()),
                p.core_config(),
                "{p:?}"
            );
        }
    }

    /// `value` moved to another valid value of its type.
    fn changed(value: &toml::Value) -> toml::Value {
        match value {
            toml::Value::Boolean(b) => toml::Value::Boolean(!b),
            toml::Value::Integer(i) => toml::Value::Integer(i + 1),
            // Halfway towards zero stays inside every documented range ([0, 1] scores,
            // windows at least the core's smallest, sizes below the submap).
            toml::Value::Float(f) if *f > 1.0 => toml::Value::Float(f * 0.75),
            toml::Value::Float(f) if *f > 0.0 => toml::Value::Float(f * 0.9),
            toml::Value::Float(f) => toml::Value::Float(f + 0.5),
            other => panic!("no test value for {other:?}"),
        }
    }

    #[test]
    fn every_key_changes_what_it_names_in_every_profile() {
        for p in PROFILES {
            let preset = MapConfig::preset(p);
            let core = p.core_config();
            let table = toml::Table::try_from(preset).unwrap();
            let mut keys = 0;
            for (section, fields) in &table {
                for (key, value) in fields.as_table().expect("sections are tables") {
                    let set = format!("{section}.{key}={}", changed(value));
                    let cfg = MapConfig::load(p, None, std::slice::from_ref(&set))
                        .unwrap_or_else(|e| panic!("{p:?} {set}: {e:#}"));
                    assert_ne!(cfg, preset, "{p:?} {set} changed nothing");
                    // The host's own sections time and schedule the run; every other key
                    // must reach the core's configuration.
                    if section != "gpe" && section != "run" {
                        assert_ne!(
                            cfg.to_core(&core),
                            core,
                            "{p:?} {set} does not reach the mapper"
                        );
                    }
                    // And the file's view of the core agrees with the key.
                    let back = MapConfig::from_core(&cfg.to_core(&core), cfg.gpe, cfg.run);
                    assert_eq!(back, cfg, "{p:?} {set} does not round-trip");
                    keys += 1;
                }
            }
            assert!(keys >= 20, "{p:?}: only {keys} keys");
        }
    }

    #[test]
    fn set_overrides_the_file_and_names_itself_in_errors() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("c.toml");
        std::fs::write(&file, "[icp]\nhuber = 0.1\n").unwrap();
        let sets = [
            "icp.huber=0.2".to_owned(),
            "run.deterministic = true".to_owned(),
        ];
        let cfg = MapConfig::load(Profile::Office, Some(&file), &sets).unwrap();
        assert_eq!(cfg.icp.huber, 0.2);
        assert!(cfg.run.deterministic);
        let err = MapConfig::load(Profile::Office, None, &["icp.hubr=1".to_owned()]).unwrap_err();
        let msg = format!("{err:#}");
        assert!(
            msg.contains("--set icp.hubr=1: unknown key `icp.hubr`"),
            "{msg}"
        );
        let err = MapConfig::load(Profile::Office, None, &["icp.huber".to_owned()]).unwrap_err();
        assert!(format!("{err:#}").contains("KEY=VALUE"));
    }

    #[test]
    fn loop_windows_below_the_cores_smallest_are_refused() {
        for key in ["search_window_xy", "search_window_theta"] {
            let set = format!("loop_closure.{key}=0");
            let err = MapConfig::load(Profile::Office, None, &[set]).unwrap_err();
            let msg = format!("{err:#}");
            assert!(msg.contains(key) && msg.contains("at least"), "{msg}");
        }
    }

    #[test]
    fn profile_names() {
        assert_eq!("Office".parse::<Profile>(), Ok(Profile::Office));
        assert!("garage".parse::<Profile>().is_err());
    }
}
