//! Map outputs: `map.pgm` + `map.yaml` (ROS `map_server` conventions), `map.png` with the
//! trajectory drawn, and `result.mcap` (map, path and poses for Foxglove). Every file is
//! written atomically.
//!
//! Cells follow `nav_msgs/OccupancyGrid`: row-major from the cell at `origin`, row 0 at the
//! lowest y; -1 unknown, 0..=100 occupancy probability in percent. Picture rows run the other
//! way (row 0 at the top, highest y), as `map_server` expects.

use std::path::Path;

use anyhow::{bail, Result};
use image::{GrayImage, Luma, Rgb, RgbImage};

use crate::atomic;
use crate::bag::BagWriter;
use crate::ros2::{Header, MapMetaData, OccupancyGrid, Path as PathMsg, Pose, PoseStamped, Time};

/// A borrowed occupancy grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridRef<'a> {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Cell edge (m).
    pub resolution: f64,
    /// Map-frame pose `(x, y, yaw)` of the outer corner of cell (0, 0).
    pub origin: (f64, f64, f64),
    /// `width * height` cells: -1 unknown, 0..=100 percent occupied.
    pub cells: &'a [i8],
}

/// `map_server` thresholds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapThresholds {
    /// Cells at least this likely occupied are drawn black.
    pub occupied: f64,
    /// Cells at most this likely occupied are drawn white.
    pub free: f64,
}

impl Default for MapThresholds {
    fn default() -> Self {
        Self {
            occupied: 0.65,
            free: 0.196,
        }
    }
}

/// Pixel values of the trinary `map_server` picture.
const OCCUPIED_PIXEL: u8 = 0;
const FREE_PIXEL: u8 = 254;
const UNKNOWN_PIXEL: u8 = 205;

impl GridRef<'_> {
    fn check(&self) -> Result<()> {
        if self.width == 0 || self.height == 0 || self.cells.len() != self.width * self.height {
            bail!(
                "grid of {}x{} cells has {} values",
                self.width,
                self.height,
                self.cells.len()
            );
        }
        if !(self.resolution.is_finite() && self.resolution > 0.0) {
            bail!("grid resolution {} is not positive", self.resolution);
        }
        Ok(())
    }

    /// The grey picture (row 0 = top = highest y).
    pub fn to_image(&self, thresholds: MapThresholds) -> Result<GrayImage> {
        self.check()?;
        let mut img = GrayImage::new(self.width as u32, self.height as u32);
        for (row, cells) in self.cells.chunks_exact(self.width).enumerate() {
            let y = (self.height - 1 - row) as u32;
            for (col, &c) in cells.iter().enumerate() {
                let v = if c < 0 {
                    UNKNOWN_PIXEL
                } else if f64::from(c) / 100.0 >= thresholds.occupied {
                    OCCUPIED_PIXEL
                } else if f64::from(c) / 100.0 <= thresholds.free {
                    FREE_PIXEL
                } else {
                    UNKNOWN_PIXEL
                };
                img.put_pixel(col as u32, y, Luma([v]));
            }
        }
        Ok(img)
    }

    /// Picture coordinates (column, row from the top) of a map-frame point.
    pub fn to_pixel(&self, x: f64, y: f64) -> (f64, f64) {
        let (ox, oy, yaw) = self.origin;
        let (c, s) = (yaw.cos(), yaw.sin());
        let (dx, dy) = (x - ox, y - oy);
        let gx = (c * dx + s * dy) / self.resolution;
        let gy = (-s * dx + c * dy) / self.resolution;
        (gx, self.height as f64 - gy)
    }
}

/// `v` in the fewest digits that read back to it: a value that came from single precision
/// (the core's grids are f32) is written as that f32 (`0.05`, not `0.05000000074505806`).
fn shortest(v: f64) -> String {
    let single = v as f32;
    if f64::from(single) == v {
        single.to_string()
    } else {
        v.to_string()
    }
}

/// The `map.yaml` text for a picture file name.
pub fn map_yaml(image_file: &str, grid: &GridRef<'_>, thresholds: MapThresholds) -> String {
    format!(
        "image: {image_file}\nmode: trinary\nresolution: {}\norigin: [{}, {}, {}]\nnegate: 0\n\
         occupied_thresh: {}\nfree_thresh: {}\n",
        shortest(grid.resolution),
        shortest(grid.origin.0),
        shortest(grid.origin.1),
        shortest(grid.origin.2),
        thresholds.occupied,
        thresholds.free
    )
}

