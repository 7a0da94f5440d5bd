//! Parameters of the mapper, with defaults for the benchmark logs (a 180-degree scanner on a
//! wheeled base) and 10 m submaps.

use crate::backend::schedule::ScheduleParams;
use crate::frontend::lidar::{LidarParams, MotionNoise};
use crate::frontend::odometry::OdometryConfig;
use crate::frontend::visual::TrackConfig;
use crate::frontend::{GridParams, IcpConfig, KeyframeConfig, PreprocessConfig};
use crate::geom::Cov3;
use crate::mapper::gpe::GpeConfig;
use nalgebra::Matrix3;

/// Uncertainty of the front-end's motion (LiDAR odometry), as a function of the path length
/// `d` and the absolute rotation `phi` travelled: variances `var_xy_per_m * d +
/// var_xy_per_rad * phi` for each position axis and `var_theta_per_m * d +
/// var_theta_per_rad * phi` for the heading, plus the floors. The same model gives the
/// covariances of the GPE terms and the loop-closure search window; for the odometry edges the
/// front-end fuses its growth with the odometry's prediction scan by scan
/// (`frontend::lidar::Spread`).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FrontendNoise {
    /// Position variance per metre, m^2/m.
    pub var_xy_per_m: f64,
    /// Position variance per radian, m^2/rad.
    pub var_xy_per_rad: f64,
    /// Heading variance per metre, rad^2/m.
    pub var_theta_per_m: f64,
    /// Heading variance per radian, rad^2/rad.
    pub var_theta_per_rad: f64,
    /// Floor of the position variance, m^2.
    pub min_var_xy: f64,
    /// Floor of the heading variance, rad^2.
    pub min_var_theta: f64,
}

impl Default for FrontendNoise {
    fn default() -> Self {
        FrontendNoise {
            var_xy_per_m: 4e-4,
            var_xy_per_rad: 1e-4,
            var_theta_per_m: 1e-4,
            var_theta_per_rad: 4e-4,
            min_var_xy: 1e-6,
            min_var_theta: 1e-7,
        }
    }
}

impl FrontendNoise {
    /// Covariance of a motion of path length `distance` and rotation `rotation` (both taken
    /// as absolute values).
    pub fn covariance(&self, distance: f64, rotation: f64) -> Cov3 {
        let (d, r) = (libm::fabs(distance), libm::fabs(rotation));
        let xy = self.var_xy_per_m * d + self.var_xy_per_rad * r + self.min_var_xy;
        let th = self.var_theta_per_m * d + self.var_theta_per_rad * r + self.min_var_theta;
        Matrix3::new(xy, 0.0, 0.0, 0.0, xy, 0.0, 0.0, 0.0, th)
    }
}

/// Loop-closure parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LoopConfig {
    /// Search on every `every`-th keyframe (1: every keyframe).
    pub every: u32,
    /// A submap whose anchor is fewer than this many keyframes older than the keyframe is not
    /// searched (it is linked by odometry already).
    pub min_keyframe_gap: u32,
    /// Search window half-width: `sigmas` standard deviations of the position uncertainty
    /// accumulated since the candidate submap's anchor (`window_from_anchor`) or since the
    /// last loop closure, clamped to `[window_min, window_max]` metres.
    pub sigmas: f64,
    /// Smallest translation window, metres.
    pub window_min: f64,
    /// Largest translation window, metres.
    pub window_max: f64,
    /// The window of a candidate submap is the uncertainty of the front-end motion since the
    /// submap's anchor (instead of since the last loop closure, which says nothing about the
    /// drift relative to an old submap when the last loop was a local one).
    pub window_from_anchor: bool,
    /// Lever arm of the heading uncertainty in the position window, as a share of the path
    /// length: a heading error made along the way displaces the end by about this lever
    /// times the path.
    pub window_lever: f64,
    /// Smallest rotation window, radians.
    pub angle_min: f64,
    /// Largest rotation window, radians.
    pub angle_max: f64,
    /// Smallest correlative score accepted.
    pub min_score: f32,
    /// Smallest share of scan points with an ICP correspondence after refinement.
    pub min_fitness: f32,
    /// Largest RMS residual after refinement, metres.
    pub max_rms: f64,
    /// Two matches against one submap confirm each other when the front-end motion between
    /// their keyframes explains their difference within this, metres (plus 2 % of the
    /// distance)...
    pub agree_xy: f64,
    /// ... and this, radians.
    pub agree_theta: f64,
    /// Smallest over largest eigenvalue of the refinement's Hessian below which the match is
    /// degenerate and rejected (stricter than the front-end's).
    pub degeneracy_ratio: f64,
    /// Most submaps searched per keyframe (nearest first).
    pub max_candidates: u8,
    /// Pyramid levels of the branch-and-bound search.
    pub pyramid_levels: u8,
    /// Floors of the loop edge's standard deviations `[metres, radians]` (the ICP information
    /// is overconfident).
    pub min_sigma: [f64; 2],
    /// Search beyond the window, over every heading and whole submaps, once the uncertainty
    /// since the last loop closure outgrows `window_max` (module `mapper::far`).
    pub far_search: bool,
    /// Weight of the max-mixture null hypothesis.
    pub null_weight: f32,
    /// Information scale of the null hypothesis.
    pub null_scale: f32,
}

