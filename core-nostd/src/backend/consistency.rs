//! Whole-graph consistency of the loop closures (section III-D's back-end; the cluster test of
//! RRR, Latif, Cadena and Neira, 2013): a revisit whose loop edges the rest of the graph had to
//! bend to fit is left out.
//!
//! The max-mixture judges each loop edge alone against the current estimate, so a group of
//! wrong edges that agree with each other (a look-alike room matched from eight keyframes in a
//! row) outvotes the odometry where it acts and stays in. Judged against the whole graph it
//! stands out: leaving a right group out lowers the optimal cost by about its degrees of
//! freedom, leaving a wrong one out by far more, because the odometry and every other loop
//! had to give way to it ([`crate::solver::leave_out_gain`]).
//!
//! **Groups.** A group is one revisit of one place: the loop edges to one anchor whose keyframes
//! follow each other by at most [`GAP`] graph nodes, at most [`MAX_GROUP`] edges (fewer in a
//! pool too small for the test of that many, see `max_group`). A group is
//! tested once it is complete (the newest node lies more than [`GAP`] nodes past its last
//! keyframe), so a revisit is judged as a whole.
//!
//! **A round** runs at an optimum (after an optimization finished) on the factor that
//! optimization left: each group's gain is divided by the 99.9 % quantile of the chi2 with its
//! degrees of freedom, and the group with the largest ratio above 1 is removed from the graph.
//! The optimization that follows moves the map to the rest's optimum, and the next round tests
//! again, so groups are removed one at a time, the worst first, as in RRR: a right group that
//! only disagreed with a wrong one passes once the wrong one is gone.
//!
//! **Every complete group, every round.** A wrong revisit seldom stands out when it completes:
//! the graph around it may have nothing yet to contradict it, and it fails only once a later
//! revisit or the closing of a larger loop brings the evidence (on the generated office 302 the
//! look-alike groups passed every test at completion and failed later). So each round tests
//! every complete group again. A group's test costs `3 (m + 1)` substitutions along the
//! elimination tree (`m` edges), a small part of a solve; a round spans as many back-end steps
//! as its work budget needs. The mapper gives it only the turns the optimizer and the far loop
//! search leave and drops it when an optimization starts first, so tests that remove nothing
//! change nothing.
//!
//! Scratch: the pruning's per-node and per-edge arrays, free between prunings (the group of
//! each anchor, the group's last edge, the chain of edges of each group, the dense matrix of
//! the test).

use super::prune::PruneScratch;
use crate::geom::chi2_quantile;
use crate::graph::{EdgeKind, PoseGraph};
use crate::solver::{factor_usable, leave_out_gain, work, SolverBuffers, MAX_GROUP};

/// Most graph nodes between consecutive keyframes of one revisit's loop edges.
pub const GAP: u32 = 10;
/// The standard normal's 99.9 % point: a group is inconsistent beyond the chi2's 99.9 %
/// quantile of its degrees of freedom.
const Z: f64 = 3.090_232;
/// Work units (`solver::work`) of a group's set-up, besides its substitutions.
const GROUP_WORK: u64 = 40;

const NONE: u32 = u32::MAX;

/// What a finished round removed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Removed {
    /// Loop edges removed.
    pub edges: usize,
    /// The group's gain over its chi2 quantile.
    pub ratio: f64,
}

/// Where a round is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RoundProgress {
    /// The budget ran out; the round continues on the next call.
    Working,
    /// The round ended; the group it removed, if any.
    Done(Option<Removed>),
}

/// A round of tests in progress (see the module documentation). While it runs, the solver's
/// factor, the graph's existing edges and estimates and the pruning scratch must not change;
/// frame nodes and edges may be added.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Round {
    /// Edges grouped when the round started.
    edges: usize,
    /// Next edge to look at as the head of a group.
    cursor: usize,
    /// Newest node when the round started.
    newest: u32,
    /// The largest ratio above 1 so far and the head of its group.
    worst: Option<(f64, u32)>,
    /// Groups tested so far.
    tested: u32,
}

impl Round {
    /// A round over `graph` at its current estimate with the factor the last solve left in
    /// `solver`; `None` when that factor is not usable or the scratch is too small.
    pub fn start(
        graph: &PoseGraph<'_>,
        solver: &SolverBuffers<'_>,
        scratch: &mut PruneScratch<'_>,
    ) -> Option<Round> {
        let n = graph.node_count();
        let m = graph.edge_count();
        if n < 2
            || !factor_usable(solver, n, m)
            || scratch.order.len() < n
            || scratch.head.len() < n
            || scratch.next.len() < 2 * m
        {
            return None;
        }
        group_edges(graph, scratch);
        Some(Round {
            edges: m,
            cursor: 0,
            newest: (n - 1) as u32,
            worst: None,
            tested: 0,
        })
    }

