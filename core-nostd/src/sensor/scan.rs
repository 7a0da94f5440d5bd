//! Planar laser scans: a checked view over borrowed ranges, the per-beam rejection counts, and
//! the time-order check.

use core::fmt;

use super::Timestamp;

/// Most beams one scan may hold: 1081, the beam count of a 270 degree scanner with a
/// quarter-degree step (Hokuyo UTM-30LX), the densest scanner in the benchmark logs. Every
/// fixed-capacity scan buffer (the `.cloilog` record, the front-end's points) is sized by it.
pub const MAX_BEAMS: usize = 1081;

/// Why a scan (as a whole) cannot be used. Single bad beams are not errors: they are counted
/// in [`BeamStats`] and skipped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ScanError {
    /// The scan has no beams.
    NoBeams,
    /// `angle_min` or `angle_increment` is not finite, or the increment is zero.
    InvalidAngles,
    /// `range_min`/`range_max` are not finite, `range_min` is negative, or
    /// `range_min >= range_max`.
    InvalidRangeLimits,
    /// Intensities were given, but not one per range.
    IntensityCountMismatch {
        /// Number of ranges.
        ranges: usize,
        /// Number of intensities.
        intensities: usize,
    },
    /// Every beam was rejected (NaN, infinite or out of range).
    NoValidBeams,
    /// The scan is not later than the previous one.
    NonMonotonicTimestamp {
        /// Stamp of the previous accepted scan.
        previous: Timestamp,
        /// Stamp of this scan.
        current: Timestamp,
    },
}

impl fmt::Display for ScanError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::NoBeams => write!(f, "the scan has no beams"),
            Self::InvalidAngles => {
                write!(f, "the scan angles are not finite or the increment is zero")
            }
            Self::InvalidRangeLimits => write!(f, "the scan's range limits are invalid"),
            Self::IntensityCountMismatch {
                ranges,
                intensities,
            } => write!(f, "{intensities} intensities for {ranges} ranges"),
            Self::NoValidBeams => write!(f, "every beam of the scan was rejected"),
            Self::NonMonotonicTimestamp { previous, current } => write!(
                f,
                "scan time {current} is not after the previous scan's {previous}"
            ),
        }
    }
}

impl core::error::Error for ScanError {}

/// Angles and range limits of a scanner (ROS `LaserScan` conventions: beams counter-clockwise
/// from `angle_min`; ranges outside `[range_min, range_max]` are not measurements).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ScanGeometry {
    /// Angle of beam 0 (rad) in the laser frame.
    pub angle_min: f32,
    /// Angle between consecutive beams (rad); negative for clockwise scanners.
    pub angle_increment: f32,
    /// Shortest valid range (m).
    pub range_min: f32,
    /// Longest valid range (m).
    pub range_max: f32,
}

/// How many beams of a scan were used, and why the others were not.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct BeamStats {
    /// Finite ranges within the limits.
    pub valid: usize,
    /// NaN ranges.
    pub nan: usize,
    /// Infinite ranges (REP 117: +inf is "no return").
    pub infinite: usize,
    /// Finite ranges shorter than `range_min`.
    pub below_min: usize,
    /// Finite ranges longer than `range_max` (often the scanner's "no return" value).
    pub above_max: usize,
}

impl BeamStats {
    /// Beams rejected for any reason.
    pub fn rejected(&self) -> usize {
        self.nan + self.infinite + self.below_min + self.above_max
    }
}

/// One valid beam.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Beam {
    /// Index in the scan.
    pub index: usize,
    /// Direction in the laser frame (rad).
    pub angle: f32,
    /// Measured range (m).
    pub range: f32,
    /// Intensity, when the scan has them.
    pub intensity: Option<f32>,
}

impl Beam {
    /// The end point `(x, y)` in the laser frame (m).
    pub fn point(&self) -> (f32, f32) {
        (
            self.range * libm::cosf(self.angle),
            self.range * libm::sinf(self.angle),
        )
    }
}

/// A checked, borrowed laser scan.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LaserScanView<'a> {
    stamp: Timestamp,
    geometry: ScanGeometry,
    ranges: &'a [f32],
    intensities: Option<&'a [f32]>,
    stats: BeamStats,
}

