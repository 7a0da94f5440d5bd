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
//! Storage: the caller lends a [`CellScratch`] of a few words per node; nothing else is used.

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
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord)]
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

/// Per-cell sums over the nodes of one cell, for the geometric term in O(1) per cell:
/// `sum_j |p_j - p|^2 = s2 - 2 p . (sx, sy) + k |p|^2`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CellMoments {
    /// The cell.
    pub key: CellKey,
    /// Nodes in it.
    pub count: u32,
    /// Sum of x.
    pub sx: f64,
    /// Sum of y.
    pub sy: f64,
    /// Sum of x^2 + y^2.
    pub s2: f64,
    /// Index in the sorted order where the cell starts.
    pub start: u32,
}

impl CellMoments {
    /// An empty cell at the origin (storage initialiser).
    pub const EMPTY: CellMoments = CellMoments {
        key: CellKey { ix: 0, iy: 0 },
        count: 0,
        sx: 0.0,
        sy: 0.0,
        s2: 0.0,
        start: 0,
    };

    fn squared_distances_to(&self, x: f64, y: f64) -> f64 {
        let k = f64::from(self.count);
        (self.s2 - 2.0 * (x * self.sx + y * self.sy) + k * (x * x + y * y)).max(0.0)
    }
}

/// Borrowed scratch of [`select`]: every slice at least as long as the candidates.
#[derive(Debug)]
pub struct CellScratch<'a> {
    /// Node indices sorted by cell.
    pub order: &'a mut [u32],
    /// The cell of each node.
    pub keys: &'a mut [CellKey],
    /// Geometric term of each node.
    pub geometric: &'a mut [f64],
    /// Moments of each occupied cell, sorted by key.
    pub cells: &'a mut [CellMoments],
}

