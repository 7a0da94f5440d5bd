//! The Gauss-Newton solve of eq. 10 (the paper's section III-D, optimization of the pruned
//! graph) as a resumable state machine, so that one back-end step does a bounded amount of
//! work and the real-time part keeps its frame rate on a single core.
//!
//! [`ChunkedSolve`] performs the same arithmetic, in the same order, as [`super::solve`] with
//! Gauss-Newton, one stage and no linear initialisation (with or without the gated
//! max-mixture warm start of module `gate`): with an unlimited budget and a graph that does
//! not grow, its result equals that of `solve` to the bit. It only adds places to stop:
//! * the measured angles' trigonometry, the cost evaluations (the initial cost, the trial
//!   cost of every step and of every step halving, the final cost) and the assembly of
//!   `H dx = -g` stop between edges; sums run in edge order, so a split sum is the same sum;
//! * the numeric factorization stops between columns (its pending-update lists live in the
//!   workspace), and so do the forward and the backward substitution;
//! * the minimum-degree ordering of a structural analysis stops between pivots (its
//!   elimination graph lives in the workspace, see `ordering::Elimination`);
//! * the odometry-chain gate stops between nodes of the chain and between edges of its test,
//!   its support test between the loops' lower ends;
//! * the innovation tests stop between loops and inside a test's forward and backward solves;
//! * the set-up and end of the gate and of its support test, the active-edge flags of the
//!   structural refresh, the set-up and the end of an analysis and the variance of unit weight
//!   run whole: a call that has already worked hands them to the next call instead of
//!   starting them.
//!
//! **Work units.** One unit is one `3x3` block multiply-subtract of the factorization (27
//! multiply-adds). The other items are charged by their measured cost in those units on the
//! Cortex-A9 ([`work`]): a call stops as soon as its units reach the budget, so it overshoots
//! by at most one item (one edge, one column).
//!
//! **A graph that grows meanwhile.** The mapper appends frame nodes and loop edges between
//! back-end steps. A solve works on the node and edge prefix that existed when it started
//! (the gate, the ordering and the cost comparisons of its stopping rule all refer to that
//! set). Nodes appended after it are chained to the prefix's last node by odometry and have no
//! other edge in the prefix, so whenever the solve moves that node (a step applied, or
//! halved), they are moved rigidly with it: this keeps their odometry residuals, hence what the
//! front-end measured, unchanged, and keeps the GPE's reference node consistent with its
//! neighbours. They and the appended edges join the next solve, which the schedule starts as
//! soon as this one ends.

use super::cholesky::{self, Factor};
use super::iterate::apply_step;
use super::linearize::{self, Stage, Warm};
use super::{admission, check_buffers, gate, ordering, refresh_flags};
use super::{Method, SolveError, SolveFailure, SolveReport, SolverBuffers, SolverOptions};
use crate::graph::{PoseEdge, PoseGraph, PoseNode, RobustKernel};
use crate::storage::NodeId;

mod run;
use run::{carry, chunk_end};

/// The cost of each item in work units (one `3x3` block multiply-subtract of the
/// factorization), measured on the Cortex-A9 (85 to 110 instructions per unit).
pub mod work {
    /// Cosine and sine of one edge's measured angle.
    pub const EDGE_TRIG: u64 = 4;
    /// One edge's residual and cost.
    pub const EDGE_COST: u64 = 6;
    /// One edge's residual, Jacobians and blocks of `H` and `-g`.
    pub const EDGE_ASSEMBLY: u64 = 14;
    /// One pose saved, stepped or restored.
    pub const NODE_UPDATE: u64 = 1;
    /// Substitution blocks per unit (a block-vector product is a third of a block product).
    pub const SOLVE_BLOCKS_PER_UNIT: u64 = 3;
    /// Per max-mixture loop the innovation tests look at (its residual), and per resumption
    /// of its test.
    pub const ADMISSION_EDGE: u64 = 12;
    /// Substitution blocks per unit in the innovation tests (measured: their solves cost half
    /// as much again per block as the iteration's).
    pub const ADMISSION_BLOCKS_PER_UNIT: u64 = 2;
    /// Per node of the odometry chain of the gate, and per node visited by its support test.
    pub const GATE_NODE: u64 = 16;
    /// Per edge of the gate's test that is not a max-mixture loop.
    pub const GATE_EDGE: u64 = 1;
    /// Per max-mixture loop tested by the gate, and per loop visited by the support test.
    pub const GATE_LOOP: u64 = 24;
    /// Per pair of loops whose consistency the support test computes.
    pub const GATE_PAIR: u64 = 48;
    /// Per edge of the structural refresh's active flags and fingerprint (run whole).
    pub const EDGE_REFRESH: u64 = 2;
    /// Per node and edge of a structural analysis's set-up, and per node, edge and factor
    /// block of its end (each run whole, when the structure changed).
    pub const ANALYSIS_ITEM: u64 = 1;
    /// Adjacency entries the minimum-degree elimination visits per unit.
    pub const ORDERING_ENTRIES_PER_UNIT: u64 = 3;
}