impl Default for LoopConfig {
    fn default() -> Self {
        LoopConfig {
            every: 2,
            min_keyframe_gap: 30,
            sigmas: 3.0,
            window_min: 0.5,
            window_max: 2.5,
            window_from_anchor: true,
            window_lever: 0.03,
            angle_min: 0.2,
            angle_max: 0.6,
            min_score: 0.55,
            min_fitness: 0.5,
            max_rms: 0.08,
            agree_xy: 0.05,
            agree_theta: 0.02,
            degeneracy_ratio: 0.01,
            max_candidates: 3,
            pyramid_levels: 5,
            min_sigma: [0.03, 0.01],
            far_search: true,
            null_weight: 1e-3,
            null_scale: 1e-6,
        }
    }
}

/// Back-end parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct BackendConfig {
    /// Optimize after this many new keyframes even without a new loop closure.
    pub every_keyframes: u32,
    /// Most Gauss-Newton iterations of one optimization (spread over back-end steps).
    pub max_iterations: u32,
    /// Cell of the pruning that makes room when a pool is full, metres.
    pub prune_cell: f64,
    /// Share of the information term in the pruning weight (eq. 4).
    pub prune_s: f64,
    /// The newest keyframes are never pruned.
    pub prune_keep_recent: u32,
    /// Chi2 threshold of the odometry-chain gate that warm-starts max-mixture loops (see
    /// `solver::gate`); 0 disables it.
    pub gate_chi2: f64,
    /// Most work units of one back-end step (`solver::work`, about 100 Cortex-A9 instructions
    /// each): a solve spans as many steps as it needs. 0: no limit (each step runs whole
    /// solves of the step's iterations).
    pub work_budget: u64,
    /// Back-end steps after each frame in an interleaved schedule
    /// ([`Mapper::step_backend_frame`](super::Mapper::step_backend_frame): the firmware and
    /// `cloi map --deterministic`), so the back-end's share of a frame is several bounded
    /// steps rather than one larger one; a threaded host runs steps back to back instead.
    pub steps_per_frame: u32,
    /// Test the groups of loop closures for consistency with the whole graph after an
    /// optimization and remove the worst inconsistent one (module
    /// [`consistency`](crate::backend::consistency)), in the back-end's spare turns.
    pub consistency_test: bool,
}

impl BackendConfig {
    /// The default work budget of one back-end step: about 4 M Cortex-A9 instructions, so a
    /// step stays within 5 M with the parts of a solve that run whole.
    pub const WORK_BUDGET: u64 = 32_000;
}

impl Default for BackendConfig {
    fn default() -> Self {
        BackendConfig {
            every_keyframes: 50,
            max_iterations: 20,
            prune_cell: 0.5,
            prune_s: 0.5,
            prune_keep_recent: 30,
            gate_chi2: 16.27,
            work_budget: BackendConfig::WORK_BUDGET,
            steps_per_frame: 3,
            consistency_test: true,
        }
    }
}

