//! The visual odometry's use of the bundle window: filling it with the keyframes, landmarks,
//! sightings and wheel+gyro priors, solving it, dropping the outliers, and sliding it.

use super::*;

impl<const N: usize, const M: usize, const K: usize> VisualOdometry<N, M, K> {
    /// Fills the window, solves it, copies the estimates back and drops the outliers.
    /// Returns the solve, the observations and the landmarks dropped.
    pub(super) fn solve(
        &mut self,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        cfg: &VoConfig,
    ) -> (Result<WindowSummary, WindowError>, usize, usize) {
        if self.keyframe_count < 2 {
            // One keyframe: the fixed gauge alone, nothing to solve.
            return (Err(WindowError::NoMeasurements), 0, 0);
        }
        let filled = self.fill(cfg);
        let mut window_cfg = cfg.window;
        window_cfg.fixed_poses = 1;
        let summary = filled.and_then(|()| self.window.solve(model, mount, &window_cfg));
        if summary.is_err() {
            self.stats.solve_failures += 1;
            return (summary, 0, 0);
        }
        for (i, kf) in self
            .keyframes
            .iter_mut()
            .enumerate()
            .take(self.keyframe_count)
        {
            if let Some(p) = self.window.pose(i) {
                kf.pose = p;
            }
        }
        // Outlying sightings leave their keyframe.
        let mut dropped = 0;
        for (o, src) in self
            .sources
            .iter()
            .enumerate()
            .take(self.window.observation_count())
        {
            let outlier = self
                .window
                .observation_report(o)
                .is_some_and(|r| r.status == ObservationStatus::Outlier);
            let feature = self
                .keyframes
                .get_mut(usize::from(src.keyframe))
                .and_then(|k| k.features.get_mut(usize::from(src.feature)));
            if let (true, Some(f)) = (outlier, feature) {
                f.track = NO_TRACK;
                dropped += 1;
                self.stats.backfilled_outliers += u32::from(f.backfilled);
            }
        }
        if dropped > 0 {
            self.keyframes
                .iter_mut()
                .take(self.keyframe_count)
                .for_each(Keyframe::compact);
        }
        // Landmarks: new positions; those mostly seen as outliers, or pushed out of range,
        // leave.
        let newest = self
            .keyframe_count
            .checked_sub(1)
            .and_then(|i| self.keyframes.get(i))
            .map_or(Se2::IDENTITY, |k| k.pose);
        let centre = CameraPose::of_robot(&newest, mount).centre;
        let mut lost = 0;
        for (i, l) in self
            .landmarks
            .iter_mut()
            .enumerate()
            .take(self.landmark_count)
        {
            let Some(r) = self.window.landmark_report(i) else {
                continue;
            };
            if r.status == LandmarkStatus::Active {
                l.position = r.position;
                let range = (r.position - centre).norm();
                let far = range.is_nan() || range > cfg.max_range;
                if far || 2 * r.outliers > r.observations {
                    l.track = NO_TRACK;
                    lost += 1;
                }
            }
        }
        if lost > 0 {
            self.compact_landmarks();
        }
        self.stats.outliers_dropped += u32::try_from(dropped).unwrap_or(u32::MAX);
        self.stats.landmarks_dropped += u32::try_from(lost).unwrap_or(u32::MAX);
        (summary, dropped, lost)
    }

    /// Puts the keyframes, landmarks, sightings and motion priors into the window.
    pub(super) fn fill(&mut self, cfg: &VoConfig) -> Result<(), WindowError> {
        let w = &mut self.window;
        w.clear();
        for kf in self.keyframes.iter().take(self.keyframe_count) {
            w.push_pose(kf.pose)?;
        }
        for l in self.landmarks.iter().take(self.landmark_count) {
            w.push_landmark(l.position)?;
        }
        let landmarks = self
            .landmarks
            .get(..self.landmark_count)
            .unwrap_or_default();
        let mut used = 0;
        'keyframes: for (k, kf) in self.keyframes.iter().enumerate().take(self.keyframe_count) {
            for (i, f) in kf.features().iter().enumerate() {
                let Ok(landmark) = landmarks.binary_search_by_key(&f.track, |l| l.track) else {
                    continue;
                };
                let Some(src) = self.sources.get_mut(used) else {
                    self.stats.capacity_dropped += 1;
                    break 'keyframes;
                };
                let sigma = cfg.sigma_px * f64::from(1u16 << f.level.min(8));
                let obs = PixelObservation {
                    keyframe: k,
                    landmark,
                    px: Vector2::new(f64::from(f.px[0]), f64::from(f.px[1])),
                    sigma_px: sigma,
                };
                if w.push_observation(obs).is_err() {
                    self.stats.capacity_dropped += 1;
                    continue;
                }
                *src = ObservationSource {
                    keyframe: u16::try_from(k).unwrap_or(u16::MAX),
                    feature: u16::try_from(i).unwrap_or(u16::MAX),
                };
                used += 1;
            }
        }
        let count = self.keyframe_count;
        for (k, pair) in self
            .keyframes
            .get(..count)
            .unwrap_or_default()
            .windows(2)
            .enumerate()
        {
            let [a, b] = pair else { continue };
            let motion = a.odometry.between(&b.odometry);
            w.push_motion_prior(MotionPrior {
                from: k,
                to: k + 1,
                motion,
                information: odometry_information(&motion, cfg),
            })?;
        }
        Ok(())
    }

    /// Drops the oldest keyframe and the landmarks no remaining keyframe sees.
    pub(super) fn slide(&mut self) {
        let Some(kfs) = self
            .keyframes
            .get_mut(..self.keyframe_count)
            .filter(|k| !k.is_empty())
        else {
            return;
        };
        kfs.rotate_left(1);
        self.keyframe_count -= 1;
        let kfs = self
            .keyframes
            .get(..self.keyframe_count)
            .unwrap_or_default();
        for l in self.landmarks.iter_mut().take(self.landmark_count) {
            if !kfs.iter().any(|k| k.find(l.track).is_some()) {
                l.track = NO_TRACK;
            }
        }
        self.compact_landmarks();
    }

    pub(super) fn compact_landmarks(&mut self) {
        let l = self
            .landmarks
            .get_mut(..self.landmark_count)
            .unwrap_or_default();
        crate::sort::sort_by_key(l, |l| l.track);
        self.landmark_count = l.iter().take_while(|l| l.track != NO_TRACK).count();
    }
}

/// A keyframe feature as a triangulation input.
pub(super) fn observation(f: &KeyFeature, sigma_px: f64) -> Observation {
    Observation {
        px: Vector2::new(f64::from(f.px[0]), f64::from(f.px[1])),
        sigma_px: sigma_px * f64::from(1u16 << f.level.min(8)),
    }
}

/// Information of the wheel+gyro `motion` under the configured noise model.
pub(super) fn odometry_information(motion: &Se2, cfg: &VoConfig) -> Matrix3<f64> {
    let d = libm::hypot(motion.x, motion.y);
    let [xy0, xy_m] = cfg.odometry_sigma_xy;
    let [t0, t_m, t_rad] = cfg.odometry_sigma_theta;
    let sxy = xy0 + xy_m * d;
    let st = t0 + t_m * d + t_rad * libm::fabs(motion.theta);
    let (a, b) = (1.0 / (sxy * sxy), 1.0 / (st * st));
    if a.is_finite() && b.is_finite() {
        Matrix3::new(a, 0.0, 0.0, 0.0, a, 0.0, 0.0, 0.0, b)
    } else {
        Matrix3::zeros()
    }
}
