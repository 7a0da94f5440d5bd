//! Multi-session mapping: a new session that extends a saved map.
//!
//! The session starts as localization-only mode does (module `localize`): the map is frozen
//! and the robot is found in it, from a given pose or by global localization. The first
//! confirmed fix **joins** the session to the map, and from that keyframe on the mapper maps
//! as in a new map (the stages of Fig. 2): frame nodes, submaps, loop and far searches and
//! the back-end, over the old graph and the new nodes together, so the old map is corrected
//! by what this session sees and pruning keeps the whole bounded by area.
//!
//! **The first node.** The fix's keyframe becomes a frame node at the fix, tied not to the
//! previous node (there is none in this session) but to the map: an edge from the anchor of
//! the submap nearest to it, measuring the fix as seen from that anchor, with the information
//! of the map match (world axes, with the loop matches' floor added). It is a plain edge, not
//! a max-mixture loop: as the only link between the session's odometry chain and the map's it
//! must hold in the back-end's warm start (which uses only loops the odometry chain predicts,
//! and none between two chains); the fix was confirmed by several keyframes before. The loops
//! this session then closes with the map's submaps are ordinary max-mixture loops, admitted
//! once consistent with the map.
//!
//! **One front-end frame.** The map's front-end poses and travels (of its nodes and submap
//! anchors) were measured in another session's odometry frame, and the stages compare them
//! with this session's: loop windows grow with the travel since a submap's anchor, the local
//! map refills from the newest submaps by their front-end poses, the GPE's anchor is chosen by
//! the travel between nodes. At the join the map is re-expressed in this session's frame as
//! if it had been seen at the fix: a node's front-end pose becomes its optimized pose carried
//! by the transform that takes the fix to the keyframe's front-end pose, and its travel the
//! travel at the join. The motion model then says what holds: relative to the map, the
//! uncertainty starts at the fix.

use super::super::frames::Link;
use super::super::{Mapper, MapperConfig, MapperError, MapperParts};
use crate::geom::{information_in_frame_of, spd_inverse, Info3, Se2};

impl<'r> MapperParts<'r> {
    /// Starts a session that extends the map these parts hold (read with
    /// [`MapReader::read_into_parts`](crate::mapper::mapfile::MapReader::read_into_parts)):
    /// localizing from `initial` (the robot's pose in the map) or by global localization, then
    /// mapping from the first fix on (see the module documentation). The local map, scan,
    /// odometry history and small state start empty; the frame nodes continue the map's
    /// serials.
    ///
    /// # Errors
    /// As [`MapperParts::start`].
    pub fn extend(
        self,
        config: MapperConfig,
        initial: Option<Se2>,
    ) -> Result<Mapper<'r>, MapperError> {
        self.start_in_map(config, initial, true)
    }
}

impl Mapper<'_> {
    /// Serial of the first frame node of this session when it extends a saved map and has
    /// joined it; `None` for a new map, in localization-only mode, or before the first fix.
    pub fn session_first_serial(&self) -> Option<u32> {
        self.st
            .localize
            .as_ref()
            .filter(|l| l.joined)
            .map(|_| self.st.frames.session_first())
    }

    /// Joins the session to the map at the keyframe just fixed: front-end pose `frontend`,
    /// world pose `fix` from a match with `information` over world-axis steps.
    pub(super) fn join_map(&mut self, stamp: i64, frontend: &Se2, fix: &Se2, information: &Info3) {
        let Some(l) = self.st.localize.as_mut() else {
            return;
        };
        l.joined = true;
        self.rebase_map(frontend, fix);
        let travel = self.st.frontend.travel();
        self.st.loops.at_loop = travel;
        // The anchor of the in-use submap nearest to the fix: the match was made with the
        // submaps around it.
        let anchor = self
            .submaps
            .iter()
            .filter(|m| m.in_use)
            .filter_map(|m| Some((m.anchor_serial, m.anchor_estimate?)))
            .min_by(|a, b| {
                let da = libm::hypot(a.1.x - fix.x, a.1.y - fix.y);
                let db = libm::hypot(b.1.x - fix.x, b.1.y - fix.y);
                da.total_cmp(&db)
            });
        let Some((anchor, at)) = anchor else {
            return;
        };
        let [sxy, sth] = self.cfg.loops.min_sigma;
        let Some(mut cov) = spd_inverse(information) else {
            return;
        };
        cov[(0, 0)] += sxy * sxy;
        cov[(1, 1)] += sxy * sxy;
        cov[(2, 2)] += sth * sth;
        let Some(world) = spd_inverse(&cov) else {
            return;
        };
        let link = Link::Map {
            anchor,
            z: at.between(fix),
            information: information_in_frame_of(&world, fix),
        };
        // The keyframe decision already took this front-end pose (localization offers every
        // keyframe to the selector).
        let _ = self.add_frame_node(stamp, frontend, fix, link);
    }

    /// Re-expresses the map's front-end poses and travels in this session's front-end frame,
    /// as seen at the fix `fix` of the keyframe at front-end pose `frontend`.
    fn rebase_map(&mut self, frontend: &Se2, fix: &Se2) {
        let to_session = frontend.compose(&fix.inverse());
        let travel = self.st.frontend.travel();
        self.back.rebase(to_session, travel);
        for s in self.submaps.iter_mut().filter(|s| s.in_use) {
            let Some(pose) = s.anchor_estimate else {
                continue;
            };
            s.anchor_frontend = to_session.compose(&pose);
            s.anchor_travel = travel;
        }
        self.refresh_mirror();
    }
}
