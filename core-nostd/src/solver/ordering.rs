//! Structural analysis: a fill-reducing elimination order and the block pattern of the
//! Cholesky factor, computed together.
//!
//! The order is an exact minimum-degree order on the elimination graph of the free nodes. The
//! graph lives in linked adjacency lists whose entries come from a fixed pool with a free list:
//! eliminating a node turns its remaining neighbours into a clique and returns every entry that
//! pointed at it, so the pool never holds more than twice the edges of the current elimination
//! graph, and those edges are all blocks of the factor. The neighbours of each pivot at the
//! moment it is eliminated are exactly the rows of its factor column, so the symbolic
//! factorization comes for free.

use super::workspace::SolverBuffers;
use super::SolveError;
use crate::graph::{EdgeKind, PoseEdge, PoseNode};

const NONE: u32 = u32::MAX;
/// Marks an edge without an off-diagonal block (prior, or touching a fixed node).
pub(crate) const NO_SLOT: u32 = u32::MAX;
/// Set in an edge slot when the stored block is `H_ji` rather than `H_ij`.
pub(crate) const TRANSPOSED: u32 = 1 << 31;

/// A cheap hash of everything the analysis depends on.
pub(crate) fn fingerprint(
    nodes: &[PoseNode],
    edges: &[PoseEdge],
    flags: &[u8],
    gauge_first: bool,
) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut mix = |v: u64| {
        h ^= v;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    };
    mix(gauge_first as u64);
    for n in nodes {
        mix(n.fixed as u64);
    }
    for (e, &f) in edges.iter().zip(flags) {
        mix(((e.from.0 as u64) << 32) | e.to.0 as u64);
        mix(f as u64);
    }
    h
}

/// Whether the first node is held fixed to remove the gauge freedom: yes unless a prior exists.
pub(crate) fn gauge_fixes_first(edges: &[PoseEdge]) -> bool {
    !edges.iter().any(|e| e.kind == EdgeKind::Prior)
}

/// Numbers the free nodes, orders them, and builds the factor's pattern and the edge slots.
///
/// # Errors
/// [`SolveError::Capacity`] when the graph or the factor does not fit the workspace.
pub(crate) fn analyze(
    nodes: &[PoseNode],
    edges: &[PoseEdge],
    gauge_first: bool,
    b: &mut SolverBuffers<'_>,
) -> Result<(), SolveError> {
    let mut state = analyze_begin(nodes, edges, gauge_first, b)?;
    eliminate(&mut state, b, u64::MAX)?;
    analyze_end(nodes.len(), edges, &state, b)
}

/// The state of a minimum-degree elimination between calls of [`eliminate`]: everything else
/// lives in the workspace, so an analysis may stop after any pivot and resume later with the
/// same result.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Elimination {
    /// Free variables.
    nv: usize,
    /// Next pivot.
    k: usize,
    min_deg: usize,
    /// Factor blocks so far.
    nnz: usize,
    stamp: u32,
    /// Head of the adjacency pool's free list.
    free: u32,
    /// Adjacency pool entries ever used.
    used: usize,
}

impl Elimination {
    /// True when every variable is eliminated.
    pub(crate) fn done(&self) -> bool {
        self.k >= self.nv
    }

    /// Factor blocks so far.
    pub(crate) fn blocks(&self) -> usize {
        self.nnz
    }
}

