//! # cloi-sim
//!
//! The simulator behind `cloi sim`: worlds with exact ground truth, and the sensors of a
//! cleaning or guide robot (2D LiDAR, wheel odometry, gyro, one or two ceiling cameras) with
//! documented noise, realistic timestamps and scheduled faults.
//!
//! * [`world`]: floor plans, the TOML world format and the ray-casting grid;
//! * [`builtin`]: the `home`, `office` and `airport` worlds;
//! * [`generate`]: random buildings from a seed (`gen:SEED[:SIZE][:nogyro]`);
//! * [`path`]: zigzag coverage and guide tours as exact trajectories;
//! * [`lidar`], [`odometry`], [`camera`] (+ [`texture`]): the sensor models;
//! * [`engine`]: the time-ordered stream of [`engine::Sample`]s, deterministic from a seed,
//!   rendered in parallel;
//! * [`output`]: the ROS 2 bag, TUM ground truth and fault sidecar writers;
//! * [`preview`]: the PNG preview;
//! * [`command`]: `cloi sim`.

pub mod builtin;
pub mod camera;
pub mod command;
pub mod engine;
pub mod generate;
pub mod lidar;
pub mod odometry;
pub mod output;
pub mod path;
pub mod preview;
pub mod texture;
pub mod world;

pub use engine::{SampleSink, SensorSet, SimConfig, Simulation};
pub use world::{World, WorldFile};