    /// Tests groups until `budget` work units are spent (0: no limit); at the end of the round,
    /// removes the worst inconsistent group from `graph`.
    pub fn advance(
        &mut self,
        graph: &mut PoseGraph<'_>,
        solver: &mut SolverBuffers<'_>,
        scratch: &mut PruneScratch<'_>,
        budget: u64,
    ) -> RoundProgress {
        let budget = if budget == 0 { u64::MAX } else { budget };
        let mut spent = 0u64;
        let mut members = heapless::Vec::<usize, MAX_GROUP>::new();
        while spent < budget {
            if self.cursor >= self.edges {
                return RoundProgress::Done(self.finish(graph, solver, scratch));
            }
            let k = self.cursor;
            self.cursor += 1;
            if scratch.next.get(2 * k).copied() != Some(k as u32) {
                continue;
            }
            if !complete(graph, scratch, k, self.newest) {
                continue;
            }
            collect(scratch, k, &mut members);
            spent = spent.saturating_add(GROUP_WORK);
            let Some(test) = leave_out_gain(graph, solver, &members, scratch.node_information)
            else {
                continue;
            };
            spent = spent.saturating_add(test.blocks / work::SOLVE_BLOCKS_PER_UNIT);
            self.tested += 1;
            let ratio = test.gain / chi2_quantile(3.0 * test.edges as f64, Z);
            if ratio > 1.0 && self.worst.is_none_or(|(r, _)| ratio > r) {
                self.worst = Some((ratio, k as u32));
            }
        }
        RoundProgress::Working
    }

    /// Groups tested so far in this round.
    pub fn tested(&self) -> u32 {
        self.tested
    }

    /// Removes the worst group found, if any.
    fn finish(
        &self,
        graph: &mut PoseGraph<'_>,
        solver: &mut SolverBuffers<'_>,
        scratch: &PruneScratch<'_>,
    ) -> Option<Removed> {
        let (ratio, head) = self.worst?;
        let mut members = heapless::Vec::<usize, MAX_GROUP>::new();
        collect(scratch, head as usize, &mut members);
        let edges = graph.retain_edges(|k, _| !members.contains(&k));
        solver.invalidate();
        Some(Removed { edges, ratio })
    }
}

/// Groups the loop edges: `next[2 k]` is the first edge of edge k's group (`NONE` for other
/// edges), `next[2 k + 1]` the group's next edge; `order[a]` is the first edge of anchor a's
/// newest group, `head[a]` that group's last edge.
fn group_edges(graph: &PoseGraph<'_>, s: &mut PruneScratch<'_>) {
    let n = graph.node_count();
    let longest = max_group(s.node_information.len());
    s.order.iter_mut().take(n).for_each(|o| *o = NONE);
    for (k, e) in graph.edges().iter().enumerate() {
        if 2 * k + 1 >= s.next.len() {
            break;
        }
        s.next[2 * k] = NONE;
        s.next[2 * k + 1] = NONE;
        if e.kind != EdgeKind::Loop {
            continue;
        }
        let a = e.from.0 as usize;
        let open = s.order.get(a).copied().unwrap_or(NONE);
        let joins = open != NONE && {
            let last = s.head[a] as usize;
            let close = graph
                .edges()
                .get(last)
                .is_some_and(|l| e.to.0 >= l.to.0 && e.to.0 - l.to.0 <= GAP);
            close && chain_len(s, open as usize) < longest
        };
        if joins {
            let last = s.head[a] as usize;
            s.next[2 * last + 1] = k as u32;
            s.next[2 * k] = open;
        } else if let Some(o) = s.order.get_mut(a) {
            *o = k as u32;
            s.next[2 * k] = k as u32;
        } else {
            continue;
        }
        s.head[a] = k as u32;
    }
}

/// Most edges of a group whose test fits a dense scratch of `scratch` values (`(3 m)^2` for `m`
/// edges; the scratch is the pruning's per-node array): [`MAX_GROUP`] in the profiles' pools, so
/// a small pool tests a long revisit in parts rather than not at all.
fn max_group(scratch: usize) -> usize {
    (1..=MAX_GROUP)
        .rev()
        .find(|m| 9 * m * m <= scratch)
        .unwrap_or(1)
}

/// Edges in the group that starts at edge `first`.
fn chain_len(s: &PruneScratch<'_>, first: usize) -> usize {
    let mut len = 0;
    let mut k = first as u32;
    while k != NONE && len <= MAX_GROUP {
        len += 1;
        k = s.next.get(2 * k as usize + 1).copied().unwrap_or(NONE);
    }
    len
}

/// The edges of the group that starts at edge `first`, into `out`.
fn collect(s: &PruneScratch<'_>, first: usize, out: &mut heapless::Vec<usize, MAX_GROUP>) {
    out.clear();
    let mut k = first as u32;
    while k != NONE && out.push(k as usize).is_ok() {
        k = s.next.get(2 * k as usize + 1).copied().unwrap_or(NONE);
    }
}

