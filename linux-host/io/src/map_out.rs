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

/// The map picture in colour with a trajectory (`(x, y)` map-frame points) drawn in red and
/// its start marked in green.
///
/// # Errors
/// An inconsistent grid.
pub fn map_with_trajectory(grid: &GridRef<'_>, trajectory: &[(f64, f64)]) -> Result<RgbImage> {
    let grey = grid.to_image(MapThresholds::default())?;
    let mut img = RgbImage::from_fn(grey.width(), grey.height(), |x, y| {
        let v = grey.get_pixel(x, y).0[0];
        Rgb([v, v, v])
    });
    let red = Rgb([220, 30, 30]);
    for w in trajectory.windows(2) {
        if let [a, b] = w {
            draw_line(
                &mut img,
                grid.to_pixel(a.0, a.1),
                grid.to_pixel(b.0, b.1),
                red,
            );
        }
    }
    if let Some(&(x, y)) = trajectory.first() {
        let (px, py) = grid.to_pixel(x, y);
        for dy in -1..=1 {
            for dx in -1..=1 {
                let (qx, qy) = (px + f64::from(dx), py + f64::from(dy));
                draw_line(&mut img, (qx, qy), (qx, qy), Rgb([30, 160, 30]));
            }
        }
    }
    Ok(img)
}

/// Writes `map.png` (or any `.png` path) with the trajectory drawn.
///
/// # Errors
/// An inconsistent grid or an IO error.
pub fn write_map_png(path: &Path, grid: &GridRef<'_>, trajectory: &[(f64, f64)]) -> Result<()> {
    let img = map_with_trajectory(grid, trajectory)?;
    let mut bytes = Vec::new();
    img.write_to(
        &mut std::io::Cursor::new(&mut bytes),
        image::ImageFormat::Png,
    )?;
    atomic::write_file(path, &bytes)
}

/// A trajectory pose for `result.mcap`: time (ns) and planar pose.
pub type TimedPose2 = (i64, (f64, f64, f64));

/// Writes `result.mcap`: the map on `/map` (`nav_msgs/OccupancyGrid`, which Foxglove draws),
/// the whole trajectory on `/trajectory` (`nav_msgs/Path`), and each pose on `/pose`
/// (`geometry_msgs/PoseStamped`) at its own time, all in frame `map`.
///
/// # Errors
/// An inconsistent grid or an IO error.
pub fn write_result_mcap(path: &Path, grid: &GridRef<'_>, trajectory: &[TimedPose2]) -> Result<()> {
    grid.check()?;
    let end = trajectory.last().map_or(0, |p| p.0.max(0));
    let start = trajectory.first().map_or(0, |p| p.0.max(0));
    let mut bag = BagWriter::create(path)?;
    let poses: Vec<PoseStamped> = trajectory
        .iter()
        .map(|&(t, (x, y, th))| PoseStamped {
            header: Header::new(Time::from_nanos(t), "map"),
            pose: Pose::planar(x, y, th),
        })
        .collect();
    let map = OccupancyGrid {
        header: Header::new(Time::from_nanos(end), "map"),
        info: MapMetaData {
            map_load_time: Time::from_nanos(end),
            resolution: grid.resolution as f32,
            width: grid.width as u32,
            height: grid.height as u32,
            origin: Pose::planar(grid.origin.0, grid.origin.1, grid.origin.2),
        },
        data: grid.cells.to_vec(),
    };
    // The map first (at the start) so a viewer has it from the beginning, again at the end.
    bag.write("/map", start, &map)?;
    for p in &poses {
        bag.write("/pose", p.header.stamp.to_nanos().max(0), p)?;
    }
    bag.write(
        "/trajectory",
        end,
        &PathMsg {
            header: Header::new(Time::from_nanos(end), "map"),
            poses,
        },
    )?;
    if end != start {
        bag.write("/map", end, &map)?;
    }
    bag.finish()?;
    Ok(())
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
