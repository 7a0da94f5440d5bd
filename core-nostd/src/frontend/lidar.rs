//! The LiDAR odometry stage of the front-end (the paper's section III-B.2): one scan in, the
//! front-end pose out.
//!
//! The front-end pose drifts but is locally exact. Each scan is placed in three steps:
//! 1. **seed**: the previous front-end pose composed with the fused wheel odometry's increment
//!    since the previous scan (identity when the odometry has a gap);
//! 2. **match**: ICP of the preprocessed scan against the local point map, from the seed and,
//!    while turning fast, from seeds rotated by multiples of the turn (a wheel heading that
//!    lags or leads the scan by a frame puts the seed outside ICP's basin); a match below the
//!    fitness floor leaves the seed;
//! 3. **stall compensation**: when the odometry reports exactly no motion while the matcher
//!    sees the robot move, the stream has stalled and will report that motion later in one
//!    increment; the motion seen meanwhile is taken off that increment so it is not seeded
//!    twice.
//!
//! The stage also keeps the [`Travel`] (path length and absolute rotation) of the front-end,
//! the variable of the motion-uncertainty model ([`MotionNoise`]) that the GPE, the odometry
//! edges and the loop-closure windows share.

use super::icp::{align, IcpConfig, IcpResult, MatchError};
use super::pointmap::PointMap;
use super::scan::ScanPoint;
use crate::geom::{Cov3, Se2};

/// The rotated seeds tried while turning, as multiples of the odometry's rotation step.
const TURN_RESEED_MULTIPLES: [f64; 4] = [-2.0, -1.0, 1.0, 2.0];
/// A rotated seed's match may lose at most this much fitness against the current best...
const RESEED_FITNESS_SLACK: f32 = 0.05;
/// ... and must bring the RMS residual below this share of the best one: clearly better only,
/// so a wrong minimum near a good one cannot win on noise.
const RESEED_RMS_RATIO: f64 = 0.7;

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

/// The front-end's motion-uncertainty model: the covariance of a motion as a function of its
/// path length and rotation.
pub trait MotionNoise {
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
    /// odometry yet: taken off its next increment.
    stall: Se2,
    travel: Travel,
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
            travel: Travel::ZERO,
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

    /// Counters so far.
    pub fn counters(&self) -> FrontendCounters {
        self.counters
    }

    /// True once a scan has been tracked.
    pub fn started(&self) -> bool {
        self.previous.is_some()
    }

    /// Places `scan` (robot frame) against `local` (front-end frame), seeded by the fused
    /// `odometry` pose at the scan's stamp.
    pub fn track<const N: usize>(
        &mut self,
        scan: &[ScanPoint],
        local: &mut PointMap<N>,
        odometry: Option<Se2>,
        params: &LidarParams<'_>,
    ) -> FrontendStep {
        let previous = self.previous.unwrap_or(PreviousScan {
            pose: Se2::IDENTITY,
            odometry,
        });
        let (increment, odometry_still) = self.odometry_increment(&previous, odometry);
        let seed = previous.pose.compose(&increment);
        let mut pose = seed;
        if !local.points().is_empty() {
            match Self::match_scan(scan, local, &seed, libm::fabs(increment.theta), params) {
                Ok(r) if r.fitness >= params.min_fitness => {
                    pose = r.pose;
                    if r.degenerate.is_some() {
                        self.counters.icp_degenerate += 1;
                    }
                }
                _ => self.counters.icp_failures += 1,
            }
        }
        let step = previous.pose.between(&pose);
        self.compensate_stall(&step, odometry_still, params.stall_motion);
        if self.previous.is_some() {
            self.travel.path += libm::sqrt(step.x * step.x + step.y * step.y);
            self.travel.rotation += libm::fabs(step.theta);
        }
        self.pose = pose;
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
            (Some(a), Some(b)) => (self.stall.inverse().compose(&a.between(&b)), false),
            _ => {
                if self.previous.is_some() {
                    self.counters.odometry_gaps += 1;
                }
                (Se2::IDENTITY, false)
            }
        }
    }

    /// ICP from `seed`, and while turning by more than `turn` allows, from the rotated seeds.
    fn match_scan<const N: usize>(
        scan: &[ScanPoint],
        local: &mut PointMap<N>,
        seed: &Se2,
        turn: f64,
        params: &LidarParams<'_>,
    ) -> Result<IcpResult, MatchError> {
        let tree = local.tree();
        let mut best = align(scan, &tree, seed, params.icp);
        // A primary match whose residual is at the noise level has found its basin: the
        // rotated seeds are for rescuing the ones that have not.
        let settled = matches!(&best, Ok(b) if b.rms <= params.turn_reseed_rms);
        if params.turn_reseed > 0.0 && turn > params.turn_reseed && !settled {
            for k in TURN_RESEED_MULTIPLES {
                let alt = Se2::new(seed.x, seed.y, seed.theta + k * turn);
                let Ok(r) = align(scan, &tree, &alt, params.icp) else {
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
            }
        } else {
            self.stall = Se2::IDENTITY;
        }
    }
}
