//! `cloi convert`: CARMEN logs to ROS 2 bags, and ROS 2 bags to trajectories and reports.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Result};
use clap::Args;
use serde_json::json;

use crate::bag_read::{BagReadOptions, BagReader, SensorMsg, TopicSelection};
use crate::cloilog::carmen_to_cloilog;
use crate::convert::carmen_to_bag;
use crate::tum::{write_tum, StampedPose};

/// Arguments of `cloi convert`.
#[derive(Debug, Args)]
pub struct ConvertArgs {
    /// Input: a CARMEN log (`.clf`, `.log`, optionally `.gz`/`.bz2`) or a ROS 2 bag (`.mcap`).
    pub input: PathBuf,
    /// Output: `.mcap` (ROS 2 bag, from a CARMEN log), `.tum` (the odometry of a bag or
    /// log as a TUM trajectory) or `.cloilog` (the firmware's binary sensor log, from a CARMEN
    /// log). Alternatively `--out`.
    #[arg(required_unless_present = "out")]
    pub output: Option<PathBuf>,
    /// Output file (instead of the positional argument).
    #[arg(long = "out", conflicts_with = "output")]
    pub out: Option<PathBuf>,
    /// Output format; default: from the output's extension.
    #[arg(long, value_enum)]
    pub to: Option<OutputFormat>,
    /// Stop after this many scans (`.cloilog` output; e.g. a short log for CI).
    #[arg(long)]
    pub max_scans: Option<u64>,
    /// Treat damaged or truncated input as an error instead of a warning.
    #[arg(long)]
    pub strict: bool,
    /// `range_max` of the written scans (m); default: from the log, else 80.
    #[arg(long)]
    pub range_max: Option<f32>,
    /// Laser scan topic of an input bag (default: every `sensor_msgs/msg/LaserScan` topic).
    #[arg(long)]
    pub scan_topic: Option<String>,
    /// Odometry topic of an input bag (default: every `nav_msgs/msg/Odometry` topic).
    #[arg(long)]
    pub odom_topic: Option<String>,
    /// IMU topic of an input bag.
    #[arg(long)]
    pub imu_topic: Option<String>,
    /// Camera topic of an input bag.
    #[arg(long)]
    pub image_topic: Option<String>,
}

/// Output formats of `cloi convert`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum OutputFormat {
    /// ROS 2 bag (MCAP).
    Mcap,
    /// TUM trajectory of the odometry.
    Tum,
    /// The firmware's compact binary sensor log.
    Cloilog,
}

impl OutputFormat {
    fn extension(self) -> &'static str {
        match self {
            Self::Mcap => "mcap",
            Self::Tum => "tum",
            Self::Cloilog => "cloilog",
        }
    }
}

impl ConvertArgs {
    /// The output path (positional or `--out`).
    pub fn output_path(&self) -> &Path {
        self.output
            .as_deref()
            .or(self.out.as_deref())
            .unwrap_or(Path::new(""))
    }
}

fn extension(path: &Path) -> String {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    let name = name
        .strip_suffix(".gz")
        .or_else(|| name.strip_suffix(".bz2"))
        .unwrap_or(&name)
        .to_owned();
    name.rsplit_once('.')
        .map(|(_, e)| e.to_owned())
        .unwrap_or_default()
}

/// Runs `cloi convert`, printing a JSON report to `out` and warnings to stderr.
///
/// # Errors
/// Unsupported formats, unreadable input, damage with `--strict`, or unwritable output.
pub fn run(args: &ConvertArgs, out: &mut dyn Write) -> Result<()> {
    let started = Instant::now();
    let input_bytes = std::fs::metadata(&args.input).map(|m| m.len()).unwrap_or(0);
    let output = args.output_path();
    let in_ext = extension(&args.input);
    let out_ext = match args.to {
        Some(format) => format.extension().to_owned(),
        None => extension(output),
    };
    if args.max_scans.is_some() && out_ext != "cloilog" {
        bail!("--max-scans applies to .cloilog output only");
    }
    let report = match (in_ext.as_str(), out_ext.as_str()) {
        ("clf" | "log", "cloilog") => {
            let r = carmen_to_cloilog(
                &args.input,
                output,
                args.strict,
                args.range_max,
                args.max_scans,
            )?;
            json!({
                "input": args.input,
                "output": output,
                "format": "cloilog",
                "scans": r.scans,
                "odometry": r.odometry,
                "other_lasers_skipped": r.other_lasers,
                "bytes": r.bytes,
                "cut_at_max_scans": r.cut,
                "lines": r.input.lines,
                "damaged_lines": r.input.damaged,
                "truncated": r.input.truncated,
            })
        }
        ("clf" | "log", "mcap") => {
            let r = carmen_to_bag(&args.input, output, args.strict, args.range_max)?;
            if r.scans == 0 && r.odoms == 0 {
                // An empty bag would only move the failure to whoever reads it next.
                let _ = std::fs::remove_file(output);
                bail!(
                    "{}: no laser or odometry line in {} lines ({} damaged, {} of unknown \
                     types): not a CARMEN log?",
                    args.input.display(),
                    r.input.lines,
                    r.input.damaged,
                    r.input.unknown.values().sum::<u64>()
                );
            }
            json!({
                "input": args.input,
                "output": output,
                "scans": r.scans,
                "odometry": r.odoms,
                "tf": r.tfs,
                "lines": r.input.lines,
                "skipped_lines": r.input.skipped,
                "unknown_lines": r.input.unknown,
                "damaged_lines": r.input.damaged,
                "stamps_stepping_back": r.input.stamps_stepping_back,
                "truncated": r.input.truncated,
            })
        }
        ("mcap", "tum") => bag_odometry_to_tum(args)?,
        ("clf" | "log", "tum") => carmen_odometry_to_tum(args)?,
        _ => bail!(
            "cannot convert .{in_ext} to .{out_ext}: use .clf/.log -> .mcap, .tum or .cloilog, .mcap -> .tum"
        ),
    };
    let secs = started.elapsed().as_secs_f64();
    let mut report = report;
    report["seconds"] = json!(secs);
    report["input_mb_per_s"] = json!(input_bytes as f64 / 1e6 / secs.max(1e-9));
    writeln!(out, "{}", serde_json::to_string_pretty(&report)?)?;
    Ok(())
}

