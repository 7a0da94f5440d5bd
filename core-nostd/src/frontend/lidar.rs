//! The LiDAR odometry stage of the front-end (the paper's section III-B.2): one scan in, the
//! front-end pose out.
//!
//! The front-end pose drifts but is locally exact. Each scan is placed in three steps:
//! 1. **seed**: the previous front-end pose composed with the fused wheel odometry's increment
//!    since the previous scan (identity when the odometry has a gap). An input that has given
//!    no odometry at all (a LiDAR alone) is seeded with the previous scan's step instead: a
//!    robot keeps its speed and turn rate over one scan far better than it stops;
//! 2. **match**: ICP of the preprocessed scan against the local point map, from the seed and,
//!    while turning fast, from seeds rotated by multiples of the turn (a wheel heading that
//!    lags or leads the scan by a frame puts the seed outside ICP's basin); a match below the
//!    fitness floor leaves the seed. The odometry's prediction enters the match as a prior
//!    ([`align_with_prior`]) with the increment's covariance from the noise model: where the
//!    scan pins the pose down (walls in several directions) the prior hardly moves it; where
//!    it leaves a direction weak (the heading in a round hall, a hall mostly beyond the
//!    LiDAR's range, the axis of a corridor) the wheels and the gyro decide it in proportion
//!    to the two informations, instead of the match sliding into a wrong minimum;
//! 3. **stall compensation**: when the odometry reports exactly no motion for two scans or
//!    more while the matcher sees the robot move, the stream has stalled and will report that
//!    motion later in one increment; the motion seen meanwhile is taken off that increment so
//!    it is not seeded twice. A single still scan is an odometry that lags by a frame when the
//!    robot starts to move (intel's does, dozens of times), whose next increments are each a
//!    frame late rather than a burst: taking the first frame's motion off would seed the
//!    second with none.
//!
//! The noise model is a preset, not this robot's calibration: real odometry may slip, or be
//! stamped a frame late (as in the CARMEN logs), and then a prior that trusts the model drags
//! good matches toward a wrong prediction. So the prior's covariance is scaled by a running
//! mean of the normalized squared difference between match and prediction (its expectation is
//! 1 when the model is right; adaptive noise estimation from the innovations): the plain mean
//! of the samples so far, then a running mean over about the last 100 scans. Before the first
//! sample the scale is at its largest, so the odometry is trusted only once the scans have
//! shown how far it deserves it; it never goes below 1. A still odometry (possibly stalled)
//! and an odometry gap give no prior. Where the gyro gave the prediction's heading, the same
//! match-prediction difference measures the gyro's bias ([`GyroBias`]), which the caller takes
//! off the gyro's rates.
//!
//! The stage also keeps the [`Travel`] (path length and absolute rotation) of the front-end,
//! the variable of the motion-uncertainty model ([`MotionNoise`]) that the GPE and the
//! loop-closure windows share, and the [`Spread`]: the covariance its estimate accumulated,
//! which the odometry edges carry. A step rests on two measurements: the match, whose error is
//! the model's (errors of the map matched against, which a scan's own residuals do not show)
//! plus its own (the inverse of the scan's information, which is small where walls in several
//! directions pin the pose down and unbounded along a corridor's axis), and the odometry's
//! prediction, with its own model's covariance scaled as above. The step's covariance is that
//! of the two fused. So an edge says what the front-end knew: the heading of a robot whose
//! gyro keeps a small scale better than the matcher's model alone claims, the position along
//! a corridor no better than the wheels, and a robot whose odometry proves poor (a large
//! scale) about the model's covariance. The model's constants are presets; the scale is measured on this run.
//! Without a prediction (a LiDAR alone, an odometry gap or stall) the step adds the model's
//! growth, as the travel does.

use super::gyro_bias::GyroBias;
use super::icp::{align_with_prior, IcpConfig, IcpResult, MatchError, Prior};
use super::odometry::OdomIncrement;
use super::pointmap::PointMap;
use super::scan::ScanPoint;
use nalgebra::{Matrix3, Vector3};

use crate::geom::{cov_in_frame, cov_out_of_frame, spd_inverse, wrap_angle, Cov3, Se2};

