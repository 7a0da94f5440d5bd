//! The Gauss-Newton runs of a [`ChunkedSolve`]: the end of an iteration (step halving and the
//! stopping rule of `iterate::gauss_newton`), the sequence of runs of [`super::super::solve`]
//! (warm start, free run, admission rounds), and the small helpers of the chunked phases.

use super::{work, ChunkedSolve, GateStep, Gn, Phase, Progress, Resume, Run};
use crate::geom::Se2;
use crate::graph::{PoseEdge, PoseNode};
use crate::solver::admission;
use crate::solver::gate;
use crate::solver::iterate::{apply_step, MAX_HALVINGS, SETTLE_ITERATIONS};
use crate::solver::linearize::{self, Warm};
use crate::solver::{analysis_done, ordering, SolveError, SolverBuffers, ADMISSION_ROUNDS};

impl ChunkedSolve {
    /// The end of a Gauss-Newton iteration: step halving, divergence and the stopping rule
    /// (as `iterate::gauss_newton`).
    pub(super) fn judge(
        &mut self,
        nodes: &mut [PoseNode],
        tail: &mut [PoseNode],
        edges: &[PoseEdge],
        ws: &mut SolverBuffers<'_>,
        spent: &mut u64,
    ) -> Option<Progress> {
        let (new_cost, new_chi2) = self.acc;
        let g = &mut self.gn;
        if (new_cost.is_nan() || new_cost > g.cost)
            && g.halvings < MAX_HALVINGS
            && g.cost.is_finite()
            && (!self.mixtures || g.warm == Warm::Dcs)
        {
            g.halvings += 1;
            let vars = ws.key.vars;
            for d in ws.rhs.iter_mut().take(vars) {
                d[0] *= 0.5;
                d[1] *= 0.5;
                d[2] *= 0.5;
            }
            let before = nodes.last().map(|x| x.pose);
            for (node, s) in nodes.iter_mut().zip(ws.saved.iter()) {
                node.pose = *s;
            }
            g.largest = apply_step(nodes, ws.var_node, ws.rhs, vars);
            carry(nodes, tail, before);
            *spent = spent.saturating_add(2 * nodes.len() as u64 * work::NODE_UPDATE);
            self.begin_sum(Phase::GnTrialCost);
            return None;
        }
        self.report.final_cost = new_cost;
        self.report.final_chi2 = new_chi2;
        if !new_cost.is_finite() || new_cost > g.bound {
            return self.run_ended(nodes, edges, ws, Some(SolveError::Diverged));
        }
        let decrease = g.cost - new_cost;
        g.cost = new_cost;
        let o = &self.options;
        let settled = !g.changed || g.done > SETTLE_ITERATIONS;
        if settled
            && (g.largest < o.step_tolerance
                || (decrease >= 0.0 && decrease <= o.relative_tolerance * new_cost)
                || g.halvings == MAX_HALVINGS)
        {
            self.report.converged = true;
            return self.run_ended(nodes, edges, ws, None);
        }
        self.phase = Phase::GnTop;
        None
    }

    /// A Gauss-Newton run ended with `result` (`None`: converged): the next run, the
    /// innovation tests or the final evaluation, in the order of [`super::solve`].
    pub(super) fn run_ended(
        &mut self,
        nodes: &[PoseNode],
        edges: &[PoseEdge],
        ws: &SolverBuffers<'_>,
        result: Option<SolveError>,
    ) -> Option<Progress> {
        let usable = matches!(result, None | Some(SolveError::MaxIterations));
        let max = self.options.max_iterations;
        match self.gn.run {
            Run::Nominal | Run::Dcs if !usable => {
                return Some(self.fail(result.unwrap_or(SolveError::InvalidGraph)));
            }
            Run::Nominal => self.begin_run(Run::Dcs, Warm::Dcs, max),
            Run::Dcs => {
                // Whole: one pass over the edges, the cost of an evaluation.
                let v = gate::unit_variance(nodes, edges, ws);
                self.free = Warm::Admit(self.options.gate_chi2 * v);
                self.begin_run(Run::Free, self.free, max);
            }
            Run::Free | Run::Admission(_) => {
                self.result = result;
                let round = match self.gn.run {
                    Run::Admission(k) => k + 1,
                    _ => 0,
                };
                if self.gated && usable && round < ADMISSION_ROUNDS {
                    // `rejected` counts the loops this round admits until the final count.
                    self.rejected = 0;
                    self.admit = admission::Admit::START;
                    self.phase = Phase::Admission(round);
                } else {
                    self.begin_sum(Phase::FinalCost);
                }
            }
        }
        None
    }

