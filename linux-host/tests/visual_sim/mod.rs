//! The image front-end of `cloi-core` on frames rendered by `cloi-sim`, and the simulator's
//! exact geometry to check it with. Shared by `tests/camera_frontend_sim.rs` and
//! `examples/camera_frontend_timing.rs`, so the figures of both come from one pipeline.

#![allow(dead_code)]

use std::time::{Duration, Instant};

use anyhow::Result;
use cloi_core::frontend::visual::pyramid::pyramid_bytes;
use cloi_core::frontend::visual::{
    describe, detect_pyramid, match_brute_force, match_guided, smooth_into, CameraExtrinsic,
    CameraModel, Descriptor, DetectStats, FastConfig, GrayImage, Keypoint, Match, MatchConfig,
    Pyramid,
};
use cloi_core::Se2;
use cloi_sim::camera::Frame;
use cloi_sim::engine::{Payload, Sample, SampleSink};
use cloi_sim::world::{Material, World};
use cloi_sim::Simulation;
use nalgebra::{Vector2, Vector3};

/// Pyramid levels asked for (320 x 240 gives four: 320, 160, 80, 40 px wide).
pub const LEVELS: usize = 4;
/// Keypoints kept per frame, all levels together.
pub const MAX_FEATURES: usize = 500;
/// Reprojection error allowed for a correct match, in pixels of the coarser of the two
/// features' levels. A FAST corner sits on its level's pixel grid (half a pixel of rounding
/// each side) and its response peak can move by a pixel when the view changes; the rendering
/// noise adds well under a pixel. Three pixels covers both with margin, and stays far below
/// the spacing of distinct corners (the detector's grid cells are 32 px).
pub const TOL_PX: f32 = 3.0;
/// Search radius of the guided matcher around the predicted pixel, level-0 pixels. The wheel
/// odometry drifts by millimetres over 0.1-0.5 s; at 1-2 m from the camera that is a pixel or
/// two; the radius covers the level-3 rounding (8 px) with margin.
pub const GUIDE_RADIUS: f32 = 16.0;

/// One camera frame of the simulated stream, with its capture time.
#[derive(Debug)]
pub struct Shot {
    /// Capture time, seconds.
    pub t: f64,
    /// The rendered frame.
    pub frame: Frame,
}

/// What a short simulated run gives the front-end: camera 0's frames and the wheel odometry.
#[derive(Debug, Default)]
pub struct Recording {
    /// Frames of camera 0, in capture order.
    pub shots: Vec<Shot>,
    /// Wheel-odometry poses with their capture times, in order.
    pub odometry: Vec<(f64, Se2)>,
}

impl SampleSink for Recording {
    fn accept(&mut self, s: &Sample) -> Result<()> {
        match &s.payload {
            Payload::Image(0, frame) => self.shots.push(Shot {
                t: s.capture,
                frame: frame.clone(),
            }),
            Payload::Odometry(o) => self.odometry.push((s.capture, o.pose)),
            _ => {}
        }
        Ok(())
    }
}

impl Recording {
    /// Runs `sim` (the same stream `cloi sim` writes to a bag) and keeps what the camera
    /// front-end needs.
    pub fn of(sim: &Simulation) -> Recording {
        let mut rec = Recording::default();
        sim.run(&mut rec).expect("the simulation runs");
        rec.shots.sort_by(|a, b| a.t.total_cmp(&b.t));
        rec.odometry.sort_by(|a, b| a.0.total_cmp(&b.0));
        rec
    }

    /// The odometry pose at `t`, interpolated between the two readings around it.
    pub fn odometry_at(&self, t: f64) -> Option<Se2> {
        let i = self.odometry.partition_point(|(ts, _)| *ts <= t);
        let (ta, a) = *self.odometry.get(i.checked_sub(1)?)?;
        let Some(&(tb, b)) = self.odometry.get(i) else {
            return Some(a);
        };
        let f = if tb > ta { (t - ta) / (tb - ta) } else { 0.0 };
        let d = a.between(&b);
        Some(a.compose(&Se2::new(f * d.x, f * d.y, f * d.theta)))
    }
}