/// Share of a scan interval whose heading must come from the gyro for the match to measure the
/// gyro's bias (the rest: a wheel sample at either end without a live gyro).
const GYRO_COVER: f64 = 0.99;
/// Weight of one scan in the running mean of the odometry noise scale (about the last 100
/// scans).
const NOISE_SCALE_RATE: f64 = 0.01;
/// One scan's sample of the noise scale is clamped to this, so once the horizon is full a
/// single wrong match or wheel slip moves the mean by at most `NOISE_SCALE_RATE` times it.
const NOISE_SCALE_MAX: f64 = 100.0;
/// The rotated seeds tried while turning, as multiples of the odometry's rotation step.
const TURN_RESEED_MULTIPLES: [f64; 4] = [-2.0, -1.0, 1.0, 2.0];
/// A rotated seed's match may lose at most this much fitness against the current best...
const RESEED_FITNESS_SLACK: f32 = 0.05;
/// ... and must bring the RMS residual below this share of the best one: clearly better only,
/// so a wrong minimum near a good one cannot win on noise.
const RESEED_RMS_RATIO: f64 = 0.7;

/// Fewest still scans with matched motion that make a stall (module docs, step 3).
const MIN_STALL_SCANS: u32 = 2;

/// Path length (metres) and absolute rotation (radians) travelled by the front-end.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Travel {
    /// Path length, metres.
    pub path: f64,
    /// Sum of absolute heading changes, radians.
    pub rotation: f64,
}

impl Travel {
    /// Nothing travelled.
    pub const ZERO: Travel = Travel {
        path: 0.0,
        rotation: 0.0,
    };

    /// The travel from `earlier` to `self`.
    pub fn since(&self, earlier: &Travel) -> Travel {
        Travel {
            path: self.path - earlier.path,
            rotation: self.rotation - earlier.rotation,
        }
    }
}

/// Covariance accumulated by the front-end's estimate, summed over its steps in the front-end
/// frame's axes (module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Spread {
    /// `[x, y, theta]` covariance, front-end axes.
    pub cov: Cov3,
}

impl Default for Spread {
    fn default() -> Self {
        Spread::ZERO
    }
}

/// What a step's estimate rests on besides the motion model (module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepEvidence {
    /// The scan match's own information (zero when the match failed and the prediction
    /// stood), front-end axes.
    pub scan: Matrix3<f64>,
    /// The information of the odometry's prediction, as scaled for the match, front-end axes.
    pub prediction: Matrix3<f64>,
}

impl Spread {
    /// Nothing accumulated.
    pub const ZERO: Spread = Spread {
        cov: Matrix3::new(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    };

    /// The covariance accumulated from `earlier` to `self`, in the axes of a frame whose
    /// heading in the front-end frame is `heading`.
    pub fn since_in(&self, earlier: &Spread, heading: f64) -> Cov3 {
        cov_in_frame(&(self.cov - earlier.cov), heading)
    }

    /// The covariance one front-end `step` adds. Without `evidence`, the growth of `noise`
    /// over the step (without the model's floor, which the consumer adds once). With it, the
    /// matcher's error is the model's plus its own measurement error (the inverse of the
    /// scan's information: negligible where the scan pins the pose down, unbounded along a
    /// direction it leaves free), and the step fuses that with the prediction.
    pub fn of_step(noise: &dyn MotionNoise, step: &Se2, evidence: Option<&StepEvidence>) -> Cov3 {
        let (d, r) = (libm::hypot(step.x, step.y), libm::fabs(step.theta));
        let model = noise.covariance(d, r) - noise.covariance(0.0, 0.0);
        let fused = evidence.and_then(|e| {
            let own = spd_inverse(&model)?;
            // (C_scan + C_model)^-1 = I_scan (I_scan + I_model)^-1 I_model, defined even when
            // the scan's information is singular.
            let matcher = e.scan * spd_inverse(&(e.scan + own))? * own;
            let matcher = (matcher + matcher.transpose()) * 0.5;
            spd_inverse(&(matcher + e.prediction))
        });
        fused.unwrap_or(model)
    }
}

/// The front-end's motion-uncertainty model: the covariance of a motion as a function of its
/// path length and rotation.
pub trait MotionNoise: core::fmt::Debug {
    /// Covariance of a motion of path length `distance` and rotation `rotation`.
    fn covariance(&self, distance: f64, rotation: f64) -> Cov3;

