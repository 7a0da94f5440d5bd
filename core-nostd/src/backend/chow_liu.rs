//! Chow-Liu trees: the maximum spanning tree of pairwise mutual information, found with
//! Kruskal's algorithm (the choice the paper makes for small sparse problems).
//!
//! Used to sparsify the dense factor that marginalizing a node leaves on its Markov blanket:
//! of all the pairs of blanket nodes, only the `k - 1` pairs of a tree are kept as new edges.
//! Everything is fixed-size: at most [`MAX_TREE_NODES`] vertices.

use heapless::Vec;

/// Most vertices a tree may have.
pub const MAX_TREE_NODES: usize = 10;
/// Most candidate pairs (`n (n - 1) / 2` for `n = MAX_TREE_NODES`).
pub const MAX_PAIRS: usize = MAX_TREE_NODES * (MAX_TREE_NODES - 1) / 2;

/// A weighted pair of vertices.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WeightedPair {
    /// First vertex (the smaller index).
    pub a: u8,
    /// Second vertex.
    pub b: u8,
    /// Weight (mutual information); larger is kept first.
    pub weight: f64,
}

/// The edges of a spanning tree (a forest when the input graph is disconnected).
pub type Tree = Vec<WeightedPair, { MAX_TREE_NODES - 1 }>;

/// Maximum spanning tree (or forest) over `n` vertices, with `weight(a, b)` for `a < b` giving
/// the weight of a candidate pair or `None` when the pair is not a candidate.
///
/// Ties are broken by vertex indices so the result never depends on sort stability. Returns
/// `None` when `n > MAX_TREE_NODES`.
pub fn maximum_spanning_tree(
    n: usize,
    mut weight: impl FnMut(usize, usize) -> Option<f64>,
) -> Option<Tree> {
    if n > MAX_TREE_NODES {
        return None;
    }
    let mut pairs: Vec<WeightedPair, MAX_PAIRS> = Vec::new();
    for a in 0..n {
        for b in (a + 1)..n {
            if let Some(w) = weight(a, b) {
                if w.is_nan() {
                    continue;
                }
                // Cannot fail: at most MAX_PAIRS pairs for n <= MAX_TREE_NODES.
                let _ = pairs.push(WeightedPair {
                    a: a as u8,
                    b: b as u8,
                    weight: w,
                });
            }
        }
    }
    // Heaviest first; insertion sort is ideal for at most 45 items.
    for i in 1..pairs.len() {
        let mut j = i;
        while j > 0 && heavier(&pairs[j], &pairs[j - 1]) {
            pairs.swap(j, j - 1);
            j -= 1;
        }
    }
    let mut parent = [0u8; MAX_TREE_NODES];
    for (i, p) in parent.iter_mut().enumerate() {
        *p = i as u8;
    }
    let mut tree = Tree::new();
    for p in pairs {
        let ra = find(&mut parent, p.a);
        let rb = find(&mut parent, p.b);
        if ra != rb {
            parent[usize::from(ra.max(rb))] = ra.min(rb);
            let _ = tree.push(p);
            if tree.len() + 1 == n {
                break;
            }
        }
    }
    Some(tree)
}

fn heavier(x: &WeightedPair, y: &WeightedPair) -> bool {
    x.weight > y.weight || (x.weight == y.weight && (x.a, x.b) < (y.a, y.b))
}

fn find(parent: &mut [u8; MAX_TREE_NODES], mut v: u8) -> u8 {
    while parent[usize::from(v)] != v {
        let grand = parent[usize::from(parent[usize::from(v)])];
        parent[usize::from(v)] = grand;
        v = grand;
    }
    v
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use proptest::prelude::*;
    use std::vec::Vec as StdVec;

    /// Brute force: the best total weight over every subset of `n - 1` pairs that forms a tree.
    fn brute_force_best(n: usize, pairs: &[WeightedPair]) -> f64 {
        let m = pairs.len();
        let mut best = f64::NEG_INFINITY;
        for mask in 0u32..(1 << m) {
            if mask.count_ones() as usize != n - 1 {
                continue;
            }
            let mut parent: StdVec<usize> = (0..n).collect();
            fn root(p: &mut [usize], mut v: usize) -> usize {
                while p[v] != v {
                    v = p[v];
                }
                v
            }
            let mut ok = true;
            let mut total = 0.0;
            for (i, p) in pairs.iter().enumerate() {
                if mask & (1 << i) != 0 {
                    let (ra, rb) = (
                        root(&mut parent, p.a as usize),
                        root(&mut parent, p.b as usize),
                    );
                    if ra == rb {
                        ok = false;
                        break;
                    }
                    parent[ra] = rb;
                    total += p.weight;
                }
            }
            if ok && total > best {
                best = total;
            }
        }
        best
    }

    proptest! {
        #[test]
        fn kruskal_matches_brute_force(n in 2usize..6, seed in proptest::collection::vec(0.0..100.0f64, 15)) {
            let mut pairs = StdVec::new();
            let mut k = 0;
            for a in 0..n {
                for b in (a + 1)..n {
                    pairs.push(WeightedPair { a: a as u8, b: b as u8, weight: seed[k] });
                    k += 1;
                }
            }
            let tree = maximum_spanning_tree(n, |a, b| {
                pairs.iter().find(|p| p.a as usize == a && p.b as usize == b).map(|p| p.weight)
            }).unwrap();
            prop_assert_eq!(tree.len(), n - 1);
            let total: f64 = tree.iter().map(|p| p.weight).sum();
            let best = brute_force_best(n, &pairs);
            prop_assert!((total - best).abs() < 1e-9, "kruskal {} brute force {}", total, best);
        }
    }

    #[test]
    fn disconnected_input_gives_a_forest() {
        // Pairs only inside {0,1} and {2,3}.
        let tree = maximum_spanning_tree(4, |a, b| {
            ((a, b) == (0, 1) || (a, b) == (2, 3)).then_some(1.0)
        })
        .unwrap();
        assert_eq!(tree.len(), 2);
        assert!(maximum_spanning_tree(MAX_TREE_NODES + 1, |_, _| Some(1.0)).is_none());
    }
}
