//! When the back-end works (the paper's section III-D, block (c) of the block diagram): the
//! optimization schedule and the pruning that makes room in a full pool.
//!
//! **Optimization.** An optimization is due after a new loop closure, after a number of new
//! frame nodes, or on request. It is a sequence of solves of at most the caller's iterations
//! each, up to a total per optimization; every solve is a [`ChunkedSolve`], and one call of
//! [`BackendSchedule::step`] advances it by at most [`ScheduleParams::work_budget`] work units
//! (module `solver::resumable`: about 100 Cortex-A9 instructions each), so the back-end's share
//! of a frame is bounded by work, not by iterations. Frame nodes and loop edges that the
//! mapper adds while a solve runs join the next solve (the running one carries the new nodes
//! along rigidly). A finished optimization is reported so the caller can take its result as
//! the GPE's new anchor.
//!
//! **Pool pruning.** When the next frame node might not fit the node or edge pool,
//! [`make_room`] optimizes the graph to convergence (pruning linearizes at the current
//! estimate), then keeps one node per grid cell ([`prune`](crate::backend::prune)), with the
//! newest nodes and the caller's protected nodes exempt. The protection is passed to the
//! pruner as the nodes' `fixed` flag for the duration of the call only.

use crate::backend::cells::CellParams;
use crate::backend::prune::{prune, PruneParams, PruneReport, PruneScratch, Weighting};
use crate::graph::PoseGraph;
use crate::solver::{
    self, ChunkedSolve, Method, Progress, SolveError, SolverBuffers, SolverOptions,
};

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
    /// Most work units of one step (see `solver::work`); 0: no limit, every step runs a whole
    /// solve.
    pub work_budget: u64,
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
    /// Solves abandoned because the graph was pruned or cleared while they ran.
    pub abandoned: u32,
    /// Groups of loop closures removed as inconsistent with the rest of the graph (module
    /// [`consistency`](crate::backend::consistency)).
    pub loop_groups_removed: u32,
    /// Loop edges in those groups.
    pub loop_edges_removed: u32,
    /// Rounds of those tests finished.
    pub consistency_rounds: u32,
    /// Groups tested in them.
    pub loop_groups_tested: u32,
}

/// The back-end's schedule state.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BackendSchedule {
    /// Frame nodes added since the last optimization started.
    pending_keyframes: u32,
    /// A loop closure (or a request) since the last optimization started.
    pending_loop: bool,
    optimizing: bool,
    iterations_done: u32,
    /// The solve in progress.
    solve: Option<ChunkedSolve>,
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
            solve: None,
            counters: BackendCounters {
                steps: 0,
                optimizations: 0,
                failures: 0,
                abandoned: 0,
                loop_groups_removed: 0,
                loop_edges_removed: 0,
                consistency_rounds: 0,
                loop_groups_tested: 0,
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
        if self.solve.take().is_some() {
            self.counters.abandoned += 1;
        }
    }

    /// A round of consistency tests of `tested` loop groups ended, removing `removed` loop
    /// edges (0: none).
    pub fn consistency_round(&mut self, tested: u32, removed: usize) {
        let c = &mut self.counters;
        c.consistency_rounds += 1;
        c.loop_groups_tested = c.loop_groups_tested.saturating_add(tested);
        if removed > 0 {
            c.loop_groups_removed += 1;
            c.loop_edges_removed = c.loop_edges_removed.saturating_add(removed as u32);
        }
    }

    /// Counters so far.
    pub fn counters(&self) -> BackendCounters {
        self.counters
    }

    /// Advances the due optimization by at most `params.work_budget` work units; a solve
    /// started by this call runs at most `iterations` Gauss-Newton iterations.
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
        // With a finite budget, what a finished solve leaves of it goes to the next solve of
        // the same optimization; without one, a step is one whole solve.
        let mut left = budget(params);
        loop {
            let (outcome, used) = self.advance(graph, solver, params, iterations, left);
            let Progress::Done(result) = outcome else {
                return BackendStep::Working;
            };
            self.solve = None;
            let (done, failed) = match result {
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
            if done {
                self.optimizing = false;
                if failed {
                    self.counters.failures += 1;
                }
                self.counters.optimizations += 1;
                return BackendStep::Finished;
            }
            left = left.saturating_sub(used);
            if params.work_budget == 0 || left == 0 || used == 0 {
                return BackendStep::Working;
            }
        }
    }

    /// Advances the running solve, or starts the optimization's next one, by at most `left`
    /// work units; returns its progress and the units used.
    fn advance(
        &mut self,
        graph: &mut PoseGraph<'_>,
        solver: &mut SolverBuffers<'_>,
        params: &ScheduleParams,
        iterations: u32,
        left: u64,
    ) -> (Progress, u64) {
        let s = match &mut self.solve {
            Some(s) => s,
            None => {
                let remaining = params.max_iterations.saturating_sub(self.iterations_done);
                let options = SolverOptions {
                    method: Method::GaussNewton,
                    max_iterations: iterations.max(1).min(remaining.max(1)),
                    linear_init: false,
                    gate_chi2: params.gate_chi2,
                    ..SolverOptions::default()
                };
                match ChunkedSolve::start(graph, solver, &options) {
                    Ok(s) => self.solve.insert(s),
                    Err(f) => return (Progress::Done(Err(f)), 0),
                }
            }
        };
        let p = s.advance(graph, solver, left);
        (p, s.last_work())
    }
}

/// The work budget of one step in `solver::work` units.
fn budget(params: &ScheduleParams) -> u64 {
    match params.work_budget {
        0 => u64::MAX,
        b => b,
    }
}

/// True when the next frame node might not fit a graph of `nodes` of `node_capacity` nodes
/// and `edges` of `edge_capacity` edges.
pub fn counts_nearly_full(
    nodes: usize,
    node_capacity: usize,
    edges: usize,
    edge_capacity: usize,
) -> bool {
    nodes + 1 > node_capacity || edges + EDGE_MARGIN > edge_capacity
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
