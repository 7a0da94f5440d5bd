//! The paper's three measures for scenes with few features (section III-B.1: a plain ceiling
//! seen by a cheap camera gives a few dozen corners at best), each set in
//! [`LowFeatureConfig`] and each off by its own zero:
//!
//! * **(a) sightings in older keyframes** ([`backfill`](VisualOdometry::backfill)): the window's
//!   landmarks are projected into each older keyframe of the window that does not see them,
//!   and matched by descriptor near the prediction against that keyframe's features whose
//!   track ended without a landmark. A match makes that feature a sighting of the landmark.
//!   A landmark triangulated late (its first track too short for parallax) thus also gets the
//!   sightings its point left in the keyframes before: more rays over a wider baseline for its
//!   depth, and one more link between those keyframes' poses.
//! * **(b) duplicates merged** ([`merge_duplicates`](VisualOdometry::merge_duplicates)): two
//!   landmarks within [`LowFeatureConfig::merge_distance`] of each other, with descriptors
//!   within [`LowFeatureConfig::merge_max_hamming`], and never seen in the same keyframe, are
//!   one point whose track broke and was triangulated twice. The one with more sightings
//!   stays, at the mean of the two positions weighted by their sightings, and takes the
//!   other's sightings (and its live track, so the next frames continue the one kept). Two
//!   half-constrained points become one better-constrained point, and the window does not
//!   count one corner twice.
//! * **(c) short-lived landmarks dropped** ([`drop_short_lived`](VisualOdometry::drop_short_lived)):
//!   when the oldest keyframe leaves the window, the landmarks it saw that are seen in fewer
//!   than [`LowFeatureConfig::min_sightings`] keyframes of the window (that one included) are
//!   dropped with all their sightings. Such a landmark has had the whole window to be seen
//!   again and was not: its few rays fix its depth poorly, and a wrong match is most often
//!   such a point. Dropping it only at that moment (not as soon as its track breaks) leaves
//!   the re-finding and measure (a) their chance to add its sightings first.

use super::*;

impl<const N: usize, const M: usize, const K: usize> VisualOdometry<N, M, K> {
    /// Keyframes of the window that see `track`.
    pub(super) fn sightings(&self, track: u32) -> usize {
        self.keyframes
            .iter()
            .take(self.keyframe_count)
            .filter(|k| k.find(track).is_some())
            .count()
    }

    /// Measure (c): drops the landmarks the oldest keyframe sees that are seen in fewer than
    /// [`LowFeatureConfig::min_sightings`] keyframes, with their sightings. Called before the
    /// oldest keyframe leaves. Returns the landmarks dropped.
    pub(super) fn drop_short_lived(&mut self, cfg: &VoConfig) -> usize {
        let min = cfg.low_feature.min_sightings;
        if min < 2 || self.keyframe_count == 0 {
            return 0;
        }
        // The tracks dropped, sorted as the landmarks are, in the re-finding's working space.
        let mut dropped = 0;
        for i in 0..self.landmark_count {
            let Some(track) = self.landmarks.get(i).map(|l| l.track) else {
                continue;
            };
            let oldest_sees = self
                .keyframes
                .first()
                .is_some_and(|k| k.find(track).is_some());
            if !oldest_sees || self.sightings(track) >= min {
                continue;
            }
            let Some(slot) = self.refind.query_track.get_mut(dropped) else {
                break;
            };
            *slot = track;
            dropped += 1;
        }
        if dropped == 0 {
            return 0;
        }
        let gone = self.refind.query_track.get(..dropped).unwrap_or_default();
        for kf in self.keyframes.iter_mut().take(self.keyframe_count) {
            let mut changed = false;
            for f in kf.features.iter_mut().take(kf.len) {
                if gone.binary_search(&f.track).is_ok() {
                    f.track = NO_TRACK;
                    changed = true;
                }
            }
            if changed {
                kf.compact();
            }
        }
        for l in self.landmarks.iter_mut().take(self.landmark_count) {
            if gone.binary_search(&l.track).is_ok() {
                l.track = NO_TRACK;
            }
        }
        self.compact_landmarks();
        self.stats.short_lived_dropped += u32::try_from(dropped).unwrap_or(u32::MAX);
        dropped
    }