    /// Covariance accumulated over `travel`.
    fn over(&self, travel: &Travel) -> Cov3 {
        self.covariance(travel.path, travel.rotation)
    }
}

/// Parameters of the LiDAR front-end, borrowed from the mapper's configuration.
#[derive(Clone, Copy, Debug)]
pub struct LidarParams<'a> {
    /// Scan-to-map ICP.
    pub icp: &'a IcpConfig,
    /// A match below this fitness falls back to the seed.
    pub min_fitness: f32,
    /// Rotated seeds are tried when the odometry turns more than this per scan, radians
    /// (0: never).
    pub turn_reseed: f64,
    /// ... and only when the primary match's RMS residual is above this, metres.
    pub turn_reseed_rms: f64,
    /// Matcher motion `[metres, radians]` above which a still odometry counts as stalled;
    /// `None` disables the stall compensation.
    pub stall_motion: Option<[f64; 2]>,
    /// Uncertainty of the matcher's motion, fused with the prediction's in [`Spread`].
    pub noise: &'a dyn MotionNoise,
}

/// Counters of the front-end.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FrontendCounters {
    /// Scans whose match failed or was too weak (the seed was used).
    pub icp_failures: u32,
    /// Scans matched with a degenerate direction left at the seed.
    pub icp_degenerate: u32,
    /// Scans without an odometry increment.
    pub odometry_gaps: u32,
    /// Scans seen as moving while the odometry stood still.
    pub odometry_stalls: u32,
}

/// The previous accepted scan, as the next one needs it.
#[derive(Clone, Copy, Debug, PartialEq)]
struct PreviousScan {
    /// Its front-end pose.
    pose: Se2,
    /// The fused odometry pose at its stamp, if there was one.
    odometry: Option<Se2>,
}

/// The result of one scan.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrontendStep {
    /// Front-end pose of the scan.
    pub pose: Se2,
    /// Motion since the previous scan (identity for the first).
    pub step: Se2,
}

/// The LiDAR odometry state carried from scan to scan.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LidarFrontend {
    previous: Option<PreviousScan>,
    pose: Se2,
    /// Motion the matcher measured while the odometry stood still, not reported by the
    /// odometry yet: taken off its next increment when the stall lasted
    /// [`MIN_STALL_SCANS`] scans or more.
    stall: Se2,
    /// Scans of the current still stretch in which the matcher saw motion.
    stall_scans: u32,
    travel: Travel,
    spread: Spread,
    /// Running mean of the normalized squared difference between the match and the odometry's
    /// prediction over three (1 when the noise model is right); the prediction's covariance is
    /// scaled by it, at least 1.
    noise_scale: f64,
    /// Samples in `noise_scale` (counted up to the averaging horizon).
    noise_samples: u32,
    /// The gyro's bias, measured by the matches.
    gyro_bias: GyroBias,
    /// Some scan so far came with an odometry pose.
    odometry_seen: bool,
    /// The last scan's step (the seed of the next when the input has no odometry).
    last_step: Se2,
    counters: FrontendCounters,
}

impl Default for LidarFrontend {
    fn default() -> Self {
        Self::new()
    }
}

impl LidarFrontend {
    /// The state before the first scan.
    pub const fn new() -> Self {
        LidarFrontend {
            previous: None,
            pose: Se2::IDENTITY,
            stall: Se2::IDENTITY,
            stall_scans: 0,
            travel: Travel::ZERO,
            spread: Spread::ZERO,
            noise_scale: NOISE_SCALE_MAX,
            noise_samples: 0,
            gyro_bias: GyroBias::new(),
            odometry_seen: false,
            last_step: Se2::IDENTITY,
            counters: FrontendCounters {
                icp_failures: 0,
                icp_degenerate: 0,
                odometry_gaps: 0,
                odometry_stalls: 0,
            },
        }
    }

    /// Front-end pose of the last scan.
    pub fn pose(&self) -> Se2 {
        self.pose
    }

