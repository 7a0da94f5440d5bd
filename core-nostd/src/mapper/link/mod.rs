//! The real-time part and the back-end (blocks (a)-(b) and (c) of the paper's Fig. 2, sections
//! III-C and III-D) joined either directly or by two fixed-capacity queues.
//!
//! The paper's real-time part never waits for the optimizer: the GPE carries the pose between
//! optimizations from the newest node and the last anchor (eq. 2-3). The mapper reaches its
//! back-end through [`BackLink`]:
//! * **interleaved** ([`BackLink::Local`]): every call reaches the back-end at once and the
//!   caller steps it between frames ([`Mapper::step_backend`]). The firmware and the host's
//!   deterministic schedule run this way; results do not depend on timing.
//! * **detached** ([`Mapper::detach_backend`]): the back-end moves into a [`BackendWorker`]
//!   that another thread steps, and the two sides exchange messages over [`LinkQueues`]
//!   (single-producer single-consumer, no lock, no heap). The real-time part sends frame
//!   nodes, submap assignments, loop edges, requests for an optimization, for room in a full
//!   pool and for a rebase; the worker answers with the estimates the real-time part mirrors
//!   (module `mirror`): the newest node, the GPE's anchor it chose, the pinned node of a far
//!   hypothesis and every submap's anchor, with the graph's sizes and its counters. The
//!   far loop search, which reads the submaps' cells, stays with the real-time part and runs
//!   in its spare time ([`Mapper::step_far_search`]).
//!
//! Nothing waits on the other side. The real-time part decides from the graph's sizes as
//! last reported plus the nodes and edges it sent since whether a frame node fits, so the
//! worker refuses none for want of room; a request for room is answered later (the keyframes
//! meanwhile are dropped and counted when the pool is full). The worker's report is
//! cumulative, so a report that did not fit the queue is simply superseded by the next one.

use super::back::{AddNodeError, BackEnd, GraphCounts, NewEdge};
use super::frames::NodeMeta;
use super::mirror::MirroredNode;
use crate::backend::prune::PruneReport;
use crate::backend::schedule::{BackendCounters, PoolPruning};
use crate::frontend::lidar::Travel;
use crate::geom::{Info3, Se2};
use crate::gpe::NodeTie;
use crate::graph::{PoseGraph, RobustKernel};
use heapless::spsc::{Consumer, Producer, Queue};

mod detach;
mod worker;

pub use worker::BackendWorker;

/// Messages each queue holds.
pub const LINK_CAPACITY: usize = 128;
/// Most submap slots a detached mapper can have (the worker keeps each slot's anchor serial).
pub const LINK_MAX_SUBMAPS: usize = 2048;
/// Submap anchors per estimate message.
const CHUNK: usize = 8;
/// Frame nodes a detached back-end may receive before it answers a request for room: the
/// request goes out this many nodes early (each with its edge and its loop search's).
const ROOM_AHEAD: usize = 4;
/// A slot without an anchor.
const NO_ANCHOR: u32 = u32::MAX;

/// What the real-time part asks of the back-end.
#[derive(Clone, Copy, Debug)]
pub(crate) enum ToBack {
    /// A frame node and the edge that ties it to the graph.
    AddNode {
        global: Se2,
        meta: NodeMeta,
        edge: Option<NewEdge>,
    },
    /// Keyframe `serial`'s scan went into submap `slot`; `opens` when the keyframe opened it
    /// (it is the slot's anchor from now on).
    SetSubmap { serial: u32, slot: u16, opens: bool },
    /// A loop edge between two keyframes.
    AddLoop {
        anchor: u32,
        serial: u32,
        z: Se2,
        info: Info3,
        robust: RobustKernel,
    },
    /// An optimization at the next step.
    Optimize,
    /// Prune to make room in the pools.
    MakeRoom(PoolPruning),
    /// Re-express the nodes' front-end poses in another session's front-end frame.
    Rebase { to_session: Se2, travel: Travel },
    /// The node a far hypothesis pins (its estimate is reported while pinned).
    Pin(Option<u32>),
}

/// What the back-end reports to the real-time part.
#[derive(Clone, Debug)]
pub(crate) enum ToRealTime {
    /// Estimates of the anchors of the submap slots from `first` on: (anchor serial, estimate).
    Anchors {
        first: u16,
        anchors: heapless::Vec<(u32, Option<Se2>), CHUNK>,
    },
    /// The back-end's state as of its last step (cumulative: the newest one supersedes all).
    State(BackState),
}

