//! What the core needs to know about a planar laser scanner before reading its ranges: the
//! beam geometry and the largest beam count any scan may carry.

/// Most beams one scan may hold: 1081, the beam count of a 270 degree scanner with a
/// quarter-degree step (Hokuyo UTM-30LX), the densest scanner in the benchmark logs. Every
/// fixed-capacity scan buffer (the `.cloilog` record, the front-end's points) is sized by it.
pub const MAX_BEAMS: usize = 1081;

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