    /// Measure (b): merges the pairs of landmarks that are one point. Returns the landmarks
    /// merged away.
    pub(super) fn merge_duplicates(&mut self, cfg: &VoConfig) -> usize {
        let radius = cfg.low_feature.merge_distance;
        if radius.is_nan() || radius <= 0.0 {
            return 0;
        }
        let count = self.landmark_count;
        let mut merged = 0;
        for i in 0..count {
            for j in (i + 1)..count {
                let (Some(&a), Some(&b)) = (self.landmarks.get(i), self.landmarks.get(j)) else {
                    continue;
                };
                if a.track == NO_TRACK {
                    // Merged away earlier in this pass.
                    break;
                }
                if b.track == NO_TRACK {
                    continue;
                }
                let distance = (a.position - b.position).norm();
                if distance.is_nan() || distance > radius {
                    continue;
                }
                let (Some(da), Some(db)) = (a.descriptor, b.descriptor) else {
                    continue;
                };
                if da.hamming(&db) > cfg.low_feature.merge_max_hamming {
                    continue;
                }
                let (mut na, mut nb, mut together) = (0usize, 0usize, false);
                for k in self.keyframes.iter().take(self.keyframe_count) {
                    let (sa, sb) = (k.find(a.track).is_some(), k.find(b.track).is_some());
                    na += usize::from(sa);
                    nb += usize::from(sb);
                    // One image showing both as two features: two points.
                    together |= sa && sb;
                }
                if together {
                    continue;
                }
                let ((keep_at, keep, n_keep), (gone_at, gone, n_gone)) = if nb > na {
                    ((j, b, nb), (i, a, na))
                } else {
                    ((i, a, na), (j, b, nb))
                };
                let (wk, wg) = match n_keep + n_gone {
                    0 => (0.5, 0.5),
                    total => (n_keep as f64 / total as f64, n_gone as f64 / total as f64),
                };
                if let Some(l) = self.landmarks.get_mut(keep_at) {
                    l.position = keep.position * wk + gone.position * wg;
                }
                if let Some(l) = self.landmarks.get_mut(gone_at) {
                    l.track = NO_TRACK;
                }
                self.retrack(gone.track, keep.track);
                merged += 1;
                if gone_at == i {
                    break;
                }
            }
        }
        if merged > 0 {
            self.compact_landmarks();
        }
        self.stats.merged += u32::try_from(merged).unwrap_or(u32::MAX);
        merged
    }

    /// Gives the sightings and live features of track `from` to track `to` (which no keyframe
    /// sees together with `from`).
    fn retrack(&mut self, from: u32, to: u32) {
        for kf in self.keyframes.iter_mut().take(self.keyframe_count) {
            let Some((i, _)) = kf.find(from) else {
                continue;
            };
            if let Some(f) = kf.features.get_mut(i) {
                f.track = to;
            }
            kf.compact();
        }
        // The frame just taken is the newest keyframe, and the previous frame of the next.
        for id in self.current.iter_mut().chain(self.previous.iter_mut()) {
            if *id == from {
                *id = to;
            }
        }
    }

    /// Measure (a): finds the window's landmarks in the older keyframes of the window that do
    /// not see them. Returns the sightings added.
    pub(super) fn backfill(
        &mut self,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        cfg: &VoConfig,
    ) -> usize {
        let radius = cfg.low_feature.backfill_radius_px;
        if radius.is_nan() || radius <= 0.0 || self.landmark_count == 0 {
            return 0;
        }
        let Some(newest) = self.keyframe_count.checked_sub(1) else {
            return 0;
        };
        let mut added = 0;
        for k in 0..newest {
            let (Some(kf), Some(last)) = (self.keyframes.get(k), self.keyframes.get(newest)) else {
                continue;
            };
            let landmarks = self
                .landmarks
                .get(..self.landmark_count)
                .unwrap_or_default();
            let s = &mut self.refind;
            let camera = CameraPose::of_robot(&kf.pose, mount);
            let queries = landmarks::landmark_queries(
                &mut s.query_track,
                &mut s.query_descriptor,
                &mut s.query_px,
                landmarks,
                &camera,
                model,
                |track| kf.find(track).is_some(),
            );
            // Every feature of the keyframe competes, so that the ratio test sees the
            // look-alikes; but only one whose track has no landmark and has ended (the newest
            // keyframe does not continue it) may become a sighting: relabelling it takes
            // nothing from another landmark or from a track that may still be triangulated.
            // The others are entered as feature `u16::MAX`, which no keyframe has.
            let mut candidates = 0;
            for (i, f) in kf.features().iter().enumerate() {
                let Some(descriptor) = f.descriptor else {
                    continue;
                };
                let has_landmark = landmarks
                    .binary_search_by_key(&f.track, |l| l.track)
                    .is_ok();
                let free = !has_landmark && last.find(f.track).is_none();
                let (Some(tf), Some(td), Some(tp), Ok(index)) = (
                    s.train_feature.get_mut(candidates),
                    s.train_descriptor.get_mut(candidates),
                    s.train_px.get_mut(candidates),
                    u16::try_from(i).map(|i| if free { i } else { u16::MAX }),
                ) else {
                    break;
                };
                *tf = index;
                *td = descriptor;
                *tp = f.px;
                candidates += 1;
            }
            if queries == 0 || candidates == 0 {
                continue;
            }
            let stats = match_guided(
                s.query_descriptor.get(..queries).unwrap_or_default(),
                s.query_px.get(..queries).unwrap_or_default(),
                s.train_descriptor.get(..candidates).unwrap_or_default(),
                s.train_px.get(..candidates).unwrap_or_default(),
                radius,
                &cfg.low_feature.backfill,
                &mut s.matches,
            );
            let Some(kf) = self.keyframes.get_mut(k) else {
                continue;
            };
            let mut found = 0;
            // Each landmark is one query, and each feature goes to one query at most.
            for m in s.matches.iter().take(stats.matched) {
                let (Some(&track), Some(&feature)) =
                    (s.query_track.get(m.query), s.train_feature.get(m.train))
                else {
                    continue;
                };
                if let Some(f) = kf.features.get_mut(usize::from(feature)) {
                    f.track = track;
                    f.backfilled = true;
                    found += 1;
                }
            }
            if found > 0 {
                kf.compact();
            }
            added += found;
        }
        self.stats.backfilled += u32::try_from(added).unwrap_or(u32::MAX);
        added
    }
}
