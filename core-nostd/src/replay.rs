//! Replaying a recorded log, one event at a time: the per-event step the firmware runs on a
//! `.cloilog` streamed from the host, and that the x86-64 check runs on the same file.
//!
//! Until the full mapper takes this place, the step is LiDAR odometry: every scan is
//! preprocessed (voxel-thinned points with normals, in the robot frame through the laser
//! offset) and aligned by ICP against the points of the recent keyframes, seeded by the wheel
//! odometry's motion since the previous scan. A keyframe adds its points to the reference; the
//! reference restarts when the robot is more than [`ReplayConfig::reference_radius`] away
//! from where it started. No loop closure, no back-end.
//!
//! All state is in one value of fixed size (about 86 KB) with a `const` constructor, so the
//! firmware can place it in a `static`.

use crate::frontend::scan::MAX_POINTS;
use crate::frontend::{
    align, preprocess, BeamGeometry, IcpConfig, KeyframeConfig, KeyframeSelector, PointMap,
    PreprocessConfig, ScanPoints,
};
use crate::geom::Se2;
use crate::sensor::log::{LogRecord, ScanRecord, MAX_BEAMS};
use crate::sensor::Timestamp;

/// Capacity of the reference point set.
pub const REFERENCE_POINTS: usize = 4096;

/// Parameters of the replay step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReplayConfig {
    /// Beams shorter than this are dropped even if the log allows them, metres.
    pub min_range: f32,
    /// Beams longer than this are dropped even if the log allows them, metres.
    pub max_range: f32,
    /// Preprocessing (its mounting is replaced by each scan's laser offset).
    pub preprocess: PreprocessConfig,
    /// ICP.
    pub icp: IcpConfig,
    /// A match with fewer inliers than this fraction keeps the odometry seed.
    pub min_fitness: f32,
    /// Keyframe thresholds.
    pub keyframes: KeyframeConfig,
    /// Keyframe points farther than this from the robot are not added, metres.
    pub insert_radius: f32,
    /// The reference restarts at a keyframe this far from its start, metres.
    pub reference_radius: f64,
}

impl ReplayConfig {
    /// The settings of the LiDAR-odometry golden test on intel.clf.
    pub const DEFAULT: ReplayConfig = ReplayConfig {
        min_range: 0.05,
        max_range: 40.0,
        preprocess: PreprocessConfig {
            mounting: Se2::IDENTITY,
            decimation: 1,
            voxel_size: 0.05,
            normal_neighbours: 3,
            normal_max_distance: 0.25,
            normal_max_flatness: 0.1,
        },
        icp: IcpConfig {
            max_iterations: 30,
            max_correspondence: 0.5,
            huber: 0.05,
            min_points: 20,
            translation_eps: 1e-5,
            rotation_eps: 1e-5,
            degeneracy_ratio: 2e-3,
            min_sigma: 0.01,
            allow_degenerate: true,
        },
        min_fitness: 0.5,
        keyframes: KeyframeConfig {
            distance: 0.2,
            angle: 0.35,
        },
        insert_radius: 8.0,
        reference_radius: 3.0,
    };
}

impl Default for ReplayConfig {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// What one scan gave.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScanOutcome {
    /// Time of the scan.
    pub stamp: Timestamp,
    /// Estimated robot pose.
    pub pose: Se2,
    /// ICP matched (else the pose is the odometry prediction).
    pub matched: bool,
    /// Points the scan kept after preprocessing.
    pub points: u32,
    /// The scan became a keyframe.
    pub keyframe: bool,
}

/// Counts over a replay.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ReplayStats {
    /// Odometry records seen.
    pub odometry: u32,
    /// Gyro records seen (not used yet).
    pub gyro: u32,
    /// Scans processed.
    pub scans: u32,
    /// Scans whose match failed or was weak (the odometry prediction was kept).
    pub unmatched: u32,
    /// Scans whose geometry was unusable (skipped).
    pub rejected: u32,
    /// Keyframes.
    pub keyframes: u32,
    /// Records of unknown kinds.
    pub unknown: u32,
}