/// The first part of [`analyze`]: numbers the free nodes and builds the elimination graph
/// and its degree buckets (`O(nodes + edges)`).
///
/// # Errors
/// As [`analyze`].
pub(crate) fn analyze_begin(
    nodes: &[PoseNode],
    edges: &[PoseEdge],
    gauge_first: bool,
    b: &mut SolverBuffers<'_>,
) -> Result<Elimination, SolveError> {
    let n_nodes = nodes.len();
    if n_nodes > b.node_var.len() {
        return Err(SolveError::Capacity {
            what: "nodes",
            capacity: b.node_var.len(),
        });
    }
    if edges.len() > b.edge_slot.len() {
        return Err(SolveError::Capacity {
            what: "edges",
            capacity: b.edge_slot.len(),
        });
    }
    // Variable numbering in node order (the ordering permutes it below).
    let mut nv = 0usize;
    for (i, node) in nodes.iter().enumerate() {
        let fixed = node.fixed || (gauge_first && i == 0);
        b.node_var[i] = if fixed { NONE } else { nv as u32 };
        if !fixed {
            nv += 1;
        }
    }
    let [adj_head, degree, bnext, bprev, bhead, mark] = &mut b.scratch;
    let adj_node = &mut *b.adj_node;
    let adj_next = &mut *b.adj_next;
    let pool = adj_node.len().min(adj_next.len());
    let factor_full = SolveError::Capacity {
        what: "factor blocks",
        capacity: b.rows.len(),
    };

    for v in 0..nv {
        adj_head[v] = NONE;
        mark[v] = 0;
    }
    // Initial adjacency, with duplicates (parallel edges) removed afterwards.
    let mut used = 0usize;
    let mut free = NONE;
    for (e, &flag) in edges.iter().zip(b.edge_flags.iter()) {
        let (Some(&a), Some(&c)) = (
            b.node_var.get(e.from.0 as usize),
            b.node_var.get(e.to.0 as usize),
        ) else {
            return Err(SolveError::InvalidGraph);
        };
        if a == NONE || c == NONE || a == c || flag == 0 {
            continue;
        }
        if used + 2 > pool {
            return Err(factor_full);
        }
        for (x, y) in [(a, c), (c, a)] {
            adj_node[used] = y;
            adj_next[used] = adj_head[x as usize];
            adj_head[x as usize] = used as u32;
            used += 1;
        }
    }
    let mut stamp: u32 = 0;
    for v in 0..nv {
        stamp += 1;
        mark[v] = stamp;
        let mut prev = NONE;
        let mut e = adj_head[v];
        let mut deg = 0u32;
        while e != NONE {
            let u = adj_node[e as usize];
            let nxt = adj_next[e as usize];
            if mark[u as usize] == stamp {
                unlink(adj_head, adj_next, v, prev, nxt);
                adj_next[e as usize] = free;
                free = e;
            } else {
                mark[u as usize] = stamp;
                deg += 1;
                prev = e;
            }
            e = nxt;
        }
        degree[v] = deg;
    }
    // Degree buckets.
    for d in 0..nv {
        bhead[d] = NONE;
    }
    let mut min_deg = nv;
    for v in (0..nv).rev() {
        let d = degree[v] as usize;
        bucket_push(bhead, bnext, bprev, v as u32, d);
        min_deg = min_deg.min(d);
    }
    Ok(Elimination {
        nv,
        k: 0,
        min_deg,
        nnz: 0,
        stamp,
        free,
        used,
    })
}

/// Eliminates the next pivots of the minimum-degree order until at least `budget` adjacency
/// entries were visited (at least one pivot per call; `u64::MAX`: to the end); returns the
/// entries visited.
///
/// # Errors
/// As [`analyze`].
pub(crate) fn eliminate(
    s: &mut Elimination,
    b: &mut SolverBuffers<'_>,
    budget: u64,
) -> Result<u64, SolveError> {
    const ELIMINATED: u32 = u32::MAX;
    let [adj_head, degree, bnext, bprev, bhead, mark] = &mut b.scratch;
    let adj_node = &mut *b.adj_node;
    let adj_next = &mut *b.adj_next;
    let pool = adj_node.len().min(adj_next.len());
    let factor_full = SolveError::Capacity {
        what: "factor blocks",
        capacity: b.rows.len(),
    };
    let Elimination {
        nv,
        k: from,
        mut min_deg,
        mut nnz,
        mut stamp,
        mut free,
        mut used,
    } = *s;
    let mut visited = 0u64;
    let mut k = from;
    while k < nv {
        if visited >= budget {
            break;
        }
        while min_deg < nv && bhead[min_deg] == NONE {
            min_deg += 1;
        }
        if min_deg >= nv {
            return Err(SolveError::InvalidGraph);
        }
        let v = bhead[min_deg];
        bucket_remove(bhead, bnext, bprev, v, min_deg);
        degree[v as usize] = ELIMINATED;
        b.var_node[k] = v;
        // The live neighbours of v become the rows of factor column k; v's list is freed.
        let start = nnz;
        let mut e = adj_head[v as usize];
        while e != NONE {
            let u = adj_node[e as usize];
            let nxt = adj_next[e as usize];
            if degree[u as usize] != ELIMINATED {
                if nnz >= b.rows.len() {
                    return Err(factor_full);
                }
                b.rows[nnz] = u;
                nnz += 1;
            }
            adj_next[e as usize] = free;
            free = e;
            e = nxt;
            visited += 1;
        }
        adj_head[v as usize] = NONE;
        b.col_end[k] = nnz as u32;
        // Make the neighbours a clique.
        for p in start..nnz {
            let a = b.rows[p] as usize;
            stamp += 1;
            mark[a] = stamp;
            let mut prev = NONE;
            let mut e = adj_head[a];
            let mut deg = 0u32;
            while e != NONE {
                let u = adj_node[e as usize];
                let nxt = adj_next[e as usize];
                if degree[u as usize] == ELIMINATED {
                    unlink(adj_head, adj_next, a, prev, nxt);
                    adj_next[e as usize] = free;
                    free = e;
                } else {
                    mark[u as usize] = stamp;
                    deg += 1;
                    prev = e;
                }
                e = nxt;
                visited += 1;
            }
            for q in start..nnz {
                let c = b.rows[q];
                visited += 1;
                if mark[c as usize] == stamp {
                    continue;
                }
                let slot = if free != NONE {
                    let s = free;
                    free = adj_next[s as usize];
                    s
                } else if used < pool {
                    used += 1;
                    (used - 1) as u32
                } else {
                    return Err(factor_full);
                };
                adj_node[slot as usize] = c;
                adj_next[slot as usize] = adj_head[a];
                adj_head[a] = slot;
                deg += 1;
            }
            let old = degree[a] as usize;
            if old != deg as usize {
                bucket_remove(bhead, bnext, bprev, a as u32, old);
                bucket_push(bhead, bnext, bprev, a as u32, deg as usize);
                degree[a] = deg;
                min_deg = min_deg.min(deg as usize);
            }
        }
        // The pivot itself (bucket search and bookkeeping) counts as a few entries.
        visited += 4;
        k += 1;
    }
    *s = Elimination {
        nv,
        k,
        min_deg,
        nnz,
        stamp,
        free,
        used,
    };
    Ok(visited)
}

