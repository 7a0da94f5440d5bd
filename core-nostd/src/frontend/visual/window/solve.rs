//! The Levenberg-Marquardt solve of a window: preparing and classifying the landmarks, the
//! cost, the linearisation with the landmarks eliminated (Schur complement), the reduced step,
//! and the chi2 flags at the end.

use super::*;

impl<const N: usize, const M: usize, const K: usize> BundleWindow<N, M, K> {
    /// Refines the keyframe poses (except the oldest `cfg.fixed_poses`) and the landmarks.
    ///
    /// The estimates are updated in place; the reports then tell which landmarks were set
    /// aside and which observations are outliers.
    ///
    /// # Errors
    /// [`WindowError::Empty`] without keyframes, [`WindowError::NoMeasurements`] when no
    /// usable observation nor prior remains. The estimates are left unchanged then.
    pub fn solve(
        &mut self,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        cfg: &WindowConfig,
    ) -> Result<WindowSummary, WindowError> {
        if self.pose_count == 0 {
            return Err(WindowError::Empty);
        }
        let fixed = cfg.fixed_poses.max(1);
        let used = self.prepare(model, mount, cfg);
        if used == 0 && self.prior_count == 0 {
            return Err(WindowError::NoMeasurements);
        }
        let initial_cost = self.cost(model, mount, cfg.huber).unwrap_or(f64::INFINITY);
        let (mut iterations, mut cost) = (0, initial_cost);
        let mut termination;
        // The Huber weights keep gross errors from dragging the first solution far; taking
        // them out entirely and solving again removes the pull they still have. A round
        // followed by another only has to tell the outliers apart, so it stops early; under
        // Huber weights the last digits come slowly.
        let mut round = 0;
        loop {
            let last = round == cfg.rejection_rounds;
            let round_cfg = WindowConfig {
                cost_tolerance: if last {
                    cfg.cost_tolerance
                } else {
                    cfg.rejection_cost_tolerance.max(cfg.cost_tolerance)
                },
                ..*cfg
            };
            let budget = cfg.max_iterations.saturating_sub(iterations);
            let (more, end, c) = self.iterate(model, mount, &round_cfg, fixed, cost, budget);
            iterations += more;
            termination = end;
            cost = c;
            // Without steps left, another round could only flip flags back and forth.
            if last || iterations >= cfg.max_iterations {
                break;
            }
            round += 1;
            if self.reclassify(model, mount, cfg.outlier_chi2) == 0 {
                // Nothing to take out: finish this round's solution instead.
                round = cfg.rejection_rounds;
                continue;
            }
            self.classify_landmarks(model, mount, cfg.min_pivot_ratio);
            cost = self.cost(model, mount, cfg.huber).unwrap_or(f64::INFINITY);
        }
        let (inliers, outliers) = self.flag(model, mount, cfg.outlier_chi2);
        let mut active = 0;
        let mut skipped = 0;
        for l in self.live_landmarks() {
            match l.status {
                LandmarkStatus::Active => active += 1,
                LandmarkStatus::TooFewViews | LandmarkStatus::NoParallax => skipped += 1,
                LandmarkStatus::Pending => {}
            }
        }
        Ok(WindowSummary {
            iterations,
            initial_cost,
            final_cost: cost,
            termination,
            active_landmarks: active,
            skipped_landmarks: skipped,
            inliers,
            outliers,
        })
    }

