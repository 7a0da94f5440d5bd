//! Grid-cell node selection, the paper's eqs. (3) and (4).
//!
//! Node positions are binned into square cells. In every cell one node survives: the one with
//! the largest weight
//!
//! `w = s * I / I_max + (1 - s) * G / G_max`,
//!
//! where `I` is the node's information term and `G` its geometric term, the sum of squared
//! distances to the nodes of the eight adjacent cells (a node far from its neighbours spreads
//! the kept nodes evenly). The paper adds the raw terms; their units differ (information per
//! m^2 against m^2) and their scales differ by orders of magnitude between datasets, so we
//! divide each by its largest value over the graph. With that normalisation `s` means what the
//! paper says it means: the share of the information term, `s = 0.5` by default.
//!
//! The information term is either eq. (4), the sum over the node's edges of each edge's
//! information (eq. 1 heuristic of its covariance: the Frobenius norm of its information
//! matrix), which needs only the edges, or eq. (3), the trace of the node's marginal
//! information, which needs the marginal covariance of the whole graph and is much slower. The
//! caller computes `I` and passes it in.
//!
//! Storage: the caller lends an index scratch of one `u32` per node; nothing else is used.

/// One candidate node.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CellCandidate {
    /// Position x, metres.
    pub x: f64,
    /// Position y, metres.
    pub y: f64,
    /// Information term (eq. 3 or eq. 4), non-negative.
    pub information: f64,
    /// A protected node always survives (the gauge node, nodes of the current window).
    pub protected: bool,
}

/// Key of a grid cell.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct CellKey {
    /// Column.
    pub ix: i32,
    /// Row.
    pub iy: i32,
}

impl CellKey {
    /// The cell of `(x, y)` for cells of `size` metres, aligned on the origin. Coordinates
    /// beyond the `i32` range saturate.
    pub fn of(x: f64, y: f64, size: f64) -> CellKey {
        let f = |v: f64| {
            let c = libm::floor(v / size);
            if c.is_nan() {
                0
            } else {
                c.clamp(i32::MIN as f64, i32::MAX as f64) as i32
            }
        };
        CellKey { ix: f(x), iy: f(y) }
    }
}

/// Parameters of the selection.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CellParams {
    /// Cell side, metres (> 0).
    pub cell_size: f64,
    /// Share of the information term in the weight, `0..=1`.
    pub s: f64,
}

impl Default for CellParams {
    fn default() -> Self {
        CellParams {
            cell_size: 1.0,
            s: 0.5,
        }
    }
}

/// Statistics of a selection.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CellStats {
    /// Occupied cells.
    pub cells: usize,
    /// Nodes kept.
    pub kept: usize,
    /// Most nodes kept in one cell (protected nodes can share a cell with the winner).
    pub max_kept_per_cell: usize,
}

/// Why a selection could not run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum CellError {
    /// `keep` or `scratch` is shorter than the candidates.
    ScratchTooSmall,
    /// `cell_size` is not a positive finite number or `s` is outside `0..=1`.
    BadParams,
}

impl core::fmt::Display for CellError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            CellError::ScratchTooSmall => "scratch or output slice shorter than the candidates",
            CellError::BadParams => "cell size must be positive and s within 0..=1",
        })
    }
}

impl core::error::Error for CellError {}

fn key(c: &CellCandidate, size: f64) -> CellKey {
    CellKey::of(c.x, c.y, size)
}

