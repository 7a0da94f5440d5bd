//! A PNG preview: the floor plan (walls black, glass cyan, furniture brown, pillars grey,
//! ceiling features pale yellow, walkways blue, slip zones orange) with the ground-truth path in
//! red (start green, camera position blue), and beside it the frame of camera 0 at a chosen
//! time (the middle of the run by default).

use std::path::Path;

use anyhow::{Context, Result};
use image::{Rgb, RgbImage};

use crate::engine::Simulation;
use crate::world::{FeatureKind, Material, RegionKind, P2};

fn line(img: &mut RgbImage, a: (f64, f64), b: (f64, f64), c: Rgb<u8>) {
    let n = ((b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil() as usize).max(1);
    for i in 0..=n {
        let t = i as f64 / n as f64;
        let x = (a.0 + (b.0 - a.0) * t).round();
        let y = (a.1 + (b.1 - a.1) * t).round();
        if x >= 0.0 && y >= 0.0 && (x as u32) < img.width() && (y as u32) < img.height() {
            img.put_pixel(x as u32, y as u32, c);
        }
    }
}

fn rect(img: &mut RgbImage, a: (f64, f64), b: (f64, f64), c: Rgb<u8>) {
    let (x0, x1) = (a.0.min(b.0).max(0.0) as u32, a.0.max(b.0).max(0.0) as u32);
    let (y0, y1) = (a.1.min(b.1).max(0.0) as u32, a.1.max(b.1).max(0.0) as u32);
    for y in y0..=y1.min(img.height().saturating_sub(1)) {
        for x in x0..=x1.min(img.width().saturating_sub(1)) {
            img.put_pixel(x, y, c);
        }
    }
}

/// Draws the preview image (`max_side` pixels for the plan's longer side) with the frame of
/// camera 0 at time `at` (seconds).
pub fn render(sim: &Simulation, max_side: u32, at: f64) -> RgbImage {
    let w = &sim.world;
    let size = [
        w.bounds_max[0] - w.bounds_min[0],
        w.bounds_max[1] - w.bounds_min[1],
    ];
    let scale = f64::from(max_side) / size[0].max(size[1]);
    let pw = (size[0] * scale).ceil() as u32;
    let ph = (size[1] * scale).ceil() as u32;
    let to_px = |p: P2| {
        (
            (p[0] - w.bounds_min[0]) * scale,
            (w.bounds_max[1] - p[1]) * scale,
        )
    };
    let frame = sim
        .rig
        .cameras
        .first()
        .and_then(|_| sim.render_frame(0, at));
    let (fw, fh, zoom) = frame.as_ref().map_or((0, 0, 1), |f| {
        let zoom = (ph / f.height).clamp(1, 2).min((480 / f.height).max(1));
        (f.width * zoom, f.height * zoom, zoom)
    });
    let mut img = RgbImage::from_pixel(
        pw + fw + if fw > 0 { 8 } else { 0 },
        ph.max(fh),
        Rgb([255, 255, 255]),
    );
    for r in &w.regions {
        let c = match r.kind {
            RegionKind::Walkway => Rgb([170, 200, 255]),
            RegionKind::Slip => Rgb([255, 215, 170]),
        };
        rect(&mut img, to_px(r.min), to_px(r.max), c);
    }
    for f in &w.features {
        let c = match f.kind {
            FeatureKind::Light => Rgb([255, 240, 150]),
            FeatureKind::Vent => Rgb([210, 230, 210]),
            FeatureKind::Beam => Rgb([230, 230, 230]),
            FeatureKind::Spot => Rgb([240, 220, 240]),
        };
        rect(&mut img, to_px(f.min), to_px(f.max), c);
    }
    for s in &w.segments {
        let c = match s.material {
            Material::Wall => Rgb([0, 0, 0]),
            Material::Glass => Rgb([0, 180, 220]),
            Material::Furniture => Rgb([150, 90, 40]),
            Material::Pillar => Rgb([110, 110, 110]),
        };
        line(&mut img, to_px(s.a), to_px(s.b), c);
    }
    let path = sim.ground_truth_path(0.25);
    for pair in path.windows(2) {
        line(
            &mut img,
            to_px([pair[0].x, pair[0].y]),
            to_px([pair[1].x, pair[1].y]),
            Rgb([220, 0, 0]),
        );
    }
    if let Some(p) = path.first() {
        let (x, y) = to_px([p.x, p.y]);
        rect(
            &mut img,
            (x - 3.0, y - 3.0),
            (x + 3.0, y + 3.0),
            Rgb([0, 160, 0]),
        );
    }
    let mid = sim.state(at).pose;
    let (x, y) = to_px([mid.x, mid.y]);
    rect(
        &mut img,
        (x - 3.0, y - 3.0),
        (x + 3.0, y + 3.0),
        Rgb([0, 0, 220]),
    );
    if let Some(f) = frame {
        let x0 = pw + 8;
        for y in 0..fh {
            for x in 0..fw {
                let g = f.pixels[((y / zoom) * f.width + x / zoom) as usize];
                img.put_pixel(x0 + x, y, Rgb([g, g, g]));
            }
        }
    }
    img
}

/// Writes the preview PNG.
///
/// # Errors
/// Encoding or IO errors.
pub fn write(sim: &Simulation, path: &Path, max_side: u32, at: f64) -> Result<()> {
    let img = render(sim, max_side, at);
    let mut bytes = Vec::new();
    img.write_to(
        &mut std::io::Cursor::new(&mut bytes),
        image::ImageFormat::Png,
    )
    .context("encoding the preview PNG")?;
    crate::output::write_bytes(path, &bytes)
}