/// Messages the back-end has taken off its queue, by effect.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct Applied {
    /// Frame nodes (added or refused).
    pub(crate) nodes: u64,
    /// Edges the frame nodes and loop messages carried (added or refused).
    pub(crate) edges: u64,
    /// Requests for room answered.
    pub(crate) prunes: u32,
}

/// The back-end's cumulative report.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct BackState {
    pub(crate) newest: Option<MirroredNode>,
    /// The GPE's anchor chosen by the last finished optimization, with its estimate.
    pub(crate) anchor: Option<MirroredNode>,
    /// The pinned node's serial and estimate.
    pub(crate) pinned: Option<(u32, Option<Se2>)>,
    pub(crate) counts: GraphCounts,
    pub(crate) counters: BackendCounters,
    pub(crate) applied: Applied,
    /// Frame nodes and loop edges the graph refused.
    pub(crate) refused_nodes: u32,
    pub(crate) refused_loops: u32,
    /// Prunings that removed nodes, and the nodes removed.
    pub(crate) prunes: u32,
    pub(crate) nodes_pruned: u32,
    /// The newest node when the last optimization finished.
    pub(crate) optimized_newest: Option<u32>,
    /// The last step found nothing to do.
    pub(crate) idle: bool,
}

/// Storage of the two queues of a detached mapper (about 110 KiB; the host allocates it, the
/// firmware interleaves and needs none).
pub struct LinkQueues {
    to_back: Queue<ToBack, LINK_CAPACITY>,
    to_real_time: Queue<ToRealTime, LINK_CAPACITY>,
}

impl LinkQueues {
    /// Two empty queues.
    pub const fn new() -> Self {
        LinkQueues {
            to_back: Queue::new(),
            to_real_time: Queue::new(),
        }
    }
}

impl Default for LinkQueues {
    fn default() -> Self {
        Self::new()
    }
}

impl core::fmt::Debug for LinkQueues {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("LinkQueues")
            .field("to_back", &self.to_back.len())
            .field("to_real_time", &self.to_real_time.len())
            .finish()
    }
}

/// The real-time part's end of a detached back-end.
pub(crate) struct Remote<'q> {
    tx: Producer<'q, ToBack>,
    rx: Consumer<'q, ToRealTime>,
    /// Stands in for the graph while the worker holds it.
    empty: PoseGraph<'q>,
    /// Messages sent, by effect (compared with the worker's [`Applied`]).
    sent: Applied,
    /// The worker's last report.
    state: BackState,
    /// The newest frame node sent.
    newest: Option<MirroredNode>,
    /// The pinned serial last sent.
    pin: Option<u32>,
    /// Messages the full queue refused.
    pub(crate) overflows: u32,
}

