//! The simulation loop: samples every sensor on its own clock, renders scans and frames in
//! parallel, and hands a stream ordered by arrival time to a [`SampleSink`].
//!
//! **Timestamps.** Sensor `s` with period `T` captures sample `k` at
//! `k T + j_k`, with jitter `j_k ~ N(0, jitter²)` clipped to `±min(T/4, 50 ms)`. The message stamp is
//! `capture + stamp_offset` (a constant driver delay the mapper does not know), and the sample
//! arrives (bag log time) at `capture + latency + |N(0, (latency/4)²)|`. Ground truth is
//! stamped with the exact capture time at 50 Hz. Two cameras are hardware-synchronised: they
//! share capture times and stamps.
//!
//! **Determinism.** Every random draw comes from a ChaCha8 stream seeded by
//! `(seed, sensor, sample index)`, so output does not depend on thread scheduling.

use std::collections::BTreeMap;

use anyhow::Result;
use cloi_core::geom::Se2;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rayon::prelude::*;

use crate::camera::{Camera, CameraParams, DirtyLens, Frame};
use crate::lidar::{self, LidarParams, Scan};
use crate::odometry::{Gyro, GyroParams, ImuReading, OdomReading, WheelOdometry, WheelParams};
use crate::path::{MotionLimits, State, Trajectory};
use crate::world::{FaultKind, FaultSpec, RegionKind, RobotKind, World};

/// Which sensors the robot carries (the paper's sensor combinations).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SensorSet {
    /// One LiDAR (`L`).
    Lidar,
    /// One camera (`C`).
    Camera,
    /// Two synchronised cameras (`2C`).
    TwoCameras,
    /// One camera and one LiDAR (`C+L`).
    CameraLidar,
}

impl std::str::FromStr for SensorSet {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_uppercase().as_str() {
            "L" => Ok(SensorSet::Lidar),
            "C" => Ok(SensorSet::Camera),
            "2C" => Ok(SensorSet::TwoCameras),
            "C+L" | "L+C" => Ok(SensorSet::CameraLidar),
            _ => Err(format!("unknown sensor set {s:?}; use L, C, 2C or C+L")),
        }
    }
}

impl SensorSet {
    /// Whether a LiDAR is present.
    pub fn has_lidar(self) -> bool {
        matches!(self, SensorSet::Lidar | SensorSet::CameraLidar)
    }

    /// Number of cameras.
    pub fn cameras(self) -> usize {
        match self {
            SensorSet::Lidar => 0,
            SensorSet::Camera | SensorSet::CameraLidar => 1,
            SensorSet::TwoCameras => 2,
        }
    }
}

/// What to simulate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SimConfig {
    /// Simulated seconds.
    pub duration: f64,
    /// Seed of every random draw.
    pub seed: u64,
    /// Sensors carried.
    pub sensors: SensorSet,
    /// Kannala-Brandt fisheye lenses (else pinhole).
    pub fisheye: bool,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Camera frames per second.
    pub camera_rate: f64,
    /// Average three sub-exposures per frame.
    pub motion_blur: bool,
    /// Apply the world's fault schedule.
    pub faults: bool,
    /// The LiDAR carried instead of the world's robot's own (an emulated device's).
    pub lidar: Option<LidarParams>,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            duration: 60.0,
            seed: 0,
            sensors: SensorSet::CameraLidar,
            fisheye: true,
            width: 320,
            height: 240,
            camera_rate: 10.0,
            motion_blur: false,
            faults: true,
            lidar: None,
        }
    }
}

/// Clock behaviour of one sensor stream.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Timing {
    /// Samples per second.
    pub rate_hz: f64,
    /// Capture jitter, seconds (1 sigma).
    pub jitter: f64,
    /// Constant offset added to the stamp, seconds.
    pub stamp_offset: f64,
    /// Mean delivery latency, seconds.
    pub latency: f64,
}

