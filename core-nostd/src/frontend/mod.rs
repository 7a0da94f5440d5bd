//! The LiDAR front-end of the paper's section III-B: odometry fusion, scan preprocessing,
//! occupancy-grid submaps, scan matching (ICP for odometry and refinement, a correlative
//! branch-and-bound search for loop closures) and the keyframe decision; and the image
//! front-end under [`visual`] (camera models, pyramid, corners, descriptors, matching,
//! triangulation, the sliding-window bundle adjustment, and the visual odometry that joins
//! them).
//!
//! Every type here works on caller-provided or fixed-capacity storage; nothing allocates and
//! nothing reads a clock. Scan points and grid cells are `f32`, poses `f64`.

pub mod csm;
pub mod far_csm;
pub mod grid;
pub mod gyro_bias;
pub mod icp;
pub mod kdtree;
pub mod keyframe;
pub mod lidar;
pub mod odometry;
pub mod pointmap;
pub mod scan;
pub mod visual;

pub use grid::{GridParams, Submap};
pub use icp::{align, IcpConfig, IcpResult, MatchError};
pub use kdtree::KdTree;
pub use keyframe::{KeyframeConfig, KeyframeSelector};
pub use lidar::{LidarFrontend, MotionNoise, Travel};
pub use pointmap::PointMap;
pub use scan::{preprocess, BeamGeometry, PreprocessConfig, ScanPoint, ScanPoints, ScanStats};
