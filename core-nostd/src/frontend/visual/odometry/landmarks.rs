//! Landmarks of the visual odometry: the window's landmarks found again in a new keyframe by
//! their predicted pixel and descriptor, and new tracks triangulated into landmarks.

use super::*;

/// Writes the `landmarks` that `skip` does not exclude and that have a descriptor, with their
/// pixels predicted in `camera`, as the queries of a guided match (track, descriptor, pixel);
/// returns how many were written (at most the queries' room).
pub(super) fn landmark_queries(
    track: &mut [u32],
    descriptor: &mut [Descriptor],
    pixel: &mut [[f32; 2]],
    landmarks: &[Landmark],
    camera: &CameraPose,
    model: &CameraModel,
    skip: impl Fn(u32) -> bool,
) -> usize {
    let mut queries = 0;
    for l in landmarks {
        let Some(desc) = l.descriptor else {
            continue;
        };
        if skip(l.track) {
            continue;
        }
        let Some(px) = model.project(&camera.world_to_camera(&l.position)) else {
            continue;
        };
        let (Some(t), Some(d), Some(p)) = (
            track.get_mut(queries),
            descriptor.get_mut(queries),
            pixel.get_mut(queries),
        ) else {
            break;
        };
        *t = l.track;
        *d = desc;
        // Off-image and non-finite predictions simply find no candidate.
        *p = [px.x as f32, px.y as f32];
        queries += 1;
    }
    queries
}

impl<const N: usize, const M: usize, const K: usize> VisualOdometry<N, M, K> {
    /// Searches the window's landmarks whose track no feature of `frame` continues near their
    /// pixel predicted from `guess` (the keyframe's first pose), by descriptor. A feature so
    /// matched takes the landmark's track id, in this frame and as the previous frame of the
    /// next. Only features whose track is in no keyframe of the window (started since the
    /// last keyframe) are candidates: an older track is not taken from its own sightings.
    /// Returns the landmarks re-found.
    pub(super) fn refind_landmarks(
        &mut self,
        frame: &VoFrame<'_>,
        guess: &Se2,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        cfg: &VoConfig,
    ) -> usize {
        let radius = cfg.refind_radius_px;
        if radius.is_nan() || radius <= 0.0 || self.landmark_count == 0 {
            return 0;
        }
        let n = frame
            .keypoints
            .len()
            .min(frame.descriptors.len())
            .min(MAX_FEATURES);
        let s = &mut self.refind;
        // The frame's tracks, sorted, to tell which landmarks it already continues.
        let tracked = s.tracked.get_mut(..n).unwrap_or_default();
        tracked.copy_from_slice(self.current.get(..n).unwrap_or_default());
        crate::sort::sort_by_key(tracked, |&t| t);
        let camera = CameraPose::of_robot(guess, mount);
        let landmarks = self
            .landmarks
            .get(..self.landmark_count)
            .unwrap_or_default();
        let queries = landmark_queries(
            &mut s.query_track,
            &mut s.query_descriptor,
            &mut s.query_px,
            landmarks,
            &camera,
            model,
            |track| tracked.binary_search(&track).is_ok(),
        );
        let keyframes = self
            .keyframes
            .get(..self.keyframe_count)
            .unwrap_or_default();
        let mut candidates = 0;
        for (i, ((&id, kp), d)) in self
            .current
            .iter()
            .zip(frame.keypoints)
            .zip(frame.descriptors)
            .enumerate()
            .take(n)
        {
            if id == NO_TRACK || keyframes.iter().any(|k| k.find(id).is_some()) {
                continue;
            }
            let (Some(f), Some(td), Some(tp), Ok(index)) = (
                s.train_feature.get_mut(candidates),
                s.train_descriptor.get_mut(candidates),
                s.train_px.get_mut(candidates),
                u16::try_from(i),
            ) else {
                break;
            };
            *f = index;
            *td = *d;
            *tp = kp.position();
            candidates += 1;
        }
        if queries == 0 || candidates == 0 {
            return 0;
        }
        let stats = match_guided(
            s.query_descriptor.get(..queries).unwrap_or_default(),
            s.query_px.get(..queries).unwrap_or_default(),
            s.train_descriptor.get(..candidates).unwrap_or_default(),
            s.train_px.get(..candidates).unwrap_or_default(),
            cfg.refind_radius_px,
            &cfg.refind,
            &mut s.matches,
        );
        let mut refound = 0;
        for m in s.matches.iter().take(stats.matched) {
            let (Some(&track), Some(&feature)) =
                (s.query_track.get(m.query), s.train_feature.get(m.train))
            else {
                continue;
            };
            let feature = usize::from(feature);
            if let (Some(c), Some(p)) = (
                self.current.get_mut(feature),
                self.previous.get_mut(feature),
            ) {
                *c = track;
                *p = track;
                refound += 1;
            }
        }
        self.stats.refound += u32::try_from(refound).unwrap_or(u32::MAX);
        refound
    }

