//! `cloi show-map`: what a saved map (`.cloimap`) holds, and its pictures, read back from the
//! file alone.

use std::io::Write;
use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use cloi_core::graph::EdgeKind;
use serde_json::json;

use super::output::{compose_global_grid, SubmapView};
use crate::io::map_file::load_map;
use crate::io::map_out::{write_map_png, write_map_server};

/// Arguments of `cloi show-map`.
#[derive(Debug, Args)]
pub struct ShowMapArgs {
    /// A map saved by `cloi map --save`.
    pub map: PathBuf,
    /// Also write `map.pgm`, `map.yaml` and `map.png` (the frame nodes drawn as the path) of
    /// the saved map into this folder.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// Checks the map file whole (every section's CRC and value) and prints its contents as JSON.
///
/// # Errors
/// The file is unreadable, not a map, of another version, truncated or corrupt; or the
/// pictures cannot be written.
pub fn run(args: &ShowMapArgs, out: &mut dyn Write) -> Result<()> {
    let map = load_map(&args.map)?;
    let s = map.summary;
    let loops = map
        .edges
        .iter()
        .filter(|e| e.kind == EdgeKind::Loop)
        .count();
    let report = json!({
        "file": args.map.display().to_string(),
        "bytes": std::fs::metadata(&args.map)?.len(),
        "grid": {"side": s.grid.side, "resolution_m": decimal(s.grid.resolution)},
        "nodes": s.nodes,
        "edges": s.edges,
        "loop_edges": loops,
        "submaps": s.submaps,
        "submap_slots": s.submap_slots,
        "next_serial": s.next_serial,
        "first_stamp_ns": map.meta.first().map(|m| m.stamp),
        "last_stamp_ns": map.meta.last().map(|m| m.stamp),
    });
    writeln!(out, "{}", serde_json::to_string_pretty(&report)?)?;
    if let Some(dir) = &args.out {
        let views: Vec<SubmapView<'_>> = map
            .submaps()
            .map(|(origin, cells)| SubmapView {
                origin,
                side: s.grid.side as usize,
                resolution: s.grid.resolution,
                cells,
            })
            .collect();
        let grid = compose_global_grid(&views)?;
        std::fs::create_dir_all(dir)?;
        write_map_server(dir, "map", &grid.as_grid_ref())?;
        let path: Vec<(f64, f64)> = map.nodes.iter().map(|n| (n.pose.x, n.pose.y)).collect();
        write_map_png(&dir.join("map.png"), &grid.as_grid_ref(), &path)?;
    }
    Ok(())
}

/// `v` as the shortest decimal that reads back as the same `f32` (0.05, not 0.0500000007).
fn decimal(v: f32) -> f64 {
    v.to_string().parse().unwrap_or(f64::from(v))
}
