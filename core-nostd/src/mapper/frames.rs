//! Frame nodes (the paper's section III-B.3): a keyframe becomes a node of the pose graph.
//!
//! The keyframe decision ([`KeyframeSelector`]) is taken on the front-end pose. The new node
//! enters the graph at the real-time (GPE) pose, tied to the previous node by an odometry edge:
//! the front-end motion between the two, with the covariance the front-end's estimate
//! accumulated between them ([`Spread`]: the motion-uncertainty model fused with the odometry's
//! prediction scan by scan) plus the model's floor. Before that, a pool too full for the node
//! and its edges is pruned (module `pool`); if no room is made the keyframe is dropped and
//! counted.
//!
//! Each node keeps, besides its graph estimate, a [`NodeMeta`]: its serial (stable while graph
//! indices change under pruning), its stamp, front-end pose and travel, and the submap its scan
//! went into. The scan then updates the maps (module `submaps`).

use super::back::{AddNodeError, EdgeFrom, NewEdge};
use super::{Mapper, NO_SUBMAP};
use crate::frontend::lidar::{Spread, Travel};
use crate::frontend::{KeyframeConfig, KeyframeSelector};
use crate::geom::{spd_inverse, Cov3, Info3, Se2};
use crate::graph::EdgeKind;

/// What the mapper remembers about a frame node besides its pose-graph estimate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NodeMeta {
    /// Keyframe number, counting from 0 (stable while the graph's indices are not).
    pub serial: u32,
    /// Time stamp, ns.
    pub stamp: i64,
    /// Front-end pose when the keyframe was taken.
    pub frontend: Se2,
    /// Front-end travel at the keyframe.
    pub travel: Travel,
    /// Submap slot its scan went into.
    pub submap: u16,
}

impl NodeMeta {
    /// Placeholder for storage initialisers.
    pub const EMPTY: NodeMeta = NodeMeta {
        serial: 0,
        stamp: 0,
        frontend: Se2::IDENTITY,
        travel: Travel::ZERO,
        submap: NO_SUBMAP,
    };
}

/// The keyframe decision and the serial of the next frame node.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct FrameState {
    selector: KeyframeSelector,
    next_serial: u32,
    /// Serial of the first frame node of this session (0 for a new map; a session extending
    /// a saved map continues its serials).
    session_first: u32,
    /// The LiDAR front-end's spread when the newest frame node (of any sensor) joined the
    /// graph: the next LiDAR keyframe's odometry edge carries what accumulated since.
    spread_at_newest: Spread,
}

impl FrameState {
    pub(crate) const fn new(keyframe: KeyframeConfig) -> Self {
        FrameState {
            selector: KeyframeSelector::new(keyframe),
            next_serial: 0,
            session_first: 0,
            spread_at_newest: Spread::ZERO,
        }
    }

    /// Starts a session whose first frame node takes `serial`.
    pub(crate) fn start_session(&mut self, serial: u32) {
        self.next_serial = serial;
        self.session_first = serial;
    }

    /// Serial of the first frame node of this session.
    pub(crate) fn session_first(&self) -> u32 {
        self.session_first
    }

    /// Serial the next frame node takes.
    pub(crate) fn next_serial(&self) -> u32 {
        self.next_serial
    }

    /// Whether the front-end pose `pose` is a keyframe, recording it when it is (for keyframes
    /// that make no frame node: localization-only mode).
    pub(crate) fn offer(&mut self, pose: &Se2) -> bool {
        self.selector.offer(pose)
    }

    /// Serial of the newest frame node (0 before the first).
    pub(crate) fn newest_serial(&self) -> u32 {
        self.next_serial.saturating_sub(1)
    }
}

/// How a new frame node is tied to the graph.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Link {
    /// By the front-end motion from the newest node (none for the first node of a map).
    Odometry,
    /// By a match with the saved map: the first node of a session that extends a map, seen
    /// from the map's node `anchor` at `z` with `information`. A plain (not max-mixture)
    /// edge: it is the only link of the session's odometry chain to the map's, which the
    /// back-end's warm start needs to hold the session's nodes in place (module
    /// `solver::gate`); the fix it comes from was confirmed by several keyframes.
    Map {
        anchor: u32,
        z: Se2,
        information: Info3,
    },
}