/// The robot: motion limits and sensor parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct Rig {
    /// Motion limits.
    pub limits: MotionLimits,
    /// LiDAR, if carried.
    pub lidar: Option<LidarParams>,
    /// Cameras (0, 1 or 2).
    pub cameras: Vec<CameraParams>,
    /// Wheels and encoders.
    pub wheels: WheelParams,
    /// Gyro.
    pub gyro: GyroParams,
    /// Whether the gyro is carried (else no IMU messages).
    pub imu: bool,
    /// Timing of the LiDAR, odometry, IMU and camera streams.
    pub timing: [Timing; 4],
}

const LIDAR: usize = 0;
const ODOM: usize = 1;
const IMU: usize = 2;
const CAMERA: usize = 3;

impl Rig {
    /// The rig for a world's robot kind and a configuration.
    pub fn new(robot: RobotKind, cfg: &SimConfig) -> Rig {
        let guide = robot == RobotKind::Guide;
        let limits = if guide {
            MotionLimits {
                speed: 0.8,
                accel: 0.4,
                turn_rate: 0.6,
                turn_accel: 0.8,
            }
        } else {
            MotionLimits {
                speed: 0.3,
                accel: 0.5,
                turn_rate: 1.0,
                turn_accel: 2.0,
            }
        };
        let lidar = cfg.sensors.has_lidar().then(|| {
            if let Some(l) = cfg.lidar {
                l
            } else if guide {
                LidarParams::guide()
            } else {
                LidarParams::cleaner()
            }
        });
        let tilt = if guide { 45.0 } else { 60.0 };
        let cameras = (0..cfg.sensors.cameras())
            .map(|i| {
                // The second camera looks backwards.
                let mut c = CameraParams::new(
                    cfg.width,
                    cfg.height,
                    cfg.fisheye,
                    tilt,
                    if i == 0 { 0.0 } else { 180.0 },
                );
                c.rate_hz = cfg.camera_rate;
                c.motion_blur = cfg.motion_blur;
                c
            })
            .collect();
        let wheels = WheelParams::default_for(limits.speed);
        let gyro = GyroParams::default();
        let lidar_rate = lidar.map_or(5.0, |l| l.rate_hz);
        let timing = [
            Timing {
                rate_hz: lidar_rate,
                jitter: 0.002,
                stamp_offset: 0.0,
                latency: 0.03,
            },
            Timing {
                rate_hz: wheels.rate_hz,
                jitter: 0.001,
                stamp_offset: 0.0,
                latency: 0.005,
            },
            Timing {
                rate_hz: gyro.rate_hz,
                jitter: 0.002,
                stamp_offset: 0.0,
                latency: 0.01,
            },
            Timing {
                rate_hz: cfg.camera_rate,
                jitter: 0.003,
                stamp_offset: 0.008,
                latency: 0.04,
            },
        ];
        Rig {
            limits,
            lidar,
            cameras,
            wheels,
            gyro,
            imu: true,
            timing,
        }
    }
}

/// Ground truth at an instant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GroundTruth {
    /// Exact pose in the world.
    pub pose: Se2,
    /// Forward speed over the floor, m/s.
    pub v: f64,
    /// Yaw rate, rad/s.
    pub w: f64,
}

/// The contents of one sample.
#[derive(Clone, Debug, PartialEq)]
pub enum Payload {
    /// Ground-truth pose.
    GroundTruth(GroundTruth),
    /// Wheel odometry.
    Odometry(OdomReading),
    /// Gyro and accelerometer.
    Imu(ImuReading),
    /// LiDAR scan.
    Scan(Scan),
    /// Camera frame of camera `.0`.
    Image(u8, Frame),
    /// A scheduled fault starting now.
    Fault(FaultSpec),
}

/// One message of the simulated stream. Times in seconds from the start of the run.
#[derive(Clone, Debug, PartialEq)]
pub struct Sample {
    /// When the sensor captured it (the ground-truth time).
    pub capture: f64,
    /// The stamp in its message header.
    pub stamp: f64,
    /// When it arrived (bag log time).
    pub arrival: f64,
    /// Per-stream sequence number.
    pub seq: u64,
    /// Contents.
    pub payload: Payload,
}