    /// Travel up to the last scan.
    pub fn travel(&self) -> Travel {
        self.travel
    }

    /// Covariance accumulated up to the last scan (see [`Spread`]).
    pub fn spread(&self) -> Spread {
        self.spread
    }

    /// Counters so far.
    pub fn counters(&self) -> FrontendCounters {
        self.counters
    }

    /// True once a scan has been tracked.
    pub fn started(&self) -> bool {
        self.previous.is_some()
    }

    /// Places `scan` (robot frame) against `local` (front-end frame), seeded by the fused
    /// `odometry` pose at the scan's stamp; `motion` is the odometry's motion since the
    /// previous scan, whose covariance (in that scan's frame) makes the prior of the match.
    pub fn track<const N: usize>(
        &mut self,
        scan: &[ScanPoint],
        local: &mut PointMap<N>,
        odometry: Option<Se2>,
        motion: Option<&OdomIncrement>,
        params: &LidarParams<'_>,
    ) -> FrontendStep {
        let previous = self.previous.unwrap_or(PreviousScan {
            pose: Se2::IDENTITY,
            odometry,
        });
        self.odometry_seen |= odometry.is_some();
        let (increment, odometry_still) = self.odometry_increment(&previous, odometry);
        let seed = previous.pose.compose(&increment);
        // The odometry's prediction as a measurement: only for a real increment (not a gap, not
        // a still stream that may be a stall).
        let predicted = motion
            .map(|m| m.motion.cov)
            .filter(|_| {
                self.previous.is_some()
                    && previous.odometry.is_some()
                    && odometry.is_some()
                    && !odometry_still
            })
            .and_then(|cov| Self::prediction_information(previous.pose.theta, &cov));
        let mut pose = seed;
        // What the step rests on besides the model, when a prediction took part.
        let mut evidence = None;
        if !local.is_empty() {
            let turn = libm::fabs(increment.theta);
            let scale = self.noise_scale.max(1.0);
            let prior = predicted.map(|information| Prior {
                pose: seed,
                information: information / scale,
            });
            match Self::match_scan(scan, local, &seed, prior.as_ref(), turn, params) {
                Ok(r) if r.fitness >= params.min_fitness => {
                    pose = r.pose;
                    evidence = prior.map(|p| StepEvidence {
                        scan: r.information,
                        prediction: p.information,
                    });
                    if let Some(info) = predicted {
                        self.calibrate(&r, &seed, &info);
                        if let Some(m) = motion {
                            self.measure_gyro_bias(&r, &seed, m);
                        }
                    }
                    if r.degenerate.is_some() {
                        self.counters.icp_degenerate += 1;
                    }
                }
                _ => {
                    self.counters.icp_failures += 1;
                    evidence = prior.map(|p| StepEvidence {
                        scan: Matrix3::zeros(),
                        prediction: p.information,
                    });
                }
            }
        }
        let step = previous.pose.between(&pose);
        self.compensate_stall(&step, odometry_still, params.stall_motion);
        if self.previous.is_some() {
            self.travel.path += libm::sqrt(step.x * step.x + step.y * step.y);
            self.travel.rotation += libm::fabs(step.theta);
            self.spread.cov += Spread::of_step(params.noise, &step, evidence.as_ref());
        }
        self.pose = pose;
        self.last_step = step;
        self.previous = Some(PreviousScan { pose, odometry });
        FrontendStep { pose, step }
    }

    /// The odometry's motion since the previous scan, less the motion a stall hid, and whether
    /// the odometry stood exactly still.
    fn odometry_increment(&mut self, previous: &PreviousScan, now: Option<Se2>) -> (Se2, bool) {
        match (previous.odometry, now) {
            (Some(a), Some(b)) if a == b => (Se2::IDENTITY, true),
            // The first increment after a stall carries the motion the stall hid, part of
            // which the scan matcher has already measured.
            (Some(a), Some(b)) if self.stall_scans >= MIN_STALL_SCANS => {
                (self.stall.inverse().compose(&a.between(&b)), false)
            }
            (Some(a), Some(b)) => (a.between(&b), false),
            _ if !self.odometry_seen => (self.last_step, false),
            _ => {
                if self.previous.is_some() {
                    self.counters.odometry_gaps += 1;
                }
                (Se2::IDENTITY, false)
            }
        }
    }

