//! `cloi map`: the host layer around the core mapper.
//!
//! * [`input`], CARMEN logs, ROS 2 bags and the simulator as one stream of sensor events;
//! * [`config`], the TOML configuration with the `home`, `office` and `airport` presets;
//! * [`run`], the driver of the core mapper and the writer of every output;
//! * [`command`], the `cloi map` arguments;
//! * [`show`], `cloi show-map`, a saved map's contents and pictures;
//! * [`output`], trajectories, the run report, the global grid from submaps, peak heap and
//!   the progress bar.

pub mod command;
pub mod config;
pub mod input;
pub mod output;
pub mod resources;
pub mod run;
pub mod show;
pub mod spool;

pub use config::{MapConfig, Profile};
pub use input::{
    open_input, sim_input, InputArgs, InputOptions, InputSize, InputStats, InputStream,
    LaserChoice, ScanEvent, SensorEvent, StatsHandle,
};
pub use output::{compose_global_grid, write_tum, MapReport, OwnedGrid, SubmapView};