/// Writes `<dir>/<stem>.pgm` and `<dir>/<stem>.yaml`.
///
/// # Errors
/// An inconsistent grid or an IO error.
pub fn write_map_server(dir: &Path, stem: &str, grid: &GridRef<'_>) -> Result<()> {
    let thresholds = MapThresholds::default();
    let img = grid.to_image(thresholds)?;
    let mut pgm = format!("P5\n{} {}\n255\n", grid.width, grid.height).into_bytes();
    pgm.extend_from_slice(img.as_raw());
    let pgm_name = format!("{stem}.pgm");
    atomic::write_file(&dir.join(&pgm_name), &pgm)?;
    atomic::write_file(
        &dir.join(format!("{stem}.yaml")),
        map_yaml(&pgm_name, grid, thresholds).as_bytes(),
    )
}

fn draw_line(img: &mut RgbImage, a: (f64, f64), b: (f64, f64), color: Rgb<u8>) {
    let steps = ((b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil() as usize).max(1);
    for i in 0..=steps {
        let t = i as f64 / steps as f64;
        let x = a.0 + (b.0 - a.0) * t;
        let y = a.1 + (b.1 - a.1) * t;
        if x >= 0.0 && y >= 0.0 && x < f64::from(img.width()) && y < f64::from(img.height()) {
            img.put_pixel(x as u32, y as u32, color);
        }
    }
}

/// The map picture in colour with a trajectory drawn on it in red, one point at a time (a path
/// of any length is drawn without being held), its start marked in green.
#[derive(Debug)]
pub struct TrajectoryPicture<'g> {
    grid: GridRef<'g>,
    img: RgbImage,
    first: Option<(f64, f64)>,
    last: Option<(f64, f64)>,
}

impl<'g> TrajectoryPicture<'g> {
    /// The map of `grid` in grey, no trajectory yet.
    ///
    /// # Errors
    /// An inconsistent grid.
    pub fn new(grid: GridRef<'g>) -> Result<Self> {
        let grey = grid.to_image(MapThresholds::default())?;
        let img = RgbImage::from_fn(grey.width(), grey.height(), |x, y| {
            let v = grey.get_pixel(x, y).0[0];
            Rgb([v, v, v])
        });
        Ok(TrajectoryPicture {
            grid,
            img,
            first: None,
            last: None,
        })
    }

    /// Draws the trajectory on to the map-frame point `(x, y)`.
    pub fn push(&mut self, x: f64, y: f64) {
        if let Some(a) = self.last {
            draw_line(
                &mut self.img,
                self.grid.to_pixel(a.0, a.1),
                self.grid.to_pixel(x, y),
                Rgb([220, 30, 30]),
            );
        }
        self.first.get_or_insert((x, y));
        self.last = Some((x, y));
    }

    /// The picture, with the start marked over the path.
    pub fn finish(mut self) -> RgbImage {
        if let Some((x, y)) = self.first {
            let (px, py) = self.grid.to_pixel(x, y);
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let (qx, qy) = (px + f64::from(dx), py + f64::from(dy));
                    draw_line(&mut self.img, (qx, qy), (qx, qy), Rgb([30, 160, 30]));
                }
            }
        }
        self.img
    }

    /// Writes the picture as a PNG file (atomically).
    ///
    /// # Errors
    /// An IO error.
    pub fn write_png(self, path: &Path) -> Result<()> {
        let img = self.finish();
        let mut bytes = Vec::new();
        img.write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )?;
        atomic::write_file(path, &bytes)
    }
}

/// The map picture in colour with a trajectory (`(x, y)` map-frame points) drawn in red and
/// its start marked in green.
///
/// # Errors
/// An inconsistent grid.
pub fn map_with_trajectory(grid: &GridRef<'_>, trajectory: &[(f64, f64)]) -> Result<RgbImage> {
    let mut picture = TrajectoryPicture::new(*grid)?;
    for &(x, y) in trajectory {
        picture.push(x, y);
    }
    Ok(picture.finish())
}

/// Writes `map.png` (or any `.png` path) with the trajectory drawn.
///
/// # Errors
/// An inconsistent grid or an IO error.
pub fn write_map_png(path: &Path, grid: &GridRef<'_>, trajectory: &[(f64, f64)]) -> Result<()> {
    let mut picture = TrajectoryPicture::new(*grid)?;
    for &(x, y) in trajectory {
        picture.push(x, y);
    }
    picture.write_png(path)
}

/// A trajectory pose for `result.mcap`: time (ns) and planar pose.
pub type TimedPose2 = (i64, (f64, f64, f64));

/// Most poses of the `/trajectory` path in `result.mcap`.
pub const MAX_PATH_POSES: usize = 16_384;