/// The last part of [`analyze`] after every pivot was eliminated: the factor's rows as sorted
/// positions, the node <-> position maps and the edge slots (`O(factor blocks + edges)`).
///
/// # Errors
/// As [`analyze`].
pub(crate) fn analyze_end(
    n_nodes: usize,
    edges: &[PoseEdge],
    s: &Elimination,
    b: &mut SolverBuffers<'_>,
) -> Result<(), SolveError> {
    let Elimination { nv, nnz, .. } = *s;
    let factor_full = SolveError::Capacity {
        what: "factor blocks",
        capacity: b.rows.len(),
    };
    let [.., mark] = &mut b.scratch;
    // Positions: var -> position (in `mark`), then rows as positions, sorted per column.
    for k in 0..nv {
        mark[b.var_node[k] as usize] = k as u32;
    }
    let mut start = 0usize;
    for k in 0..nv {
        let end = b.col_end[k] as usize;
        let col = &mut b.rows[start..end];
        for r in col.iter_mut() {
            *r = mark[*r as usize];
        }
        crate::sort::sort(col);
        start = end;
    }
    // node -> position, position -> node.
    for (i, nv_slot) in b.node_var.iter_mut().take(n_nodes).enumerate() {
        if *nv_slot != NONE {
            let pos = mark[*nv_slot as usize];
            *nv_slot = pos;
            b.var_node[pos as usize] = i as u32;
        }
    }
    // Where each edge's off-diagonal block goes.
    for ((slot, e), &flag) in b.edge_slot.iter_mut().zip(edges).zip(b.edge_flags.iter()) {
        let pi = b.node_var[e.from.0 as usize];
        let pj = b.node_var[e.to.0 as usize];
        *slot = NO_SLOT;
        if pi == NONE || pj == NONE || pi == pj || flag == 0 {
            continue;
        }
        let (row, col, flag) = if pi > pj {
            (pi, pj, 0)
        } else {
            (pj, pi, TRANSPOSED)
        };
        let lo = if col == 0 {
            0
        } else {
            b.col_end[col as usize - 1] as usize
        };
        let hi = b.col_end[col as usize] as usize;
        match b.rows[lo..hi].binary_search(&row) {
            Ok(off) => *slot = (lo + off) as u32 | flag,
            Err(_) => return Err(SolveError::InvalidGraph),
        }
    }
    if nnz >= TRANSPOSED as usize {
        return Err(factor_full);
    }
    b.key.vars = nv;
    b.key.nnz = nnz;
    Ok(())
}

#[inline]
fn unlink(head: &mut [u32], next: &mut [u32], list: usize, prev: u32, nxt: u32) {
    if prev == NONE {
        head[list] = nxt;
    } else {
        next[prev as usize] = nxt;
    }
}

#[inline]
fn bucket_push(head: &mut [u32], next: &mut [u32], prev: &mut [u32], v: u32, d: usize) {
    let h = head[d];
    next[v as usize] = h;
    prev[v as usize] = NONE;
    if h != NONE {
        prev[h as usize] = v;
    }
    head[d] = v;
}

#[inline]
fn bucket_remove(head: &mut [u32], next: &mut [u32], prev: &mut [u32], v: u32, d: usize) {
    let (p, n) = (prev[v as usize], next[v as usize]);
    if p == NONE {
        head[d] = n;
    } else {
        next[p as usize] = n;
    }
    if n != NONE {
        prev[n as usize] = p;
    }
}