fn classify(range: f32, g: &ScanGeometry) -> Result<(), fn(&mut BeamStats)> {
    if range.is_nan() {
        Err(|s| s.nan += 1)
    } else if range.is_infinite() {
        Err(|s| s.infinite += 1)
    } else if range < g.range_min {
        Err(|s| s.below_min += 1)
    } else if range > g.range_max {
        Err(|s| s.above_max += 1)
    } else {
        Ok(())
    }
}

impl<'a> LaserScanView<'a> {
    /// Checks a scan and counts its beams.
    ///
    /// # Errors
    /// [`ScanError::NoBeams`], [`ScanError::InvalidAngles`], [`ScanError::InvalidRangeLimits`],
    /// [`ScanError::IntensityCountMismatch`], or [`ScanError::NoValidBeams`] when every beam is
    /// NaN, infinite or out of range.
    pub fn new_checked(
        stamp: Timestamp,
        geometry: ScanGeometry,
        ranges: &'a [f32],
        intensities: Option<&'a [f32]>,
    ) -> Result<Self, ScanError> {
        if ranges.is_empty() {
            return Err(ScanError::NoBeams);
        }
        let g = geometry;
        if !g.angle_min.is_finite() || !g.angle_increment.is_finite() || g.angle_increment == 0.0 {
            return Err(ScanError::InvalidAngles);
        }
        if !g.range_min.is_finite()
            || !g.range_max.is_finite()
            || g.range_min < 0.0
            || g.range_min >= g.range_max
        {
            return Err(ScanError::InvalidRangeLimits);
        }
        if let Some(i) = intensities {
            if i.len() != ranges.len() {
                return Err(ScanError::IntensityCountMismatch {
                    ranges: ranges.len(),
                    intensities: i.len(),
                });
            }
        }
        let mut stats = BeamStats::default();
        for &r in ranges {
            match classify(r, &g) {
                Ok(()) => stats.valid += 1,
                Err(count) => count(&mut stats),
            }
        }
        if stats.valid == 0 {
            return Err(ScanError::NoValidBeams);
        }
        Ok(Self {
            stamp,
            geometry,
            ranges,
            intensities,
            stats,
        })
    }

    /// When the scan was taken (its first beam).
    pub fn stamp(&self) -> Timestamp {
        self.stamp
    }

    /// Angles and range limits.
    pub fn geometry(&self) -> ScanGeometry {
        self.geometry
    }

    /// All ranges, valid or not.
    pub fn ranges(&self) -> &'a [f32] {
        self.ranges
    }

    /// Intensities, one per range, if the scanner reports them.
    pub fn intensities(&self) -> Option<&'a [f32]> {
        self.intensities
    }

    /// Counts of valid and rejected beams.
    pub fn stats(&self) -> BeamStats {
        self.stats
    }

    /// Direction of beam `index` (rad).
    pub fn angle(&self, index: usize) -> f32 {
        self.geometry.angle_min + self.geometry.angle_increment * index as f32
    }

    /// The valid beams, in scan order.
    pub fn beams(&self) -> impl Iterator<Item = Beam> + 'a {
        let g = self.geometry;
        let intensities = self.intensities;
        self.ranges
            .iter()
            .enumerate()
            .filter(move |(_, &r)| classify(r, &g).is_ok())
            .map(move |(index, &range)| Beam {
                index,
                angle: g.angle_min + g.angle_increment * index as f32,
                range,
                intensity: intensities.and_then(|i| i.get(index).copied()),
            })
    }
}

/// Accepts scans only in strictly increasing time order.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ScanStampGuard {
    last: Option<Timestamp>,
    rejected: usize,
}

impl ScanStampGuard {
    /// A guard that has seen no scan.
    pub const fn new() -> Self {
        Self {
            last: None,
            rejected: 0,
        }
    }

    /// Accepts `stamp` if it is after the last accepted one.
    ///
    /// # Errors
    /// [`ScanError::NonMonotonicTimestamp`]; the rejection is counted and the last accepted
    /// stamp stays.
    pub fn check(&mut self, stamp: Timestamp) -> Result<(), ScanError> {
        match self.last {
            Some(previous) if stamp <= previous => {
                self.rejected += 1;
                Err(ScanError::NonMonotonicTimestamp {
                    previous,
                    current: stamp,
                })
            }
            _ => {
                self.last = Some(stamp);
                Ok(())
            }
        }
    }