    /// Levenberg-Marquardt from the current estimates, whose cost is `cost`, for at most
    /// `budget` accepted steps. Returns the steps taken, how it ended and the final cost.
    pub(super) fn iterate(
        &mut self,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        cfg: &WindowConfig,
        fixed: usize,
        mut cost: f64,
        budget: u32,
    ) -> (u32, Termination, f64) {
        let mut lambda = cfg.initial_lambda;
        let mut iterations = 0;
        while iterations < budget {
            self.linearize(model, mount, fixed, cfg.huber);
            // Raise the damping until a step lowers the cost.
            loop {
                let Some(step) = self.compute_step(fixed, lambda) else {
                    lambda *= 10.0;
                    if lambda > cfg.max_lambda {
                        return (iterations, Termination::NoDecrease, cost);
                    }
                    continue;
                };
                // A step at the tolerance is still taken if it lowers the cost: with exact
                // data the last step carries the solution from micrometres to round-off.
                let small = step <= cfg.step_tolerance;
                self.apply_step(fixed);
                match self.cost(model, mount, cfg.huber) {
                    Some(new_cost) if new_cost < cost => {
                        iterations += 1;
                        let decrease = cost - new_cost;
                        cost = new_cost;
                        lambda = (lambda * 0.1).max(MIN_LAMBDA);
                        if small || decrease <= cfg.cost_tolerance * cost {
                            return (iterations, Termination::Converged, cost);
                        }
                        break;
                    }
                    _ => {
                        self.restore(fixed);
                        if small {
                            return (iterations, Termination::Converged, cost);
                        }
                        lambda *= 10.0;
                        if lambda > cfg.max_lambda {
                            return (iterations, Termination::NoDecrease, cost);
                        }
                    }
                }
            }
        }
        (iterations, Termination::IterationLimit, cost)
    }

    pub(super) fn refresh_trig(&mut self) {
        let n = self.pose_count;
        for p in self.poses.iter_mut().take(n) {
            p.cos = libm::cos(p.pose.theta);
            p.sin = libm::sin(p.pose.theta);
        }
    }

    /// Links each landmark's observations and drops those that do not project, then sets
    /// aside the landmarks whose depth the rest do not fix. Returns the observations used.
    pub(super) fn prepare(
        &mut self,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        cfg: &WindowConfig,
    ) -> usize {
        self.refresh_trig();
        let (nl, no) = (self.landmark_count, self.observation_count);
        for l in self.landmarks.iter_mut().take(nl) {
            l.first_obs = NO_OBS;
            l.status = LandmarkStatus::Pending;
        }
        // Prepending in reverse keeps each list in the order of insertion.
        for i in (0..no).rev() {
            let Some(slot) = self.observations.get_mut(i) else {
                continue;
            };
            slot.chi2 = 0.0;
            slot.next = NO_OBS;
            let (k, l) = (slot.obs.keyframe, slot.obs.landmark);
            let (Some(pose), Some(lm)) = (self.poses.get(k), self.landmarks.get_mut(l)) else {
                slot.status = ObservationStatus::NotProjectable;
                continue;
            };
            let (p, c, s) = (&pose.pose, pose.cos, pose.sin);
            if residual(model, mount, p, (c, s), &lm.position, &slot.obs.px).is_none() {
                slot.status = ObservationStatus::NotProjectable;
                continue;
            }
            slot.status = ObservationStatus::Pending;
            slot.next = lm.first_obs;
            lm.first_obs = i;
        }
        self.classify_landmarks(model, mount, cfg.min_pivot_ratio)
    }

    /// Sets aside the landmarks not yet set aside whose observations in use (pending) do not
    /// fix their depth: fewer than two, or a block with a pivot below `ratio` of its scale.
    /// Their observations become [`ObservationStatus::Skipped`]. Returns the observations
    /// still in use.
    pub(super) fn classify_landmarks(
        &mut self,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        ratio: f64,
    ) -> usize {
        self.refresh_trig();
        let mut used = 0;
        for l in 0..self.landmark_count {
            let Some(lm) = self.landmarks.get(l) else {
                continue;
            };
            let open = matches!(lm.status, LandmarkStatus::Pending | LandmarkStatus::Active);
            if !open {
                continue;
            }
            let (position, first) = (lm.position, lm.first_obs);
            let mut count = 0usize;
            let mut v = ZERO3;
            let mut o = first;
            while let Some(slot) = self.observations.get(o) {
                o = slot.next;
                if slot.status != ObservationStatus::Pending {
                    continue;
                }
                let Some(pose) = self.poses.get(slot.obs.keyframe) else {
                    continue;
                };
                let (p, c, s) = (&pose.pose, pose.cos, pose.sin);
                if let Some((_, _, jl)) =
                    reprojection(model, mount, p, (c, s), &position, &slot.obs.px)
                {
                    count += 1;
                    v += jl.transpose() * jl / (slot.obs.sigma_px * slot.obs.sigma_px);
                }
            }
            let status = if count < 2 {
                LandmarkStatus::TooFewViews
            } else if spd3_inverse(&v, ratio).is_none() {
                LandmarkStatus::NoParallax
            } else {
                used += count;
                LandmarkStatus::Active
            };
            if status != LandmarkStatus::Active {
                let mut o = first;
                while let Some(slot) = self.observations.get_mut(o) {
                    if slot.status == ObservationStatus::Pending {
                        slot.status = ObservationStatus::Skipped;
                    }
                    o = slot.next;
                }
            }
            if let Some(lm) = self.landmarks.get_mut(l) {
                lm.status = status;
            }
        }
        used
    }