    /// Information of the odometry's prediction in the front-end frame's axes: the increment's
    /// covariance `cov` is in the frame of the previous pose (heading `heading`). `None` when
    /// it is not invertible.
    fn prediction_information(heading: f64, cov: &Cov3) -> Option<Matrix3<f64>> {
        spd_inverse(&cov_out_of_frame(cov, heading))
    }

    /// Updates the odometry noise scale from one match `r` against the prediction `seed`
    /// (information `info`, before scaling): the squared Mahalanobis distance of their
    /// difference, whose expectation is 3 when both covariances are right.
    fn calibrate(&mut self, r: &IcpResult, seed: &Se2, info: &Matrix3<f64>) {
        let e = Vector3::new(
            seed.x - r.pose.x,
            seed.y - r.pose.y,
            wrap_angle(seed.theta - r.pose.theta),
        );
        let Some(sum_inv) = spd_inverse(&(r.information + info)) else {
            return;
        };
        // The information of the difference of two independent estimates:
        // (C_r + C_p)^-1 = I_r (I_r + I_p)^-1 I_p, defined even when I_r is singular.
        let d2 = e.dot(&(r.information * sum_inv * info * e));
        if d2.is_finite() {
            let sample = (d2 / 3.0).min(NOISE_SCALE_MAX);
            // The plain mean of the samples so far, then a running mean over the horizon.
            self.noise_samples = self.noise_samples.saturating_add(1);
            let rate = (1.0 / self.noise_samples as f64).max(NOISE_SCALE_RATE);
            self.noise_scale += rate * (sample - self.noise_scale);
        }
    }

    /// One measurement of the gyro's bias from the match `r` against the prediction `seed`,
    /// when the gyro gave the heading over the whole interval of `motion`.
    fn measure_gyro_bias(&mut self, r: &IcpResult, seed: &Se2, motion: &OdomIncrement) {
        if !(motion.seconds > 0.0 && motion.gyro_seconds >= GYRO_COVER * motion.seconds) {
            return;
        }
        let Some(cov) = spd_inverse(&r.information) else {
            return;
        };
        let innovation = wrap_angle(seed.theta - r.pose.theta);
        let variance = cov[(2, 2)] + motion.motion.cov[(2, 2)];
        self.gyro_bias.update(innovation, variance, motion.seconds);
    }

    /// The estimated bias of the gyro, rad/s (see [`GyroBias`]).
    pub fn gyro_bias(&self) -> f64 {
        self.gyro_bias.bias()
    }

    /// ICP from `seed`, and while turning by more than `turn` allows, from the rotated seeds.
    fn match_scan<const N: usize>(
        scan: &[ScanPoint],
        local: &mut PointMap<N>,
        seed: &Se2,
        prior: Option<&Prior>,
        turn: f64,
        params: &LidarParams<'_>,
    ) -> Result<IcpResult, MatchError> {
        let tree = local.tree();
        let mut best = align_with_prior(scan, &tree, seed, prior, params.icp);
        // A primary match whose residual is at the noise level has found its basin: the
        // rotated seeds are for rescuing the ones that have not.
        let settled = matches!(&best, Ok(b) if b.rms <= params.turn_reseed_rms);
        if params.turn_reseed > 0.0 && turn > params.turn_reseed && !settled {
            for k in TURN_RESEED_MULTIPLES {
                let alt = Se2::new(seed.x, seed.y, seed.theta + k * turn);
                let Ok(r) = align_with_prior(scan, &tree, &alt, prior, params.icp) else {
                    continue;
                };
                let better = match &best {
                    Ok(b) => {
                        r.fitness >= b.fitness - RESEED_FITNESS_SLACK
                            && r.rms < RESEED_RMS_RATIO * b.rms
                    }
                    Err(_) => true,
                };
                if better {
                    best = Ok(r);
                }
            }
        }
        best
    }

