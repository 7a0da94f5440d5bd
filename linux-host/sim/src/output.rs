//! Thin adapters from the simulated stream to files: a ROS 2 bag (through
//! [`cloi_io::bag::BagWriter`]), the ground truth in TUM format, and a JSON sidecar with the
//! configuration, sensor parameters and fault schedule (including the optimisation delays the
//! mapper must honour).
//!
//! Topics: `/ground_truth` (`nav_msgs/Odometry`, frame `map`, exact capture times), `/odom`
//! (`nav_msgs/Odometry`), `/imu` (`sensor_msgs/Imu`), `/scan` (`sensor_msgs/LaserScan`),
//! `/camera0/image_raw` and `/camera1/image_raw` (`sensor_msgs/Image`, `mono8`), and the sensor
//! mounts on `/tf_static` (`tf2_msgs/TFMessage`). Times are
//! seconds from the start plus [`EPOCH_NS`].

use std::fmt::Write as _;
use std::io::Write;
use std::path::Path;

use anyhow::Result;

use crate::camera::Lens;
use crate::engine::{Payload, Sample, SampleSink, Simulation};
use cloi_io::atomic::AtomicFile;
use cloi_io::bag::BagWriter;
use cloi_io::ros2::{
    Header, Image, Imu, LaserScan, Odometry, Pose, PoseWithCovariance, Quaternion, TfMessage, Time,
    Transform, TransformStamped, Twist, TwistWithCovariance, Vector3,
};

/// The wall-clock origin of simulated time: 2023-11-14T22:13:20Z.
pub const EPOCH_NS: i64 = 1_700_000_000_000_000_000;

fn ns(t: f64) -> i64 {
    EPOCH_NS + (t * 1e9).round() as i64
}

fn time(t: f64) -> Time {
    Time::from_nanos(ns(t))
}

fn diag6(d: [f64; 6]) -> [f64; 36] {
    let mut c = [0.0; 36];
    for (i, v) in d.iter().enumerate() {
        c[i * 7] = *v;
    }
    c
}

fn diag3(d: [f64; 3]) -> [f64; 9] {
    let mut c = [0.0; 9];
    for (i, v) in d.iter().enumerate() {
        c[i * 4] = *v;
    }
    c
}

/// Writes the stream into a ROS 2 bag.
#[derive(Debug)]
pub struct BagSink {
    bag: BagWriter,
    gyro_var: f64,
    accel_var: f64,
}

impl BagSink {
    /// Starts a bag at `path` (it appears when [`BagSink::finish`] succeeds).
    ///
    /// # Errors
    /// The folder is not writable.
    pub fn create(path: &Path, sim: &Simulation) -> Result<BagSink> {
        let mut bag = BagWriter::create(path)?;
        bag.write("/tf_static", EPOCH_NS, &static_transforms(sim))?;
        Ok(BagSink {
            bag,
            gyro_var: sim.rig.gyro.noise.powi(2),
            accel_var: sim.rig.gyro.accel_noise.powi(2),
        })
    }

    /// Finishes the bag; returns the number of messages.
    ///
    /// # Errors
    /// Any IO error.
    pub fn finish(self) -> Result<u64> {
        self.bag.finish()
    }
}