/// What [`ChunkedSolve::advance`] did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Progress {
    /// The budget ran out; the solve continues on the next call.
    Working,
    /// The solve ended, as [`super::solve`] would have ended it.
    Done(Result<SolveReport, SolveFailure>),
}

/// Which Gauss-Newton run of the solve is going on.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Run {
    /// The gated warm start on the nominal component.
    Nominal,
    /// The gated warm start under dynamic covariance scaling.
    Dcs,
    /// The free max-mixture (or plain) run.
    Free,
    /// A run after innovation-test round `n` admitted loops.
    Admission(u32),
}

/// Where the solve is.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Phase {
    Trig,
    Gate(GateStep),
    Structure,
    InitialCost,
    GnCost,
    GnTop,
    GnAssemble,
    GnFactor,
    GnForward,
    GnBackward,
    GnApply,
    GnTrialCost,
    GnJudge,
    Admission(u32),
    FinalCost,
    Rejected,
    /// A structural analysis, then the initial cost or the iteration's assembly.
    Analyze(Resume),
}

/// Where the odometry-chain gate is.
#[derive(Clone, Copy, Debug, PartialEq)]
enum GateStep {
    Index,
    Chain,
    Test,
    Link,
    Pairs,
    End,
}

/// What follows a structural analysis.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Resume {
    /// The refresh before the initial cost.
    Start,
    /// The refresh at the top of a Gauss-Newton iteration.
    Iteration,
}

/// The state of one Gauss-Newton run (see `iterate::gauss_newton`).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Gn {
    run: Run,
    warm: Warm,
    cap: u32,
    done: u32,
    bound: f64,
    cost: f64,
    changed: bool,
    largest: f64,
    halvings: u32,
}

/// A Gauss-Newton solve of a [`PoseGraph`] that advances by bounded chunks of work; see the
/// module documentation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChunkedSolve {
    options: SolverOptions,
    /// The node and edge prefix the solve works on.
    nodes: usize,
    edges: usize,
    report: SolveReport,
    gauge_first: bool,
    gated: bool,
    mixtures: bool,
    free: Warm,
    /// The outcome of the last finished run (`None`: converged).
    result: Option<SolveError>,
    phase: Phase,
    gn: Gn,
    /// Next edge or column of the current chunked phase.
    cursor: usize,
    /// Running sums (robust cost, chi2) of the current evaluation or assembly.
    acc: (f64, f64),
    rejected: usize,
    /// The innovation tests in progress.
    admit: admission::Admit,
    /// The gate's odometry chain in progress.
    chain: gate::Chain,
    /// The fingerprint of the analysis in progress.
    fingerprint: u64,
    /// The minimum-degree elimination in progress (`None`: not set up yet).
    elim: Option<ordering::Elimination>,
    /// Work units of the last call.
    spent: u64,
}

