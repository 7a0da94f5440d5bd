//! The back-end's turns in an interleaved schedule (section III-D's back-end sharing one
//! processor with the real-time part, as on the firmware): the caller gives it steps between
//! frames, and the optimizer and the far loop search take turns in them; the consistency tests
//! of the loop groups take the turns both leave. While the back-end is detached (module
//! `link`) its worker steps the optimizer and the tests, and the real-time part runs the far
//! search.

use super::link::BackLink;
use super::{BackendStep, Mapper};

impl Mapper<'_> {
    /// Asks for an optimization at the next back-end step even without new loop closures (e.g.
    /// to settle the map at the end of a run).
    pub fn request_optimization(&mut self) {
        // A map being localized in stays as it was saved.
        if !self.localizing() {
            self.back.request_optimization();
        }
    }

    /// The back-end's share of one frame in an interleaved schedule: up to
    /// `config.backend.steps_per_frame` steps of [`Mapper::step_backend`], fewer when it has
    /// nothing left to do; the last step that worked (or `Idle`).
    pub fn step_backend_frame(&mut self, iterations: u32) -> BackendStep {
        let mut last = BackendStep::Idle;
        for _ in 0..self.cfg.backend.steps_per_frame.max(1) {
            match self.step_backend(iterations) {
                BackendStep::Idle => break,
                step => last = step,
            }
        }
        last
    }

    /// Runs one back-end step: at most `config.backend.work_budget` work units of the due
    /// optimization, whose solves run at most `iterations` Gauss-Newton iterations each (a
    /// finished optimization chooses the GPE's anchor), or one turn of the far loop search.
    /// `Idle` while the back-end is detached ([`Mapper::detach_backend`]): its worker steps.
    pub fn step_backend(&mut self, iterations: u32) -> BackendStep {
        if matches!(self.back, BackLink::Remote(_)) {
            return BackendStep::Idle;
        }
        // The far loop search and the optimizer share the back-end: while both have work they
        // take turns. Over a known map loops close at nearly every keyframe, so an optimizer
        // that always came first would never leave a turn to the search that finds a place
        // after the windowed search lost it.
        if self.st.far.takes_turn() && self.step_far() {
            return BackendStep::Working;
        }
        let BackLink::Local(back) = &mut self.back else {
            return BackendStep::Idle;
        };
        let step = back.step(&self.cfg, iterations);
        if step == BackendStep::Finished {
            let anchor = back.choose_anchor(&self.cfg.noise);
            self.st.gpe.set_anchor(anchor);
        }
        if step != BackendStep::Idle {
            self.refresh_mirror();
        }
        // The far loop search also takes every turn the optimizer leaves idle, and the
        // consistency tests of the loop groups every turn both leave.
        if step == BackendStep::Idle {
            if self.step_far() {
                return BackendStep::Working;
            }
            if let BackLink::Local(back) = &mut self.back {
                if back.step_round(&self.cfg) {
                    return BackendStep::Working;
                }
            }
        }
        step
    }

    /// One turn of the far loop search (beyond the loop window); whether it did any work. The
    /// back-end's steps run it; while the back-end is detached the real-time part runs it in
    /// its spare time with this call.
    pub fn step_far_search(&mut self) -> bool {
        self.take_reports();
        self.step_far()
    }
}