/// Decides which candidates survive: `keep[i]` is set for the winner of every cell and for
/// every protected node; everything else is to be eliminated.
///
/// # Errors
/// See [`CellError`].
pub fn select(
    candidates: &[CellCandidate],
    params: &CellParams,
    scratch: &mut [u32],
    keep: &mut [bool],
) -> Result<CellStats, CellError> {
    let n = candidates.len();
    if scratch.len() < n || keep.len() < n {
        return Err(CellError::ScratchTooSmall);
    }
    if !(params.cell_size > 0.0 && params.cell_size.is_finite() && (0.0..=1.0).contains(&params.s))
    {
        return Err(CellError::BadParams);
    }
    let size = params.cell_size;
    let order = &mut scratch[..n];
    for (i, o) in order.iter_mut().enumerate() {
        *o = i as u32;
    }
    // Sort node indices by cell (then index, for determinism).
    order.sort_unstable_by_key(|&i| (candidates.get(i as usize).map(|c| key(c, size)), i));
    let cand = |i: u32| candidates.get(i as usize);
    let cell_of = |i: u32| cand(i).map(|c| key(c, size));

    // The range of `order` that holds cell `k`.
    let range_of = |order: &[u32], k: CellKey| {
        let lo = order.partition_point(|&i| cell_of(i).is_some_and(|c| c < k));
        let hi = order.partition_point(|&i| cell_of(i).is_some_and(|c| c <= k));
        lo..hi
    };
    let geometric = |order: &[u32], i: u32| -> f64 {
        let Some(c) = cand(i) else { return 0.0 };
        let k = key(c, size);
        let mut g = 0.0;
        for dx in -1..=1 {
            for dy in -1..=1 {
                if dx == 0 && dy == 0 {
                    continue;
                }
                let nk = CellKey {
                    ix: k.ix.saturating_add(dx),
                    iy: k.iy.saturating_add(dy),
                };
                for &j in order.get(range_of(order, nk)).unwrap_or(&[]) {
                    if let Some(o) = cand(j) {
                        g += (o.x - c.x) * (o.x - c.x) + (o.y - c.y) * (o.y - c.y);
                    }
                }
            }
        }
        g
    };

    // Normalisers: the largest information and geometric terms.
    let mut i_max: f64 = 0.0;
    let mut g_max: f64 = 0.0;
    for &i in order.iter() {
        if let Some(c) = cand(i) {
            if c.information.is_finite() {
                i_max = i_max.max(c.information);
            }
        }
        g_max = g_max.max(geometric(order, i));
    }
    let norm = |v: f64, max: f64| {
        if max > 0.0 && v.is_finite() {
            v / max
        } else {
            0.0
        }
    };

    for k in keep.iter_mut().take(n) {
        *k = false;
    }
    let mut stats = CellStats::default();
    let mut start = 0;
    while start < n {
        let k0 = order.get(start).and_then(|&i| cell_of(i));
        let mut end = start;
        while end < n && order.get(end).and_then(|&i| cell_of(i)) == k0 {
            end += 1;
        }
        let mut best: Option<(f64, u32)> = None;
        let mut kept_here = 0;
        for &i in order.get(start..end).unwrap_or(&[]) {
            let Some(c) = cand(i) else { continue };
            if c.protected {
                if let Some(k) = keep.get_mut(i as usize) {
                    *k = true;
                }
                kept_here += 1;
                continue;
            }
            let w = params.s * norm(c.information, i_max)
                + (1.0 - params.s) * norm(geometric(order, i), g_max);
            if best.is_none_or(|(bw, _)| w > bw) {
                best = Some((w, i));
            }
        }
        // A cell with a protected node keeps it as its representative.
        if kept_here == 0 {
            if let Some((_, i)) = best {
                if let Some(k) = keep.get_mut(i as usize) {
                    *k = true;
                }
                kept_here = 1;
            }
        }
        stats.cells += 1;
        stats.kept += kept_here;
        stats.max_kept_per_cell = stats.max_kept_per_cell.max(kept_here);
        start = end;
    }
    Ok(stats)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn c(x: f64, y: f64, information: f64) -> CellCandidate {
        CellCandidate {
            x,
            y,
            information,
            protected: false,
        }
    }

    #[test]
    fn one_survivor_per_cell_with_the_most_information() {
        let nodes = [
            c(0.1, 0.1, 1.0),
            c(0.5, 0.5, 9.0),
            c(0.9, 0.2, 3.0),
            c(5.5, 5.5, 1.0),
        ];
        let mut scratch = [0u32; 4];
        let mut keep = [false; 4];
        let params = CellParams {
            cell_size: 1.0,
            s: 1.0,
        };
        let stats = select(&nodes, &params, &mut scratch, &mut keep).unwrap();
        assert_eq!(keep, [false, true, false, true]);
        assert_eq!(
            stats,
            CellStats {
                cells: 2,
                kept: 2,
                max_kept_per_cell: 1
            }
        );
    }

    #[test]
    fn geometric_term_prefers_the_node_far_from_its_neighbours() {
        // Cell (0,0) holds two nodes of equal information; the neighbour cell (1,0) holds one
        // node at x = 1.1. With s = 0 the node farther from it (x = 0.1) wins.
        let nodes = [c(0.1, 0.5, 1.0), c(0.9, 0.5, 1.0), c(1.1, 0.5, 1.0)];
        let mut scratch = [0u32; 3];
        let mut keep = [false; 3];
        select(
            &nodes,
            &CellParams {
                cell_size: 1.0,
                s: 0.0,
            },
            &mut scratch,
            &mut keep,
        )
        .unwrap();
        assert_eq!(keep, [true, false, true]);
    }

    #[test]
    fn protected_nodes_always_survive_and_represent_their_cell() {
        let mut nodes = [c(0.1, 0.1, 1.0), c(0.2, 0.2, 100.0)];
        nodes[0].protected = true;
        let mut scratch = [0u32; 2];
        let mut keep = [false; 2];
        select(&nodes, &CellParams::default(), &mut scratch, &mut keep).unwrap();
        assert_eq!(keep, [true, false]);
    }

    #[test]
    fn bad_input_is_rejected_not_a_panic() {
        let nodes = [c(f64::NAN, 0.0, f64::NAN), c(1e300, -1e300, 1.0)];
        let mut scratch = [0u32; 2];
        let mut keep = [false; 2];
        assert!(select(&nodes, &CellParams::default(), &mut scratch, &mut keep).is_ok());
        assert_eq!(
            select(&nodes, &CellParams::default(), &mut scratch[..1], &mut keep),
            Err(CellError::ScratchTooSmall)
        );
        let bad = CellParams {
            cell_size: 0.0,
            s: 0.5,
        };
        assert_eq!(
            select(&nodes, &bad, &mut scratch, &mut keep),
            Err(CellError::BadParams)
        );
    }
}
