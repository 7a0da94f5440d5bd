//! What `cloi map` writes, besides the map pictures of [`crate::io::map_out`]:
//!
//! * [`write_tum`] and [`TumWriter`], a planar trajectory in TUM format with exact nanosecond
//!   stamps;
//! * [`MapReport`], the run's `report.json`;
//! * [`compose_global_grid`], the global occupancy grid from submaps at their (optimized)
//!   poses, ready for [`crate::io::map_out::write_map_server`] and
//!   [`crate::io::map_out::write_map_png`] through [`OwnedGrid::as_grid_ref`];
//! * [`CountingAlloc`] and [`peak_heap_bytes`], the host's heap high-water mark (the `cloi`
//!   binary installs the allocator);
//! * [`MapProgress`], a progress bar on standard error, hidden when it is not a terminal.

use std::alloc::{GlobalAlloc, Layout, System};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::io::{IsTerminal, Write as _};
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use anyhow::{bail, Context, Result};
use cloi_core::frontend::grid::LOG_ODDS_UNIT;
use cloi_core::Se2;
use serde::{Deserialize, Serialize};

use super::input::{InputSize, InputStats};
use crate::io::atomic;
use crate::io::map_out::GridRef;

// ---------------------------------------------------------------------------------------
// Trajectories

/// The header line of a TUM file.
const TUM_HEADER: &str = "# timestamp tx ty tz qx qy qz qw\n";

/// Appends one TUM line: `t x y z qx qy qz qw`, `t` in seconds with the nanosecond stamp
/// written exactly (9 decimals), `z = 0`, the heading as a rotation about z.
fn tum_line(s: &mut String, t_ns: i64, p: &Se2) {
    let sign = if t_ns < 0 { "-" } else { "" };
    let abs = t_ns.unsigned_abs();
    let half = 0.5 * p.theta;
    let _ = writeln!(
        s,
        "{sign}{}.{:09} {:.9} {:.9} 0.000000000 0.000000000 0.000000000 {:.9} {:.9}",
        abs / 1_000_000_000,
        abs % 1_000_000_000,
        p.x,
        p.y,
        half.sin(),
        half.cos()
    );
}

/// The TUM text of a planar trajectory (see [`TumWriter`] for the format).
pub fn tum_text(poses: &[(i64, Se2)]) -> String {
    let mut s = String::with_capacity(poses.len() * 110 + 40);
    s.push_str(TUM_HEADER);
    for (t_ns, p) in poses {
        tum_line(&mut s, *t_ns, p);
    }
    s
}

/// Writes a planar trajectory as a TUM file (atomically); read it back with
/// [`crate::io::tum::read_tum`].
///
/// # Errors
/// Any IO error.
pub fn write_tum(path: &Path, poses: &[(i64, Se2)]) -> Result<()> {
    atomic::write_file(path, tum_text(poses).as_bytes())
}

/// A TUM file written a pose at a time (a trajectory of any length, never held whole), which
/// appears at its path only on [`TumWriter::commit`]. Lines as [`tum_text`]'s: `t x y z qx qy
/// qz qw`, `t` in seconds with the nanosecond stamp written exactly, `z = 0`, the heading as
/// a rotation about z.
#[derive(Debug)]
pub struct TumWriter {
    file: atomic::AtomicFile,
    line: String,
}

impl TumWriter {
    /// Starts `path`.
    ///
    /// # Errors
    /// The folder cannot be written.
    pub fn create(path: &Path) -> Result<Self> {
        let mut file = atomic::AtomicFile::create(path)?;
        file.write_all(TUM_HEADER.as_bytes())?;
        Ok(TumWriter {
            file,
            line: String::with_capacity(128),
        })
    }

    /// Appends the pose `p` at `t_ns`.
    ///
    /// # Errors
    /// A write error.
    pub fn push(&mut self, t_ns: i64, p: &Se2) -> Result<()> {
        self.line.clear();
        tum_line(&mut self.line, t_ns, p);
        self.file
            .write_all(self.line.as_bytes())
            .with_context(|| format!("writing {}", self.file.target().display()))
    }

    /// Flushes the file and moves it to its path.
    ///
    /// # Errors
    /// An IO error.
    pub fn commit(self) -> Result<()> {
        self.file.commit()
    }
}

// ---------------------------------------------------------------------------------------
// Report

