//! # cloi-core
//!
//! The algorithms of CLOi-Mapper, a 2D SLAM system for low-cost service robots, in a form that
//! runs unchanged on a Cortex-A9 without an operating system: `no_std`, no heap, no clock (the
//! caller passes every timestamp), and no `unsafe`.
//!
//! Layers, following the paper's block diagram:
//! * [`geom`]: SE(2) poses, Jacobians, covariance compounding, Mahalanobis distances, and the
//!   information heuristic of eq. (1).
//! * [`storage`]: the typed ids of graph nodes and edges.
//! * [`graph`]: the SE(2) pose graph over caller-provided storage.
//! * [`solver`]: sparse Gauss-Newton / Levenberg-Marquardt with robust kernels and
//!   max-mixtures.
//! * [`sensor`]: sensor frames lent to the core (time stamps, odometry, IMU, laser scans,
//!   camera images) and the scan checks.
//! * [`frontend`]: odometry fusion, scan preprocessing, occupancy-grid submaps, ICP, the
//!   correlative loop-closure search and the keyframe decision (paper section III-B), and the
//!   image front-end's building blocks (camera models, pyramid, corners, descriptors,
//!   matching, triangulation, the sliding-window bundle adjustment, the visual odometry).
//! * [`mapper`]: the LiDAR mapper assembled from all of the above: front-end, frame nodes,
//!   loop closure, GPE with the worst-case prediction, and the back-end in bounded steps.
//! * [`profile`]: the memory profiles and the resources value that owns all storage.
//! * [`sort`]: sorting and selection without recursion, so the firmware's stack has a static
//!   bound.
//! * [`workload`]: a fixed workload used to check ARM and x86-64 agree, and to count
//!   instructions on the emulated Cortex-A9.
#![no_std]
#![forbid(unsafe_code)]
#![warn(missing_docs)]
// Nothing on a data path may panic. Slice indexing is left to review (and to the tests): the
// numeric code indexes fixed-size matrices by constants, where `get` would only add noise.
#![cfg_attr(
    not(test),
    warn(clippy::unwrap_used, clippy::expect_used, clippy::panic)
)]

#[macro_use]
mod fmt;

pub mod backend;
pub mod frontend;
pub mod geom;
pub mod gpe;
pub mod graph;
pub mod mapper;
pub mod profile;
pub mod sensor;
pub mod solver;
pub mod sort;
pub mod storage;
pub mod workload;

pub use geom::Se2;