impl ChunkedSolve {
    /// Starts a solve of `graph` as it is now (its node and edge prefix) with `options`,
    /// whose `method`, `stages` and `linear_init` are taken as Gauss-Newton, 1 and `false`.
    ///
    /// # Errors
    /// As [`super::solve`] before any work: the workspace is too small, or an edge names a
    /// node outside the graph.
    pub fn start(
        graph: &PoseGraph<'_>,
        ws: &SolverBuffers<'_>,
        options: &SolverOptions,
    ) -> Result<Self, SolveFailure> {
        let (nodes, edges) = (graph.nodes(), graph.edges());
        let report = SolveReport::default();
        check_buffers(nodes, edges, ws).map_err(|error| SolveFailure { error, report })?;
        let mixtures = edges
            .iter()
            .any(|e| matches!(e.robust, RobustKernel::MaxMixture { .. }));
        let gated = options.gate_chi2 > 0.0 && mixtures;
        let warm = if gated { Warm::Nominal } else { Warm::Off };
        Ok(ChunkedSolve {
            options: SolverOptions {
                method: Method::GaussNewton,
                stages: 1,
                linear_init: false,
                ..*options
            },
            nodes: nodes.len(),
            edges: edges.len(),
            report,
            gauge_first: ordering::gauge_fixes_first(edges),
            gated,
            mixtures,
            free: Warm::Off,
            result: None,
            phase: Phase::Trig,
            gn: Gn {
                run: Run::Free,
                warm,
                cap: 0,
                done: 0,
                bound: 0.0,
                cost: 0.0,
                changed: false,
                largest: 0.0,
                halvings: 0,
            },
            cursor: 0,
            acc: (0.0, 0.0),
            rejected: 0,
            admit: admission::Admit::START,
            chain: gate::Chain::START,
            fingerprint: 0,
            elim: None,
            spent: 0,
        })
    }

    /// The nodes the solve works on (the graph's node count when it started).
    pub fn prefix_nodes(&self) -> usize {
        self.nodes
    }

    /// Advances the solve by about `budget` work units (`u64::MAX`: to the end).
    ///
    /// The graph may have gained nodes and edges since the solve started (see the module
    /// documentation); if it lost some (it was pruned or cleared), the solve ends with
    /// [`SolveError::InvalidGraph`].
    pub fn advance(
        &mut self,
        graph: &mut PoseGraph<'_>,
        ws: &mut SolverBuffers<'_>,
        budget: u64,
    ) -> Progress {
        if graph.node_count() < self.nodes || graph.edge_count() < self.edges {
            return self.fail(SolveError::InvalidGraph);
        }
        let (all_nodes, all_edges) = graph.split_mut();
        let (nodes, tail) = all_nodes.split_at_mut(self.nodes);
        let edges = all_edges.get(..self.edges).unwrap_or_default();
        let mut spent = 0u64;
        loop {
            if spent >= budget {
                self.spent = spent;
                return Progress::Working;
            }
            if let Some(done) = self.phase_step(nodes, tail, edges, ws, budget, &mut spent) {
                self.spent = spent;
                return done;
            }
        }
    }

    /// The work units the last [`ChunkedSolve::advance`] used.
    pub fn last_work(&self) -> u64 {
        self.spent
    }

    fn fail(&self, error: SolveError) -> Progress {
        Progress::Done(Err(SolveFailure {
            error,
            report: self.report,
        }))
    }