/// Decides which candidates survive: `keep[i]` is set for the winner of every cell and for
/// every protected node; everything else is to be eliminated.
///
/// Cost: one sort of the nodes by cell, then O(1) per node and neighbour cell (plus a binary
/// search to find each neighbour cell).
///
/// # Errors
/// See [`CellError`].
pub fn select(
    candidates: &[CellCandidate],
    params: &CellParams,
    s: &mut CellScratch<'_>,
    keep: &mut [bool],
) -> Result<CellStats, CellError> {
    let n = candidates.len();
    if s.order.len() < n
        || s.keys.len() < n
        || s.geometric.len() < n
        || s.cells.len() < n
        || keep.len() < n
    {
        return Err(CellError::ScratchTooSmall);
    }
    if !(params.cell_size > 0.0 && params.cell_size.is_finite() && (0.0..=1.0).contains(&params.s))
    {
        return Err(CellError::BadParams);
    }
    let size = params.cell_size;
    for (c, k) in candidates.iter().zip(s.keys.iter_mut()) {
        *k = CellKey::of(c.x, c.y, size);
    }
    let keys = &*s.keys;
    let order = &mut s.order[..n];
    for (i, o) in order.iter_mut().enumerate() {
        *o = i as u32;
    }
    crate::sort::sort_by_key(order, |&i| (keys.get(i as usize).copied(), i));

    // Moments of every occupied cell, in key order.
    let mut ncells = 0usize;
    for (pos, &i) in order.iter().enumerate() {
        let (Some(c), Some(&k)) = (candidates.get(i as usize), keys.get(i as usize)) else {
            continue;
        };
        let new_cell = ncells == 0 || s.cells.get(ncells - 1).is_none_or(|m| m.key != k);
        if new_cell {
            if let Some(m) = s.cells.get_mut(ncells) {
                *m = CellMoments {
                    key: k,
                    start: pos as u32,
                    ..CellMoments::EMPTY
                };
            }
            ncells += 1;
        }
        if let Some(m) = s.cells.get_mut(ncells - 1) {
            m.count += 1;
            m.sx += c.x;
            m.sy += c.y;
            m.s2 += c.x * c.x + c.y * c.y;
        }
    }
    let cells = &s.cells[..ncells];

    // Geometric terms and the normalisers.
    let mut i_max: f64 = 0.0;
    let mut g_max: f64 = 0.0;
    // Cell by cell: the (up to eight) adjacent cells are looked up once per cell, not once per
    // node; each node still sums them in the same order.
    for m in cells {
        let k = m.key;
        let mut adjacent = [usize::MAX; 8];
        let mut slot = 0;
        for dx in -1..=1 {
            for dy in -1..=1 {
                if dx == 0 && dy == 0 {
                    continue;
                }
                let nk = CellKey {
                    ix: k.ix.saturating_add(dx),
                    iy: k.iy.saturating_add(dy),
                };
                if let (Ok(p), Some(a)) = (
                    cells.binary_search_by_key(&nk, |m| m.key),
                    adjacent.get_mut(slot),
                ) {
                    *a = p;
                }
                slot += 1;
            }
        }
        let (start, end) = (m.start as usize, m.start as usize + m.count as usize);
        for &i in order.get(start..end).unwrap_or(&[]) {
            let Some(c) = candidates.get(i as usize) else {
                continue;
            };
            let mut g = 0.0;
            for &p in &adjacent {
                if let Some(a) = cells.get(p) {
                    g += a.squared_distances_to(c.x, c.y);
                }
            }
            if let Some(slot) = s.geometric.get_mut(i as usize) {
                *slot = g;
            }
            g_max = g_max.max(g);
            if c.information.is_finite() {
                i_max = i_max.max(c.information);
            }
        }
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
    for m in cells {
        let (start, end) = (m.start as usize, m.start as usize + m.count as usize);
        let mut best: Option<(f64, u32)> = None;
        let mut kept_here = 0;
        for &i in order.get(start..end).unwrap_or(&[]) {
            let Some(c) = candidates.get(i as usize) else {
                continue;
            };
            if c.protected {
                if let Some(k) = keep.get_mut(i as usize) {
                    *k = true;
                }
                kept_here += 1;
                continue;
            }
            let g = s.geometric.get(i as usize).copied().unwrap_or(0.0);
            let w = params.s * norm(c.information, i_max) + (1.0 - params.s) * norm(g, g_max);
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
    }
    Ok(stats)
}

/// Owned storage for a [`CellScratch`] of `N` nodes.
#[derive(Debug)]
pub struct CellStorage<const N: usize> {
    order: [u32; N],
    keys: [CellKey; N],
    geometric: [f64; N],
    cells: [CellMoments; N],
}

impl<const N: usize> CellStorage<N> {
    /// Zeroed storage, usable as a `static` initialiser.
    pub const fn new() -> Self {
        CellStorage {
            order: [0; N],
            keys: [CellKey { ix: 0, iy: 0 }; N],
            geometric: [0.0; N],
            cells: [CellMoments::EMPTY; N],
        }
    }

    /// The scratch view.
    pub fn scratch(&mut self) -> CellScratch<'_> {
        CellScratch {
            order: &mut self.order,
            keys: &mut self.keys,
            geometric: &mut self.geometric,
            cells: &mut self.cells,
        }
    }
}

impl<const N: usize> Default for CellStorage<N> {
    fn default() -> Self {
        Self::new()
    }
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

    fn run<const N: usize>(
        nodes: &[CellCandidate; N],
        params: &CellParams,
    ) -> ([bool; N], CellStats) {
        let mut st = CellStorage::<N>::new();
        let mut keep = [false; N];
        let stats = select(nodes, params, &mut st.scratch(), &mut keep).unwrap();
        (keep, stats)
    }

    #[test]
    fn one_survivor_per_cell_with_the_most_information() {
        let nodes = [
            c(0.1, 0.1, 1.0),
            c(0.5, 0.5, 9.0),
            c(0.9, 0.2, 3.0),
            c(5.5, 5.5, 1.0),
        ];
        let (keep, stats) = run(
            &nodes,
            &CellParams {
                cell_size: 1.0,
                s: 1.0,
            },
        );
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
        let (keep, _) = run(
            &nodes,
            &CellParams {
                cell_size: 1.0,
                s: 0.0,
            },
        );
        assert_eq!(keep, [true, false, true]);
    }

    #[test]
    fn protected_nodes_always_survive_and_represent_their_cell() {
        let mut nodes = [c(0.1, 0.1, 1.0), c(0.2, 0.2, 100.0)];
        nodes[0].protected = true;
        let (keep, _) = run(&nodes, &CellParams::default());
        assert_eq!(keep, [true, false]);
    }

    #[test]
    fn moments_give_the_brute_force_geometric_term() {
        let nodes = [
            c(0.1, 0.2, 1.0),
            c(1.3, 0.4, 1.0),
            c(1.7, 0.9, 1.0),
            c(-0.4, 1.2, 1.0),
            c(0.5, 0.5, 1.0),
        ];
        let mut st = CellStorage::<5>::new();
        let mut keep = [false; 5];
        select(&nodes, &CellParams::default(), &mut st.scratch(), &mut keep).unwrap();
        for (i, a) in nodes.iter().enumerate() {
            let ka = CellKey::of(a.x, a.y, 1.0);
            let mut g = 0.0;
            for b in &nodes {
                let kb = CellKey::of(b.x, b.y, 1.0);
                if kb != ka && (kb.ix - ka.ix).abs() <= 1 && (kb.iy - ka.iy).abs() <= 1 {
                    g += (a.x - b.x).powi(2) + (a.y - b.y).powi(2);
                }
            }
            assert!(
                (st.geometric[i] - g).abs() < 1e-12,
                "node {i}: {} vs {g}",
                st.geometric[i]
            );
        }
    }

    #[test]
    fn bad_input_is_rejected_not_a_panic() {
        let nodes = [c(f64::NAN, 0.0, f64::NAN), c(1e300, -1e300, 1.0)];
        let mut st = CellStorage::<2>::new();
        let mut keep = [false; 2];
        assert!(select(&nodes, &CellParams::default(), &mut st.scratch(), &mut keep).is_ok());
        let mut small = CellStorage::<1>::new();
        assert_eq!(
            select(
                &nodes,
                &CellParams::default(),
                &mut small.scratch(),
                &mut keep
            ),
            Err(CellError::ScratchTooSmall)
        );
        let bad = CellParams {
            cell_size: 0.0,
            s: 0.5,
        };
        assert_eq!(
            select(&nodes, &bad, &mut st.scratch(), &mut keep),
            Err(CellError::BadParams)
        );
    }
}