/// The poses of a path of unknown length, evenly thinned to at most [`MAX_PATH_POSES`]: every
/// `stride`-th pose is kept, and when the buffer fills every other kept pose goes and the
/// stride doubles.
#[derive(Debug, Default)]
struct ThinnedPath {
    poses: Vec<PoseStamped>,
    stride: u64,
    seen: u64,
    newest: Option<PoseStamped>,
}

impl ThinnedPath {
    fn push(&mut self, p: PoseStamped) {
        let stride = self.stride.max(1);
        if self.seen.is_multiple_of(stride) {
            if self.poses.len() == MAX_PATH_POSES {
                let mut k = 0;
                self.poses.retain(|_| {
                    k += 1;
                    k % 2 == 1
                });
                self.stride = stride * 2;
            }
            if self.seen.is_multiple_of(self.stride.max(1)) {
                self.poses.push(p.clone());
            }
        }
        self.seen += 1;
        self.newest = Some(p);
    }

    /// The kept poses, ending with the newest.
    fn finish(mut self) -> Vec<PoseStamped> {
        if let Some(n) = self.newest {
            if self.poses.last() != Some(&n) {
                self.poses.push(n);
            }
        }
        self.poses
    }
}

/// `result.mcap` written as the poses come: the map on `/map` (`nav_msgs/OccupancyGrid`,
/// which Foxglove draws) at the start and again at the end, each pose on `/pose`
/// (`geometry_msgs/PoseStamped`) at its own time, and at the end the path on `/trajectory`
/// (`nav_msgs/Path`, thinned to at most [`MAX_PATH_POSES`] poses), all in frame `map`.
#[derive(Debug)]
pub struct ResultMcap {
    bag: BagWriter,
    map: OccupancyGrid,
    path: ThinnedPath,
    start: i64,
    end: i64,
}

impl ResultMcap {
    /// Starts `path` with the map of `grid` at `start` (ns).
    ///
    /// # Errors
    /// An inconsistent grid or an IO error.
    pub fn create(path: &Path, grid: &GridRef<'_>, start: i64) -> Result<Self> {
        grid.check()?;
        let start = start.max(0);
        let mut bag = BagWriter::create(path)?;
        let map = OccupancyGrid {
            header: Header::new(Time::from_nanos(start), "map"),
            info: MapMetaData {
                map_load_time: Time::from_nanos(start),
                resolution: grid.resolution as f32,
                width: grid.width as u32,
                height: grid.height as u32,
                origin: Pose::planar(grid.origin.0, grid.origin.1, grid.origin.2),
            },
            data: grid.cells.to_vec(),
        };
        // The map first, so a viewer has it from the beginning.
        bag.write("/map", start, &map)?;
        Ok(ResultMcap {
            bag,
            map,
            path: ThinnedPath::default(),
            start,
            end: start,
        })
    }

    /// Adds the pose `(x, y, theta)` at `t` (ns).
    ///
    /// # Errors
    /// An IO error.
    pub fn pose(&mut self, t: i64, (x, y, theta): (f64, f64, f64)) -> Result<()> {
        let p = PoseStamped {
            header: Header::new(Time::from_nanos(t), "map"),
            pose: Pose::planar(x, y, theta),
        };
        let t = t.max(0);
        self.bag.write("/pose", t, &p)?;
        self.end = self.end.max(t);
        self.path.push(p);
        Ok(())
    }

    /// Writes the path and the map again at the last pose's time, and closes the file.
    ///
    /// # Errors
    /// An IO error.
    pub fn finish(mut self) -> Result<()> {
        let end = self.end;
        self.bag.write(
            "/trajectory",
            end,
            &PathMsg {
                header: Header::new(Time::from_nanos(end), "map"),
                poses: self.path.finish(),
            },
        )?;
        if end != self.start {
            self.map.header = Header::new(Time::from_nanos(end), "map");
            self.map.info.map_load_time = Time::from_nanos(end);
            self.bag.write("/map", end, &self.map)?;
        }
        self.bag.finish()?;
        Ok(())
    }
}