    /// Runs (part of) the current phase; `Some` when the solve ended.
    fn phase_step(
        &mut self,
        nodes: &mut [PoseNode],
        tail: &mut [PoseNode],
        edges: &[PoseEdge],
        ws: &mut SolverBuffers<'_>,
        budget: u64,
        spent: &mut u64,
    ) -> Option<Progress> {
        let n = nodes.len();
        let m = edges.len();
        let left = budget.saturating_sub(*spent);
        // A phase that runs whole starts a call of its own unless it fits what is left.
        let whole = |cost: u64, spent: &mut u64| -> bool {
            if *spent > 0 && cost > left {
                *spent = budget;
                return false;
            }
            *spent = spent.saturating_add(cost);
            true
        };
        match self.phase {
            Phase::Trig => {
                let end = chunk_end(self.cursor, m, left, work::EDGE_TRIG);
                for k in self.cursor..end {
                    if let (Some(t), Some(e)) = (ws.edge_trig.get_mut(k), edges.get(k)) {
                        *t = [
                            libm::cos(e.measurement.theta),
                            libm::sin(e.measurement.theta),
                        ];
                    }
                }
                *spent = spent.saturating_add((end - self.cursor) as u64 * work::EDGE_TRIG);
                self.cursor = end;
                if end == m {
                    self.phase = if self.gated {
                        Phase::Gate(GateStep::Index)
                    } else {
                        Phase::Structure
                    };
                }
            }
            Phase::Gate(step) => {
                if let Some(next) = self.gate_step(step, nodes, edges, ws, whole, left, spent) {
                    self.phase = next;
                }
            }
            Phase::Structure => {
                if !whole(self.refresh_cost(n, m), spent) {
                    return None;
                }
                let (gauge, warm) = (self.gauge_first, self.gn.warm);
                match refresh_flags(nodes, edges, ws, gauge, n, warm) {
                    (_, Some(fp)) => self.begin_analysis(fp, Resume::Start),
                    (_, None) => self.begin_sum(Phase::InitialCost),
                }
            }
            Phase::Analyze(resume) => {
                let analysis = self.analyze_chunk(nodes, edges, ws, whole, left, spent);
                match analysis {
                    Ok(false) => {}
                    Ok(true) => match resume {
                        Resume::Start => self.begin_sum(Phase::InitialCost),
                        Resume::Iteration => self.assemble_begin(ws, spent),
                    },
                    Err(e) => {
                        return match resume {
                            Resume::Start => Some(self.fail(e)),
                            Resume::Iteration => self.run_ended(nodes, edges, ws, Some(e)),
                        };
                    }
                }
            }
            Phase::InitialCost => {
                if self.cost_chunk(nodes, edges, ws, Warm::Off, left, spent) {
                    let (cost0, chi0) = self.acc;
                    let r = &mut self.report;
                    (r.initial_cost, r.initial_chi2) = (cost0, chi0);
                    (r.final_cost, r.final_chi2) = (cost0, chi0);
                    if !cost0.is_finite() {
                        return Some(self.fail(SolveError::Diverged));
                    }
                    if ws.key.vars == 0 {
                        self.report.converged = true;
                        return Some(Progress::Done(Ok(self.report)));
                    }
                    if self.gated {
                        let cap = self.options.stage_iterations;
                        self.begin_run(Run::Nominal, Warm::Nominal, cap);
                    } else {
                        self.begin_run(Run::Free, Warm::Off, self.options.max_iterations);
                    }
                }
            }
            Phase::GnCost => {
                if self.cost_chunk(nodes, edges, ws, self.gn.warm, left, spent) {
                    self.gn.cost = self.acc.0;
                    self.gn.done = 0;
                    self.phase = Phase::GnTop;
                }
            }
            Phase::GnTop => {
                if self.gn.done >= self.gn.cap {
                    return self.run_ended(nodes, edges, ws, Some(SolveError::MaxIterations));
                }
                if !whole(self.refresh_cost(n, m), spent) {
                    return None;
                }
                let (gauge, warm) = (self.gauge_first, self.gn.warm);
                let (changed, due) = refresh_flags(nodes, edges, ws, gauge, n, warm);
                self.gn.changed = changed;
                match due {
                    Some(fp) => self.begin_analysis(fp, Resume::Iteration),
                    None => self.assemble_begin(ws, spent),
                }
            }
            Phase::GnAssemble => {
                let end = chunk_end(self.cursor, m, left, work::EDGE_ASSEMBLY);
                let (warm, vars) = (self.gn.warm, ws.key.vars);
                let mut s = linearize::System::of(ws, warm);
                let range = self.cursor..end;
                linearize::assemble_edges(nodes, edges, range, Stage::Full, &mut s, &mut self.acc);
                *spent = spent.saturating_add((end - self.cursor) as u64 * work::EDGE_ASSEMBLY);
                self.cursor = end;
                if end == m {
                    linearize::assemble_end(vars, Stage::Full, &mut s);
                    let [row_head, ..] = &mut ws.scratch;
                    cholesky::factorize_begin(vars, row_head);
                    self.cursor = 0;
                    self.phase = Phase::GnFactor;
                }
            }
            Phase::GnFactor => {
                let vars = ws.key.vars;
                let [row_head, link, cursor, ..] = &mut ws.scratch;
                let mut f = Factor {
                    col_end: ws.col_end,
                    rows: ws.rows,
                    values: ws.values,
                    diag: ws.diag,
                    work: ws.work,
                    row_head,
                    link,
                    cursor,
                };
                match cholesky::factorize_columns(&mut f, self.cursor, vars, left) {
                    Ok((next, touched)) => {
                        *spent = spent.saturating_add(touched);
                        self.cursor = next;
                        if next == vars {
                            ws.key.factored = true;
                            self.cursor = 0;
                            self.phase = Phase::GnForward;
                        }
                    }
                    Err(col) => {
                        let node = ws.var_node.get(col).copied().unwrap_or(0);
                        let e = SolveError::NotPositiveDefinite(NodeId(node));
                        return self.run_ended(nodes, edges, ws, Some(e));
                    }
                }
            }
            Phase::GnForward => {
                let vars = ws.key.vars;
                let per = work::SOLVE_BLOCKS_PER_UNIT;
                let (next, touched) = cholesky::forward(
                    vars,
                    ws.col_end,
                    ws.rows,
                    ws.values,
                    ws.diag,
                    ws.rhs,
                    self.cursor,
                    left.saturating_mul(per),
                );
                *spent = spent.saturating_add(touched / per);
                self.cursor = next;
                if next == vars {
                    self.phase = Phase::GnBackward;
                }
            }
            Phase::GnBackward => {
                let per = work::SOLVE_BLOCKS_PER_UNIT;
                let (until, touched) = cholesky::backward(
                    ws.col_end,
                    ws.rows,
                    ws.values,
                    ws.diag,
                    ws.rhs,
                    self.cursor,
                    left.saturating_mul(per),
                );
                *spent = spent.saturating_add(touched / per);
                self.cursor = until;
                if until == 0 {
                    self.phase = Phase::GnApply;
                }
            }
            Phase::GnApply => {
                self.report.iterations += 1;
                self.gn.done += 1;
                self.gn.halvings = 0;
                for (s, node) in ws.saved.iter_mut().zip(nodes.iter()) {
                    *s = node.pose;
                }
                let before = nodes.last().map(|x| x.pose);
                self.gn.largest = apply_step(nodes, ws.var_node, ws.rhs, ws.key.vars);
                carry(nodes, tail, before);
                *spent = spent.saturating_add(2 * n as u64 * work::NODE_UPDATE);
                self.begin_sum(Phase::GnTrialCost);
            }
            Phase::GnTrialCost => {
                if self.cost_chunk(nodes, edges, ws, self.gn.warm, left, spent) {
                    self.phase = Phase::GnJudge;
                }
            }
            Phase::GnJudge => return self.judge(nodes, tail, edges, ws, spent),
            Phase::Admission(round) => {
                let Warm::Admit(limit) = self.free else {
                    self.begin_sum(Phase::FinalCost);
                    return None;
                };
                let (used, admitted) =
                    admission::admit_chunk(nodes, edges, ws, limit, &mut self.admit, left);
                *spent = spent.saturating_add(used.max(1));
                self.rejected += admitted;
                if self.admit.next < m {
                    return None;
                }
                if self.rejected == 0 {
                    self.begin_sum(Phase::FinalCost);
                } else {
                    let cap = self.options.max_iterations;
                    self.begin_run(Run::Admission(round), self.free, cap);
                }
            }
            Phase::FinalCost => {
                if self.cost_chunk(nodes, edges, ws, self.free, left, spent) {
                    (self.report.final_cost, self.report.final_chi2) = self.acc;
                    self.report.factor_blocks = ws.key.nnz;
                    self.rejected = 0;
                    self.cursor = 0;
                    self.phase = Phase::Rejected;
                }
            }
            Phase::Rejected => {
                let end = chunk_end(self.cursor, m, left, work::EDGE_COST);
                for k in self.cursor..end {
                    let (Some(e), Some(t), Some(&f)) =
                        (edges.get(k), ws.edge_trig.get(k), ws.edge_flags.get(k))
                    else {
                        continue;
                    };
                    if matches!(e.robust, RobustKernel::MaxMixture { .. })
                        && linearize::edge_residual(nodes, e, t).is_none_or(|r| {
                            linearize::weigh(e, e.chi2_of(&r), self.free, f).0 < 1.0
                        })
                    {
                        self.rejected += 1;
                    }
                }
                *spent = spent.saturating_add((end - self.cursor) as u64 * work::EDGE_COST);
                self.cursor = end;
                if end == m {
                    self.report.rejected_loops = self.rejected;
                    return Some(match self.result {
                        None => Progress::Done(Ok(self.report)),
                        Some(e) => self.fail(e),
                    });
                }
            }
        }
        None
    }
}