/// How the mapper reaches its back-end (see the module documentation).
pub(crate) enum BackLink<'r> {
    /// In the same thread: every call at once.
    Local(BackEnd<'r>),
    /// In a [`BackendWorker`], through queues.
    Remote(Remote<'r>),
}

impl<'r> BackLink<'r> {
    /// The pose graph; empty while detached.
    pub(crate) fn graph(&self) -> &PoseGraph<'r> {
        match self {
            BackLink::Local(b) => b.graph(),
            BackLink::Remote(r) => &r.empty,
        }
    }

    /// Metadata of the graph's nodes; empty while detached.
    pub(crate) fn nodes(&self) -> &[NodeMeta] {
        match self {
            BackLink::Local(b) => b.nodes(),
            BackLink::Remote(_) => &[],
        }
    }

    /// Graph index of keyframe `serial`; `None` while detached.
    pub(crate) fn node_of(&self, serial: u32) -> Option<usize> {
        match self {
            BackLink::Local(b) => b.node_of(serial),
            BackLink::Remote(_) => None,
        }
    }

    /// The back-end's estimate of keyframe `serial`; `None` while detached.
    pub(crate) fn pose_of(&self, serial: u32) -> Option<Se2> {
        match self {
            BackLink::Local(b) => b.pose_of(serial),
            BackLink::Remote(_) => None,
        }
    }

    /// The graph's sizes: exact when interleaved; when detached, as last reported plus what
    /// was sent since (never less than the truth).
    pub(crate) fn counts(&self) -> GraphCounts {
        match self {
            BackLink::Local(b) => b.counts(),
            BackLink::Remote(r) => {
                let c = r.state.counts;
                let a = r.state.applied;
                GraphCounts {
                    nodes: c.nodes + r.sent.nodes.saturating_sub(a.nodes) as usize,
                    edges: c.edges + r.sent.edges.saturating_sub(a.edges) as usize,
                    ..c
                }
            }
        }
    }

    /// `counts` as the pool may be when a request for room made now is answered: unchanged
    /// when interleaved (the answer is immediate); [`ROOM_AHEAD`] frame nodes later, each
    /// with `edges_per_node` edges, when detached.
    pub(crate) fn ahead(&self, counts: GraphCounts, edges_per_node: usize) -> GraphCounts {
        match self {
            BackLink::Local(_) => counts,
            BackLink::Remote(_) => GraphCounts {
                nodes: counts.nodes + ROOM_AHEAD,
                edges: counts.edges + ROOM_AHEAD * edges_per_node,
                ..counts
            },
        }
    }

    /// The schedule's counters (as last reported when detached).
    pub(crate) fn counters(&self) -> BackendCounters {
        match self {
            BackLink::Local(b) => b.counters(),
            BackLink::Remote(r) => r.state.counters,
        }
    }

    /// See [`BackEnd::add_frame_node`]. Detached, a node that does not fit is refused here
    /// and one that does is sent (and mirrored as the newest node).
    pub(crate) fn add_frame_node(
        &mut self,
        global: Se2,
        meta: NodeMeta,
        edge: Option<NewEdge>,
    ) -> Result<(), AddNodeError> {
        let counts = self.counts();
        match self {
            BackLink::Local(b) => b.add_frame_node(global, meta, edge),
            BackLink::Remote(r) => {
                if !counts.has_room(edge.is_some()) {
                    return Err(AddNodeError::Full);
                }
                if !r.send(ToBack::AddNode { global, meta, edge }) {
                    return Err(AddNodeError::Full);
                }
                r.sent.nodes += 1;
                r.sent.edges += u64::from(edge.is_some());
                r.newest = Some(MirroredNode {
                    serial: meta.serial,
                    tie: NodeTie {
                        estimate: global,
                        frontend: meta.frontend,
                        travel: meta.travel,
                    },
                });
                Ok(())
            }
        }
    }

    /// See [`BackEnd::set_submap`]; `opens` when the keyframe is the submap's anchor.
    pub(crate) fn set_submap(&mut self, serial: u32, slot: u16, opens: bool) {
        match self {
            BackLink::Local(b) => b.set_submap(serial, slot),
            BackLink::Remote(r) => {
                r.send(ToBack::SetSubmap {
                    serial,
                    slot,
                    opens,
                });
            }
        }
    }

    /// See [`BackEnd::add_loop_edge`]; detached, whether it was sent.
    pub(crate) fn add_loop_edge(
        &mut self,
        anchor: u32,
        serial: u32,
        z: Se2,
        info: Info3,
        robust: RobustKernel,
    ) -> bool {
        let counts = self.counts();
        match self {
            BackLink::Local(b) => b.add_loop_edge(anchor, serial, z, info, robust),
            BackLink::Remote(r) => {
                let message = ToBack::AddLoop {
                    anchor,
                    serial,
                    z,
                    info,
                    robust,
                };
                let sent = counts.edges < counts.edge_capacity && r.send(message);
                r.sent.edges += u64::from(sent);
                sent
            }
        }
    }

    /// See [`BackEnd::request_optimization`].
    pub(crate) fn request_optimization(&mut self) {
        match self {
            BackLink::Local(b) => b.request_optimization(),
            BackLink::Remote(r) => {
                r.send(ToBack::Optimize);
            }
        }
    }

    /// See [`BackEnd::make_room`]. Detached, the request is sent (once until it is answered)
    /// and the pruning is counted when the worker reports it, so this returns `None`.
    pub(crate) fn make_room(
        &mut self,
        params: &PoolPruning,
        protected: impl IntoIterator<Item = u32>,
    ) -> Option<PruneReport> {
        match self {
            BackLink::Local(b) => b.make_room(params, protected),
            BackLink::Remote(r) => {
                if r.sent.prunes == r.state.applied.prunes && r.send(ToBack::MakeRoom(*params)) {
                    r.sent.prunes += 1;
                }
                None
            }
        }
    }

    /// See [`BackEnd::rebase`].
    pub(crate) fn rebase(&mut self, to_session: Se2, travel: Travel) {
        match self {
            BackLink::Local(b) => b.rebase(to_session, travel),
            BackLink::Remote(r) => {
                r.send(ToBack::Rebase { to_session, travel });
            }
        }
    }
}

impl Remote<'_> {
    /// Queues `message`; false (counted) when the queue is full.
    fn send(&mut self, message: ToBack) -> bool {
        let sent = self.tx.enqueue(message).is_ok();
        self.overflows += u32::from(!sent);
        sent
    }

    /// Messages waiting for the worker.
    pub(crate) fn backlog(&self) -> usize {
        self.tx.len()
    }
}