    /// Gives each landmark the descriptor of its sighting in `frame` (the newest keyframe).
    pub(super) fn remember_descriptors(&mut self, frame: &VoFrame<'_>) {
        let n = frame.keypoints.len().min(MAX_FEATURES);
        let landmarks = self
            .landmarks
            .get_mut(..self.landmark_count)
            .unwrap_or_default();
        for (&id, d) in self.current.iter().zip(frame.descriptors).take(n) {
            if let Ok(i) = landmarks.binary_search_by_key(&id, |l| l.track) {
                if let Some(l) = landmarks.get_mut(i) {
                    l.descriptor = Some(*d);
                }
            }
        }
    }

    /// Triangulates the tracks of keyframe `slot` that have no landmark yet from the oldest
    /// keyframe that saw them. Returns the landmarks added.
    pub(super) fn triangulate_new(
        &mut self,
        slot: usize,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        cfg: &VoConfig,
    ) -> usize {
        let Some(kf) = self.keyframes.get(slot) else {
            return 0;
        };
        let pose_b = CameraPose::of_robot(&kf.pose, mount);
        let before = self.landmark_count;
        let mut count = self.landmark_count;
        for f in kf.features() {
            if self.landmark_index(f.track).is_some() {
                continue;
            }
            let Some((older, g)) = self
                .keyframes
                .get(..slot)
                .unwrap_or_default()
                .iter()
                .find_map(|k| Some((k, k.find(f.track)?.1)))
            else {
                continue;
            };
            let pose_a = CameraPose::of_robot(&older.pose, mount);
            let result = triangulate(
                model,
                &pose_a,
                &observation(g, cfg.sigma_px),
                &pose_b,
                &observation(f, cfg.sigma_px),
                &cfg.triangulate,
            );
            let in_range = |p: &WorldPoint| (p.position - pose_b.centre).norm() <= cfg.max_range;
            let point = match result {
                Ok(p) if in_range(&p) => p,
                Err(TriangulateError::LowParallax) => {
                    self.stats.low_parallax += 1;
                    continue;
                }
                _ => {
                    self.stats.triangulation_refused += 1;
                    continue;
                }
            };
            // Appended after the sorted ones; sorted below, so lookups here see only the old.
            match self.landmarks.get_mut(count) {
                Some(l) => {
                    *l = Landmark {
                        track: f.track,
                        position: point.position,
                        descriptor: None,
                    };
                    count += 1;
                }
                None => self.stats.capacity_dropped += 1,
            }
        }
        self.landmark_count = count;
        if let Some(l) = self.landmarks.get_mut(..count) {
            crate::sort::sort_by_key(l, |l| l.track);
        }
        let added = count - before;
        self.stats.landmarks += u32::try_from(added).unwrap_or(u32::MAX);
        added
    }
}
