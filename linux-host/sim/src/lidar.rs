//! A rotating 2D LiDAR simulated by ray casting the floor plan.
//!
//! Model (per beam `i` of a scan captured at `t`):
//! * the beam leaves the sensor at time `t + i * time_increment` (the head rotates during the
//!   scan, so a moving robot distorts the scan exactly like a real one), at the bearing
//!   `angle_min + i * angle_increment` in the robot frame, from the mount point;
//! * it hits the nearest segment that reaches above the scan plane; glass is skipped with
//!   probability `glass_pass` (the beam goes through and returns from what lies behind);
//! * the measured range is `r + N(0, (sigma + sigma_rel * r)^2)`;
//! * with probability `dropout` the return is lost and reported as NaN;
//! * ranges beyond `range_max` (or no hit) are reported as `+inf`, ranges below `range_min`
//!   as `-inf` (REP 117 conventions).

use rand::RngExt;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::path::{MotionLimits, Trajectory};
use crate::world::{Material, World};

/// LiDAR parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LidarParams {
    /// Beams per scan.
    pub beams: usize,
    /// Bearing of the first beam in the robot frame, radians.
    pub angle_min: f64,
    /// Bearing step, radians.
    pub angle_increment: f64,
    /// Closest valid range, metres.
    pub range_min: f64,
    /// Farthest valid range, metres.
    pub range_max: f64,
    /// Scans per second (1 to 10 Hz).
    pub rate_hz: f64,
    /// Constant range noise, metres (1 sigma).
    pub sigma: f64,
    /// Range noise proportional to the range (1 sigma, fraction).
    pub sigma_rel: f64,
    /// Probability that a return is lost.
    pub dropout: f64,
    /// Probability that a beam passes through glass.
    pub glass_pass: f64,
    /// Scan plane height above the floor, metres.
    pub height: f64,
    /// Mount offset forward of the robot centre, metres.
    pub mount_x: f64,
    /// Time one revolution takes (beams spread over it), seconds.
    pub sweep_time: f64,
}

impl LidarParams {
    /// A cleaning robot's LiDAR: 360 x 1 deg, 10 m, 5 Hz.
    pub fn cleaner() -> LidarParams {
        LidarParams {
            beams: 360,
            angle_min: -std::f64::consts::PI,
            angle_increment: std::f64::consts::PI / 180.0,
            range_min: 0.12,
            range_max: 10.0,
            rate_hz: 5.0,
            sigma: 0.01,
            sigma_rel: 0.002,
            dropout: 0.01,
            glass_pass: 0.9,
            height: 0.1,
            mount_x: 0.0,
            sweep_time: 0.2,
        }
    }

    /// An LDRobot LD06: 450 points a turn (0.8 deg), 0.02 to 12 m, 10 Hz, beams spread over
    /// the whole turn (the vendor's data sheet; the noise is the cleaner LiDAR's).
    pub fn ld06() -> LidarParams {
        LidarParams {
            beams: 450,
            angle_increment: std::f64::consts::TAU / 450.0,
            range_min: 0.02,
            range_max: 12.0,
            rate_hz: 10.0,
            sweep_time: 0.1,
            ..LidarParams::cleaner()
        }
    }

    /// A guide robot's LiDAR: 360 x 1 deg, 0.3 to 30 m, 1 Hz (as in the paper's airport robot).
    pub fn guide() -> LidarParams {
        LidarParams {
            beams: 360,
            angle_min: -std::f64::consts::PI,
            angle_increment: std::f64::consts::PI / 180.0,
            range_min: 0.3,
            range_max: 30.0,
            rate_hz: 1.0,
            sigma: 0.02,
            sigma_rel: 0.002,
            dropout: 0.02,
            glass_pass: 0.9,
            height: 0.3,
            mount_x: 0.1,
            sweep_time: 0.1,
        }
    }

    /// Time between beams, seconds.
    pub fn time_increment(&self) -> f64 {
        self.sweep_time / self.beams as f64
    }
}

/// One simulated scan (the fields of a `sensor_msgs/LaserScan`).
#[derive(Clone, Debug, PartialEq)]
pub struct Scan {
    /// Bearing of the first beam.
    pub angle_min: f32,
    /// Bearing step.
    pub angle_increment: f32,
    /// Time between beams.
    pub time_increment: f32,
    /// Time between scans.
    pub scan_time: f32,
    /// Closest valid range.
    pub range_min: f32,
    /// Farthest valid range.
    pub range_max: f32,
    /// Ranges (NaN: lost return, +inf: nothing in range, -inf: too close).
    pub ranges: Vec<f32>,
}

