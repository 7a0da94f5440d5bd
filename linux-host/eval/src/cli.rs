//! `cloi eval relations | ate | rpe | ref | arps | loops`: each prints one JSON object.

use std::io::Write;
use std::path::PathBuf;

use anyhow::Result;
use clap::{Args, Subcommand};
use cloi_core::Se2;
use cloi_io::parse_pose;
use serde_json::json;

use crate::arps::{eval_arps, BatchOptimum};
use crate::loops::{check_loops, switched_off_edges};
use crate::metrics::{ate, rpe, DeltaUnit};
use crate::relations::{load_relations, relations_from_reference, score, PlanarTrajectory};
use crate::traj::{Alignment, Trajectory};

/// The `cloi eval` subcommands.
#[derive(Debug, Subcommand)]
pub enum EvalCommand {
    /// Relation metric (Kuemmerle et al. 2009) against a relations file.
    Relations(RelationsArgs),
    /// Absolute trajectory error after alignment (as `evo_ape`).
    Ate(AteArgs),
    /// Relative pose error (as `evo_rpe`).
    Rpe(RpeArgs),
    /// Relative errors against GMapping reference poses (`*.gfs_reference_poses.txt`).
    Ref(RefArgs),
    /// Average relative pose shift (ARPS) of a pruned pose graph against its original.
    Arps(ArpsArgs),
    /// Loop edges of a `cloi map` pose graph that disagree with ground truth.
    Loops(LoopsArgs),
}

/// Arguments of `cloi eval loops`.
#[derive(Debug, Args)]
pub struct LoopsArgs {
    /// The pose graph `cloi map` wrote (`graph.g2o`).
    #[arg(long)]
    pub graph: PathBuf,
    /// The trajectory of the same run (`trajectory.tum`): it gives each vertex its time.
    #[arg(long)]
    pub trajectory: PathBuf,
    /// Ground truth: a TUM file (`cloi sim`'s `X.gt.tum`) or GMapping reference poses
    /// (`*.gfs_reference_poses.txt`, recognised by the name).
    #[arg(long)]
    pub reference: PathBuf,
    /// Pose of the sensor on the robot (`X,Y,THETA`) whose poses the reference holds; the
    /// reference is moved back to the robot's frame (as for `cloi eval ref`).
    #[arg(long, value_name = "X,Y,THETA", value_parser = parse_pose, allow_hyphen_values = true)]
    pub sensor_offset: Option<Se2>,
    /// Largest time difference between a vertex's scan and its ground-truth pose (s).
    #[arg(long, default_value_t = 0.02)]
    pub max_time_diff: f64,
    /// Without a ground-truth pose within `--max-time-diff`, interpolate between the poses
    /// around the time if they are at most this many seconds apart (GMapping's reference
    /// holds only the scans it processed); 0 never interpolates.
    #[arg(long, default_value_t = 0.0)]
    pub max_gap: f64,
    /// A loop edge whose translation differs from ground truth by more than this (m) is wrong.
    #[arg(long, default_value_t = 0.3)]
    pub threshold: f64,
    /// The run's `report.json`: its list of loop edges the back-end switched off separates
    /// the wrong loop closures acting on the map (`wrong_active`) from the rejected ones.
    #[arg(long)]
    pub report: Option<PathBuf>,
}

/// Arguments of `cloi eval arps`.
#[derive(Debug, Args)]
pub struct ArpsArgs {
    /// The full pose graph (g2o or TORO); it is optimized first unless `--as-is`.
    #[arg(long)]
    pub original: PathBuf,
    /// The pruned graph (as `cloi prune --out` writes it: original vertex ids kept).
    #[arg(long)]
    pub pruned: PathBuf,
    /// Take the original's vertex poses as they are (already optimized).
    #[arg(long)]
    pub as_is: bool,
}