    /// Accumulates the matcher's `step` while the odometry stands still and moves are seen;
    /// forgets it once the odometry moves again.
    fn compensate_stall(&mut self, step: &Se2, odometry_still: bool, stall: Option<[f64; 2]>) {
        if let (true, Some(d)) = (odometry_still, stall) {
            if libm::sqrt(step.x * step.x + step.y * step.y) > d[0] || libm::fabs(step.theta) > d[1]
            {
                self.counters.odometry_stalls += 1;
                self.stall = self.stall.compose(step);
                self.stall_scans += 1;
            }
        } else {
            self.stall = Se2::IDENTITY;
            self.stall_scans = 0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Variances growing with path and rotation over a floor, as the mapper's model does.
    #[derive(Debug)]
    struct Linear;

    impl MotionNoise for Linear {
        fn covariance(&self, distance: f64, rotation: f64) -> Cov3 {
            let xy = 4e-4 * distance + 1e-4 * rotation + 1e-6;
            let th = 1e-4 * distance + 4e-4 * rotation + 1e-7;
            Matrix3::from_diagonal(&Vector3::new(xy, xy, th))
        }
    }

    #[test]
    fn without_a_prediction_the_spread_is_the_models_growth() {
        let steps = [
            Se2::new(0.1, 0.0, 0.02),
            Se2::new(0.12, 0.01, -0.05),
            Se2::new(0.0, 0.0, 0.3),
        ];
        let (mut total, mut travel) = (Spread::ZERO, Travel::ZERO);
        for s in &steps {
            total.cov += Spread::of_step(&Linear, s, None);
            travel.path += libm::hypot(s.x, s.y);
            travel.rotation += libm::fabs(s.theta);
        }
        let model = Linear.over(&travel) - Linear.covariance(0.0, 0.0);
        assert!((total.since_in(&Spread::ZERO, 1.0) - model).norm() < 1e-15);
        let still = StepEvidence {
            scan: Matrix3::identity(),
            prediction: Matrix3::identity(),
        };
        assert_eq!(
            Spread::of_step(&Linear, &Se2::IDENTITY, Some(&still)),
            Matrix3::zeros()
        );
    }

    #[test]
    fn a_prediction_narrows_the_spread_and_a_free_direction_follows_it() {
        let step = Se2::new(0.2, 0.0, 0.05);
        let model = Spread::of_step(&Linear, &step, None);
        let expect = |a: f64, b: f64| 1.0 / (1.0 / a + 1.0 / b);
        // A gyro-like prediction (loose position, heading variance 1e-6 rad^2) and a scan that
        // pins every direction down: the model fused with the prediction.
        let gyro = Matrix3::from_diagonal(&Vector3::new(1e2, 1e2, 1e6));
        let sharp = StepEvidence {
            scan: Matrix3::from_diagonal_element(1e12),
            prediction: gyro,
        };
        let fused = Spread::of_step(&Linear, &step, Some(&sharp));
        assert!((fused[(2, 2)] - expect(model[(2, 2)], 1e-6)).abs() < 1e-12);
        assert!((fused[(0, 0)] - expect(model[(0, 0)], 1e-2)).abs() < 1e-9);
        // A corridor along x: the scan says nothing about x, so the prediction alone decides it.
        let corridor = StepEvidence {
            scan: Matrix3::from_diagonal(&Vector3::new(0.0, 1e12, 1e12)),
            prediction: gyro,
        };
        let along = Spread::of_step(&Linear, &step, Some(&corridor));
        assert!((along[(0, 0)] - 1e-2).abs() < 1e-9);
        assert!((along[(1, 1)] - fused[(1, 1)]).abs() < 1e-9);
        // A failed match (no scan information): the prediction's covariance.
        let failed = StepEvidence {
            scan: Matrix3::zeros(),
            prediction: gyro,
        };
        let odo = Spread::of_step(&Linear, &step, Some(&failed));
        assert!((odo - gyro.try_inverse().expect("invertible")).norm() < 1e-12);
        // Seen from a frame turned by 90 degrees, x and y swap.
        let mut s = Spread::ZERO;
        s.cov += along;
        let turned = s.since_in(&Spread::ZERO, core::f64::consts::FRAC_PI_2);
        assert!((turned[(1, 1)] - along[(0, 0)]).abs() < 1e-12);
    }
}