impl SampleSink for BagSink {
    fn accept(&mut self, s: &Sample) -> Result<()> {
        let log = ns(s.arrival);
        let stamp = time(s.stamp);
        match &s.payload {
            Payload::GroundTruth(g) => self.bag.write(
                "/ground_truth",
                log,
                &Odometry {
                    header: Header::new(stamp, "map"),
                    child_frame_id: "base_link".into(),
                    pose: PoseWithCovariance {
                        pose: Pose::planar(g.pose.x, g.pose.y, g.pose.theta),
                        covariance: [0.0; 36],
                    },
                    twist: TwistWithCovariance {
                        twist: Twist {
                            linear: Vector3 {
                                x: g.v,
                                y: 0.0,
                                z: 0.0,
                            },
                            angular: Vector3 {
                                x: 0.0,
                                y: 0.0,
                                z: g.w,
                            },
                        },
                        covariance: [0.0; 36],
                    },
                },
            ),
            Payload::Odometry(o) => self.bag.write(
                "/odom",
                log,
                &Odometry {
                    header: Header::new(stamp, "odom"),
                    child_frame_id: "base_link".into(),
                    pose: PoseWithCovariance {
                        pose: Pose::planar(o.pose.x, o.pose.y, o.pose.theta),
                        covariance: diag6([1e-2, 1e-2, 1e6, 1e6, 1e6, 1e-2]),
                    },
                    twist: TwistWithCovariance {
                        twist: Twist {
                            linear: Vector3 {
                                x: o.v,
                                y: 0.0,
                                z: 0.0,
                            },
                            angular: Vector3 {
                                x: 0.0,
                                y: 0.0,
                                z: o.w,
                            },
                        },
                        covariance: diag6([1e-3, 1e-6, 1e6, 1e6, 1e6, 1e-3]),
                    },
                },
            ),
            Payload::Imu(i) => {
                let mut orientation_covariance = [0.0; 9];
                orientation_covariance[0] = -1.0;
                self.bag.write(
                    "/imu",
                    log,
                    &Imu {
                        header: Header::new(stamp, "imu"),
                        orientation: Quaternion::IDENTITY,
                        orientation_covariance,
                        angular_velocity: Vector3 {
                            x: 0.0,
                            y: 0.0,
                            z: i.yaw_rate,
                        },
                        angular_velocity_covariance: diag3([self.gyro_var; 3]),
                        linear_acceleration: Vector3 {
                            x: i.accel[0],
                            y: i.accel[1],
                            z: i.accel[2],
                        },
                        linear_acceleration_covariance: diag3([self.accel_var; 3]),
                    },
                )
            }
            Payload::Scan(sc) => self.bag.write(
                "/scan",
                log,
                &LaserScan {
                    header: Header::new(stamp, "laser"),
                    angle_min: sc.angle_min,
                    angle_max: sc.angle_min
                        + sc.angle_increment * (sc.ranges.len().saturating_sub(1)) as f32,
                    angle_increment: sc.angle_increment,
                    time_increment: sc.time_increment,
                    scan_time: sc.scan_time,
                    range_min: sc.range_min,
                    range_max: sc.range_max,
                    ranges: sc.ranges.clone(),
                    intensities: Vec::new(),
                },
            ),
            Payload::Image(cam, f) => self.bag.write(
                &format!("/camera{cam}/image_raw"),
                log,
                &Image {
                    header: Header::new(stamp, &format!("camera{cam}")),
                    height: f.height,
                    width: f.width,
                    encoding: "mono8".into(),
                    is_bigendian: 0,
                    step: f.width,
                    data: f.pixels.clone(),
                },
            ),
            // Faults are not sensor data: they go to the sidecar.
            Payload::Fault(_) => Ok(()),
        }
    }
}

/// The quaternion of a rotation matrix given by its columns.
fn quaternion_from_columns(c: [[f64; 3]; 3]) -> Quaternion {
    // m[row][col]
    let m = |r: usize, k: usize| c[k][r];
    let trace = m(0, 0) + m(1, 1) + m(2, 2);
    if trace > 0.0 {
        let s = 0.5 / (trace + 1.0).sqrt();
        Quaternion {
            w: 0.25 / s,
            x: (m(2, 1) - m(1, 2)) * s,
            y: (m(0, 2) - m(2, 0)) * s,
            z: (m(1, 0) - m(0, 1)) * s,
        }
    } else if m(0, 0) > m(1, 1) && m(0, 0) > m(2, 2) {
        let s = 2.0 * (1.0 + m(0, 0) - m(1, 1) - m(2, 2)).sqrt();
        Quaternion {
            w: (m(2, 1) - m(1, 2)) / s,
            x: 0.25 * s,
            y: (m(0, 1) + m(1, 0)) / s,
            z: (m(0, 2) + m(2, 0)) / s,
        }
    } else if m(1, 1) > m(2, 2) {
        let s = 2.0 * (1.0 + m(1, 1) - m(0, 0) - m(2, 2)).sqrt();
        Quaternion {
            w: (m(0, 2) - m(2, 0)) / s,
            x: (m(0, 1) + m(1, 0)) / s,
            y: 0.25 * s,
            z: (m(1, 2) + m(2, 1)) / s,
        }
    } else {
        let s = 2.0 * (1.0 + m(2, 2) - m(0, 0) - m(1, 1)).sqrt();
        Quaternion {
            w: (m(1, 0) - m(0, 1)) / s,
            x: (m(0, 2) + m(2, 0)) / s,
            y: (m(1, 2) + m(2, 1)) / s,
            z: 0.25 * s,
        }
    }
}

