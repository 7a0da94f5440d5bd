//! Visual frame nodes: the camera's keyframes as nodes of the pose graph (the paper's section
//! III-B.1 feeding III-B.3, Fig. 3), for a mapper without LiDAR (sensor set C).
//!
//! Each image of camera 0 that the camera stage tracked goes on to the visual odometry
//! ([`VisualOdometry`], III-B.1), with the fused wheel+gyro pose at the image's time as its
//! prior. Nothing here depends on the sensor: a visual keyframe becomes a frame node exactly as
//! a LiDAR keyframe does (module `frames`), the pose graph, the GPE and the back-end do not
//! know which sensor made it.
//!
//! # The camera's front-end pose
//! The LiDAR front-end gives a drifting but locally exact pose per scan; here that role is
//! played by the odometry's own estimate of each keyframe when it is made
//! ([`KeyframeOutput::pose`], in the frame of the first keyframe's wheel+gyro pose, so the
//! odometry's frame). Between keyframes, the wheel+gyro motion since the newest keyframe is
//! composed onto it. The odometry edge between two nodes is the difference of their front-end
//! poses, as for LiDAR keyframes. Chaining only the odometry's keyframe-to-keyframe poses
//! ([`KeyframeOutput::relative`]) instead would drop what each solve corrects in the previous
//! keyframes of its window: the node of keyframe `k - 1` was made before solve `k` moved it.
//! Keeping the odometry's poses carries that correction into the next edge (measured in
//! docs/benchmarks.md, "Sensor set C mapped end to end").
//!
//! # Per image
//! 1. the odometry takes the tracked features (refused frames are counted, the image still
//!    gets a pose from the wheels);
//! 2. the front-end pose as above, and the travel (path length and heading change) since the
//!    last image;
//! 3. the GPE (III-C: eq. 5, or the worst-case prediction of eqs. 6-7) on that pose, as for
//!    a scan;
//! 4. a keyframe of the odometry becomes a frame node at the GPE's pose, tied to the newest
//!    node by an odometry edge whose measurement is the motion between the two keyframes as
//!    the odometry estimated them (the difference of their front-end poses). The odometry
//!    reports no covariance (its window does not expose its reduced system), so the edge's
//!    information is the front-end motion model's over the travel between the two nodes, the
//!    one LiDAR keyframes use.
//!
//! The frame gets no submap and no loop search: there are no scans to grid, and visual loop
//! closure is not implemented yet.
//!
//! Memory: the odometry's storage comes with the camera stage's ([`VisualParts`]), lent by
//! the caller; a mapper without it only tracks images, as before. [`CameraOdometry`] takes
//! at most 1.1 MB (1.05 MB on x86-64, 0.97 MB on 32-bit ARM; a window of [`VO_KEYFRAMES`] keyframes, [`VO_LANDMARKS`] landmarks and
//! [`VO_OBSERVATIONS`] sightings), the same in every profile: it is bounded by what the camera
//! sees at once, not by the area mapped. The profiles' static resources (the LiDAR firmware's)
//! lend no camera storage, so `cloi-budget` does not count it yet.

use super::back::{EdgeFrom, NewEdge};
use super::frames::{fixed_info, NodeMeta};
use super::{FrameOutput, Mapper, NO_SUBMAP};
use crate::frontend::lidar::{MotionNoise, Travel};
use crate::frontend::visual::{
    CameraExtrinsic, CameraModel, KeyframeOutput, VisualOdometry, VoConfig, VoFrame,
};
use crate::geom::Se2;
use crate::gpe::GpeFrame;
use crate::graph::EdgeKind;

/// Keyframes in the visual odometry's sliding window.
pub const VO_KEYFRAMES: usize = 8;
/// Landmarks the window holds.
pub const VO_LANDMARKS: usize = 600;
/// Landmark sightings the window holds.
pub const VO_OBSERVATIONS: usize = 5000;