    /// Takes out of use the observations whose chi2 at the current estimates is beyond
    /// `gate`, and puts back those taken out earlier that are now within it. Returns how many
    /// changed.
    pub(super) fn reclassify(
        &mut self,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        gate: f64,
    ) -> usize {
        self.refresh_trig();
        let mut changed = 0;
        let no = self.observation_count;
        for slot in self.observations.iter_mut().take(no) {
            let open = matches!(
                slot.status,
                ObservationStatus::Pending | ObservationStatus::Outlier
            );
            let (Some(pose), Some(lm)) = (
                self.poses.get(slot.obs.keyframe),
                self.landmarks.get(slot.obs.landmark),
            ) else {
                continue;
            };
            if !open || lm.status != LandmarkStatus::Active {
                continue;
            }
            let (p, c, s) = (&pose.pose, pose.cos, pose.sin);
            let lin = residual(model, mount, p, (c, s), &lm.position, &slot.obs.px);
            let chi2 = lin.map_or(f64::INFINITY, |r| {
                r.norm_squared() / (slot.obs.sigma_px * slot.obs.sigma_px)
            });
            let status = if chi2 <= gate {
                ObservationStatus::Pending
            } else {
                ObservationStatus::Outlier
            };
            if status != slot.status {
                changed += 1;
                slot.status = status;
            }
        }
        changed
    }

    /// The robust cost at the current estimates, or `None` when an observation in use no
    /// longer projects (a step that put a landmark behind a camera is refused).
    pub(super) fn cost(
        &mut self,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        k: f64,
    ) -> Option<f64> {
        self.refresh_trig();
        let mut total = 0.0;
        for slot in self.live_observations() {
            if slot.status != ObservationStatus::Pending {
                continue;
            }
            let pose = self.poses.get(slot.obs.keyframe)?;
            let lm = self.landmarks.get(slot.obs.landmark)?;
            let (p, c, s) = (&pose.pose, pose.cos, pose.sin);
            let r = residual(model, mount, p, (c, s), &lm.position, &slot.obs.px)?;
            let e2 = r.norm_squared() / (slot.obs.sigma_px * slot.obs.sigma_px);
            total += huber(e2, k).1;
        }
        for slot in self.priors.iter().take(self.prior_count) {
            let p = &slot.prior;
            let (from, to) = (self.poses.get(p.from)?, self.poses.get(p.to)?);
            let (e, _, _) = prior_residual(p, &from.pose, &to.pose);
            total += e.dot(&(p.information * e));
        }
        total.is_finite().then_some(total)
    }