/// Summary of a planar odometry track.
fn odometry_summary(poses: &[StampedPose]) -> serde_json::Value {
    let length = poses
        .windows(2)
        .map(|w| (w[1].p - w[0].p).norm())
        .fold(0.0, |a, b| a + b);
    let first = poses.first();
    let last = poses.last();
    let pose_json = |p: Option<&StampedPose>| {
        p.map(|p| {
            json!({"t": p.t, "x": p.p.x, "y": p.p.y, "z": p.p.z,
                   "yaw": p.q.euler_angles().2})
        })
    };
    json!({
        "poses": poses.len(),
        "duration_s": match (first, last) { (Some(a), Some(b)) => b.t - a.t, _ => 0.0 },
        "path_length_m": length,
        "first": pose_json(first),
        "last": pose_json(last),
    })
}

fn bag_odometry_to_tum(args: &ConvertArgs) -> Result<serde_json::Value> {
    let options = BagReadOptions {
        strict: args.strict,
        topics: TopicSelection {
            scan: args.scan_topic.clone(),
            odom: args.odom_topic.clone(),
            imu: args.imu_topic.clone(),
            image: args.image_topic.clone(),
        },
        ..Default::default()
    };
    let mut reader = BagReader::open(&args.input, options)?;
    let mut poses = Vec::new();
    let mut odom_topics = std::collections::BTreeSet::new();
    // One odometry topic: the named one, else the first to deliver outside a global frame
    // (as `cloi map` chooses: an Odometry in `map`/`world` is a ground truth or a localizer).
    let mut chosen: Option<String> = args.odom_topic.clone();
    let (mut scans, mut tf, mut other) = (0u64, 0u64, 0u64);
    for msg in reader.by_ref() {
        let msg = msg?;
        match &msg.msg {
            SensorMsg::Odom(o) => {
                odom_topics.insert(msg.topic.to_string());
                let global = matches!(o.header.frame_id.trim_start_matches('/'), "map" | "world");
                match &chosen {
                    Some(t) if **t == *msg.topic => {}
                    Some(_) => {
                        other += 1;
                        continue;
                    }
                    None if global => {
                        other += 1;
                        continue;
                    }
                    None => chosen = Some(msg.topic.to_string()),
                }
                let p = o.pose.pose;
                poses.push(StampedPose {
                    t: o.header.stamp.as_secs_f64(),
                    p: nalgebra::Vector3::new(p.position.x, p.position.y, p.position.z),
                    q: nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                        p.orientation.w,
                        p.orientation.x,
                        p.orientation.y,
                        p.orientation.z,
                    )),
                });
            }
            SensorMsg::Scan(_) => scans += 1,
            SensorMsg::Tf { .. } => tf += 1,
            _ => other += 1,
        }
    }
    let stats = reader.stats().clone();
    if odom_topics.len() > 1 {
        log::warn!(
            "odometry on several topics {odom_topics:?}: wrote {} (pick another with \
             --odom-topic)",
            chosen.as_deref().unwrap_or("none")
        );
    }
    write_tum(args.output_path(), &poses)?;
    let topics: serde_json::Map<String, serde_json::Value> = stats
        .topics
        .iter()
        .map(|(k, v)| {
            (
                k.clone(),
                json!({"type": v.type_name, "delivered": v.delivered, "skipped": v.skipped}),
            )
        })
        .collect();
    Ok(json!({
        "input": args.input,
        "output": args.output_path(),
        "topics": topics,
        "odometry_topics": odom_topics,
        "odometry_topic": chosen,
        "odometry": odometry_summary(&poses),
        "scans": scans,
        "tf": tf,
        "other_sensor_messages": other,
        "undecodable": stats.undecodable,
        "foreign_encoding": stats.foreign_encoding,
        "unknown_channel": stats.unknown_channel,
        "out_of_order": stats.out_of_order,
        "truncated": stats.truncated,
    }))
}

fn carmen_odometry_to_tum(args: &ConvertArgs) -> Result<serde_json::Value> {
    let mut reader = crate::carmen::CarmenReader::open(&args.input, args.strict)?;
    let mut conv = crate::convert::CarmenToRos::new(args.range_max);
    let mut poses = Vec::new();
    for record in reader.by_ref() {
        for m in conv.convert(&record?) {
            if let crate::convert::RosOut::Odom(o) = m.msg {
                let (x, y, th) = o.pose.pose.to_planar();
                poses.push(StampedPose::planar(o.header.stamp.as_secs_f64(), x, y, th));
            }
        }
    }
    write_tum(args.output_path(), &poses)?;
    Ok(json!({
        "input": args.input,
        "output": args.output_path(),
        "odometry": odometry_summary(&poses),
        "truncated": reader.stats().truncated,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn extensions_ignore_compression() {
        assert_eq!(extension(Path::new("a/intel.clf.gz")), "clf");
        assert_eq!(extension(Path::new("x.LOG.bz2")), "log");
        assert_eq!(extension(Path::new("b.mcap")), "mcap");
        assert_eq!(extension(Path::new("noext")), "");
    }
}