/// `report.json` of a run.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MapReport {
    /// Scans read.
    pub scans: u64,
    /// Scans the mapper rejected (bad stamps, unusable geometry).
    pub scans_rejected: u64,
    /// LiDAR keyframes.
    pub keyframes: u64,
    /// Pose-graph nodes at the end.
    pub nodes: u64,
    /// Pose-graph edges at the end.
    pub edges: u64,
    /// Loop closures accepted.
    pub loop_closures: u64,
    /// Seconds of data (last stamp minus first).
    pub data_seconds: f64,
    /// Wall-clock seconds of the run.
    pub wall_seconds: f64,
    /// Largest heap in use during the run (bytes), when measured (the `cloi` binary).
    pub peak_heap_bytes: Option<u64>,
    /// Largest resident memory of the whole process so far (bytes; Linux's `VmHWM`), read
    /// after every output but this report was written.
    #[serde(default)]
    pub peak_rss_bytes: Option<u64>,
    /// Largest step between consecutive real-time poses minus the odometry step, metres.
    pub gpe_max_jump_m: f64,
    /// Real-time poses per wall-clock second.
    pub gpe_rate_hz: f64,
    /// Anything else, written as further top-level keys.
    #[serde(flatten)]
    pub extra: BTreeMap<String, serde_json::Value>,
}

impl MapReport {
    /// Data seconds per wall-clock second.
    pub fn speed(&self) -> f64 {
        self.data_seconds / self.wall_seconds.max(1e-9)
    }

    /// Adds the input's counts under `input` in [`MapReport::extra`].
    pub fn add_input_stats(&mut self, stats: &InputStats) {
        let offset = stats.laser_offset.map(|o| [o.x, o.y, o.theta]);
        self.extra.insert(
            "input".into(),
            serde_json::json!({
                "scans": stats.scans,
                "odometry": stats.odometry,
                "odometry_from_scans": stats.odometry_from_scans,
                "gyro": stats.gyro,
                "backwards_stamps": stats.backwards_stamps,
                "skipped": stats.skipped,
                "laser_offset": offset,
                "laser_offset_source": stats.laser_offset_source,
                "warnings": stats.warnings,
            }),
        );
    }

    /// Writes the report as pretty JSON (atomically).
    ///
    /// # Errors
    /// Any IO error.
    pub fn write(&self, path: &Path) -> Result<()> {
        let mut text = serde_json::to_string_pretty(self).context("serialising the report")?;
        text.push('\n');
        atomic::write_file(path, text.as_bytes())
    }
}

// ---------------------------------------------------------------------------------------
// Global grid

/// A submap as the mapper holds it: `side x side` cells of `resolution` metres centred on
/// `origin`, row-major from the cell at local (-side/2, -side/2), log-odds in units of
/// [`LOG_ODDS_UNIT`] (0: unknown).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SubmapView<'a> {
    /// Pose of the submap's centre in the world (optimized).
    pub origin: Se2,
    /// Cells per side.
    pub side: usize,
    /// Cell edge, metres.
    pub resolution: f32,
    /// `side * side` log-odds cells.
    pub cells: &'a [i8],
}

/// An owned occupancy grid in the conventions of [`GridRef`] (-1 unknown, 0..=100 percent).
#[derive(Debug, Clone, PartialEq)]
pub struct OwnedGrid {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Cell edge, metres.
    pub resolution: f64,
    /// World pose `(x, y, yaw)` of the outer corner of cell (0, 0); yaw is 0.
    pub origin: (f64, f64, f64),
    /// `width * height` cells, row 0 at the lowest y.
    pub cells: Vec<i8>,
}

impl OwnedGrid {
    /// The borrowed view the map writers take.
    pub fn as_grid_ref(&self) -> GridRef<'_> {
        GridRef {
            width: self.width,
            height: self.height,
            resolution: self.resolution,
            origin: self.origin,
            cells: &self.cells,
        }
    }

    /// The cell holding a world point, if inside.
    pub fn cell_at(&self, x: f64, y: f64) -> Option<i8> {
        let cx = ((x - self.origin.0) / self.resolution).floor();
        let cy = ((y - self.origin.1) / self.resolution).floor();
        if cx < 0.0 || cy < 0.0 || cx >= self.width as f64 || cy >= self.height as f64 {
            return None;
        }
        Some(self.cells[cy as usize * self.width + cx as usize])
    }
}

