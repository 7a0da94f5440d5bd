//! When the back-end works (the paper's section III-D, block (c) of the block diagram): the
//! optimization schedule and the pruning that makes room in a full pool.
//!
//! **Optimization.** An optimization is due after a new loop closure, after a number of new
//! frame nodes, or on request. It runs over several calls of [`BackendSchedule::step`], each a
//! few Gauss-Newton iterations, up to a total per optimization, so the caller decides how much
//! back-end work fits between frames. A finished optimization is reported so the caller can
//! take its result as the GPE's new anchor.
//!
//! **Pool pruning.** When the next frame node might not fit the node or edge pool,
//! [`make_room`] optimizes the graph to convergence (pruning linearizes at the current
//! estimate), then keeps one node per grid cell ([`prune`](crate::backend::prune)), with the
//! newest nodes and the caller's protected nodes exempt. The protection is passed to the
//! pruner as the nodes' `fixed` flag for the duration of the call only.

use crate::backend::cells::CellParams;
use crate::backend::prune::{prune, PruneParams, PruneReport, PruneScratch, Weighting};
use crate::graph::PoseGraph;
use crate::solver::{self, Method, SolveError, SolverBuffers, SolverOptions};

/// Free edge slots kept for the loop closures of one frame node and the pruner's tree edges.
const EDGE_MARGIN: usize = 16;
/// Fewest nodes worth pruning.
const MIN_PRUNE_NODES: usize = 3;

/// What one back-end step did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BackendStep {
    /// Nothing to optimize.
    Idle,
    /// Iterations ran; the optimization continues on the next step.
    Working,
    /// An optimization finished; its result is the GPE's new anchor.
    Finished,
}

/// Parameters of the schedule.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScheduleParams {
    /// Optimize after this many new frame nodes even without a new loop closure.
    pub every_keyframes: u32,
    /// Most Gauss-Newton iterations of one optimization.
    pub max_iterations: u32,
    /// Chi2 threshold of the solver's odometry-chain gate (0: off).
    pub gate_chi2: f64,
}

/// Parameters of the pool pruning.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoolPruning {
    /// Grid cell, metres.
    pub cell_size: f64,
    /// Share of the information term in the node weight (eq. 11).
    pub s: f64,
    /// The newest nodes never pruned.
    pub keep_recent: u32,
    /// Iterations of the optimization before pruning.
    pub max_iterations: u32,
}

/// Counters of the back-end.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BackendCounters {
    /// Steps run.
    pub steps: u32,
    /// Optimizations finished.
    pub optimizations: u32,
    /// Optimizations that failed (the estimate was kept).
    pub failures: u32,
}

/// The back-end's schedule state.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BackendSchedule {
    /// Frame nodes added since the last optimization started.
    pending_keyframes: u32,
    /// A loop closure (or a request) since the last optimization started.
    pending_loop: bool,
    optimizing: bool,
    iterations_done: u32,
    counters: BackendCounters,
}

impl BackendSchedule {
    /// Nothing pending.
    pub const fn new() -> Self {
        BackendSchedule {
            pending_keyframes: 0,
            pending_loop: false,
            optimizing: false,
            iterations_done: 0,
            counters: BackendCounters {
                steps: 0,
                optimizations: 0,
                failures: 0,
            },
        }
    }

    /// A frame node was added.
    pub fn keyframe_added(&mut self) {
        self.pending_keyframes += 1;
    }

    /// A loop closure was added, or an optimization is requested: one is due.
    pub fn loop_added(&mut self) {
        self.pending_loop = true;
    }

    /// The graph was optimized and changed outside the schedule: a running optimization is
    /// abandoned.
    pub fn interrupt(&mut self) {
        self.optimizing = false;
    }

    /// Counters so far.
    pub fn counters(&self) -> BackendCounters {
        self.counters
    }

    /// Runs at most `iterations` Gauss-Newton iterations of the due optimization.
    pub fn step(
        &mut self,
        graph: &mut PoseGraph<'_>,
        solver: &mut SolverBuffers<'_>,
        params: &ScheduleParams,
        iterations: u32,
    ) -> BackendStep {
        if !self.optimizing {
            let due = self.pending_loop || self.pending_keyframes >= params.every_keyframes;
            if !due || graph.node_count() < 2 {
                return BackendStep::Idle;
            }
            self.optimizing = true;
            self.iterations_done = 0;
            self.pending_loop = false;
            self.pending_keyframes = 0;
        }
        self.counters.steps += 1;
        let left = params.max_iterations.saturating_sub(self.iterations_done);
        let options = SolverOptions {
            method: Method::GaussNewton,
            max_iterations: iterations.max(1).min(left.max(1)),
            linear_init: false,
            gate_chi2: params.gate_chi2,
            ..SolverOptions::default()
        };
        let (done, failed) = match solver::solve(graph, solver, &options) {
            Ok(r) => {
                self.iterations_done += r.iterations;
                (true, false)
            }
            Err(f) if f.error == SolveError::MaxIterations => {
                self.iterations_done += f.report.iterations;
                (self.iterations_done >= params.max_iterations, false)
            }
            Err(_) => (true, true),
        };
        if !done {
            return BackendStep::Working;
        }
        self.optimizing = false;
        if failed {
            self.counters.failures += 1;
        }
        self.counters.optimizations += 1;
        BackendStep::Finished
    }
}

/// True when the next frame node might not fit `graph`.
pub fn pool_nearly_full(graph: &PoseGraph<'_>) -> bool {
    graph.node_count() + 1 > graph.node_capacity()
        || graph.edge_count() + EDGE_MARGIN > graph.edge_capacity()
}

/// Optimizes and prunes `graph` to make room, `protected` (node indices) exempt; abandons
/// `schedule`'s running optimization. On success the pruner's `scratch.order` maps each old
/// node index to its new one (`u32::MAX`: eliminated) and the solver's cached ordering is
/// dropped; `None` when the graph is too small or the pruner refused.
pub fn make_room(
    graph: &mut PoseGraph<'_>,
    solver: &mut SolverBuffers<'_>,
    scratch: &mut PruneScratch<'_>,
    schedule: &mut BackendSchedule,
    params: &PoolPruning,
    protected: impl IntoIterator<Item = usize>,
) -> Option<PruneReport> {
    let n = graph.node_count();
    if n < MIN_PRUNE_NODES {
        return None;
    }
    let options = SolverOptions {
        method: Method::GaussNewton,
        max_iterations: params.max_iterations,
        linear_init: false,
        ..SolverOptions::default()
    };
    // A failed optimization still leaves a usable estimate to prune at.
    let _ = solver::solve(graph, solver, &options);
    schedule.interrupt();
    for k in protected {
        if let Some(node) = graph.nodes_mut().get_mut(k) {
            node.fixed = true;
        }
    }
    let keep_recent = (params.keep_recent as usize).min(n - 1);
    let prune_params = PruneParams {
        cells: CellParams {
            cell_size: params.cell_size,
            s: params.s,
        },
        weighting: Weighting::EdgeInformation,
        protect_from: n - keep_recent,
        ..PruneParams::default()
    };
    let result = prune(graph, &prune_params, scratch);
    for node in graph.nodes_mut() {
        node.fixed = false;
    }
    let report = result.ok()?;
    solver.invalidate();
    Some(report)
}
