//! TORO text format: `VERTEX2 id x y theta`,
//! `EDGE2 i j dx dy dtheta I11 I12 I22 I33 I13 I23` (note the information order).

use std::fmt::Write as _;
use std::path::Path;

use anyhow::{bail, Result};
use cloi_core::geom::{Info3, Se2};

use super::{check_information, number, vertex_id, GraphFile, RawGraph, Where};

const INFO_NAMES: [&str; 6] = ["I11", "I12", "I22", "I33", "I13", "I23"];

/// Parses TORO text; `path` is only used in messages.
///
/// # Errors
/// A malformed line, named by file and line number.
pub fn read_toro(text: &str, path: &Path) -> Result<GraphFile> {
    let mut raw = RawGraph::default();
    for (i, line) in text.lines().enumerate() {
        let at = Where { path, line: i + 1 };
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut tok = line.split_whitespace();
        match tok.next().unwrap_or_default() {
            "VERTEX2" | "VERTEX" => {
                let id = vertex_id(tok.next(), "vertex id", &at)?;
                let x = number(tok.next(), "x", &at)?;
                let y = number(tok.next(), "y", &at)?;
                let t = number(tok.next(), "theta", &at)?;
                if let Some(extra) = tok.next() {
                    bail!("{at}: unexpected extra value {extra:?}");
                }
                raw.add_vertex(id, Se2::new(x, y, t), &at)?;
            }
            "EDGE2" | "EDGE" => {
                let a = vertex_id(tok.next(), "first vertex id", &at)?;
                let b = vertex_id(tok.next(), "second vertex id", &at)?;
                let x = number(tok.next(), "dx", &at)?;
                let y = number(tok.next(), "dy", &at)?;
                let t = number(tok.next(), "dtheta", &at)?;
                let mut v = [0.0; 6];
                for (k, slot) in v.iter_mut().enumerate() {
                    *slot = number(tok.next(), INFO_NAMES[k], &at)?;
                }
                if let Some(extra) = tok.next() {
                    bail!("{at}: unexpected extra value {extra:?}");
                }
                let [i11, i12, i22, i33, i13, i23] = v;
                let info = Info3::new(i11, i12, i13, i12, i22, i23, i13, i23, i33);
                check_information(&info, &at)?;
                raw.edges.push((a, b, Se2::new(x, y, t), info, at.line));
            }
            other => {
                bail!("{at}: unsupported TORO record {other:?} (expected VERTEX2 or EDGE2)")
            }
        }
    }
    raw.finish(path)
}

/// Writes TORO text: every node at `poses` (original ids) and every edge.
pub fn write_toro(graph: &GraphFile, poses: &[Se2]) -> String {
    let mut s = String::with_capacity(128 * (poses.len() + graph.edges.len()));
    for (id, p) in graph.ids.iter().zip(poses) {
        let _ = writeln!(s, "VERTEX2 {id} {} {} {}", p.x, p.y, p.theta);
    }
    for e in &graph.edges {
        let m = &e.information;
        let z = &e.measurement;
        let _ = writeln!(
            s,
            "EDGE2 {} {} {} {} {} {} {} {} {} {} {}",
            graph.ids[e.from],
            graph.ids[e.to],
            z.x,
            z.y,
            z.theta,
            m[(0, 0)],
            m[(0, 1)],
            m[(1, 1)],
            m[(2, 2)],
            m[(0, 2)],
            m[(1, 2)]
        );
    }
    s
}