/// Largest global grid composed (cells).
const MAX_GLOBAL_CELLS: usize = 200_000_000;

/// Composes the submaps into one axis-aligned grid at the finest submap resolution.
///
/// Every global cell takes, from each submap that covers its centre, the submap cell under
/// that centre (nearest cell), and adds up their log-odds: independent evidence combines by
/// adding log-odds. A cell no submap has observed (all log-odds 0) stays unknown (-1);
/// others hold the occupancy probability in percent. The grid spans the submaps' rotated
/// squares.
///
/// # Errors
/// No submaps, a submap whose cells do not match its side, a non-positive resolution, a
/// non-finite pose, or a grid of more than 200 million cells.
pub fn compose_global_grid(submaps: &[SubmapView<'_>]) -> Result<OwnedGrid> {
    if submaps.is_empty() {
        bail!("no submaps to compose");
    }
    let mut res = f64::INFINITY;
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for (i, s) in submaps.iter().enumerate() {
        if s.side == 0 || s.cells.len() != s.side * s.side {
            bail!(
                "submap {i}: {} cells for a side of {}",
                s.cells.len(),
                s.side
            );
        }
        if !(s.resolution.is_finite() && s.resolution > 0.0) {
            bail!("submap {i}: resolution {} is not positive", s.resolution);
        }
        if !s.origin.is_finite() {
            bail!("submap {i}: pose is not finite");
        }
        res = res.min(f64::from(s.resolution));
        let half = 0.5 * s.side as f64 * f64::from(s.resolution);
        for (cx, cy) in [(-half, -half), (half, -half), (-half, half), (half, half)] {
            let p = s.origin.transform_point(&nalgebra::Vector2::new(cx, cy));
            for k in 0..2 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
    }
    // Snap the corner to the cell lattice so that equal inputs give equal grids (with a
    // tolerance for the rounding of rotated corners).
    const SNAP: f64 = 1e-6;
    let x0 = (lo[0] / res + SNAP).floor() * res;
    let y0 = (lo[1] / res + SNAP).floor() * res;
    let width = ((hi[0] - x0) / res - SNAP).ceil().max(1.0) as usize;
    let height = ((hi[1] - y0) / res - SNAP).ceil().max(1.0) as usize;
    if width.saturating_mul(height) > MAX_GLOBAL_CELLS {
        bail!("the global grid would have {width} x {height} cells");
    }
    let mut sums = vec![0i32; width * height];
    let mut seen = vec![false; width * height];
    for s in submaps {
        let sres = f64::from(s.resolution);
        let half = 0.5 * s.side as f64 * sres;
        let to_local = s.origin.inverse();
        // Bounding box of this submap in global cells.
        let r = half * std::f64::consts::SQRT_2;
        let gx0 = (((s.origin.x - r - x0) / res).floor().max(0.0)) as usize;
        let gy0 = (((s.origin.y - r - y0) / res).floor().max(0.0)) as usize;
        let gx1 = ((((s.origin.x + r - x0) / res).ceil()) as usize).min(width);
        let gy1 = ((((s.origin.y + r - y0) / res).ceil()) as usize).min(height);
        for gy in gy0..gy1 {
            let wy = y0 + (gy as f64 + 0.5) * res;
            for gx in gx0..gx1 {
                let wx = x0 + (gx as f64 + 0.5) * res;
                let l = to_local.transform_point(&nalgebra::Vector2::new(wx, wy));
                let ix = ((l.x + half) / sres).floor();
                let iy = ((l.y + half) / sres).floor();
                if ix < 0.0 || iy < 0.0 || ix >= s.side as f64 || iy >= s.side as f64 {
                    continue;
                }
                let v = s.cells[iy as usize * s.side + ix as usize];
                if v != 0 {
                    let k = gy * width + gx;
                    sums[k] += i32::from(v);
                    seen[k] = true;
                }
            }
        }
    }
    let cells = sums
        .iter()
        .zip(&seen)
        .map(|(&l, &seen)| {
            if !seen {
                return -1;
            }
            let p = 1.0 / (1.0 + (-(l as f64) * f64::from(LOG_ODDS_UNIT)).exp());
            (p * 100.0).round() as i8
        })
        .collect();
    Ok(OwnedGrid {
        width,
        height,
        resolution: res,
        origin: (x0, y0, 0.0),
        cells,
    })
}

// ---------------------------------------------------------------------------------------
// Heap

static HEAP_CURRENT: AtomicU64 = AtomicU64::new(0);
static HEAP_PEAK: AtomicU64 = AtomicU64::new(0);
static HEAP_COUNTING: AtomicBool = AtomicBool::new(false);

/// The system allocator, counting the bytes in use and their high-water mark. The `cloi`
/// binary installs it (`#[global_allocator]`); [`peak_heap_bytes`] reads it.
#[derive(Debug, Clone, Copy, Default)]
pub struct CountingAlloc;

fn grew(size: usize) {
    let now = HEAP_CURRENT.fetch_add(size as u64, Ordering::Relaxed) + size as u64;
    HEAP_PEAK.fetch_max(now, Ordering::Relaxed);
}

fn shrank(size: usize) {
    HEAP_CURRENT.fetch_sub(size as u64, Ordering::Relaxed);
}

// SAFETY: every call is forwarded unchanged to the system allocator; the counters are
// atomics and never allocate.
#[allow(unsafe_code)]
unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's contract for `layout` is passed on.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            HEAP_COUNTING.store(true, Ordering::Relaxed);
            grew(layout.size());
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: as for `alloc`.
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            HEAP_COUNTING.store(true, Ordering::Relaxed);
            grew(layout.size());
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from this allocator, i.e. from `System`, with `layout`.
        unsafe { System.dealloc(ptr, layout) };
        shrank(layout.size());
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: `ptr` came from `System` with `layout`; the caller guarantees `new_size`.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            if new_size >= layout.size() {
                grew(new_size - layout.size());
            } else {
                shrank(layout.size() - new_size);
            }
        }
        p
    }
}

