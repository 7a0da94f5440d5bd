//! Semi-real-time global pose estimation, the GPE (the paper's section III-C): block (b) of the
//! block diagram, between the front-end and the back-end.
//!
//! The back-end's optimization is slow and runs late, so the pose the robot drives on comes
//! from a small problem solved every frame: the current pose tied to the newest frame node (the
//! reference) and to the node the last optimization settled (the anchor), both through the
//! front-end's motion since them, and to the previous real-time pose through the motion of the
//! last frame. When even that cannot run in time, the worst-case prediction carries the last
//! correction forward.
//!
//! * [`problem`]: the weighted least-squares problem of eq. 5 and its solver;
//! * [`anchor`]: the choice of the anchor node after an optimization;
//! * [`predict`]: the worst-case prediction of eqs. 6-7;
//! * [`tracker`]: the per-frame update that assembles the terms and falls back to the
//!   prediction.

pub mod anchor;
pub mod predict;
pub mod problem;
pub mod tracker;

pub use anchor::{choose_anchor, AnchorCandidate};
pub use predict::worst_case;
pub use problem::{solve, GpeConfig, GpeSolution, PoseTerm, MAX_TERMS};
pub use tracker::{GpeFrame, GpeTracker, NodeTie, RealTimePose};