    /// Scans rejected so far.
    pub fn rejected(&self) -> usize {
        self.rejected
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    const G: ScanGeometry = ScanGeometry {
        angle_min: -1.0,
        angle_increment: 0.5,
        range_min: 0.1,
        range_max: 10.0,
    };

    #[test]
    fn bad_beams_are_counted_and_skipped() {
        let ranges = [1.0, f32::NAN, f32::INFINITY, 0.05, 81.83, 10.0, -1.0];
        let scan = LaserScanView::new_checked(Timestamp(7), G, &ranges, None).unwrap();
        let s = scan.stats();
        assert_eq!(
            s,
            BeamStats {
                valid: 2,
                nan: 1,
                infinite: 1,
                below_min: 2,
                above_max: 1
            }
        );
        assert_eq!(s.rejected(), 5);
        let mut beams = scan.beams();
        let b0 = beams.next().unwrap();
        assert_eq!((b0.index, b0.angle, b0.range), (0, -1.0, 1.0));
        let b5 = beams.next().unwrap();
        assert_eq!((b5.index, b5.angle), (5, 1.5));
        assert!(beams.next().is_none());
        let (x, y) = b0.point();
        assert!((x - libm::cosf(-1.0)).abs() < 1e-6 && (y - libm::sinf(-1.0)).abs() < 1e-6);
    }

    #[test]
    fn whole_scan_errors() {
        let r = [1.0_f32; 3];
        assert_eq!(
            LaserScanView::new_checked(Timestamp(0), G, &[], None),
            Err(ScanError::NoBeams)
        );
        let mut g = G;
        g.angle_increment = 0.0;
        assert_eq!(
            LaserScanView::new_checked(Timestamp(0), g, &r, None),
            Err(ScanError::InvalidAngles)
        );
        g = G;
        g.angle_min = f32::NAN;
        assert_eq!(
            LaserScanView::new_checked(Timestamp(0), g, &r, None),
            Err(ScanError::InvalidAngles)
        );
        g = G;
        g.range_max = 0.1;
        assert_eq!(
            LaserScanView::new_checked(Timestamp(0), g, &r, None),
            Err(ScanError::InvalidRangeLimits)
        );
        g = G;
        g.range_max = f32::INFINITY;
        assert_eq!(
            LaserScanView::new_checked(Timestamp(0), g, &r, None),
            Err(ScanError::InvalidRangeLimits)
        );
        assert_eq!(
            LaserScanView::new_checked(Timestamp(0), G, &r, Some(&[1.0])),
            Err(ScanError::IntensityCountMismatch {
                ranges: 3,
                intensities: 1
            })
        );
        assert_eq!(
            LaserScanView::new_checked(Timestamp(0), G, &[f32::NAN, 20.0], None),
            Err(ScanError::NoValidBeams)
        );
    }

    #[test]
    fn intensities_follow_their_beams() {
        let scan = LaserScanView::new_checked(Timestamp(0), G, &[f32::NAN, 2.0], Some(&[5.0, 6.0]))
            .unwrap();
        let b: heapless::Vec<Beam, 2> = scan.beams().collect();
        assert_eq!(b.len(), 1);
        assert_eq!(b[0].intensity, Some(6.0));
    }

    #[test]
    fn stamps_must_increase() {
        let mut guard = ScanStampGuard::new();
        assert!(guard.check(Timestamp(10)).is_ok());
        assert_eq!(
            guard.check(Timestamp(10)),
            Err(ScanError::NonMonotonicTimestamp {
                previous: Timestamp(10),
                current: Timestamp(10)
            })
        );
        assert!(guard.check(Timestamp(5)).is_err());
        assert!(guard.check(Timestamp(11)).is_ok());
        assert_eq!(guard.rejected(), 2);
    }

    proptest! {
        #[test]
        fn stats_partition_the_beams(ranges in proptest::collection::vec(
            prop_oneof![any::<f32>(), -1.0f32..20.0], 1..64)) {
            match LaserScanView::new_checked(Timestamp(0), G, &ranges, None) {
                Ok(scan) => {
                    let s = scan.stats();
                    prop_assert_eq!(s.valid + s.rejected(), ranges.len());
                    prop_assert_eq!(scan.beams().count(), s.valid);
                    for b in scan.beams() {
                        prop_assert!(b.range >= G.range_min && b.range <= G.range_max);
                    }
                }
                Err(e) => {
                    prop_assert_eq!(e, ScanError::NoValidBeams);
                    prop_assert!(ranges.iter().all(|r| !(G.range_min..=G.range_max).contains(r)));
                }
            }
        }
    }
}