/// The sensor mounts as `/tf_static`: `base_link` to `laser`, `imu` and `cameraN` (optical
/// frame: z forward, x right, y down).
pub fn static_transforms(sim: &Simulation) -> TfMessage {
    let header = Header::new(Time::from_nanos(EPOCH_NS), "base_link");
    let mut transforms = vec![TransformStamped {
        header: header.clone(),
        child_frame_id: "imu".into(),
        transform: Transform::planar(0.0, 0.0, 0.0),
    }];
    if let Some(l) = &sim.rig.lidar {
        let mut t = Transform::planar(l.mount_x, 0.0, 0.0);
        t.translation.z = l.height;
        transforms.push(TransformStamped {
            header: header.clone(),
            child_frame_id: "laser".into(),
            transform: t,
        });
    }
    for (i, c) in sim.rig.cameras.iter().enumerate() {
        transforms.push(TransformStamped {
            header: header.clone(),
            child_frame_id: format!("camera{i}"),
            transform: Transform {
                translation: Vector3 {
                    x: c.mount[0],
                    y: c.mount[1],
                    z: c.mount[2],
                },
                rotation: quaternion_from_columns(c.body_from_optical()),
            },
        });
    }
    TfMessage { transforms }
}

/// Collects the ground truth in TUM format (`t x y z qx qy qz qw`, one pose per line).
#[derive(Debug, Default)]
pub struct TumSink {
    /// The text so far.
    pub text: String,
}

impl SampleSink for TumSink {
    fn accept(&mut self, s: &Sample) -> Result<()> {
        if let Payload::GroundTruth(g) = &s.payload {
            let t = ns(s.capture);
            let q = Quaternion::from_yaw(g.pose.theta);
            writeln!(
                self.text,
                "{}.{:09} {:.6} {:.6} 0 0 0 {:.9} {:.9}",
                t.div_euclid(1_000_000_000),
                t.rem_euclid(1_000_000_000),
                g.pose.x,
                g.pose.y,
                q.z,
                q.w
            )?;
        }
        Ok(())
    }
}

/// Sends every sample to several sinks.
#[derive(Debug)]
pub struct Tee<'a, A: SampleSink, B: SampleSink>(pub &'a mut A, pub &'a mut B);

impl<A: SampleSink, B: SampleSink> SampleSink for Tee<'_, A, B> {
    fn accept(&mut self, s: &Sample) -> Result<()> {
        self.0.accept(s)?;
        self.1.accept(s)
    }
}