/// Everything the mapper can be tuned by.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MapperConfig {
    /// Scan preprocessing (the mounting is taken from each scan).
    pub preprocess: PreprocessConfig,
    /// Ranges beyond this are dropped, metres (also bounded by the scanner's own maximum).
    pub max_range: f32,
    /// Ranges below this are dropped, metres (when the scanner's own minimum is lower; applied
    /// by [`Feeder`](crate::mapper::Feeder)).
    pub min_range: f32,
    /// Wheel odometry and gyro fusion.
    pub odometry: OdometryConfig,
    /// Scan-to-map ICP of the front-end.
    pub icp: IcpConfig,
    /// A front-end match below this fitness falls back to the odometry seed.
    pub min_fitness: f32,
    /// While turning (odometry rotation step above this, radians), the front-end also tries
    /// seeds rotated by plus and minus the odometry's rotation step (a wheel heading that
    /// lags or leads the scan by a frame) and keeps the best match; 0 disables it.
    pub turn_reseed: f64,
    /// The rotated seeds are tried only when the match from the odometry seed has an RMS
    /// point-to-line residual above this, metres (0: always). In the `home` profile's runs of
    /// the three CARMEN logs a rotated seed won over a primary match at or below 5 cm RMS in
    /// 5 of 5,768 turning scans (all on intel, all within 0.1 m of the primary), and never on
    /// fr079 and mit-csail; skipping them there saves four ICP runs on most turning scans,
    /// which is what brings the front-end's p99 under its budget on the robot's processor.
    pub turn_reseed_rms: f64,
    /// Stalled odometry: a scan-matcher step above `[metres, radians]` while the odometry
    /// reports exactly no motion, for two scans or more (one is a frame of lag), counts as
    /// motion the odometry has not reported yet (the stream stalled, as it does three times in
    /// mit-csail, hiding about 0.8 rad of turn each time); it is taken off the odometry's next
    /// increment, which would otherwise seed that scan with the whole hidden turn again.
    /// `None` leaves the odometry as it is.
    pub stall_motion: Option<[f64; 2]>,
    /// Keyframe thresholds.
    pub keyframe: KeyframeConfig,
    /// Keyframe points within this radius of the robot enter the local point map, metres.
    pub local_radius: f32,
    /// The local point map restarts when the robot is this far from its start, metres.
    pub local_reset: f64,
    /// Voxel of the local point map, metres.
    pub local_voxel: f32,
    /// When positive, the local point map slides instead of restarting: a point is kept
    /// while it is within `local_radius`, was seen within this much front-end path
    /// (metres), and a second keyframe saw it (`frontend::pointmap`). Zero restarts the map
    /// every `local_reset` metres.
    pub local_span: f64,
    /// On a restart, the local point map is refilled from the occupied cells of the two
    /// newest submaps (instead of starting from the current scan alone).
    pub local_from_submaps: bool,
    /// Occupied-cell threshold (log-odds units) of that refill.
    pub local_min_log_odds: i8,
    /// Occupancy grid of a submap.
    pub grid: GridParams,
    /// A new submap starts when the robot is this far from the active one's anchor, metres.
    pub submap_length: f64,
    /// Front-end motion uncertainty.
    pub noise: FrontendNoise,
    /// Loop closure.
    pub loops: LoopConfig,
    /// Real-time pose estimation.
    pub gpe: GpeConfig,
    /// Back-end.
    pub backend: BackendConfig,
    /// Camera tracking (module `cameras`).
    pub camera: TrackConfig,
}

impl Default for MapperConfig {
    fn default() -> Self {
        MapperConfig {
            preprocess: PreprocessConfig {
                voxel_size: 0.05,
                ..PreprocessConfig::default()
            },
            max_range: 40.0,
            min_range: 0.1,
            odometry: OdometryConfig::default(),
            icp: IcpConfig {
                allow_degenerate: true,
                ..IcpConfig::default()
            },
            min_fitness: 0.5,
            turn_reseed: 0.05,
            turn_reseed_rms: 0.0,
            stall_motion: Some(Self::STALL_MOTION),
            keyframe: KeyframeConfig::default(),
            local_radius: 30.0,
            local_reset: 3.0,
            local_voxel: 0.05,
            local_span: 30.0,
            local_from_submaps: true,
            local_min_log_odds: 10,
            grid: GridParams::LARGE,
            submap_length: 3.0,
            noise: FrontendNoise::default(),
            loops: LoopConfig::default(),
            gpe: GpeConfig::default(),
            backend: BackendConfig::default(),
            camera: TrackConfig::default(),
        }
    }
}