/// Features of one frame: keypoints whose descriptor could be computed, level-0 positions.
#[derive(Debug, Default)]
pub struct Features {
    /// Keypoints, in the order of `descriptors`.
    pub keypoints: Vec<Keypoint>,
    /// Level-0 positions of the keypoints.
    pub positions: Vec<[f32; 2]>,
    /// Their descriptors.
    pub descriptors: Vec<Descriptor>,
    /// What detection did.
    pub stats: DetectStats,
}

/// Time spent in each stage of [`extract`].
#[derive(Clone, Copy, Debug, Default)]
pub struct StageTimes {
    /// Halving pyramid.
    pub pyramid: Duration,
    /// FAST on every level, bucketing, orientation.
    pub detect: Duration,
    /// Smoothing every level and computing the descriptors.
    pub describe: Duration,
}

/// The core's front-end on one frame: pyramid, FAST with bucketing and orientation, smoothing
/// and rotated BRIEF on the keypoint's level. Storage is allocated here (the host's job) and
/// lent to the core.
pub fn extract(frame: &Frame, cfg: &FastConfig) -> (Features, StageTimes) {
    let (w, h) = (frame.width as usize, frame.height as usize);
    let mut times = StageTimes::default();
    let base = GrayImage::new_checked(w, h, w, &frame.pixels).expect("a valid frame");
    let t0 = Instant::now();
    let mut store = vec![0u8; pyramid_bytes(w, h, LEVELS)];
    let pyr = Pyramid::build(base, LEVELS, &mut store).expect("storage sized by pyramid_bytes");
    times.pyramid = t0.elapsed();

    let t1 = Instant::now();
    let mut keypoints = vec![Keypoint::default(); MAX_FEATURES];
    let stats = detect_pyramid(&pyr, cfg, &mut keypoints);
    keypoints.truncate(stats.kept);
    times.detect = t1.elapsed();

    let t2 = Instant::now();
    let mut out = Features {
        stats,
        ..Features::default()
    };
    let mut smooth = vec![0u8; w * h];
    for l in 0..pyr.len() {
        let level = pyr.level(l).expect("a level below len()");
        let smoothed = smooth_into(&level, &mut smooth).expect("sized for level 0");
        for kp in keypoints.iter().filter(|k| usize::from(k.level) == l) {
            if let Some(d) = describe(&smoothed, kp) {
                out.keypoints.push(*kp);
                out.positions.push(kp.position());
                out.descriptors.push(d);
            }
        }
    }
    times.describe = t2.elapsed();
    (out, times)
}

/// Brute-force matching of `a` against `b` (mutual best, ratio test).
pub fn brute_force(a: &Features, b: &Features, cfg: &MatchConfig) -> Vec<Match> {
    let mut out = vec![Match::default(); a.descriptors.len()];
    let s = match_brute_force(&a.descriptors, &b.descriptors, cfg, &mut out);
    out.truncate(s.matched);
    out
}

/// Guided matching of `a` (with its predicted positions in `b`) against `b`.
pub fn guided(
    a: &Features,
    predicted: &[[f32; 2]],
    b: &Features,
    radius: f32,
    cfg: &MatchConfig,
) -> Vec<Match> {
    let mut out = vec![Match::default(); a.descriptors.len()];
    let s = match_guided(
        &a.descriptors,
        predicted,
        &b.descriptors,
        &b.positions,
        radius,
        cfg,
        &mut out,
    );
    out.truncate(s.matched);
    out
}

/// The surface a pixel sees.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Surface {
    /// The ceiling plane.
    Ceiling,
    /// A wall, pillar or piece of furniture.
    Wall,
    /// The floor.
    Floor,
}

/// One camera of the robot as the core models it, with the world it moves in.
#[derive(Debug)]
pub struct Geometry<'w> {
    /// The world (ceiling height and walls).
    pub world: &'w World,
    /// The lens.
    pub model: CameraModel,
    /// The mounting on the robot.
    pub extrinsic: CameraExtrinsic,
}