    /// The normal equations at the current estimates: the pose blocks, the landmark blocks,
    /// the pose-landmark blocks per observation, and the priors' off-diagonal blocks.
    pub(super) fn linearize(
        &mut self,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        fixed: usize,
        k: f64,
    ) {
        self.refresh_trig();
        let (np, nl, no) = (self.pose_count, self.landmark_count, self.observation_count);
        for p in self.poses.iter_mut().take(np) {
            p.u = ZERO3;
            p.b = ZERO_V;
        }
        for l in self.landmarks.iter_mut().take(nl) {
            l.v = ZERO3;
            l.b = ZERO_V;
        }
        for slot in self.observations.iter_mut().take(no) {
            slot.w = ZERO3;
            if slot.status != ObservationStatus::Pending {
                continue;
            }
            let (kf, l) = (slot.obs.keyframe, slot.obs.landmark);
            let (Some(pose), Some(lm)) = (self.poses.get_mut(kf), self.landmarks.get_mut(l)) else {
                continue;
            };
            let (p, c, s) = (&pose.pose, pose.cos, pose.sin);
            let Some((r, jx, jl)) =
                reprojection(model, mount, p, (c, s), &lm.position, &slot.obs.px)
            else {
                // The cost was evaluated at this same point, so this does not happen; the
                // observation would simply contribute nothing.
                continue;
            };
            let inv_sigma = 1.0 / slot.obs.sigma_px;
            let (r, jx, jl) = (r * inv_sigma, jx * inv_sigma, jl * inv_sigma);
            let (w, _) = huber(r.norm_squared(), k);
            let jl_tw = jl.transpose() * w;
            lm.v += jl_tw * jl;
            lm.b -= jl_tw * r;
            if kf >= fixed {
                let jx_tw = jx.transpose() * w;
                pose.u += jx_tw * jx;
                pose.b -= jx_tw * r;
                slot.w = jx_tw * jl;
            }
        }
        for i in 0..self.prior_count {
            let Some(slot) = self.priors.get(i) else {
                continue;
            };
            let p = slot.prior;
            let (Some(from), Some(to)) = (self.poses.get(p.from), self.poses.get(p.to)) else {
                continue;
            };
            let (e, ja, jb) = prior_residual(&p, &from.pose, &to.pose);
            let (ja_to, jb_to) = (
                ja.transpose() * p.information,
                jb.transpose() * p.information,
            );
            if let Some(from) = self.poses.get_mut(p.from).filter(|_| p.from >= fixed) {
                from.u += ja_to * ja;
                from.b -= ja_to * e;
            }
            if let Some(to) = self.poses.get_mut(p.to).filter(|_| p.to >= fixed) {
                to.u += jb_to * jb;
                to.b -= jb_to * e;
            }
            if let Some(slot) = self.priors.get_mut(i) {
                slot.cross = ja_to * jb;
            }
        }
    }

    /// Solves the damped normal equations by eliminating the landmarks; leaves the steps in
    /// the slots and returns the largest of them, or `None` when a block or the reduced
    /// system is not positive definite at this damping.
    pub(super) fn compute_step(&mut self, fixed: usize, lambda: f64) -> Option<f64> {
        let np = self.pose_count;
        let free = np.saturating_sub(fixed);
        for row in self.reduced.iter_mut().take(free) {
            for block in row.iter_mut().take(free) {
                *block = ZERO3;
            }
        }
        for f in 0..free {
            let pose = self.poses.get(f + fixed)?;
            *self.reduced.get_mut(f)?.get_mut(f)? = damped(&pose.u, lambda);
            *self.reduced_rhs.get_mut(f)? = pose.b;
        }
        // The factorisation reads only the blocks on and below the diagonal: only those are
        // formed, which halves the landmark pairs below.
        for slot in self.priors.iter().take(self.prior_count) {
            let (a, b) = (slot.prior.from, slot.prior.to);
            if a >= fixed && b >= fixed {
                let (a, b) = (a - fixed, b - fixed);
                if a > b {
                    *self.reduced.get_mut(a)?.get_mut(b)? += slot.cross;
                } else {
                    *self.reduced.get_mut(b)?.get_mut(a)? += slot.cross.transpose();
                }
            }
        }
        for l in 0..self.landmark_count {
            let lm = self.landmarks.get_mut(l)?;
            if lm.status != LandmarkStatus::Active {
                continue;
            }
            // The damping itself keeps the block invertible; only a breakdown is refused.
            lm.v_inv = spd3_inverse(&damped(&lm.v, lambda), 0.0)?;
            let (v_inv, b_l, first) = (lm.v_inv, lm.b, lm.first_obs);
            let mut a = first;
            while let Some(oa) = self.observations.get(a) {
                if oa.status == ObservationStatus::Pending && oa.obs.keyframe >= fixed {
                    let ka = oa.obs.keyframe - fixed;
                    let t = oa.w * v_inv;
                    *self.reduced_rhs.get_mut(ka)? -= t * b_l;
                    let mut b = first;
                    while let Some(ob) = self.observations.get(b) {
                        let lower = ob.obs.keyframe >= fixed && ob.obs.keyframe - fixed <= ka;
                        if ob.status == ObservationStatus::Pending && lower {
                            let kb = ob.obs.keyframe - fixed;
                            *self.reduced.get_mut(ka)?.get_mut(kb)? -= t * ob.w.transpose();
                        }
                        b = ob.next;
                    }
                }
                a = oa.next;
            }
        }
        dense::cholesky_solve(&mut self.reduced, &mut self.reduced_rhs, free)?;
        let mut largest = 0.0f64;
        for p in self.poses.iter_mut().take(fixed.min(np)) {
            p.step = ZERO_V;
        }
        for f in 0..free {
            let step = *self.reduced_rhs.get(f)?;
            largest = largest.max(step.amax());
            self.poses.get_mut(f + fixed)?.step = step;
        }
        // Back-substitution: each landmark's step given the poses'.
        for l in 0..self.landmark_count {
            let lm = self.landmarks.get(l)?;
            if lm.status != LandmarkStatus::Active {
                continue;
            }
            let mut rhs = lm.b;
            let mut o = lm.first_obs;
            while let Some(slot) = self.observations.get(o) {
                if slot.status == ObservationStatus::Pending {
                    if let Some(pose) = self.poses.get(slot.obs.keyframe) {
                        rhs -= slot.w.transpose() * pose.step;
                    }
                }
                o = slot.next;
            }
            let lm = self.landmarks.get_mut(l)?;
            lm.step = lm.v_inv * rhs;
            largest = largest.max(lm.step.amax());
        }
        largest.is_finite().then_some(largest)
    }