impl MapperConfig {
    /// The [`MapperConfig::stall_motion`] thresholds of every profile: 1 cm, 0.01 rad.
    pub const STALL_MOTION: [f64; 2] = [0.01, 0.01];

    /// The `home` profile (a cleaning robot in a home, [`crate::profile::HOME`]): 4.1 m
    /// submaps, a 10 m LiDAR, loop searches within 1.5 m and 0.5 rad (the drift between
    /// revisits of a small home is small), windows from the motion since the last loop
    /// closure (the cheaper search), and rotated turn seeds only for a primary match above
    /// 5 cm RMS. Its local point map restarts every 3 m, refilled from the newest submaps:
    /// the generated buildings that showed the sliding map's worth are mapped with the other
    /// profiles, and in the ten-session home test sliding was level on average but not in
    /// its late sessions. `docs/benchmarks.md` has the measurements behind these choices.
    pub fn home() -> Self {
        let base = MapperConfig::default();
        MapperConfig {
            grid: GridParams::HOME,
            submap_length: 1.5,
            max_range: 10.0,
            local_span: 0.0,
            turn_reseed_rms: 0.05,
            loops: LoopConfig {
                window_max: 1.5,
                angle_max: 0.5,
                window_from_anchor: false,
                window_lever: 0.0,
                ..base.loops
            },
            ..base
        }
    }

    /// The `office` profile (an office floor, [`crate::profile::OFFICE`]): the defaults. The
    /// front-end's local point map slides over the last 30 m of path (`local_span`, the
    /// local map's radius): it keeps the walls the LiDAR saw on the way, which a restart
    /// every few metres drops, while no point older than 30 m of drift stays in it.
    pub fn office() -> Self {
        MapperConfig::default()
    }

    /// The `airport` profile (a guide robot in a hall, [`crate::profile::AIRPORT`]): 10 m
    /// submaps at 10 cm, scans voxelised at 10 cm, a keyframe every 0.5 m and a 1 m pruning
    /// cell, so that the graph of a 60,000 m^2 hall fits the profile's pools.
    ///
    /// The local point map slides over the last 30 m of path, as in the office profile: a
    /// guide robot scanning at 1 Hz in halls wider than its range needs the far walls and the
    /// sparse returns of glass that the scans of the last few metres alone do not hold, and a
    /// restart refilled from the submaps' cells would not either (10 cm cells of a wall at a
    /// slant to the grid form a staircase whose centres leave the heading nearly free and
    /// tilt it where two submaps meet). With `local_span` = 0 it restarts from the current
    /// scan (`local_from_submaps` off). `docs/benchmarks.md` has the measurements.
    pub fn airport() -> Self {
        let base = MapperConfig::office();
        MapperConfig {
            preprocess: PreprocessConfig {
                voxel_size: 0.1,
                ..base.preprocess
            },
            keyframe: KeyframeConfig {
                distance: 0.5,
                ..base.keyframe
            },
            grid: GridParams {
                side: 100,
                resolution: 0.1,
                ..GridParams::LARGE
            },
            backend: BackendConfig {
                prune_cell: 1.0,
                ..base.backend
            },
            local_from_submaps: false,
            ..base
        }
    }
}

impl MotionNoise for FrontendNoise {
    fn covariance(&self, distance: f64, rotation: f64) -> Cov3 {
        FrontendNoise::covariance(self, distance, rotation)
    }
}

impl MapperConfig {
    /// The front-end's part of the configuration.
    pub(crate) fn lidar(&self) -> LidarParams<'_> {
        LidarParams {
            icp: &self.icp,
            min_fitness: self.min_fitness,
            turn_reseed: self.turn_reseed,
            turn_reseed_rms: self.turn_reseed_rms,
            stall_motion: self.stall_motion,
            noise: &self.noise,
        }
    }

    /// The back-end schedule's part of the configuration.
    pub(crate) fn schedule(&self) -> ScheduleParams {
        ScheduleParams {
            every_keyframes: self.backend.every_keyframes,
            max_iterations: self.backend.max_iterations,
            gate_chi2: self.backend.gate_chi2,
            work_budget: self.backend.work_budget,
        }
    }
}