/// Arguments of `cloi eval relations`.
#[derive(Debug, Args)]
pub struct RelationsArgs {
    /// Estimated trajectory (TUM).
    #[arg(long)]
    pub trajectory: PathBuf,
    /// Relations file (`t1 t2 x y z roll pitch yaw` or `t1 t2 x y theta`).
    #[arg(long)]
    pub relations: PathBuf,
    /// Time stamp tolerance (s); 0 matches exactly.
    #[arg(long, default_value_t = 0.0)]
    pub tolerance: f64,
    /// Pose on the robot (`X,Y,THETA`: m, m, rad) of the sensor whose poses the relations
    /// describe; the trajectory (the robot's) is moved into that frame before scoring.
    #[arg(long, value_name = "X,Y,THETA", value_parser = parse_pose, allow_hyphen_values = true)]
    pub sensor_offset: Option<Se2>,
}

/// Arguments of `cloi eval ate`.
#[derive(Debug, Args)]
pub struct AteArgs {
    /// Estimated trajectory (TUM or KITTI).
    #[arg(long)]
    pub trajectory: PathBuf,
    /// Reference trajectory (TUM or KITTI).
    #[arg(long)]
    pub reference: PathBuf,
    /// Alignment of the estimate to the reference.
    #[arg(long, value_enum, default_value_t = Alignment::Se3)]
    pub align: Alignment,
    /// Largest time difference of matched poses (s), as evo's `--t_max_diff`.
    #[arg(long, default_value_t = 0.01)]
    pub max_time_diff: f64,
}

/// Arguments of `cloi eval rpe`.
#[derive(Debug, Args)]
pub struct RpeArgs {
    /// Estimated trajectory (TUM or KITTI).
    #[arg(long)]
    pub trajectory: PathBuf,
    /// Reference trajectory (TUM or KITTI).
    #[arg(long)]
    pub reference: PathBuf,
    /// Step between compared poses.
    #[arg(long, default_value_t = 1.0)]
    pub delta: f64,
    /// Unit of the step.
    #[arg(long, value_enum, default_value_t = DeltaUnit::Frames)]
    pub delta_unit: DeltaUnit,
    /// Accepted for symmetry with `ate`; a rigid alignment does not change the RPE.
    #[arg(long, value_enum, default_value_t = Alignment::None)]
    pub align: Alignment,
    /// Largest time difference of matched poses (s).
    #[arg(long, default_value_t = 0.01)]
    pub max_time_diff: f64,
    /// With `--delta-unit meters`: start the first pair at the first pose `delta` metres
    /// along, as evo did before it always included pose 0 (the stored evo results).
    #[arg(long)]
    pub first_pair_at_delta: bool,
}

/// Arguments of `cloi eval ref`.
#[derive(Debug, Args)]
pub struct RefArgs {
    /// Estimated trajectory (TUM) with the logs' scan time stamps.
    #[arg(long)]
    pub trajectory: PathBuf,
    /// GMapping reference poses (`timestamp index x y theta`).
    #[arg(long)]
    pub reference: PathBuf,
    /// Pairs of reference poses at most this far apart (m) become relations.
    #[arg(long, default_value_t = 1.0)]
    pub max_distance: f64,
    /// Time stamp tolerance (s); 0 matches exactly.
    #[arg(long, default_value_t = 0.0)]
    pub tolerance: f64,
    /// Pose of the laser on the robot (`X,Y,THETA`: m, m, rad). GMapping's corrected logs,
    /// hence the reference poses, hold the laser's poses; the trajectory (the robot's, as
    /// `cloi map` writes it) is moved into the laser's frame before scoring. `cloi map`
    /// reports the mounting it used as `input.laser_offset` in `report.json` (fr079: -0.04,
    /// 0, 0; intel and mit-csail: 0).
    #[arg(long, value_name = "X,Y,THETA", value_parser = parse_pose, allow_hyphen_values = true)]
    pub sensor_offset: Option<Se2>,
}