    pub(super) fn apply_step(&mut self, fixed: usize) {
        let np = self.pose_count;
        for p in self.poses.iter_mut().take(np).skip(fixed) {
            p.backup = p.pose;
            p.pose = Se2::new(
                p.pose.x + p.step.x,
                p.pose.y + p.step.y,
                p.pose.theta + p.step.z,
            );
        }
        let nl = self.landmark_count;
        for l in self.landmarks.iter_mut().take(nl) {
            l.backup = l.position;
            if l.status == LandmarkStatus::Active {
                l.position += l.step;
            }
        }
    }

    pub(super) fn restore(&mut self, fixed: usize) {
        let (np, nl) = (self.pose_count, self.landmark_count);
        for p in self.poses.iter_mut().take(np).skip(fixed) {
            p.pose = p.backup;
        }
        for l in self.landmarks.iter_mut().take(nl) {
            l.position = l.backup;
        }
    }

    /// Each used observation's chi2 at the result and its inlier flag; returns the counts.
    pub(super) fn flag(
        &mut self,
        model: &CameraModel,
        mount: &CameraExtrinsic,
        gate: f64,
    ) -> (usize, usize) {
        self.refresh_trig();
        let (mut inliers, mut outliers) = (0, 0);
        let no = self.observation_count;
        for slot in self.observations.iter_mut().take(no) {
            let in_use = matches!(
                slot.status,
                ObservationStatus::Pending | ObservationStatus::Inlier | ObservationStatus::Outlier
            );
            if !in_use {
                continue;
            }
            let (Some(pose), Some(lm)) = (
                self.poses.get(slot.obs.keyframe),
                self.landmarks.get(slot.obs.landmark),
            ) else {
                continue;
            };
            // A landmark set aside in a later round takes its rejected observations along.
            if lm.status != LandmarkStatus::Active {
                slot.status = ObservationStatus::Skipped;
                continue;
            }
            let (p, c, s) = (&pose.pose, pose.cos, pose.sin);
            let lin = residual(model, mount, p, (c, s), &lm.position, &slot.obs.px);
            let chi2 = lin.map_or(f64::INFINITY, |r| {
                r.norm_squared() / (slot.obs.sigma_px * slot.obs.sigma_px)
            });
            slot.chi2 = chi2;
            if chi2 <= gate {
                slot.status = ObservationStatus::Inlier;
                inliers += 1;
            } else {
                slot.status = ObservationStatus::Outlier;
                outliers += 1;
            }
        }
        (inliers, outliers)
    }
}