/// The replay state: current pose, reference points, scratch for one scan.
#[derive(Debug, Clone)]
pub struct Replay {
    config: ReplayConfig,
    reference: PointMap<REFERENCE_POINTS>,
    query: ScanPoints<MAX_POINTS>,
    ranges: [f32; MAX_BEAMS],
    keyframes: KeyframeSelector,
    pose: Se2,
    origin: Se2,
    last_odometry: Option<Se2>,
    previous_scan_odometry: Option<Se2>,
    stats: ReplayStats,
}

impl Replay {
    /// A replay at the origin with nothing seen.
    pub const fn new(config: ReplayConfig) -> Self {
        Replay {
            config,
            reference: PointMap::new(config.preprocess.voxel_size),
            query: ScanPoints::new(),
            ranges: [0.0; MAX_BEAMS],
            keyframes: KeyframeSelector::new(config.keyframes),
            pose: Se2::IDENTITY,
            origin: Se2::IDENTITY,
            last_odometry: None,
            previous_scan_odometry: None,
            stats: ReplayStats {
                odometry: 0,
                gyro: 0,
                scans: 0,
                unmatched: 0,
                rejected: 0,
                keyframes: 0,
                unknown: 0,
            },
        }
    }

    /// The counts so far.
    pub fn stats(&self) -> ReplayStats {
        self.stats
    }

    /// The current pose estimate.
    pub fn pose(&self) -> Se2 {
        self.pose
    }

    /// Feeds one record; returns the outcome when it was a usable scan.
    pub fn process(&mut self, record: &LogRecord<'_>) -> Option<ScanOutcome> {
        match record {
            LogRecord::Odometry(o) => {
                self.stats.odometry += 1;
                self.last_odometry = Some(o.pose);
                None
            }
            LogRecord::Gyro(_) => {
                self.stats.gyro += 1;
                None
            }
            LogRecord::Scan(scan) => self.scan(scan),
            LogRecord::Unknown { .. } => {
                self.stats.unknown += 1;
                None
            }
        }
    }

    fn scan(&mut self, scan: &ScanRecord<'_>) -> Option<ScanOutcome> {
        let cfg = self.config;
        let meta = &scan.meta;
        let geometry = BeamGeometry {
            angle_min: meta.geometry.angle_min,
            angle_increment: meta.geometry.angle_increment,
            range_min: meta.geometry.range_min.max(cfg.min_range),
            range_max: meta.geometry.range_max.min(cfg.max_range),
        };
        let pre = PreprocessConfig {
            mounting: meta.laser_offset,
            ..cfg.preprocess
        };
        let Ok(ranges) = scan.ranges_into(&mut self.ranges) else {
            self.stats.rejected += 1;
            return None;
        };
        let Ok(stats) = preprocess(ranges, &geometry, &pre, &mut self.query) else {
            self.stats.rejected += 1;
            return None;
        };
        // Odometry at the scan: its own pose if the log has it, else the latest sample.
        let odometry = meta.odom.or(self.last_odometry);
        let first = self.stats.scans == 0;
        self.stats.scans += 1;
        let mut matched = false;
        if !first {
            if let (Some(prev), Some(now)) = (self.previous_scan_odometry, odometry) {
                self.pose = self.pose.compose(&prev.between(&now));
            }
            match align(&self.query, &self.reference.tree(), &self.pose, &cfg.icp) {
                Ok(r) if r.fitness > cfg.min_fitness => {
                    self.pose = r.pose;
                    matched = true;
                }
                _ => self.stats.unmatched += 1,
            }
        }
        if odometry.is_some() {
            self.previous_scan_odometry = odometry;
        }
        let keyframe = self.keyframes.offer(&self.pose);
        if keyframe {
            self.stats.keyframes += 1;
            let (dx, dy) = (self.pose.x - self.origin.x, self.pose.y - self.origin.y);
            if libm::sqrt(dx * dx + dy * dy) > cfg.reference_radius {
                self.reference.clear();
                self.origin = self.pose;
            }
            self.reference
                .insert(&self.pose, &self.query, cfg.insert_radius);
        }
        Some(ScanOutcome {
            stamp: meta.stamp,
            pose: self.pose,
            matched,
            points: stats.points,
            keyframe,
        })
    }
}