/// Where the simulated stream goes (a bag, a TUM file, a test digest, a mapper).
pub trait SampleSink {
    /// Takes the next sample; samples come in order of arrival time.
    ///
    /// # Errors
    /// Whatever the sink fails with; the simulation stops.
    fn accept(&mut self, sample: &Sample) -> Result<()>;
}

/// Counts of what was generated.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Summary {
    /// Ground-truth samples.
    pub ground_truth: u64,
    /// Odometry messages.
    pub odometry: u64,
    /// IMU messages.
    pub imu: u64,
    /// LiDAR scans.
    pub scans: u64,
    /// Camera frames (all cameras).
    pub frames: u64,
    /// Frames dropped by a dirty lens.
    pub dropped_frames: u64,
    /// Scans lost to a LiDAR outage.
    pub lost_scans: u64,
    /// Fault events.
    pub faults: u64,
}

/// A prepared simulation.
#[derive(Debug)]
pub struct Simulation {
    /// The world.
    pub world: World,
    /// The configuration.
    pub cfg: SimConfig,
    /// The robot.
    pub rig: Rig,
    /// The ground-truth trajectory.
    pub trajectory: Trajectory,
    cameras: Vec<Camera>,
}

fn mix(seed: u64, stream: u64, index: u64) -> u64 {
    // splitmix64 over the three words.
    let mut z = seed
        ^ stream.wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ index.wrapping_mul(0xD1B5_4A32_D192_ED03);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A random stream for `(seed, stream, index)`.
pub fn rng_for(seed: u64, stream: u64, index: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(mix(seed, stream, index))
}

const GT_RATE: f64 = 50.0;

/// Capture jitter never exceeds this (keeps the arrival-order merge window small).
const MAX_JITTER: f64 = 0.05;

enum Job {
    Scan(u64, f64),
    Frame(usize, u64, f64, Option<DirtyLens>),
}

impl Simulation {
    /// Prepares the trajectory and cameras.
    pub fn new(world: World, cfg: SimConfig) -> Simulation {
        let mut rig = Rig::new(world.robot, &cfg);
        let o = &world.odometry;
        rig.wheels.scale_offset = o.wheel_scale_error;
        if o.wheel_noise > 0.0 {
            rig.wheels.noise = rig.wheels.noise.hypot(o.wheel_noise);
        }
        rig.gyro.bias_offset = o.gyro_bias;
        rig.imu = o.gyro;
        let trajectory = Trajectory::new(&world.route, &rig.limits, cfg.duration + 2.0);
        let cameras = rig.cameras.iter().map(|p| Camera::new(*p)).collect();
        Simulation {
            world,
            cfg,
            rig,
            trajectory,
            cameras,
        }
    }

    /// The robot state at `t`.
    pub fn state(&self, t: f64) -> State {
        self.trajectory.at(t, &self.rig.limits)
    }

    /// Faults in force at `t`.
    fn active(&self, t: f64) -> impl Iterator<Item = &FaultSpec> {
        let on = self.cfg.faults;
        self.world
            .faults
            .iter()
            .filter(move |f| on && t >= f.start && t < f.end)
    }

    /// The capture time of sample `k` of stream `s`.
    fn capture_time(&self, s: usize, k: u64) -> f64 {
        let tm = &self.rig.timing[s];
        let period = 1.0 / tm.rate_hz;
        let mut rng = rng_for(self.cfg.seed, 100 + s as u64, k);
        let j: f64 = rng.sample(StandardNormal);
        let bound = MAX_JITTER.min(period / 4.0);
        (k as f64 * period + (j * tm.jitter).clamp(-bound, bound)).max(0.0)
    }

    fn stamped(&self, s: usize, k: u64, capture: f64, payload: Payload) -> Sample {
        let tm = &self.rig.timing[s];
        let mut rng = rng_for(self.cfg.seed, 200 + s as u64, k);
        let l: f64 = rng.sample(StandardNormal);
        Sample {
            capture,
            stamp: capture + tm.stamp_offset,
            arrival: capture + tm.latency + (0.25 * tm.latency * l).abs(),
            seq: k,
            payload,
        }
    }

    /// Renders the frame of camera `cam` at time `t`, with a dirty lens if one is scheduled
    /// then (frames are never dropped here).
    pub fn render_frame(&self, cam: usize, t: f64) -> Option<Frame> {
        let camera = self.cameras.get(cam)?;
        let mut rng = rng_for(self.cfg.seed, 300 + cam as u64, (t * 1000.0) as u64);
        Some(camera.render(
            &self.world,
            |t| self.pose3(t),
            t,
            self.dirty_lens(cam, t),
            &mut rng,
        ))
    }

    /// The lens contamination of camera `cam` at time `t`, if any.
    fn dirty_lens(&self, cam: usize, t: f64) -> Option<DirtyLens> {
        self.world
            .faults
            .iter()
            .enumerate()
            .find_map(|(i, f)| match f.kind {
                FaultKind::DirtyLens { camera, blur, .. }
                    if self.cfg.faults
                        && t >= f.start
                        && t < f.end
                        && camera.is_none_or(|x| usize::from(x) == cam) =>
                {
                    Some(DirtyLens {
                        blur,
                        seed: mix(self.cfg.seed, 500, i as u64),
                    })
                }
                _ => None,
            })
    }

    fn pose3(&self, t: f64) -> (f64, f64, f64) {
        let p = self.state(t).pose;
        (p.x, p.y, p.theta)
    }

    /// True wheel travel (left, right) between `ta` and `tb`, relative to the floor under the
    /// wheels (a walkway's belt motion along the heading is removed).
    fn wheel_travel(&self, ta: f64, tb: f64) -> [f64; 2] {
        let a = self.state(ta);
        let b = self.state(tb);
        let mut ds = b.distance - a.distance;
        let dth = b.heading - a.heading;
        if self
            .world
            .regions
            .iter()
            .any(|r| r.kind == RegionKind::Walkway)
        {
            let n = 4;
            let h = (tb - ta) / f64::from(n);
            for i in 0..n {
                let s = self.state(ta + (f64::from(i) + 0.5) * h);
                let p = [s.pose.x, s.pose.y];
                for r in &self.world.regions {
                    if r.kind == RegionKind::Walkway && r.contains(p) {
                        let along =
                            r.velocity[0] * s.pose.theta.cos() + r.velocity[1] * s.pose.theta.sin();
                        ds -= along * h;
                    }
                }
            }
        }
        let half = 0.5 * self.rig.wheels.track * dth;
        [ds - half, ds + half]
    }

    /// Slip multiplier and extra noise at time `t` (slip zones and slip faults).
    fn slip(&self, t: f64) -> (f64, f64) {
        let s = self.state(t);
        let p = [s.pose.x, s.pose.y];
        let mut scale = 1.0;
        let mut var = 0.0;
        for r in &self.world.regions {
            if r.kind == RegionKind::Slip && r.contains(p) {
                scale *= r.scale;
                var += r.noise * r.noise;
            }
        }
        for f in self.active(t) {
            if let FaultKind::Slip { scale: k, noise } = f.kind {
                scale *= k;
                var += noise * noise;
            }
        }
        (scale, var.sqrt())
    }

    /// The world location of the robot's ground truth over the run (for previews).
    pub fn ground_truth_path(&self, step: f64) -> Vec<Se2> {
        let n = (self.cfg.duration / step).ceil() as usize;
        (0..=n).map(|i| self.state(i as f64 * step).pose).collect()
    }

    /// Runs the whole simulation into `sink`.
    ///
    /// # Errors
    /// Whatever the sink reports.
    pub fn run(&self, sink: &mut dyn SampleSink) -> Result<Summary> {
        let cfg = &self.cfg;
        let mut summary = Summary::default();
        let mut odo = WheelOdometry::new(self.rig.wheels, &mut rng_for(cfg.seed, 1, 0));
        let mut gyro = Gyro::new(self.rig.gyro, &mut rng_for(cfg.seed, 2, 0));
        let mut odo_rng = rng_for(cfg.seed, 3, 0);
        let mut gyro_rng = rng_for(cfg.seed, 4, 0);
        let mut next = [0u64; 4];
        let mut last_capture = [0f64; 4];
        let mut next_gt = 0u64;
        let mut pending: BTreeMap<(i64, u8, u64), Sample> = BTreeMap::new();
        let key = |s: &Sample, order: u8| ((s.arrival * 1e9).round() as i64, order, s.seq);
        let mut faults_emitted = vec![false; self.world.faults.len()];
        let chunk = 2.0;
        let mut t0 = 0.0;
        while t0 < cfg.duration {
            let t1 = (t0 + chunk).min(cfg.duration);
            // Ground truth.
            while (next_gt as f64) / GT_RATE < t1 {
                let t = next_gt as f64 / GT_RATE;
                let s = self.state(t);
                let sample = Sample {
                    capture: t,
                    stamp: t,
                    arrival: t,
                    seq: next_gt,
                    payload: Payload::GroundTruth(GroundTruth {
                        pose: s.pose,
                        v: s.v,
                        w: s.w,
                    }),
                };
                pending.insert(key(&sample, 0), sample);
                next_gt += 1;
                summary.ground_truth += 1;
            }
            // Faults, announced when they start.
            if cfg.faults {
                for (i, f) in self.world.faults.iter().enumerate() {
                    if !faults_emitted[i] && f.start < t1 {
                        faults_emitted[i] = true;
                        let sample = Sample {
                            capture: f.start,
                            stamp: f.start,
                            arrival: f.start,
                            seq: i as u64,
                            payload: Payload::Fault(f.clone()),
                        };
                        pending.insert(key(&sample, 1), sample);
                        summary.faults += 1;
                    }
                }
            }
            // Odometry (sequential: encoder state).
            loop {
                let k = next[ODOM];
                let tc = self.capture_time(ODOM, k);
                if tc >= t1 {
                    break;
                }
                let ta = last_capture[ODOM];
                let travel = self.wheel_travel(ta, tc);
                let (scale, noise) = self.slip(tc);
                let r = odo.step(travel, scale, noise, tc - ta, &mut odo_rng);
                let sample = self.stamped(ODOM, k, tc, Payload::Odometry(r));
                pending.insert(key(&sample, 2), sample);
                last_capture[ODOM] = tc;
                next[ODOM] += 1;
                summary.odometry += 1;
            }
            // Gyro (sequential: bias walk).
            loop {
                let k = next[IMU];
                let tc = self.capture_time(IMU, k);
                if tc >= t1 || !self.rig.imu {
                    break;
                }
                let ta = last_capture[IMU];
                let (a, b) = (self.state(ta), self.state(tc));
                let dt = tc - ta;
                let mean_rate = if dt > 0.0 {
                    (b.heading - a.heading) / dt
                } else {
                    b.w
                };
                let r = gyro.sample(mean_rate, b.a, b.v, b.w, dt, &mut gyro_rng);
                let sample = self.stamped(IMU, k, tc, Payload::Imu(r));
                pending.insert(key(&sample, 3), sample);
                last_capture[IMU] = tc;
                next[IMU] += 1;
                summary.imu += 1;
            }
            // LiDAR scans and camera frames: collect, then render in parallel.
            let mut jobs = Vec::new();
            if self.rig.lidar.is_some() {
                loop {
                    let k = next[LIDAR];
                    let tc = self.capture_time(LIDAR, k);
                    if tc >= t1 {
                        break;
                    }
                    next[LIDAR] += 1;
                    if self
                        .active(tc)
                        .any(|f| matches!(f.kind, FaultKind::LidarOutage))
                    {
                        summary.lost_scans += 1;
                        continue;
                    }
                    jobs.push(Job::Scan(k, tc));
                }
            }
            if !self.cameras.is_empty() {
                loop {
                    let k = next[CAMERA];
                    let tc = self.capture_time(CAMERA, k);
                    if tc >= t1 {
                        break;
                    }
                    next[CAMERA] += 1;
                    for c in 0..self.cameras.len() {
                        let dirty = self.dirty_lens(c, tc);
                        let mut kept = true;
                        for f in self.active(tc) {
                            if let FaultKind::DirtyLens { camera, drop, .. } = f.kind {
                                if camera.is_none_or(|x| usize::from(x) == c) {
                                    let mut r = rng_for(cfg.seed, 400 + c as u64, k);
                                    kept &= r.random::<f64>() >= drop;
                                }
                            }
                        }
                        if kept {
                            jobs.push(Job::Frame(c, k, tc, dirty));
                        } else {
                            summary.dropped_frames += 1;
                        }
                    }
                }
            }
            let rendered: Vec<(u8, Sample)> = jobs
                .par_iter()
                .filter_map(|job| match *job {
                    Job::Scan(k, tc) => {
                        let p = self.rig.lidar.as_ref()?;
                        let mut rng = rng_for(cfg.seed, 10, k);
                        let scan = lidar::scan(
                            &self.world,
                            &self.trajectory,
                            &self.rig.limits,
                            p,
                            tc,
                            &mut rng,
                        );
                        Some((4, self.stamped(LIDAR, k, tc, Payload::Scan(scan))))
                    }
                    Job::Frame(cam, k, tc, dirty) => {
                        let mut rng = rng_for(cfg.seed, 20 + cam as u64, k);
                        let frame = self.cameras[cam].render(
                            &self.world,
                            |t| self.pose3(t),
                            tc,
                            dirty,
                            &mut rng,
                        );
                        Some((
                            5 + cam as u8,
                            self.stamped(CAMERA, k, tc, Payload::Image(cam as u8, frame)),
                        ))
                    }
                })
                .collect();
            for (order, sample) in rendered {
                match sample.payload {
                    Payload::Scan(_) => summary.scans += 1,
                    Payload::Image(..) => summary.frames += 1,
                    _ => {}
                }
                pending.insert(key(&sample, order), sample);
            }
            // Everything captured later arrives at or after t1 - MAX_JITTER.
            let horizon = ((t1 - MAX_JITTER) * 1e9) as i64;
            while let Some(entry) = pending.first_entry() {
                if entry.key().0 >= horizon && t1 < cfg.duration {
                    break;
                }
                sink.accept(&entry.remove())?;
            }
            t0 = t1;
        }
        while let Some((_, s)) = pending.pop_first() {
            sink.accept(&s)?;
        }
        Ok(summary)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::builtin;

    /// A sink that turns every sample into bytes.
    struct Bytes(Vec<u8>);

    impl SampleSink for Bytes {
        fn accept(&mut self, s: &Sample) -> Result<()> {
            let b = &mut self.0;
            for t in [s.capture, s.stamp, s.arrival] {
                b.extend_from_slice(&t.to_le_bytes());
            }
            b.extend_from_slice(&s.seq.to_le_bytes());
            match &s.payload {
                Payload::GroundTruth(g) => {
                    for v in [g.pose.x, g.pose.y, g.pose.theta, g.v, g.w] {
                        b.extend_from_slice(&v.to_le_bytes());
                    }
                }
                Payload::Odometry(o) => {
                    for v in [o.pose.x, o.pose.y, o.pose.theta, o.v, o.w] {
                        b.extend_from_slice(&v.to_le_bytes());
                    }
                }
                Payload::Imu(i) => {
                    for v in [i.yaw_rate, i.accel[0], i.accel[1], i.accel[2]] {
                        b.extend_from_slice(&v.to_le_bytes());
                    }
                }
                Payload::Scan(sc) => {
                    for r in &sc.ranges {
                        b.extend_from_slice(&r.to_le_bytes());
                    }
                }
                Payload::Image(c, f) => {
                    b.push(*c);
                    b.extend_from_slice(&f.pixels);
                }
                Payload::Fault(f) => b.extend_from_slice(format!("{f:?}").as_bytes()),
            }
            Ok(())
        }
    }

    fn run(seed: u64, sensors: SensorSet) -> (Vec<u8>, Summary) {
        let file = builtin::builtin("home", 3.0).expect("home");
        let cfg = SimConfig {
            duration: 3.0,
            seed,
            sensors,
            width: 80,
            height: 60,
            ..SimConfig::default()
        };
        let sim = Simulation::new(World::from_file(&file), cfg);
        let mut sink = Bytes(Vec::new());
        let summary = sim.run(&mut sink).expect("runs");
        (sink.0, summary)
    }

    #[test]
    fn same_seed_same_bytes_different_seed_differs() {
        let (a, sa) = run(7, SensorSet::CameraLidar);
        let (b, _) = run(7, SensorSet::CameraLidar);
        let (c, _) = run(8, SensorSet::CameraLidar);
        assert_eq!(a, b);
        assert_ne!(a, c);
        assert_eq!(sa.ground_truth, 150);
        // Jitter may move the sample due at exactly 3 s to just before it.
        assert!((150..=151).contains(&sa.odometry), "{sa:?}");
        assert!((60..=61).contains(&sa.imu), "{sa:?}");
        // Scans stop during the outage (1.5 s .. 1.65 s).
        assert!((15..=16).contains(&(sa.scans + sa.lost_scans)), "{sa:?}");
        assert!(sa.lost_scans >= 1, "{sa:?}");
        assert!(
            (30..=31).contains(&(sa.frames + sa.dropped_frames)),
            "{sa:?}"
        );
        assert_eq!(sa.faults, 4);
    }

    #[test]
    fn stream_is_ordered_by_arrival_and_two_cameras_share_stamps() {
        struct Check(f64, Vec<(f64, u8)>);
        impl SampleSink for Check {
            fn accept(&mut self, s: &Sample) -> Result<()> {
                assert!(s.arrival >= self.0 - 1e-9, "{} after {}", s.arrival, self.0);
                self.0 = s.arrival;
                assert!(s.stamp >= s.capture && s.arrival >= s.capture);
                if let Payload::Image(c, _) = s.payload {
                    self.1.push((s.stamp, c));
                }
                Ok(())
            }
        }
        let file = builtin::builtin("home", 2.0).expect("home");
        let cfg = SimConfig {
            duration: 2.0,
            sensors: SensorSet::TwoCameras,
            width: 40,
            height: 30,
            faults: false,
            ..SimConfig::default()
        };
        let sim = Simulation::new(World::from_file(&file), cfg);
        let mut sink = Check(0.0, Vec::new());
        sim.run(&mut sink).expect("runs");
        let frames = sink.1;
        assert_eq!(frames.len(), 40);
        for c in [0, 1] {
            let stamps: Vec<f64> = frames.iter().filter(|f| f.1 == c).map(|f| f.0).collect();
            assert_eq!(stamps.len(), 20);
        }
        let mut s0: Vec<f64> = frames.iter().filter(|f| f.1 == 0).map(|f| f.0).collect();
        let mut s1: Vec<f64> = frames.iter().filter(|f| f.1 == 1).map(|f| f.0).collect();
        s0.sort_by(f64::total_cmp);
        s1.sort_by(f64::total_cmp);
        assert_eq!(s0, s1);
    }

    #[test]
    fn walkway_makes_wheels_under_report() {
        let file = builtin::builtin("airport", 60.0).expect("airport");
        let sim = Simulation::new(
            World::from_file(&file),
            SimConfig {
                duration: 60.0,
                sensors: SensorSet::Lidar,
                faults: false,
                ..SimConfig::default()
            },
        );
        // Well inside the walkway (x 20..100 at 0.8 m/s from x = 19 after the initial turn).
        let (ta, tb) = (30.0, 40.0);
        let (a, b) = (sim.state(ta), sim.state(tb));
        assert!(a.pose.x > 20.0 && b.pose.x < 100.0, "{a:?} {b:?}");
        let travel = sim.wheel_travel(ta, tb);
        let ground = b.distance - a.distance;
        assert!((travel[0] - (ground - 0.65 * (tb - ta))).abs() < 1e-6);
    }
}