/// Graph index of the node `serial` among `nodes` (sorted by serial).
pub(crate) fn node_index(nodes: &[NodeMeta], serial: u32) -> Option<usize> {
    nodes.binary_search_by_key(&serial, |m| m.serial).ok()
}

/// Information of a covariance, the identity when it cannot be inverted.
pub(crate) fn fixed_info(cov: &Cov3) -> Info3 {
    spd_inverse(cov).unwrap_or_else(Info3::identity)
}

impl Mapper<'_> {
    /// Adds the frame node `meta` (its serial the next one) at `global` with `edge` to the
    /// graph, pruning first when the pools are nearly full; its serial, or `None` (counted)
    /// when no room was made. Whatever sensor made the keyframe, a node joins the graph here.
    pub(crate) fn join_graph(
        &mut self,
        global: &Se2,
        mut meta: NodeMeta,
        edge: Option<NewEdge>,
    ) -> Option<u32> {
        // A detached back-end answers later: the request goes out early enough.
        let per_node = 1 + usize::from(self.cfg.loops.max_candidates);
        if self
            .back
            .ahead(self.st.mirror.counts, per_node)
            .nearly_full()
        {
            self.prune_pool();
        }
        // The edge joins the newest node, or the map's node, as they are after the pruning.
        let serial = self.st.frames.next_serial;
        meta.serial = serial;
        match self.back.add_frame_node(*global, meta, edge) {
            Ok(()) => {}
            Err(AddNodeError::Unlinked | AddNodeError::Full) => {
                self.st.stats.keyframes_dropped += 1;
                return None;
            }
        }
        self.st.frames.next_serial += 1;
        self.st.frames.spread_at_newest = self.st.frontend.spread();
        self.st.stats.keyframes += 1;
        Some(serial)
    }

    /// Makes the scan at front-end pose `pose` a frame node when it is a keyframe; its serial
    /// when one was made.
    pub(crate) fn keyframe(&mut self, stamp: i64, pose: &Se2, global: &Se2) -> Option<u32> {
        if !self.st.frames.selector.is_keyframe(pose) {
            return None;
        }
        let serial = self.add_frame_node(stamp, pose, global, Link::Odometry)?;
        self.st.frames.selector.accept(*pose);
        Some(serial)
    }

    /// Adds a frame node at `global` tied by `link`, then updates the maps; `None` when a pool
    /// is full.
    pub(crate) fn add_frame_node(
        &mut self,
        stamp: i64,
        pose: &Se2,
        global: &Se2,
        link: Link,
    ) -> Option<u32> {
        let travel = self.st.frontend.travel();
        let spread = self.st.frontend.spread();
        let edge = match link {
            Link::Odometry => self.newest_node().map(|prev| {
                let prev = prev.tie;
                let grown = spread.since_in(&self.st.frames.spread_at_newest, prev.frontend.theta);
                let cov = self.cfg.noise.covariance(0.0, 0.0) + grown;
                NewEdge {
                    from: EdgeFrom::Newest,
                    z: prev.frontend.between(pose),
                    information: fixed_info(&cov),
                    kind: EdgeKind::Odometry,
                }
            }),
            Link::Map {
                anchor,
                z,
                information,
            } => Some(NewEdge {
                from: EdgeFrom::Keyframe(anchor),
                z,
                information,
                kind: EdgeKind::Loop,
            }),
        };
        let meta = NodeMeta {
            serial: self.st.frames.next_serial,
            stamp,
            frontend: *pose,
            travel,
            submap: NO_SUBMAP,
        };
        let serial = self.join_graph(global, meta, edge)?;
        let submap = self.submap_for(serial, pose);
        if let Some(slot) = submap {
            let opens =
                (self.submaps.get(slot as usize)).is_some_and(|m| m.anchor_serial == serial);
            self.back.set_submap(serial, slot, opens);
        }
        self.refresh_mirror();
        if let Some(slot) = submap {
            self.insert_into_submap(slot, pose);
        }
        self.update_local_map(pose, &travel);
        Some(serial)
    }
}