#[cfg(test)]
mod tests {
    extern crate std;

    use std::vec;

    use super::*;
    use crate::sensor::log::{
        encode_header, encode_odometry, encode_scan, LogReader, OdometryRecord, ScanMeta,
        HEADER_LEN, MAX_FRAME, MIN_READER_BUFFER,
    };
    use crate::sensor::ScanGeometry;

    /// Ranges of a 180-beam scan from `pose` inside a 10 m x 6 m rectangular room centred on
    /// the origin.
    fn room_scan(pose: &Se2) -> [f32; 180] {
        let mut out = [0f32; 180];
        for (i, r) in out.iter_mut().enumerate() {
            let a = pose.theta - core::f64::consts::FRAC_PI_2
                + i as f64 * core::f64::consts::PI / 180.0;
            let (c, s) = (libm::cos(a), libm::sin(a));
            let tx = if c > 0.0 {
                (5.0 - pose.x) / c
            } else {
                (-5.0 - pose.x) / c
            };
            let ty = if s > 0.0 {
                (3.0 - pose.y) / s
            } else {
                (-3.0 - pose.y) / s
            };
            *r = tx.min(ty) as f32;
        }
        out
    }

    #[test]
    fn lidar_odometry_corrects_a_biased_odometry() {
        // The robot drives 1 m along x in 10 steps while its odometry reports 20 % more, and
        // rotates a little.
        let mut log = vec![0u8; HEADER_LEN];
        encode_header(None, &mut log).unwrap();
        let mut frame = vec![0u8; MAX_FRAME];
        for k in 0..=10 {
            let truth = Se2::new(0.1 * k as f64, 0.0, 0.02 * k as f64);
            let odom = Se2::new(0.12 * k as f64, 0.0, 0.02 * k as f64);
            let t = Timestamp::from_nanos(k * 100_000_000);
            let n = encode_odometry(
                &OdometryRecord {
                    stamp: t,
                    pose: odom,
                },
                &mut frame,
            )
            .unwrap();
            log.extend_from_slice(&frame[..n]);
            let meta = ScanMeta {
                stamp: t,
                geometry: ScanGeometry {
                    angle_min: -core::f32::consts::FRAC_PI_2,
                    angle_increment: core::f32::consts::PI / 180.0,
                    range_min: 0.0,
                    range_max: 80.0,
                },
                laser_offset: Se2::IDENTITY,
                odom: None,
            };
            let n = encode_scan(&meta, &room_scan(&truth), &mut frame).unwrap();
            log.extend_from_slice(&frame[..n]);
        }
        let mut buf = vec![0u8; MIN_READER_BUFFER];
        let mut reader = LogReader::new(&log[..], &mut buf).unwrap();
        let mut replay = std::boxed::Box::new(Replay::new(ReplayConfig::DEFAULT));
        let mut last = None;
        while let Some(record) = reader.next_record().unwrap() {
            if let Some(out) = replay.process(&record) {
                last = Some(out);
            }
        }
        let last = last.unwrap();
        let stats = replay.stats();
        assert_eq!((stats.scans, stats.odometry, stats.unmatched), (11, 11, 0));
        assert!((last.pose.x - 1.0).abs() < 0.02, "{:?}", last.pose);
        assert!(last.pose.y.abs() < 0.02 && (last.pose.theta - 0.2).abs() < 0.01);
    }
}