impl Geometry<'_> {
    /// The camera centre and a pixel's ray in the world, for the robot at `pose`.
    fn ray(&self, pose: &Se2, px: [f32; 2]) -> Option<(Vector3<f64>, Vector3<f64>)> {
        let bearing = self
            .model
            .unproject(&Vector2::new(f64::from(px[0]), f64::from(px[1])))?;
        let body = self.extrinsic.rotation() * bearing;
        let (c, s) = (pose.theta.cos(), pose.theta.sin());
        let t = self.extrinsic.translation();
        let o = Vector3::new(pose.x + c * t.x - s * t.y, pose.y + s * t.x + c * t.y, t.z);
        let d = Vector3::new(c * body.x - s * body.y, s * body.x + c * body.y, body.z);
        Some((o, d))
    }

    /// The world point a pixel sees from `pose`: the first wall below its top edge (glass is
    /// see-through), else the ceiling or the floor, as the renderer decides it.
    pub fn world_point(&self, pose: &Se2, px: [f32; 2]) -> Option<(Vector3<f64>, Surface)> {
        let (o, d) = self.ray(pose, px)?;
        let h = d.x.hypot(d.y);
        if h < 1e-9 {
            let up = d.z > 0.0;
            let z = if up { self.world.ceiling_height } else { 0.0 };
            let surface = if up { Surface::Ceiling } else { Surface::Floor };
            return Some((Vector3::new(o.x, o.y, z), surface));
        }
        let slope = d.z / h;
        let dir = [d.x / h, d.y / h];
        let (s_end, surface) = if slope > 1e-9 {
            ((self.world.ceiling_height - o.z) / slope, Surface::Ceiling)
        } else if slope < -1e-9 {
            (-o.z / slope, Surface::Floor)
        } else {
            return None;
        };
        let hit = self.world.cast([o.x, o.y], dir, s_end, |seg, s| {
            seg.material != Material::Glass && o.z + slope * s <= seg.height
        });
        let (s, surface) = hit.map_or((s_end, surface), |hit| (hit.s, Surface::Wall));
        Some((
            Vector3::new(o.x + dir[0] * s, o.y + dir[1] * s, o.z + slope * s),
            surface,
        ))
    }

    /// Where the points that `a`'s features see from `pose_a` fall in a frame taken from
    /// `pose_b` (`f32::MAX` where they leave the view): A's points as landmarks, reprojected
    /// with a predicted pose, as the visual odometry will do it.
    pub fn predict(&self, pose_a: &Se2, pose_b: &Se2, a: &Features) -> Vec<[f32; 2]> {
        a.positions
            .iter()
            .map(|&px| {
                self.world_point(pose_a, px)
                    .and_then(|(p, _)| self.project(pose_b, &p))
                    .unwrap_or([f32::MAX, f32::MAX])
            })
            .collect()
    }

    /// Whether match `m` of features `a` (seen from `pa`) and `b` (seen from `pb`) is
    /// geometrically correct: the point A's feature sees reprojects within [`TOL_PX`] pixels
    /// (of the coarser of the two features' levels) of B's feature.
    pub fn is_correct(&self, pa: &Se2, pb: &Se2, a: &Features, b: &Features, m: &Match) -> bool {
        let (Some(ka), Some(kb)) = (a.keypoints.get(m.query), b.keypoints.get(m.train)) else {
            return false;
        };
        let (Some(&pxa), Some(&q)) = (a.positions.get(m.query), b.positions.get(m.train)) else {
            return false;
        };
        let Some(px) = self
            .world_point(pa, pxa)
            .and_then(|(p, _)| self.project(pb, &p))
        else {
            return false;
        };
        let tol = TOL_PX * Pyramid::scale(usize::from(ka.level.max(kb.level)));
        (px[0] - q[0]).hypot(px[1] - q[1]) <= tol
    }

    /// The pixel of world point `p` seen from `pose`, or `None` outside the lens's field.
    pub fn project(&self, pose: &Se2, p: &Vector3<f64>) -> Option<[f32; 2]> {
        let (c, s) = (pose.theta.cos(), pose.theta.sin());
        let (dx, dy) = (p.x - pose.x, p.y - pose.y);
        let body = Vector3::new(c * dx + s * dy, -s * dx + c * dy, p.z);
        let px = self.model.project(&self.extrinsic.robot_to_camera(&body))?;
        Some([px.x as f32, px.y as f32])
    }
}

/// Median of a list of durations (the list is sorted in place).
pub fn median(v: &mut [Duration]) -> Duration {
    v.sort();
    v.get(v.len() / 2).copied().unwrap_or_default()
}