/// The trajectory in the frame of the sensor at `offset`, if any.
fn in_frame(traj: PlanarTrajectory, offset: Option<Se2>) -> PlanarTrajectory {
    match offset {
        Some(o) => traj.in_sensor_frame(&o),
        None => traj,
    }
}

/// Runs an eval subcommand, printing JSON to `out`. `batch_optimum` optimizes the original
/// graph of `cloi eval arps` (see [`eval_arps`]).
///
/// # Errors
/// Unreadable inputs or nothing to compare.
pub fn run(cmd: &EvalCommand, batch_optimum: &BatchOptimum, out: &mut dyn Write) -> Result<()> {
    let value = match cmd {
        EvalCommand::Arps(a) => {
            serde_json::to_value(eval_arps(&a.original, &a.pruned, a.as_is, batch_optimum)?)?
        }
        EvalCommand::Loops(a) => {
            if !(a.max_time_diff >= 0.0 && a.max_time_diff < 10.0) {
                anyhow::bail!("--max-time-diff must be in [0, 10) seconds");
            }
            if !(a.max_gap >= 0.0 && a.max_gap < 600.0) {
                anyhow::bail!("--max-gap must be in [0, 600) seconds");
            }
            let graph = cloi_io::graph_io::read_graph(&a.graph, None)?;
            let estimate = PlanarTrajectory::load_tum(&a.trajectory)?;
            let is_gfs = a
                .reference
                .to_string_lossy()
                .ends_with("gfs_reference_poses.txt");
            let mut truth = if is_gfs {
                PlanarTrajectory::load_reference(&a.reference)?
            } else {
                PlanarTrajectory::load_tum(&a.reference)?
            };
            if let Some(o) = a.sensor_offset {
                truth = truth.in_sensor_frame(&o.inverse());
            }
            let tolerance_ns = (a.max_time_diff * 1e9).round() as i64;
            let switched_off = match &a.report {
                Some(path) => switched_off_edges(path)?,
                None => Default::default(),
            };
            serde_json::to_value(check_loops(
                &graph,
                &switched_off,
                &estimate,
                &truth,
                tolerance_ns,
                (a.max_gap * 1e9).round() as i64,
                a.threshold,
            )?)?
        }
        EvalCommand::Relations(a) => {
            let traj = in_frame(PlanarTrajectory::load_tum(&a.trajectory)?, a.sensor_offset);
            let rels = load_relations(&a.relations)?;
            serde_json::to_value(score(&traj, &rels, a.tolerance)?)?
        }
        EvalCommand::Ate(a) => {
            let est = Trajectory::load(&a.trajectory)?;
            let reference = Trajectory::load(&a.reference)?;
            serde_json::to_value(ate(&est, &reference, a.align, a.max_time_diff)?)?
        }
        EvalCommand::Rpe(a) => {
            let est = Trajectory::load(&a.trajectory)?;
            let reference = Trajectory::load(&a.reference)?;
            serde_json::to_value(rpe(
                &est,
                &reference,
                a.delta,
                a.delta_unit,
                a.max_time_diff,
                a.first_pair_at_delta,
            )?)?
        }
        EvalCommand::Ref(a) => {
            let traj = in_frame(PlanarTrajectory::load_tum(&a.trajectory)?, a.sensor_offset);
            let reference = PlanarTrajectory::load_reference(&a.reference)?;
            let rels = relations_from_reference(&reference, a.max_distance);
            let mut v = serde_json::to_value(score(&traj, &rels, a.tolerance)?)?;
            v["max_distance_m"] = json!(a.max_distance);
            v["sensor_offset"] = json!(a.sensor_offset.map(|o| [o.x, o.y, o.theta]));
            v["reference_poses"] = json!(reference.poses.len());
            v["relations"] = json!(rels.len());
            v
        }
    };
    writeln!(out, "{}", serde_json::to_string_pretty(&value)?)?;
    Ok(())
}