    /// Starts Gauss-Newton run `run` (at most `cap` iterations, stage caps as in
    /// [`super::solve`]) with its initial cost evaluation.
    pub(super) fn begin_run(&mut self, run: Run, warm: Warm, cap: u32) {
        self.gn = Gn {
            run,
            warm,
            cap: cap.min(self.options.max_iterations),
            done: 0,
            bound: self.options.divergence_factor * self.report.initial_cost.max(1.0),
            cost: 0.0,
            changed: false,
            largest: 0.0,
            halvings: 0,
        };
        self.begin_sum(Phase::GnCost);
    }

    pub(super) fn begin_sum(&mut self, phase: Phase) {
        self.acc = (0.0, 0.0);
        self.cursor = 0;
        self.phase = phase;
    }

    /// The cost in work units of the structural refresh's active flags and fingerprint.
    pub(super) fn refresh_cost(&self, n: usize, m: usize) -> u64 {
        (m as u64) * work::EDGE_REFRESH + (n as u64) * work::NODE_UPDATE
    }

    /// Starts a structural analysis whose fingerprint will be `fp`, then `resume`.
    pub(super) fn begin_analysis(&mut self, fp: u64, resume: Resume) {
        self.fingerprint = fp;
        self.elim = None;
        self.phase = Phase::Analyze(resume);
    }

    /// Runs the next part of the structural analysis: its set-up, a chunk of pivots or its
    /// end; true when the analysis is complete. `whole` charges a part that runs whole (false:
    /// it starts the next call).
    pub(super) fn analyze_chunk(
        &mut self,
        nodes: &[PoseNode],
        edges: &[PoseEdge],
        ws: &mut SolverBuffers<'_>,
        whole: impl Fn(u64, &mut u64) -> bool,
        left: u64,
        spent: &mut u64,
    ) -> Result<bool, SolveError> {
        let (n, m) = (nodes.len(), edges.len());
        let per = work::ORDERING_ENTRIES_PER_UNIT;
        match self.elim {
            None => {
                if whole((n + m) as u64 * work::ANALYSIS_ITEM, spent) {
                    let elim = ordering::analyze_begin(nodes, edges, self.gauge_first, ws)?;
                    self.elim = Some(elim);
                }
                Ok(false)
            }
            Some(mut elim) if !elim.done() => {
                let visited = ordering::eliminate(&mut elim, ws, left.saturating_mul(per))?;
                *spent = spent.saturating_add(visited.div_ceil(per));
                self.elim = Some(elim);
                Ok(false)
            }
            Some(elim) => {
                let cost = (n + m + elim.blocks()) as u64 * work::ANALYSIS_ITEM;
                if !whole(cost, spent) {
                    return Ok(false);
                }
                ordering::analyze_end(n, edges, &elim, ws)?;
                analysis_done(n, m, self.fingerprint, ws, &mut self.report);
                self.elim = None;
                Ok(true)
            }
        }
    }