/// Heap bytes in use, `None` when [`CountingAlloc`] is not the global allocator (e.g. in
/// the library's tests).
pub fn current_heap_bytes() -> Option<u64> {
    HEAP_COUNTING
        .load(Ordering::Relaxed)
        .then(|| HEAP_CURRENT.load(Ordering::Relaxed))
}

/// The most heap bytes in use at once since the start (or the last
/// [`reset_peak_heap`]), `None` when [`CountingAlloc`] is not the global allocator.
pub fn peak_heap_bytes() -> Option<u64> {
    HEAP_COUNTING
        .load(Ordering::Relaxed)
        .then(|| HEAP_PEAK.load(Ordering::Relaxed))
}

/// The process's peak resident memory so far (`VmHWM` of `/proc/self/status`), bytes; `None`
/// where the kernel does not tell.
pub fn peak_rss_bytes() -> Option<u64> {
    proc_status_bytes("self", "VmHWM")
}

/// A memory line (`VmRSS`, `VmHWM`, ...) of `/proc/PROCESS/status` (`PROCESS`: a process id,
/// or `self`), bytes; `None` where the kernel does not tell or the process has ended.
pub fn proc_status_bytes(process: &str, key: &str) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{process}/status")).ok()?;
    let kb = status
        .lines()
        .find_map(|l| l.strip_prefix(key)?.strip_prefix(':'))?
        .trim()
        .strip_suffix("kB")?
        .trim()
        .parse::<u64>()
        .ok()?;
    Some(kb * 1024)
}

/// Restarts the high-water mark from the bytes in use now (to measure one phase).
pub fn reset_peak_heap() {
    HEAP_PEAK.store(HEAP_CURRENT.load(Ordering::Relaxed), Ordering::Relaxed);
}

// ---------------------------------------------------------------------------------------
// Progress

/// A progress bar for reading an input, on standard error; hidden (and free) when standard
/// error is not a terminal.
#[derive(Debug)]
pub struct MapProgress {
    bar: indicatif::ProgressBar,
    size: InputSize,
}

impl MapProgress {
    /// A bar for an input of `size`, shown only on a terminal.
    pub fn new(size: InputSize) -> Self {
        Self::with_visibility(size, std::io::stderr().is_terminal())
    }