/// The visual odometry the mapper runs. Its size depends on what one camera sees at once, not
/// on the area mapped, so it is the same in every profile.
pub type CameraOdometry = VisualOdometry<VO_KEYFRAMES, VO_LANDMARKS, VO_OBSERVATIONS>;

/// What the mapper needs to turn camera 0's images into frame nodes: the odometry's storage
/// (lent by the caller) and the camera's calibration.
#[derive(Debug)]
pub struct VisualParts<'r> {
    /// The odometry's storage (large: keep it in a static or on the heap).
    pub odometry: &'r mut CameraOdometry,
    /// The camera's lens.
    pub model: CameraModel,
    /// The camera's mounting on the robot.
    pub mount: CameraExtrinsic,
    /// The odometry's parameters.
    pub config: VoConfig,
    /// The stage's small state (start from [`VisualState::NEW`]).
    pub state: VisualState,
}

/// Counters of the visual frame nodes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct VisualCounters {
    /// Images given a pose.
    pub frames: u32,
    /// Images without a wheel+gyro pose at their time (no pose given).
    pub no_odometry: u32,
    /// Images the odometry refused (posed by the wheels alone).
    pub refused: u32,
    /// Keyframes of the odometry.
    pub keyframes: u32,
    /// Of them, made frame nodes.
    pub nodes: u32,
    /// Keyframes whose window solve failed (their relative pose is the wheel+gyro one).
    pub unsolved: u32,
}

/// The visual front-end's small state.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VisualState {
    /// Newest keyframe: its front-end pose and its wheel+gyro pose.
    keyframe: Option<(Se2, Se2)>,
    /// Previous image: stamp and front-end pose.
    previous: Option<(i64, Se2)>,
    travel: Travel,
    counters: VisualCounters,
}

impl VisualState {
    /// Before the first image.
    pub const NEW: VisualState = VisualState {
        keyframe: None,
        previous: None,
        travel: Travel::ZERO,
        counters: VisualCounters {
            frames: 0,
            no_odometry: 0,
            refused: 0,
            keyframes: 0,
            nodes: 0,
            unsolved: 0,
        },
    };

    /// The counters so far.
    pub fn counters(&self) -> VisualCounters {
        self.counters
    }

    /// The front-end pose of a frame whose wheel+gyro pose is `wheel`: the newest keyframe's
    /// front-end pose with the wheel motion since it, or the wheel pose before any keyframe.
    fn frontend(&self, wheel: &Se2) -> Se2 {
        match self.keyframe {
            Some((front, at)) => front.compose(&at.between(wheel)),
            None => *wheel,
        }
    }

    /// Takes keyframe `k`, made at wheel+gyro pose `wheel`, as the newest and gives its
    /// front-end pose: the odometry's estimate of it (the wheels' guess if that is not finite).
    fn keyframe(&mut self, k: &KeyframeOutput, wheel: &Se2) -> Se2 {
        let front = if k.pose.is_finite() {
            k.pose
        } else {
            self.frontend(wheel)
        };
        self.keyframe = Some((front, *wheel));
        front
    }
}