/// Whether the group starting at edge `first` is complete: a later group of its anchor began,
/// or the newest node lies more than [`GAP`] nodes past its last keyframe.
fn complete(graph: &PoseGraph<'_>, s: &PruneScratch<'_>, first: usize, newest: u32) -> bool {
    let Some(a) = graph.edges().get(first).map(|e| e.from.0 as usize) else {
        return false;
    };
    let mut last = first as u32;
    let mut k = first as u32;
    while k != NONE {
        last = k;
        k = s.next.get(2 * k as usize + 1).copied().unwrap_or(NONE);
    }
    let closed = s.order.get(a).copied() != Some(first as u32);
    closed
        || graph
            .edges()
            .get(last as usize)
            .is_some_and(|e| newest.saturating_sub(e.to.0) > GAP)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::prune::PruneStorage;
    use crate::geom::{Info3, Se2};
    use crate::graph::{GraphStorage, PoseEdge, RobustKernel};
    use crate::solver::{solve, SolverOptions, SolverWorkspace, DENSE_SCRATCH};
    use crate::storage::NodeId;

    /// A corridor driven out and back along x (node k at x = k for k <= 20, then back), loop
    /// edges from each returning node to the outbound node at the same place, and `wrong`
    /// consecutive returning nodes (from node 25) instead matched 0.67 m off, as a look-alike
    /// would be.
    fn out_and_back(storage: &mut GraphStorage<64, 256>, wrong: usize) -> PoseGraph<'_> {
        let mut g = storage.graph();
        let odo = Info3::from_diagonal(&nalgebra::Vector3::new(400.0, 400.0, 2000.0));
        let lp = Info3::from_diagonal(&nalgebra::Vector3::new(100.0, 100.0, 400.0));
        let pose = |k: usize| {
            if k <= 20 {
                Se2::new(k as f64, 0.0, 0.0)
            } else {
                Se2::new(40.0 - k as f64, 0.5, core::f64::consts::PI)
            }
        };
        for k in 0..=40 {
            g.add_node(pose(k)).unwrap();
        }
        for k in 1..=40u32 {
            let z = pose(k as usize - 1).inverse().compose(&pose(k as usize));
            g.add_edge(PoseEdge::new(
                NodeId(k - 1),
                NodeId(k),
                z,
                odo,
                EdgeKind::Odometry,
            ))
            .unwrap();
        }
        // Returning node 40 - j meets outbound node j; anchors every fourth outbound node, so
        // that each anchor's edges form one group.
        for k in 21..=40usize {
            let j = 40 - k;
            let anchor = j - j % 4;
            let mut z = pose(anchor).inverse().compose(&pose(k));
            if (25..25 + wrong).contains(&k) {
                z = Se2::new(z.x + 0.6, z.y + 0.3, z.theta);
            }
            let mut e = PoseEdge::new(
                NodeId(anchor as u32),
                NodeId(k as u32),
                z,
                lp,
                EdgeKind::Loop,
            );
            e.robust = RobustKernel::max_mixture_with_null(1e-3, 1e-6);
            g.add_edge(e).unwrap();
        }
        g
    }

    fn rounds(wrong: usize) -> (usize, usize) {
        let mut storage = GraphStorage::<64, 256>::new();
        let mut g = out_and_back(&mut storage, wrong);
        let mut ws = SolverWorkspace::<64, 256, 1024>::new();
        let mut prune = PruneStorage::<DENSE_SCRATCH, 256>::new();
        let (mut groups, mut edges) = (0, 0);
        for _ in 0..10 {
            let mut b = ws.buffers();
            let _ = solve(&mut g, &mut b, &SolverOptions::default());
            let mut p = prune.scratch();
            let mut round = Round::start(&g, &b, &mut p).expect("the solve left a factor");
            // A small budget: the round spans several calls.
            let removed = loop {
                if let RoundProgress::Done(r) = round.advance(&mut g, &mut b, &mut p, 30) {
                    break r;
                }
            };
            let Some(r) = removed else {
                return (groups, edges);
            };
            groups += 1;
            edges += r.edges;
        }
        panic!("no end");
    }

    #[test]
    fn a_group_is_as_long_as_its_test_fits_the_scratch() {
        // The core tests' 512-node pool: 21 x 21 values at most, 7 edges.
        assert_eq!(max_group(512), 7);
        assert_eq!(max_group(9 * 7 * 7), 7);
        assert_eq!(max_group(9 * 7 * 7 - 1), 6);
        // The smallest profile (4,096 nodes) holds a full group.
        assert_eq!(max_group(4096), MAX_GROUP);
        assert_eq!(max_group(0), 1);
    }

    #[test]
    fn a_consistent_graph_keeps_every_loop() {
        assert_eq!(rounds(0), (0, 0));
    }

    #[test]
    fn an_agreeing_wrong_group_is_removed_and_only_it() {
        // Returning nodes 25..29 all land 0.67 m off: they are one anchor's group (anchor 12);
        // the max-mixture keeps them (each alone is within its nominal component), the test
        // removes exactly them.
        let (groups, edges) = rounds(4);
        assert_eq!(groups, 1);
        assert_eq!(edges, 4);
    }
}
