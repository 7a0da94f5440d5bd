//! g2o text format, 2D subset: `VERTEX_SE2 id x y theta`,
//! `EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33` (information, upper triangle, row
//! major), `FIX id`.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::{bail, Result};
use cloi_core::geom::{Info3, Se2};

use super::{check_information, number, vertex_id, GraphFile, RawGraph, Where};

/// Parses g2o text; `path` is only used in messages.
///
/// # Errors
/// A malformed line, named by file and line number.
pub fn read_g2o(text: &str, path: &Path) -> Result<GraphFile> {
    let mut raw = RawGraph::default();
    for (i, line) in text.lines().enumerate() {
        let at = Where { path, line: i + 1 };
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut tok = line.split_whitespace();
        let tag = tok.next().unwrap_or_default();
        match tag {
            "VERTEX_SE2" => {
                let id = vertex_id(tok.next(), "vertex id", &at)?;
                let x = number(tok.next(), "x", &at)?;
                let y = number(tok.next(), "y", &at)?;
                let t = number(tok.next(), "theta", &at)?;
                end(&mut tok, &at)?;
                raw.add_vertex(id, Se2::new(x, y, t), &at)?;
            }
            "EDGE_SE2" => {
                let a = vertex_id(tok.next(), "first vertex id", &at)?;
                let b = vertex_id(tok.next(), "second vertex id", &at)?;
                let x = number(tok.next(), "dx", &at)?;
                let y = number(tok.next(), "dy", &at)?;
                let t = number(tok.next(), "dtheta", &at)?;
                let mut v = [0.0; 6];
                for (k, slot) in v.iter_mut().enumerate() {
                    *slot = number(tok.next(), INFO_NAMES[k], &at)?;
                }
                end(&mut tok, &at)?;
                let [i11, i12, i13, i22, i23, i33] = v;
                let info = Info3::new(i11, i12, i13, i12, i22, i23, i13, i23, i33);
                check_information(&info, &at)?;
                raw.edges.push((a, b, Se2::new(x, y, t), info, at.line));
            }
            "FIX" => {
                let mut any = false;
                for t in tok {
                    let id = vertex_id(Some(t), "vertex id", &at)?;
                    raw.fixed.push((id, at.line));
                    any = true;
                }
                if !any {
                    bail!("{at}: FIX without a vertex id");
                }
            }
            other => bail!(
                "{at}: unsupported g2o record {other:?} (expected VERTEX_SE2, EDGE_SE2 or FIX)"
            ),
        }
    }
    raw.finish(path)
}

const INFO_NAMES: [&str; 6] = ["I11", "I12", "I13", "I22", "I23", "I33"];

fn end<'a>(tok: &mut impl Iterator<Item = &'a str>, at: &Where<'_>) -> Result<()> {
    if let Some(extra) = tok.next() {
        bail!("{at}: unexpected extra value {extra:?}");
    }
    Ok(())
}

/// Writes g2o text: every node at `poses` (original ids), `FIX` lines, and every edge.
/// Numbers are printed in Rust's shortest round-trip form, so reading back is exact.
pub fn write_g2o(graph: &GraphFile, poses: &[Se2]) -> String {
    let mut s = String::with_capacity(128 * (poses.len() + graph.edges.len()));
    for (id, p) in graph.ids.iter().zip(poses) {
        let _ = writeln!(s, "VERTEX_SE2 {id} {} {} {}", p.x, p.y, p.theta);
    }
    for (id, &f) in graph.ids.iter().zip(&graph.fixed) {
        if f {
            let _ = writeln!(s, "FIX {id}");
        }
    }
    for e in &graph.edges {
        let m = &e.information;
        let z = &e.measurement;
        let _ = writeln!(
            s,
            "EDGE_SE2 {} {} {} {} {} {} {} {} {} {} {}",
            graph.ids[e.from],
            graph.ids[e.to],
            z.x,
            z.y,
            z.theta,
            m[(0, 0)],
            m[(0, 1)],
            m[(0, 2)],
            m[(1, 1)],
            m[(1, 2)],
            m[(2, 2)]
        );
    }
    s
}
