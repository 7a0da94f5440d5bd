//! ARPS, the average relative pose shift of a pruned pose graph against its original (the
//! accuracy column of the paper's Table III): [`arps`] on matched positions, and
//! [`eval_arps`] on two graph files (`cloi eval arps`).

use std::collections::HashMap;
use std::path::Path;

use anyhow::{bail, Result};
use cloi_core::geom::Se2;
use cloi_io::graph_io::{read_graph, GraphFile};
use serde::Serialize;

/// The batch optimum of a whole graph file from an initial guess, one pose per node in the
/// file's order. The optimizer lives with the commands that solve graphs (`cloi-host`).
pub type BatchOptimum = dyn Fn(&GraphFile, &[Se2]) -> Result<Vec<Se2>>;

/// ARPS, the average relative pose shift: the mean over kept nodes of
/// `|t_original - t_pruned| / |t_original| * 100`, where `t_original` is the node's position
/// in the optimized full graph. A node whose original position is within 1 mm of the origin
/// (in practice the gauge node, which never moves) has no meaningful relative shift and is left
/// out; the count left out is returned with the value. `None` when no node counts.
pub fn arps(original: &[Se2], pruned: &[Se2]) -> Option<(f64, usize)> {
    let mut sum = 0.0;
    let mut used = 0usize;
    let mut at_origin = 0usize;
    for (o, p) in original.iter().zip(pruned) {
        let norm = o.x.hypot(o.y);
        if norm < 1e-3 {
            at_origin += 1;
            continue;
        }
        sum += (o.x - p.x).hypot(o.y - p.y) / norm;
        used += 1;
    }
    (used > 0).then(|| (100.0 * sum / used as f64, at_origin))
}

/// Result of [`eval_arps`].
#[derive(Debug, Clone, Serialize)]
pub struct ArpsJson {
    /// ARPS, percent.
    pub arps_percent: f64,
    /// Vertices of the pruned graph matched by id in the original.
    pub nodes_matched: usize,
    /// Matched nodes left out because they sit within 1 mm of the origin in the original.
    pub nodes_at_origin: usize,
    /// Largest position shift of a matched node, metres.
    pub max_shift_m: f64,
    /// Whether the original graph was optimized first.
    pub original_optimized: bool,
}

/// `cloi eval arps`: ARPS of a pruned graph against its original, matching vertices by id.
/// The original is optimized first (the paper's reference is the optimized full graph) unless
/// `as_is` is set.
///
/// `batch_optimum` optimizes the original; `cloi-host` passes the solver of `cloi optimize`
/// and `cloi prune`, so that both commands measure against the same optimum.
///
/// # Errors
/// A file cannot be read, a pruned vertex is missing from the original, or the solve fails.
pub fn eval_arps(
    original: &Path,
    pruned: &Path,
    as_is: bool,
    batch_optimum: &BatchOptimum,
) -> Result<ArpsJson> {
    let a = read_graph(original, None)?;
    let b = read_graph(pruned, None)?;
    let reference = if as_is {
        a.poses.clone()
    } else {
        batch_optimum(&a, &a.poses)?
    };
    let index: HashMap<i64, usize> = a.ids.iter().enumerate().map(|(i, id)| (*id, i)).collect();
    let mut orig = Vec::with_capacity(b.ids.len());
    for id in &b.ids {
        let Some(&i) = index.get(id) else {
            bail!(
                "{}: vertex {id} is not in {}",
                pruned.display(),
                original.display()
            );
        };
        orig.push(reference[i]);
    }
    let (arps_percent, nodes_at_origin) = arps(&orig, &b.poses).unwrap_or((0.0, 0));
    let max_shift_m = orig
        .iter()
        .zip(&b.poses)
        .map(|(o, p)| (o.x - p.x).hypot(o.y - p.y))
        .fold(0.0, f64::max);
    Ok(ArpsJson {
        arps_percent,
        nodes_matched: b.ids.len(),
        nodes_at_origin,
        max_shift_m,
        original_optimized: !as_is,
    })
}
