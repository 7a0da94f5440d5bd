//! Detaching the back-end from the mapper and attaching it again, and the real-time part's
//! side of the reports (module `link`).

use super::NO_ANCHOR;
use super::{Applied, BackLink, BackState, BackendWorker, LinkQueues, Remote, ToBack, ToRealTime};
use crate::graph::PoseGraph;
use crate::mapper::{Mapper, MapperError, MapperStats};

impl<'r> Mapper<'r> {
    /// Moves the back-end into a [`BackendWorker`] that another thread steps, the two joined
    /// by `queues` (see the module documentation); give it back with
    /// [`Mapper::attach_backend`]. While detached, [`Mapper::step_backend`] does nothing and
    /// the graph reads as empty here; run the far loop search with
    /// [`Mapper::step_far_search`].
    ///
    /// # Errors
    /// [`MapperError::Config`] when the mapper is localizing (its map is frozen, there is no
    /// back-end work), is already detached, or has more than [`LINK_MAX_SUBMAPS`](super::LINK_MAX_SUBMAPS) submap
    /// slots; then nothing changed.
    pub fn detach_backend(
        &mut self,
        queues: &'r mut LinkQueues,
    ) -> Result<BackendWorker<'r>, MapperError> {
        if self.localizing() || matches!(self.back, BackLink::Remote(_)) {
            return Err(MapperError::Config("no back-end to detach"));
        }
        let mut watch = heapless::Vec::new();
        for m in self.submaps.iter() {
            let anchor = if m.in_use { m.anchor_serial } else { NO_ANCHOR };
            if watch.push(anchor).is_err() {
                return Err(MapperError::Config("too many submap slots to detach"));
            }
        }
        let (to_back, from_real_time) = queues.to_back.split();
        let (to_real_time, from_back) = queues.to_real_time.split();
        let mirror = self.st.mirror;
        let state = BackState {
            newest: mirror.newest,
            anchor: mirror.anchor,
            pinned: mirror.pinned,
            counts: self.back.counts(),
            counters: self.back.counters(),
            ..BackState::default()
        };
        let remote = Remote {
            tx: to_back,
            rx: from_back,
            empty: PoseGraph::new(&mut [], &mut []),
            sent: Applied::default(),
            state,
            newest: mirror.newest,
            pin: self.st.far.pinned_serial(),
            overflows: 0,
        };
        let BackLink::Local(back) = core::mem::replace(&mut self.back, BackLink::Remote(remote))
        else {
            return Err(MapperError::Config("no back-end to detach"));
        };
        Ok(BackendWorker {
            back,
            cfg: self.cfg,
            rx: from_real_time,
            tx: to_real_time,
            watch,
            chosen: self.st.gpe.anchor(),
            pinned: self.st.far.pinned_serial(),
            state,
            cursor: 0,
            due: 0,
            dirty: false,
        })
    }

    /// Takes the back-end back from `worker` after the last message was applied and
    /// reported, and mirrors its estimates again; the mapper interleaves from here on.
    pub fn attach_backend(&mut self, mut worker: BackendWorker<'r>) {
        worker.take_messages();
        self.take_reports();
        let BackLink::Remote(remote) = &self.back else {
            return;
        };
        let (seen, overflows) = (remote.state, remote.overflows);
        self.back = BackLink::Local(worker.back);
        count_reported(&mut self.st.stats, &seen, &worker.state);
        self.st.stats.link_overflows += overflows;
        if worker.chosen != self.st.gpe.anchor() {
            self.st.gpe.set_anchor(worker.chosen);
        }
        self.refresh_mirror();
    }

    /// Messages waiting for the detached back-end (0 when interleaved): a caller that
    /// produces frames faster than the worker takes them waits while this is high.
    pub fn backend_backlog(&self) -> usize {
        match &self.back {
            BackLink::Local(_) => 0,
            BackLink::Remote(r) => r.backlog(),
        }
    }

    /// Keyframes sent to the detached back-end since the newest one its last finished
    /// optimization held, and whether it was idle at its last report; `None` when
    /// interleaved.
    pub fn backend_lag(&self) -> Option<(u32, bool)> {
        let BackLink::Remote(r) = &self.back else {
            return None;
        };
        let sent = r.newest.map_or(0, |n| n.serial + 1);
        let held = r.state.optimized_newest.map_or(0, |s| s + 1);
        Some((sent.saturating_sub(held), r.state.idle && r.backlog() == 0))
    }

    /// Applies the detached back-end's reports to the mirror (module `mirror`).
    pub(crate) fn take_reports(&mut self) {
        let BackLink::Remote(remote) = &mut self.back else {
            return;
        };
        let pin = self.st.far.pinned_serial();
        if pin != remote.pin && remote.send(ToBack::Pin(pin)) {
            remote.pin = pin;
        }
        let before = remote.state;
        while let Some(report) = remote.rx.dequeue() {
            match report {
                ToRealTime::Anchors { first, anchors } => {
                    let slots = self.submaps.iter_mut().skip(first as usize);
                    for (m, (serial, estimate)) in slots.zip(anchors) {
                        if m.in_use && m.anchor_serial == serial && estimate.is_some() {
                            m.anchor_estimate = estimate;
                        }
                    }
                }
                ToRealTime::State(s) => remote.state = s,
            }
        }
        let s = remote.state;
        let mirror = &mut self.st.mirror;
        // The newest node sent may not have reached the graph yet.
        mirror.newest = match (remote.newest, s.newest) {
            (Some(sent), Some(seen)) if seen.serial >= sent.serial => Some(seen),
            (sent, seen) => sent.or(seen),
        };
        if s.anchor.map(|a| a.serial) != before.anchor.map(|a| a.serial) {
            self.st.gpe.set_anchor(s.anchor.map(|a| a.serial));
        }
        mirror.anchor = s.anchor;
        if let (Some(p), Some(seen)) = (mirror.pinned.as_mut(), s.pinned) {
            if p.0 == seen.0 && seen.1.is_some() {
                *p = seen;
            }
        }
        mirror.counts = self.back.counts();
        count_reported(&mut self.st.stats, &before, &s);
        // A submap opened by a node the worker has not reported yet lies where it was sent.
        if let Some(newest) = mirror.newest {
            for m in self.submaps.iter_mut() {
                if m.in_use && m.anchor_estimate.is_none() && m.anchor_serial == newest.serial {
                    m.anchor_estimate = Some(newest.tie.estimate);
                }
            }
        }
    }
}

/// Adds to `stats` what the worker counted between its reports `before` and `after`: the
/// prunings, and the frame nodes and loop edges the graph refused (counted as sent before).
fn count_reported(stats: &mut MapperStats, before: &BackState, after: &BackState) {
    stats.prunes += after.prunes.saturating_sub(before.prunes);
    stats.nodes_pruned += after.nodes_pruned.saturating_sub(before.nodes_pruned);
    stats.keyframes_dropped += after.refused_nodes.saturating_sub(before.refused_nodes);
    let refused = after.refused_loops.saturating_sub(before.refused_loops);
    stats.loop_closures = stats.loop_closures.saturating_sub(refused);
}
