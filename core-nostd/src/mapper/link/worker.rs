//! The back-end's end of a detached mapper (module `link`): the worker applies the real-time
//! part's messages, steps the optimizer and reports the estimates the real-time part mirrors.

use super::{BackState, ToBack, ToRealTime, CHUNK, LINK_MAX_SUBMAPS, NO_ANCHOR};
use crate::backend::schedule::BackendStep;
use crate::mapper::back::BackEnd;
use crate::mapper::MapperConfig;
use heapless::spsc::{Consumer, Producer};

/// The back-end of a detached mapper (module `link`): step it from any thread
/// with [`BackendWorker::step`], give it back with
/// [`Mapper::attach_backend`](crate::mapper::Mapper::attach_backend).
pub struct BackendWorker<'q> {
    pub(super) back: BackEnd<'q>,
    pub(super) cfg: MapperConfig,
    pub(super) rx: Consumer<'q, ToBack>,
    pub(super) tx: Producer<'q, ToRealTime>,
    /// Anchor serial per submap slot.
    pub(super) watch: heapless::Vec<u32, LINK_MAX_SUBMAPS>,
    /// The GPE's anchor the last finished optimization chose.
    pub(super) chosen: Option<u32>,
    pub(super) pinned: Option<u32>,
    pub(super) state: BackState,
    /// The next anchor chunk to send and how many are still due since the estimates changed.
    pub(super) cursor: usize,
    pub(super) due: usize,
    /// The report changed since it was last sent.
    pub(super) dirty: bool,
}

impl core::fmt::Debug for BackendWorker<'_> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("BackendWorker")
            .field("nodes", &self.back.graph().node_count())
            .field("edges", &self.back.graph().edge_count())
            .finish()
    }
}

impl BackendWorker<'_> {
    /// Takes the real-time part's messages, then runs one step of the due optimization (at
    /// most `config.backend.work_budget` work units, solves of at most `iterations`
    /// Gauss-Newton iterations), or else of the consistency tests in progress, and reports
    /// what changed. `Idle` when there was nothing to do at all.
    pub fn step(&mut self, iterations: u32) -> BackendStep {
        let took = self.take_messages();
        let step = self.back.step(&self.cfg, iterations);
        // The consistency tests take the turns the optimizer leaves; they move no estimate.
        let tested = step == BackendStep::Idle && self.back.step_round(&self.cfg);
        if step == BackendStep::Finished {
            self.chosen = self.back.choose_anchor(&self.cfg.noise);
            let newest = self.back.newest().and_then(|i| self.back.meta(i));
            self.state.optimized_newest = newest.map(|m| m.serial);
        }
        if step != BackendStep::Idle {
            self.estimates_changed();
        }
        let idle = step == BackendStep::Idle && !took && !tested;
        self.dirty |= idle != self.state.idle;
        self.state.idle = idle;
        self.publish();
        match step {
            BackendStep::Idle if took || tested || self.due > 0 || self.dirty => {
                BackendStep::Working
            }
            s => s,
        }
    }

    /// Takes the real-time part's messages and reports, without a step of the optimizer
    /// (for a back-end held back on purpose, which must still take the frame nodes: the
    /// queue would fill otherwise); whether there was any.
    pub fn receive(&mut self) -> bool {
        let took = self.take_messages();
        self.publish();
        took
    }

    /// Applies every waiting message; whether there was any.
    pub(super) fn take_messages(&mut self) -> bool {
        let mut took = false;
        while let Some(message) = self.rx.dequeue() {
            took = true;
            self.dirty = true;
            self.apply(message);
        }
        took
    }

    fn apply(&mut self, message: ToBack) {
        let s = &mut self.state;
        match message {
            ToBack::AddNode { global, meta, edge } => {
                s.applied.nodes += 1;
                s.applied.edges += u64::from(edge.is_some());
                if self.back.add_frame_node(global, meta, edge).is_err() {
                    s.refused_nodes += 1;
                }
            }
            ToBack::SetSubmap {
                serial,
                slot,
                opens,
            } => {
                self.back.set_submap(serial, slot);
                if let Some(w) = self.watch.get_mut(slot as usize).filter(|_| opens) {
                    *w = serial;
                }
            }
            ToBack::AddLoop {
                anchor,
                serial,
                z,
                info,
                robust,
            } => {
                s.applied.edges += 1;
                if !self.back.add_loop_edge(anchor, serial, z, info, robust) {
                    s.refused_loops += 1;
                }
            }
            ToBack::Optimize => self.back.request_optimization(),
            ToBack::MakeRoom(params) => {
                s.applied.prunes += 1;
                let anchors = self.watch.iter().copied().filter(|&a| a != NO_ANCHOR);
                if let Some(report) = self.back.make_room(&params, anchors.chain(self.chosen)) {
                    s.prunes += 1;
                    s.nodes_pruned += report.eliminated as u32;
                }
                self.estimates_changed();
            }
            ToBack::Rebase { to_session, travel } => {
                self.back.rebase(to_session, travel);
                self.estimates_changed();
            }
            ToBack::Pin(serial) => self.pinned = serial,
        }
    }

    /// Every anchor estimate is due again.
    fn estimates_changed(&mut self) {
        self.due = self.watch.len().div_ceil(CHUNK);
        self.dirty = true;
    }

    /// Sends the due anchor chunks and the state, as far as the queue takes them (the rest at
    /// the next step).
    fn publish(&mut self) {
        let chunks = self.watch.len().div_ceil(CHUNK);
        // One place is kept for the state, which the real-time part needs most.
        while self.due > 0 && self.tx.len() + 2 <= self.tx.capacity() {
            let first = self.cursor * CHUNK;
            let anchors = self
                .watch
                .iter()
                .skip(first)
                .take(CHUNK)
                .map(|&serial| (serial, self.back.pose_of(serial)))
                .collect();
            let message = ToRealTime::Anchors {
                first: first as u16,
                anchors,
            };
            if self.tx.enqueue(message).is_err() {
                break;
            }
            self.cursor = (self.cursor + 1) % chunks.max(1);
            self.due -= 1;
        }
        if !self.dirty {
            return;
        }
        let back = &self.back;
        let s = &mut self.state;
        s.newest = back.newest().and_then(|i| back.mirrored(i));
        s.anchor = (self.chosen)
            .and_then(|a| back.node_of(a))
            .and_then(|i| back.mirrored(i));
        s.pinned = self.pinned.map(|p| (p, back.pose_of(p)));
        s.counts = back.counts();
        s.counters = back.counters();
        if self.tx.enqueue(ToRealTime::State(*s)).is_ok() {
            self.dirty = false;
        }
    }
}