/// The sidecar: configuration, sensor parameters and fault schedule as JSON.
pub fn sidecar(sim: &Simulation) -> serde_json::Value {
    let cfg = &sim.cfg;
    let rig = &sim.rig;
    let cameras: Vec<serde_json::Value> = rig
        .cameras
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let (model, k) = match c.lens {
                Lens::Pinhole => ("pinhole", [0.0; 4]),
                Lens::KannalaBrandt(k) => ("kannala_brandt", k),
            };
            serde_json::json!({
                "topic": format!("/camera{i}/image_raw"),
                "model": model, "width": c.width, "height": c.height,
                "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "k": k,
                "tilt_deg": c.tilt.to_degrees(), "yaw_deg": c.yaw.to_degrees(),
                "mount_xyz": c.mount, "rate_hz": c.rate_hz,
                "exposure_s": c.exposure, "motion_blur": c.motion_blur,
                "gain_sigma": c.gain_sigma, "read_noise": c.read_noise, "shot_noise": c.shot_noise,
            })
        })
        .collect();
    let lidar = rig.lidar.map(|l| {
        serde_json::json!({
            "topic": "/scan", "beams": l.beams, "angle_min": l.angle_min,
            "angle_increment": l.angle_increment, "range_min": l.range_min,
            "range_max": l.range_max, "rate_hz": l.rate_hz, "sigma": l.sigma,
            "sigma_rel": l.sigma_rel, "dropout": l.dropout, "glass_pass": l.glass_pass,
            "height": l.height, "mount_x": l.mount_x, "sweep_time": l.sweep_time,
        })
    });
    let faults: Vec<serde_json::Value> = if cfg.faults {
        sim.world
            .faults
            .iter()
            .map(|f| serde_json::to_value(f).unwrap_or(serde_json::Value::Null))
            .collect()
    } else {
        Vec::new()
    };
    let timing: Vec<serde_json::Value> = ["lidar", "odom", "imu", "camera"]
        .iter()
        .zip(&rig.timing)
        .map(|(n, t)| {
            serde_json::json!({
                "stream": n, "rate_hz": t.rate_hz, "jitter_s": t.jitter,
                "stamp_offset_s": t.stamp_offset, "latency_s": t.latency,
            })
        })
        .collect();
    let mut side = serde_json::json!({
        "world": sim.world.name,
        "seed": cfg.seed,
        "duration_s": cfg.duration,
        "epoch_ns": EPOCH_NS,
        "sensors": format!("{:?}", cfg.sensors),
        "cameras": cameras,
        "lidar": lidar,
        "wheels": {
            "topic": "/odom", "radius": rig.wheels.radius, "track": rig.wheels.track,
            "ticks_per_rev": rig.wheels.ticks_per_rev, "scale_sigma": rig.wheels.scale_sigma,
            "scale_offset": rig.wheels.scale_offset,
            "noise_per_sqrt_m": rig.wheels.noise, "rate_hz": rig.wheels.rate_hz,
        },
        "gyro": {
            "topic": "/imu", "rate_hz": rig.gyro.rate_hz, "noise": rig.gyro.noise,
            "present": rig.imu, "bias_offset": rig.gyro.bias_offset,
            "bias_sigma": rig.gyro.bias_sigma, "bias_walk": rig.gyro.bias_walk,
            "accel_noise": rig.gyro.accel_noise,
        },
        "timing": timing,
        "faults": faults,
    });
    // Only a changed world says which session it is, so the sidecar of a world as written
    // keeps its bytes.
    if sim.world.session > 0 {
        side["session"] = sim.world.session.into();
    }
    side
}

/// Writes text to `path` atomically.
///
/// # Errors
/// Any IO error.
pub fn write_text(path: &Path, text: &str) -> Result<()> {
    write_bytes(path, text.as_bytes())
}

/// Writes bytes to `path` atomically.
///
/// # Errors
/// Any IO error.
pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    let mut f = AtomicFile::create(path)?;
    f.write_all(bytes)?;
    f.commit()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::CameraParams;

    #[test]
    fn camera_mount_quaternion_rotates_optical_axes_into_the_body() {
        for (tilt, yaw) in [(45.0, 0.0), (60.0, 180.0), (30.0, 90.0)] {
            let p = CameraParams::new(320, 240, true, tilt, yaw);
            let cols = p.body_from_optical();
            let q = quaternion_from_columns(cols);
            // Rotate the optical unit vectors with q and compare with the columns.
            let rot = |v: [f64; 3]| {
                let (w, x, y, z) = (q.w, q.x, q.y, q.z);
                let t = [
                    2.0 * (y * v[2] - z * v[1]),
                    2.0 * (z * v[0] - x * v[2]),
                    2.0 * (x * v[1] - y * v[0]),
                ];
                [
                    v[0] + w * t[0] + (y * t[2] - z * t[1]),
                    v[1] + w * t[1] + (z * t[0] - x * t[2]),
                    v[2] + w * t[2] + (x * t[1] - y * t[0]),
                ]
            };
            for (k, col) in cols.iter().enumerate() {
                let mut e = [0.0; 3];
                e[k] = 1.0;
                let r = rot(e);
                for i in 0..3 {
                    assert!(
                        (r[i] - col[i]).abs() < 1e-9,
                        "tilt {tilt} yaw {yaw}: {r:?} vs {col:?}"
                    );
                }
            }
        }
    }
}
