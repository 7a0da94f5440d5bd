//! Ground-truth poses: a g2o file (its `VERTEX_SE2` lines) or a plain text file of `x y theta`
//! rows, one per node in node order.

use std::path::Path;

use anyhow::{bail, Context, Result};
use cloi_core::geom::Se2;

use super::{number, read_g2o, Where};

/// Reads ground-truth poses, in node order.
///
/// # Errors
/// The file cannot be read or a line is malformed (named by file and line).
pub fn read_ground_truth(path: &Path) -> Result<Vec<Se2>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let first = text
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))
        .unwrap_or_default();
    if first.starts_with("VERTEX_SE2") || first.starts_with("EDGE_SE2") {
        let g = read_g2o(&text, path)?;
        if !g.has_vertices {
            bail!("{}: ground truth has no VERTEX_SE2 lines", path.display());
        }
        return Ok(g.poses);
    }
    let mut poses = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let at = Where { path, line: i + 1 };
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut tok = line.split_whitespace();
        let x = number(tok.next(), "x", &at)?;
        let y = number(tok.next(), "y", &at)?;
        let t = number(tok.next(), "theta", &at)?;
        if let Some(extra) = tok.next() {
            bail!("{at}: expected `x y theta`, found extra value {extra:?}");
        }
        poses.push(Se2::new(x, y, t));
    }
    Ok(poses)
}

/// Position RMSE (metres) of `estimate` against `truth` after aligning the first poses: the
/// estimate is moved rigidly so that its first pose coincides with the truth's first pose.
pub fn aligned_rmse(estimate: &[Se2], truth: &[Se2]) -> Option<f64> {
    let (e0, t0) = (estimate.first()?, truth.first()?);
    let n = estimate.len().min(truth.len());
    let align = t0.compose(&e0.inverse());
    let mut sum = 0.0;
    for (e, t) in estimate.iter().zip(truth).take(n) {
        let p = align.compose(e);
        sum += (p.x - t.x).powi(2) + (p.y - t.y).powi(2);
    }
    Some((sum / n as f64).sqrt())
}