    /// Runs the next part of the odometry-chain gate and its support test (module `gate`);
    /// returns the phase that follows when this part ended.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn gate_step(
        &mut self,
        step: GateStep,
        nodes: &[PoseNode],
        edges: &[PoseEdge],
        ws: &mut SolverBuffers<'_>,
        whole: impl Fn(u64, &mut u64) -> bool,
        left: u64,
        spent: &mut u64,
    ) -> Option<Phase> {
        let (n, m) = (nodes.len(), edges.len());
        let chi2 = self.options.gate_chi2;
        let setup = (n + m) as u64 * work::ANALYSIS_ITEM;
        match step {
            GateStep::Index => {
                if !whole(setup, spent) {
                    return None;
                }
                gate::gate_index(n, edges, ws);
                self.chain = gate::Chain::START;
                Some(Phase::Gate(GateStep::Chain))
            }
            GateStep::Chain => {
                let used = gate::gate_chain(&mut self.chain, n, edges, ws, left);
                *spent = spent.saturating_add(used);
                (self.chain.next >= n).then(|| {
                    self.cursor = 0;
                    Phase::Gate(GateStep::Test)
                })
            }
            GateStep::Test => {
                let (next, used, _) = gate::gate_test(n, edges, ws, chi2, self.cursor, left);
                *spent = spent.saturating_add(used);
                self.cursor = next;
                (next >= m).then_some(Phase::Gate(GateStep::Link))
            }
            GateStep::Link => {
                if !whole(setup, spent) {
                    return None;
                }
                self.cursor = 0;
                match gate::support_begin(n, edges, ws) {
                    Some(kept) => {
                        self.report.gated_loops = kept;
                        Some(Phase::Structure)
                    }
                    None => Some(Phase::Gate(GateStep::Pairs)),
                }
            }
            GateStep::Pairs => {
                let (next, used) = gate::support_pairs(n, edges, ws, chi2, self.cursor, left);
                *spent = spent.saturating_add(used);
                self.cursor = next;
                (next >= n).then_some(Phase::Gate(GateStep::End))
            }
            GateStep::End => {
                if !whole(m as u64 * work::ANALYSIS_ITEM, spent) {
                    return None;
                }
                self.report.gated_loops = gate::support_end(edges, ws);
                self.cursor = 0;
                Some(Phase::Structure)
            }
        }
    }

    /// The start of an iteration's assembly, once the structure is current.
    pub(super) fn assemble_begin(&mut self, ws: &mut SolverBuffers<'_>, spent: &mut u64) {
        let (vars, nnz, warm) = (ws.key.vars, ws.key.nnz, self.gn.warm);
        ws.key.factored = false;
        linearize::assemble_begin(vars, nnz, &mut linearize::System::of(ws, warm));
        *spent = spent.saturating_add(((vars + nnz) / 8) as u64);
        self.begin_sum(Phase::GnAssemble);
    }

    /// Evaluates the next edges of a cost sum into `acc`; true when the sum is complete.
    pub(super) fn cost_chunk(
        &mut self,
        nodes: &[PoseNode],
        edges: &[PoseEdge],
        ws: &SolverBuffers<'_>,
        warm: Warm,
        left: u64,
        spent: &mut u64,
    ) -> bool {
        let m = edges.len();
        let end = chunk_end(self.cursor, m, left, work::EDGE_COST);
        linearize::evaluate_range(
            nodes,
            edges,
            ws.edge_trig,
            nodes.len(),
            warm,
            ws.edge_flags,
            self.cursor..end,
            &mut self.acc,
        );
        *spent = spent.saturating_add((end - self.cursor) as u64 * work::EDGE_COST);
        self.cursor = end;
        end == m
    }
}

/// The end of a chunk of items `from..m` costing `each` units with `left` units left (at least
/// one item, so every call makes progress).
pub(super) fn chunk_end(from: usize, m: usize, left: u64, each: u64) -> usize {
    let items = (left / each.max(1)).max(1);
    from.saturating_add(usize::try_from(items).unwrap_or(usize::MAX))
        .min(m)
}

/// Moves the nodes appended after the solve started rigidly with the prefix's last node,
/// which was at `before` (see the module documentation).
pub(super) fn carry(prefix: &[PoseNode], tail: &mut [PoseNode], before: Option<Se2>) {
    let (Some(before), Some(last)) = (before, prefix.last()) else {
        return;
    };
    if tail.is_empty() || before == last.pose {
        return;
    }
    for node in tail.iter_mut() {
        node.pose = last.pose.compose(&before.between(&node.pose));
    }
}
