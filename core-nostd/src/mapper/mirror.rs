//! The real-time part's copy of the back-end's estimates (the GPE's inputs of section III-C and
//! the submap poses the loop searches of section III-B.2 start from).
//!
//! The real-time part needs the estimates of three kinds of node only: the newest frame node
//! (the GPE's reference, and the keyframe the loop searches place), the GPE's anchor, and the
//! anchor of each submap (the submap's world pose). It keeps them here and in
//! [`SubmapMeta::anchor_estimate`](super::SubmapMeta::anchor_estimate), so its memory and its
//! refresh are bounded by the number of submap slots, not by the graph's nodes. One more node
//! is pinned while a far hypothesis waits for confirmation (module `far`): the anchor of its
//! first match, whose submap may be recycled before the following keyframes test it. The copy
//! is refreshed whenever the back-end's estimates or the set of these nodes change: after a
//! back-end step that worked, after a pruning, after a new frame node and after a new anchor.
//! A node outside these has no estimate on the real-time side.
//!
//! With the estimates come the graph's sizes, also refreshed after each loop edge: the
//! real-time part decides from them whether a frame node fits or a pruning is due.

use super::back::GraphCounts;
use super::link::BackLink;
use super::Mapper;
use crate::geom::Se2;
use crate::gpe::NodeTie;

/// A frame node as the real-time part sees it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct MirroredNode {
    /// Keyframe serial.
    pub(crate) serial: u32,
    /// Estimate, front-end pose and travel.
    pub(crate) tie: NodeTie,
}

/// The newest node, the GPE's anchor and the pinned node, as of the last refresh.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct PoseMirror {
    pub(crate) newest: Option<MirroredNode>,
    pub(crate) anchor: Option<MirroredNode>,
    /// The anchor of a far hypothesis' first match (serial and estimate), kept while the
    /// hypothesis lives: its submap may be recycled before the following keyframes test it.
    pub(crate) pinned: Option<(u32, Option<Se2>)>,
    /// The graph's sizes: whether a frame node fits is decided on them.
    pub(crate) counts: GraphCounts,
}

impl PoseMirror {
    /// Nothing mirrored.
    pub(crate) const EMPTY: PoseMirror = PoseMirror {
        newest: None,
        anchor: None,
        pinned: None,
        counts: GraphCounts::ZERO,
    };
}

impl Mapper<'_> {
    /// Copies the estimates the real-time part needs from the back-end.
    pub(crate) fn refresh_mirror(&mut self) {
        let BackLink::Local(back) = &self.back else {
            // Detached: the worker's reports are the copy.
            self.take_reports();
            return;
        };
        let node = |i: usize| back.mirrored(i);
        self.st.mirror = PoseMirror {
            newest: back.newest().and_then(node),
            anchor: self
                .st
                .gpe
                .anchor()
                .and_then(|s| back.node_of(s))
                .and_then(node),
            pinned: (self.st.far).pinned_serial().map(|s| (s, back.pose_of(s))),
            counts: back.counts(),
        };
        for m in self.submaps.iter_mut() {
            m.anchor_estimate = if m.in_use {
                back.pose_of(m.anchor_serial)
            } else {
                None
            };
        }
    }

    /// The newest frame node, as of the last refresh.
    pub(crate) fn newest_node(&self) -> Option<MirroredNode> {
        self.st.mirror.newest
    }

    /// The newest frame node when it is keyframe `serial`.
    pub(crate) fn newest_if(&self, serial: u32) -> Option<MirroredNode> {
        self.st.mirror.newest.filter(|n| n.serial == serial)
    }

    /// The estimate of keyframe `serial` when the real-time part mirrors it (a submap's
    /// anchor, the newest node, the GPE's anchor or the pinned node).
    pub(crate) fn mirrored_pose(&self, serial: u32) -> Option<Se2> {
        self.submaps
            .iter()
            .find(|m| m.in_use && m.anchor_serial == serial)
            .map(|m| m.anchor_estimate)
            .or_else(|| {
                let mirror = &self.st.mirror;
                let nodes = [mirror.newest, mirror.anchor];
                match nodes.into_iter().flatten().find(|n| n.serial == serial) {
                    Some(n) => Some(Some(n.tie.estimate)),
                    None => mirror.pinned.filter(|p| p.0 == serial).map(|p| p.1),
                }
            })
            .flatten()
    }
}