/// Simulates the scan that starts at time `t`.
pub fn scan(
    world: &World,
    traj: &Trajectory,
    limits: &MotionLimits,
    p: &LidarParams,
    t: f64,
    rng: &mut ChaCha8Rng,
) -> Scan {
    let mut ranges = Vec::with_capacity(p.beams);
    let dt = p.time_increment();
    for i in 0..p.beams {
        let pose = traj.at(t + i as f64 * dt, limits).pose;
        let (c, s) = (pose.theta.cos(), pose.theta.sin());
        let o = [pose.x + p.mount_x * c, pose.y + p.mount_x * s];
        let bearing = pose.theta + p.angle_min + i as f64 * p.angle_increment;
        let d = [bearing.cos(), bearing.sin()];
        let through_glass = rng.random::<f64>() < p.glass_pass;
        let lost = rng.random::<f64>() < p.dropout;
        let noise: f64 = rng.sample(StandardNormal);
        let hit = world.cast(o, d, p.range_max * 1.5, |seg, _| {
            seg.height >= p.height && !(through_glass && seg.material == Material::Glass)
        });
        let r = match hit {
            _ if lost => f32::NAN,
            None => f32::INFINITY,
            Some(h) => {
                let r = h.s + noise * (p.sigma + p.sigma_rel * h.s);
                if r > p.range_max {
                    f32::INFINITY
                } else if r < p.range_min {
                    f32::NEG_INFINITY
                } else {
                    r as f32
                }
            }
        };
        ranges.push(r);
    }
    Scan {
        angle_min: p.angle_min as f32,
        angle_increment: p.angle_increment as f32,
        time_increment: dt as f32,
        scan_time: (1.0 / p.rate_hz) as f32,
        range_min: p.range_min as f32,
        range_max: p.range_max as f32,
        ranges,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::{LegSpec, RouteSpec, WorldFile};
    use rand::SeedableRng;

    fn room() -> (World, Trajectory, MotionLimits) {
        let text = r#"
name = "room"
ceiling_height = 2.5
[[wall]]
points = [[0, 0], [10, 0], [10, 8], [0, 8]]
closed = true
[[wall]]
points = [[0, 6], [10, 6]]
material = "glass"
[route]
start = [2, 3]
legs = [{ type = "waypoints", points = [[3, 3]] }]
"#;
        let file = WorldFile::parse(text, "room.toml").expect("valid");
        let world = World::from_file(&file);
        let limits = MotionLimits {
            speed: 0.3,
            accel: 0.5,
            turn_rate: 1.0,
            turn_accel: 2.0,
        };
        let route = RouteSpec {
            start: [2.0, 3.0],
            legs: vec![LegSpec::Waypoints {
                points: vec![[2.0, 3.0]],
            }],
        };
        let traj = Trajectory::new(&route, &limits, 1.0);
        (world, traj, limits)
    }

    #[test]
    fn beams_hit_walls_at_the_known_distance() {
        let (world, traj, limits) = room();
        let mut p = LidarParams::cleaner();
        p.sigma = 0.0;
        p.sigma_rel = 0.0;
        p.dropout = 0.0;
        p.glass_pass = 0.0;
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let s = scan(&world, &traj, &limits, &p, 0.0, &mut rng);
        // Robot at (2, 3) heading 0; beam i has bearing -180 + i deg.
        let at = |deg: i32| s.ranges[(deg + 180) as usize];
        assert!((at(0) - 8.0).abs() < 1e-5, "{}", at(0)); // wall x = 10
        assert!((at(-90) - 3.0).abs() < 1e-5); // wall y = 0
        assert!((at(90) - 3.0).abs() < 1e-5); // glass y = 6, opaque here
        assert!((at(-180) - 2.0).abs() < 1e-5); // wall x = 0
                                                // 45 deg: hits the glass at y = 6 after 3 * sqrt(2).
        assert!((at(45) - 3.0 * 2f32.sqrt()).abs() < 1e-5);
        // Glass fully transparent: the beam continues to y = 8.
        p.glass_pass = 1.0;
        let s = scan(&world, &traj, &limits, &p, 0.0, &mut rng);
        assert!((s.ranges[270] - 5.0).abs() < 1e-5);
        // Short range: the far wall is out of range.
        p.range_max = 5.0;
        let s = scan(&world, &traj, &limits, &p, 0.0, &mut rng);
        assert_eq!(s.ranges[180], f32::INFINITY);
    }

    #[test]
    fn range_noise_matches_sigma() {
        let (world, traj, limits) = room();
        let mut p = LidarParams::cleaner();
        p.sigma = 0.02;
        p.sigma_rel = 0.0;
        p.dropout = 0.0;
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut errs = Vec::new();
        for _ in 0..100 {
            let s = scan(&world, &traj, &limits, &p, 0.0, &mut rng);
            errs.push(f64::from(s.ranges[180]) - 8.0);
        }
        let n = errs.len() as f64;
        let mean = errs.iter().sum::<f64>() / n;
        let sd = (errs.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        assert!(mean.abs() < 0.006, "{mean}");
        assert!((sd - 0.02).abs() < 0.005, "{sd}");
    }
}