impl Mapper<'_> {
    /// Camera 0's tracked image at `stamp` (`tracked` of its features matched to the previous
    /// image) through the visual odometry, the GPE and, for a
    /// keyframe, a new frame node; `None` when the mapper runs no visual odometry or has no
    /// wheel+gyro pose at `stamp` (counted).
    pub(crate) fn visual_frame(
        &mut self,
        stamp: i64,
        tracked: usize,
        deadline_passed: bool,
    ) -> Option<FrameOutput> {
        let wheel = self.odometry.pose_at(stamp);
        let cameras = self.cameras.as_mut()?;
        let visual = cameras.visual.as_mut()?;
        let Ok(wheel) = wheel else {
            visual.state.counters.no_odometry += 1;
            return None;
        };
        let newest = cameras.tracks.first().and_then(|t| t.newest());
        let frame = VoFrame {
            stamp,
            odometry: wheel,
            keypoints: newest.map(|f| f.keypoints()).unwrap_or_default(),
            matches: cameras.matches.get(..tracked).unwrap_or_default(),
            descriptors: newest.map(|f| f.descriptors()).unwrap_or_default(),
        };
        let step = (visual.odometry).process(&frame, &visual.model, &visual.mount, &visual.config);
        let st = &mut visual.state;
        st.counters.frames += 1;
        let keyframe = match step {
            Ok(s) => s.keyframe,
            Err(_) => {
                st.counters.refused += 1;
                None
            }
        };
        let front = match &keyframe {
            Some(k) => {
                st.counters.keyframes += 1;
                st.counters.unsolved += u32::from(k.relative.is_some() && k.solve.is_err());
                st.keyframe(k, &wheel)
            }
            None => st.frontend(&wheel),
        };
        let step = st
            .previous
            .map_or(Se2::IDENTITY, |(_, p)| p.between(&front));
        if st.previous.is_some() {
            st.travel.path += libm::hypot(step.x, step.y);
            st.travel.rotation += libm::fabs(step.theta);
        }
        st.previous = Some((stamp, front));
        let travel = st.travel;

        // GPE (III-C) on the camera's front-end pose, as for a scan.
        let mirror = &self.st.mirror;
        let reference = mirror.newest;
        let anchor = mirror
            .anchor
            .filter(|a| reference.is_none_or(|r| r.serial != a.serial));
        let gpe = GpeFrame {
            step,
            frontend: front,
            travel,
            reference: reference.map(|n| n.tie),
            anchor: anchor.map(|n| n.tie),
            deadline_passed,
        };
        let global = self.st.gpe.update(&gpe, &self.cfg.gpe, &self.cfg.noise);
        let mut out = FrameOutput {
            stamp,
            pose: global.pose,
            frontend: front,
            reference_serial: self.st.frames.newest_serial(),
            keyframe: false,
            predicted: global.predicted,
            loops: 0,
            localized: true,
        };
        if keyframe.is_some() {
            if let Some(serial) = self.add_visual_node(stamp, &front, &global.pose, travel) {
                out.keyframe = true;
                out.reference_serial = serial;
            }
        }
        Some(out)
    }

    /// Adds a frame node for the visual keyframe at front-end pose `front`, tied to the newest
    /// node by the front-end motion between them; its serial, or `None` when no room was made.
    fn add_visual_node(
        &mut self,
        stamp: i64,
        front: &Se2,
        global: &Se2,
        travel: Travel,
    ) -> Option<u32> {
        let edge = self.newest_node().map(|prev| {
            let prev = prev.tie;
            let cov = self.cfg.noise.over(&travel.since(&prev.travel));
            NewEdge {
                from: EdgeFrom::Newest,
                z: prev.frontend.between(front),
                information: fixed_info(&cov),
                kind: EdgeKind::Odometry,
            }
        });
        let meta = NodeMeta {
            serial: self.st.frames.next_serial(),
            stamp,
            frontend: *front,
            travel,
            submap: NO_SUBMAP,
        };
        let serial = self.join_graph(global, meta, edge)?;
        self.refresh_mirror();
        if let Some(v) = self.cameras.as_mut().and_then(|c| c.visual.as_mut()) {
            v.state.counters.nodes += 1;
        }
        Some(serial)
    }

    /// The fused wheel+gyro pose at `stamp` (the odometry's frame), if its history covers it:
    /// the dead reckoning a camera run is compared with.
    pub fn wheel_pose_at(&self, stamp: i64) -> Option<Se2> {
        self.odometry.pose_at(stamp).ok()
    }

    /// The visual frame nodes' counters, when the mapper runs the visual odometry.
    pub fn visual_counters(&self) -> Option<VisualCounters> {
        let visual = self.cameras.as_ref()?.visual.as_ref()?;
        Some(visual.state.counters)
    }

    /// The visual odometry's own counters, when the mapper runs it.
    pub fn visual_odometry_stats(&self) -> Option<crate::frontend::visual::VoStats> {
        let visual = self.cameras.as_ref()?.visual.as_ref()?;
        Some(visual.odometry.stats())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frontend::visual::{KeyframeReason, WindowError};

    fn keyframe(pose: Se2) -> KeyframeOutput {
        KeyframeOutput {
            stamp: 0,
            reason: KeyframeReason::Motion,
            relative: None,
            pose,
            landmarks_seen: 0,
            new_landmarks: 0,
            refound: 0,
            outliers_dropped: 0,
            landmarks_dropped: 0,
            backfilled: 0,
            merged: 0,
            short_lived_dropped: 0,
            solve: Err(WindowError::NoMeasurements),
        }
    }

    fn close(a: &Se2, b: &Se2) -> bool {
        (a.x - b.x).abs() < 1e-12 && (a.y - b.y).abs() < 1e-12 && (a.theta - b.theta).abs() < 1e-12
    }

    #[test]
    fn the_front_end_pose_is_the_odometrys_keyframe_pose_plus_the_wheels_since() {
        let mut st = VisualState::NEW;
        // Before any keyframe: the wheels.
        let w0 = Se2::new(1.0, 2.0, 0.3);
        assert!(close(&st.frontend(&w0), &w0));
        // A keyframe sits at the odometry's estimate of it.
        let k0 = Se2::new(1.01, 2.0, 0.29);
        assert!(close(&st.keyframe(&keyframe(k0), &w0), &k0));
        // Between keyframes: the wheel motion since the keyframe on top of it.
        let step = Se2::new(0.1, 0.0, 0.05);
        assert!(close(&st.frontend(&w0.compose(&step)), &k0.compose(&step)));
        // The next keyframe replaces it.
        let k1 = Se2::new(1.3, 2.1, 0.35);
        let w1 = w0.compose(&Se2::new(0.25, 0.0, 0.0));
        assert!(close(&st.keyframe(&keyframe(k1), &w1), &k1));
        assert!(close(&st.frontend(&w1.compose(&step)), &k1.compose(&step)));
    }

    #[test]
    fn a_keyframe_pose_that_is_not_finite_is_replaced_by_the_wheels() {
        let mut st = VisualState::NEW;
        let w0 = Se2::new(0.0, 0.0, 0.0);
        st.keyframe(&keyframe(w0), &w0);
        let w1 = Se2::new(0.3, 0.0, 0.1);
        let bad = Se2::new(f64::NAN, 0.0, 0.0);
        assert!(close(&st.keyframe(&keyframe(bad), &w1), &w1));
    }

    extern crate std;
    use std::boxed::Box;
    use std::vec;
    use std::vec::Vec;

    use super::super::{CameraParts, MapperConfig};
    use crate::frontend::visual::frame::{scratch_bytes, MAX_FEATURES};
    use crate::frontend::visual::synth::{cleaner_camera, Rng};
    use crate::frontend::visual::{CameraTrack, Keypoint, Match};
    use crate::graph::EdgeKind;
    use crate::profile::MapperResources;
    use crate::sensor::{ImageView, PixelFormat, Timestamp};

    const W: usize = 320;
    const H: usize = 240;

    /// A texture of 8-pixel blocks of random grey, `shift` pixels to the left: enough corners
    /// for the tracker, moving in the image as the wheels move the robot.
    fn blocks(seed: u64, shift: usize) -> Vec<u8> {
        let mut rng = Rng::new(seed);
        let cols = (W + 8 * 64) / 8;
        let grey: Vec<u8> = (0..cols * (H / 8 + 1))
            .map(|_| (rng.next_u64() % 256) as u8)
            .collect();
        let mut img = vec![0u8; W * H];
        for (i, px) in img.iter_mut().enumerate() {
            let (x, y) = (i % W + shift, i / W);
            *px = grey[(y / 8) * cols + x / 8];
        }
        img
    }

    /// A mapper with camera storage and the visual odometry fed a still then moving robot:
    /// every image is posed, each visual keyframe is a frame node, and the odometry edge
    /// between two nodes is the difference of their front-end poses.
    #[test]
    fn visual_keyframes_become_frame_nodes_tied_by_odometry_edges() {
        std::thread::Builder::new()
            .stack_size(256 << 20)
            .spawn(|| {
                type Res = MapperResources<512, 1536, 12, { 82 * 82 }, 8192>;
                let mut res: Box<Res> = Box::default();
                let mut tracks = vec![CameraTrack::new()];
                let mut bytes = vec![0u8; scratch_bytes(W, H)];
                let mut corners = vec![Keypoint::default(); MAX_FEATURES];
                let mut matches = vec![Match::default(); MAX_FEATURES];
                let mut odometry = Box::new(CameraOdometry::new());
                let (model, mount) = cleaner_camera();
                let mut parts = res.parts();
                parts.cameras = Some(CameraParts {
                    tracks: &mut tracks,
                    bytes: &mut bytes,
                    corners: &mut corners,
                    matches: &mut matches,
                    visual: Some(VisualParts {
                        odometry: &mut odometry,
                        model,
                        mount,
                        config: VoConfig::default(),
                        state: VisualState::NEW,
                    }),
                });
                let mut m = parts.start(MapperConfig::home()).expect("resources fit");
                let mut keyframes = 0;
                let mut posed = 0;
                for k in 0..400i64 {
                    // 50 Hz wheels: still for 2 s, then 0.2 m/s forward.
                    let t = k * 20_000_000;
                    let x = 0.2 * ((k - 100).max(0) as f64) * 0.02;
                    m.push_odometry(t, Se2::new(x, 0.0, 0.0)).expect("odometry");
                    if k % 5 != 4 {
                        continue;
                    }
                    // The image 10 ms before the newest wheel sample: covered.
                    let stamp = t - 10_000_000;
                    let img = blocks(7, (x * 100.0) as usize);
                    let view = ImageView::new_checked(
                        Timestamp::from_nanos(stamp),
                        W,
                        H,
                        W,
                        PixelFormat::Mono8,
                        &img,
                    )
                    .expect("a valid frame");
                    let out = m.push_image(0, stamp, &view, false).expect("image taken");
                    let frame = out.frame.expect("a pose for every image");
                    assert!(frame.pose.is_finite() && frame.frontend.is_finite());
                    posed += 1;
                    keyframes += usize::from(frame.keyframe);
                }
                let counters = m.visual_counters().expect("visual odometry");
                assert_eq!(posed, 80);
                assert_eq!(counters.frames, 80);
                assert!(keyframes >= 3, "{counters:?}");
                assert_eq!(counters.nodes as usize, keyframes);
                assert_eq!(m.graph().node_count(), keyframes);
                let odometry_edges: Vec<_> = (m.graph().edges().iter())
                    .filter(|e| e.kind == EdgeKind::Odometry)
                    .collect();
                assert_eq!(odometry_edges.len(), keyframes - 1);
                for e in odometry_edges {
                    let (a, b) = (e.from.0 as usize, e.to.0 as usize);
                    let z = m.nodes()[a].frontend.between(&m.nodes()[b].frontend);
                    assert!(close(&z, &e.measurement), "{z:?} {:?}", e.measurement);
                }
                // A still robot makes no keyframe after the first.
                assert!(m.nodes()[1].stamp >= 2_000_000_000);
            })
            .expect("thread")
            .join()
            .expect("test body");
    }

    /// The odometry's storage, what sensor set C adds to the camera stage's.
    #[test]
    fn the_camera_odometry_size() {
        let bytes = size_of::<CameraOdometry>();
        std::println!("CameraOdometry: {bytes} bytes");
        // 1,053,216 bytes on x86-64 and 965,256 on 32-bit ARM (half-size `usize`): the module
        // docs quote the bound.
        assert!(bytes <= 1_100_000, "{bytes} bytes");
    }
}