/// Writes `result.mcap` of a whole trajectory (see [`ResultMcap`]).
///
/// # Errors
/// An inconsistent grid or an IO error.
pub fn write_result_mcap(path: &Path, grid: &GridRef<'_>, trajectory: &[TimedPose2]) -> Result<()> {
    let start = trajectory.first().map_or(0, |p| p.0);
    let mut out = ResultMcap::create(path, grid, start)?;
    for &(t, pose) in trajectory {
        out.pose(t, pose)?;
    }
    out.finish()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bag_read::{BagReadOptions, BagReader};
    use crate::ros2::RosMessage;

    fn grid(cells: &[i8]) -> GridRef<'_> {
        GridRef {
            width: 3,
            height: 2,
            resolution: 0.5,
            origin: (-1.0, -0.5, 0.0),
            cells,
        }
    }

    #[test]
    fn pgm_and_yaml_follow_map_server() {
        let dir = tempfile::tempdir().unwrap();
        // Row 0 (bottom): occupied, free, unknown. Row 1 (top): 50%, 19%, 65%.
        let cells = [100, 0, -1, 50, 19, 65];
        write_map_server(dir.path(), "map", &grid(&cells)).unwrap();
        let pgm = std::fs::read(dir.path().join("map.pgm")).unwrap();
        let header = b"P5\n3 2\n255\n";
        assert_eq!(&pgm[..header.len()], header);
        // Top row first in the picture.
        assert_eq!(&pgm[header.len()..], &[205, 254, 0, 0, 254, 205]);
        let yaml = std::fs::read_to_string(dir.path().join("map.yaml")).unwrap();
        assert!(yaml.contains("image: map.pgm\n"));
        assert!(yaml.contains("resolution: 0.5\n"));
        assert!(yaml.contains("origin: [-1, -0.5, 0]\n"));
        assert!(yaml.contains("negate: 0\n"));
        assert!(yaml.contains("occupied_thresh: 0.65\nfree_thresh: 0.196\n"));
        let single = GridRef {
            resolution: f64::from(0.05f32),
            ..grid(&cells)
        };
        let yaml = map_yaml("m.pgm", &single, MapThresholds::default());
        assert!(yaml.contains("resolution: 0.05\n"), "{yaml}");
        assert!(write_map_server(dir.path(), "bad", &grid(&[0, 0])).is_err());
    }

    #[test]
    fn png_has_the_trajectory() {
        let dir = tempfile::tempdir().unwrap();
        let cells = [0i8; 6];
        let path = dir.path().join("map.png");
        // From the centre of cell (0, 0) to the centre of cell (2, 0): the bottom row.
        write_map_png(&path, &grid(&cells), &[(-0.75, -0.25), (0.25, -0.25)]).unwrap();
        let img = image::open(&path).unwrap().into_rgb8();
        assert_eq!(img.dimensions(), (3, 2));
        assert_eq!(img.get_pixel(2, 1).0, [220, 30, 30]);
        assert_eq!(img.get_pixel(0, 1).0, [30, 160, 30]);
        assert_eq!(img.get_pixel(2, 0).0, [254, 254, 254]);
    }

    #[test]
    fn a_long_path_is_thinned_evenly_and_keeps_its_ends() {
        let mut path = ThinnedPath::default();
        let n = 5 * MAX_PATH_POSES as i64 + 123;
        for k in 0..n {
            path.push(PoseStamped {
                header: Header::new(Time::from_nanos(k), "map"),
                pose: Pose::planar(k as f64, 0.0, 0.0),
            });
        }
        let poses = path.finish();
        assert!(poses.len() <= MAX_PATH_POSES + 1 && poses.len() > MAX_PATH_POSES / 2);
        let x: Vec<i64> = poses.iter().map(|p| p.pose.position.x as i64).collect();
        assert_eq!((x[0], *x.last().unwrap()), (0, n - 1));
        let step = x[1] - x[0];
        assert!(
            x[..x.len() - 1].windows(2).all(|w| w[1] - w[0] == step),
            "{step}"
        );
    }

    #[test]
    fn result_mcap_holds_map_and_poses() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("result.mcap");
        let cells = [100, 0, -1, 50, 19, 65];
        let traj = [(1_000, (0.0, 0.0, 0.0)), (2_000, (1.0, 0.5, 0.3))];
        write_result_mcap(&path, &grid(&cells), &traj).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let mut topics = Vec::new();
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            let m = m.unwrap();
            if m.channel.topic == "/map" {
                let g = OccupancyGrid::from_cdr(&m.data).unwrap();
                assert_eq!(g.data, cells);
                assert_eq!(g.info.resolution, 0.5);
            }
            topics.push(m.channel.topic.clone());
        }
        assert_eq!(topics, ["/map", "/pose", "/pose", "/trajectory", "/map"]);
        // Our reader skips these (not sensor types) without complaint.
        let mut r = BagReader::open(&path, BagReadOptions::default()).unwrap();
        assert_eq!(r.by_ref().count(), 0);
        assert!(r.stats().warnings.is_empty());
    }
}