    /// A bar that is drawn if `visible` (tests use a hidden one).
    pub fn with_visibility(size: InputSize, visible: bool) -> Self {
        let (len, template) = match size {
            InputSize::Bytes(n) => (
                Some(n),
                "{spinner} [{elapsed_precise}] {wide_bar} {bytes}/{total_bytes} ({eta}) {msg}",
            ),
            // Thousandths of a second of data.
            InputSize::Seconds(s) => (
                Some((s * 1e3).max(0.0) as u64),
                "{spinner} [{elapsed_precise}] {wide_bar} {percent}% ({eta}) {msg}",
            ),
            InputSize::Unknown => (None, "{spinner} [{elapsed_precise}] {bytes} {msg}"),
        };
        let bar = if !visible {
            indicatif::ProgressBar::hidden()
        } else if let Some(n) = len {
            indicatif::ProgressBar::new(n)
        } else {
            indicatif::ProgressBar::new_spinner()
        };
        if let Ok(style) = indicatif::ProgressStyle::with_template(template) {
            bar.set_style(style);
        }
        Self { bar, size }
    }

    /// Moves the bar to where the input's counts say it is, with a message (e.g. the scans
    /// mapped). Cheap: call it every few hundred events.
    pub fn update(&self, stats: &InputStats, message: &str) {
        let pos = match self.size {
            InputSize::Bytes(_) | InputSize::Unknown => stats.bytes_read,
            InputSize::Seconds(_) => (stats.data_seconds() * 1e3) as u64,
        };
        self.bar.set_position(pos);
        self.bar.set_message(message.to_owned());
    }

    /// Where the bar is (in its units: bytes or thousandths of a data second).
    pub fn position(&self) -> u64 {
        self.bar.position()
    }

    /// Removes the bar.
    pub fn finish(&self) {
        self.bar.finish_and_clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::tum::read_tum;

    #[test]
    fn tum_round_trip_through_the_reader() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.tum");
        let poses = vec![
            (976_052_857_337_530_000, Se2::new(1.0, 2.0, 0.5)),
            (976_052_857_537_530_001, Se2::new(-1.5, 0.25, -3.0)),
            (-1_500_000_000, Se2::new(0.0, 0.0, 3.1)),
        ];
        write_tum(&path, &poses).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert!(lines[1].starts_with("976052857.337530000 1.000000000 2.000000000 0.000000000 "));
        assert!(lines[2].starts_with("976052857.537530001 "));
        assert!(lines[3].starts_with("-1.500000000 "));
        let back = read_tum(&path).unwrap();
        assert_eq!(back.len(), 3);
        for ((t, p), b) in poses.iter().zip(&back) {
            assert!((*t as f64 * 1e-9 - b.t).abs() < 1e-6);
            assert!((b.p.x - p.x).abs() < 1e-9 && (b.p.y - p.y).abs() < 1e-9);
            assert_eq!(b.p.z, 0.0);
            let yaw = b.q.euler_angles().2;
            assert!(
                cloi_core::geom::wrap_angle(yaw - p.theta).abs() < 1e-8,
                "{yaw}"
            );
        }
    }

    #[test]
    fn report_is_pretty_json_with_extra_keys() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("report.json");
        let mut r = MapReport {
            scans: 10,
            keyframes: 3,
            data_seconds: 20.0,
            wall_seconds: 0.1,
            peak_heap_bytes: Some(1234),
            peak_rss_bytes: Some(4321),
            ..MapReport::default()
        };
        r.extra.insert("note".into(), serde_json::json!("x"));
        let stats = InputStats {
            scans: 10,
            backwards_stamps: 2,
            ..InputStats::default()
        };
        r.add_input_stats(&stats);
        r.write(&path).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.contains("\n  \"scans\": 10,"), "{text}");
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        for key in [
            "scans",
            "scans_rejected",
            "keyframes",
            "nodes",
            "edges",
            "loop_closures",
            "data_seconds",
            "wall_seconds",
            "peak_heap_bytes",
            "peak_rss_bytes",
            "gpe_max_jump_m",
            "gpe_rate_hz",
        ] {
            assert!(v.get(key).is_some(), "{key} missing");
        }
        assert_eq!(v["note"], "x");
        assert_eq!(v["input"]["backwards_stamps"], 2);
        let back: MapReport = serde_json::from_str(&text).unwrap();
        assert_eq!(back, r);
        assert!((r.speed() - 200.0).abs() < 1e-9);
    }

    /// A submap with one occupied cell at local `(lx, ly)`, a free cell beside it.
    fn submap(side: usize, res: f32, lx: f64, ly: f64) -> Vec<i8> {
        let mut cells = vec![0i8; side * side];
        let half = side as f64 * f64::from(res) / 2.0;
        let ix = ((lx + half) / f64::from(res)) as usize;
        let iy = ((ly + half) / f64::from(res)) as usize;
        cells[iy * side + ix] = 40;
        cells[iy * side + ix - 1] = -30;
        cells
    }

    #[test]
    fn two_submaps_compose_into_one_grid() {
        let res = 0.1f32;
        let a_cells = submap(20, res, 0.55, 0.35);
        // The second submap is turned by 90 degrees: its local (0.55, 0.35) lies at
        // world (5 - 0.35, 0.55).
        let b_cells = submap(20, res, 0.55, 0.35);
        let a = SubmapView {
            origin: Se2::new(0.0, 0.0, 0.0),
            side: 20,
            resolution: res,
            cells: &a_cells,
        };
        let b = SubmapView {
            origin: Se2::new(5.0, 0.0, std::f64::consts::FRAC_PI_2),
            side: 20,
            resolution: res,
            cells: &b_cells,
        };
        let g = compose_global_grid(&[a, b]).unwrap();
        assert_eq!(g.resolution, f64::from(res));
        // Spans x from -1 to 6 and y from -1 to 1 (whole cells).
        assert!(
            (g.origin.0 + 1.0).abs() < 1e-6 && (g.origin.1 + 1.0).abs() < 1e-6,
            "{:?}",
            g.origin
        );
        assert_eq!((g.width, g.height), (70, 20));
        assert_eq!(g.cells.len(), 70 * 20);
        let occupied = |x: f64, y: f64| g.cell_at(x, y).unwrap();
        // Occupied cells: probability of 40 units (4 nats) = 98 %.
        assert_eq!(occupied(0.55, 0.35), 98);
        assert_eq!(occupied(5.0 - 0.35, 0.55), 98);
        // Free neighbours: -30 units, 5 %; a's is at -x, b's at -y of the world.
        assert_eq!(occupied(0.45, 0.35), 5);
        assert_eq!(occupied(5.0 - 0.35, 0.45), 5);
        // Everything else is unknown, and exactly four cells are known.
        assert_eq!(occupied(2.5, 0.0), -1);
        assert_eq!(g.cells.iter().filter(|&&c| c >= 0).count(), 4);
        // Overlap adds evidence: the same submap twice is more certain.
        let g2 = compose_global_grid(&[a, a]).unwrap();
        assert_eq!(g2.cell_at(0.45, 0.35), Some(0));
        assert_eq!(g2.cell_at(0.55, 0.35), Some(100));
        // The grid feeds the existing map writers.
        let dir = tempfile::tempdir().unwrap();
        crate::io::map_out::write_map_server(dir.path(), "map", &g.as_grid_ref()).unwrap();
        assert!(dir.path().join("map.pgm").exists());
    }

    #[test]
    fn bad_submaps_are_errors() {
        assert!(compose_global_grid(&[]).is_err());
        let cells = vec![0i8; 10];
        let s = SubmapView {
            origin: Se2::IDENTITY,
            side: 4,
            resolution: 0.05,
            cells: &cells,
        };
        assert!(compose_global_grid(&[s]).is_err());
        let cells = vec![0i8; 16];
        let s = SubmapView {
            origin: Se2::new(f64::NAN, 0.0, 0.0),
            side: 4,
            resolution: 0.05,
            cells: &cells,
        };
        assert!(compose_global_grid(&[s]).is_err());
    }

    #[test]
    fn heap_counters_and_hidden_progress() {
        // The library's tests run on the system allocator: nothing is measured.
        assert_eq!(peak_heap_bytes(), None);
        grew(100);
        shrank(100);
        let p = MapProgress::with_visibility(InputSize::Bytes(1000), false);
        let stats = InputStats {
            bytes_read: 400,
            ..InputStats::default()
        };
        p.update(&stats, "10 scans");
        assert_eq!(p.position(), 400);
        p.finish();
        let p = MapProgress::with_visibility(InputSize::Seconds(10.0), false);
        let stats = InputStats {
            first_ns: Some(0),
            last_ns: Some(2_500_000_000),
            ..InputStats::default()
        };
        p.update(&stats, "");
        assert_eq!(p.position(), 2500);
    }
}
