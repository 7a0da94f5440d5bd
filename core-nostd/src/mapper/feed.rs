//! How sensor events reach the mapper, shared by every driver (the `cloi map` host, the
//! firmware) so that they feed it identically:
//! * **odometry on scans**: a source whose scans carry the odometry at their own time (CARMEN
//!   logs) gives the most exact seed; once a scan does, separate odometry events are ignored
//!   (they are logged at other times and would only be interpolated);
//! * **stamps that step back**: with `file_order`, the input's order is taken as the true one
//!   (a log whose stamps jitter, like intel.clf's) and such a stamp is moved to 1 µs after the
//!   previous one of its stream (counted); without it, the mapper rejects the event (counted);
//! * **shortest range**: the configured one applies when the scan's own is shorter.

use super::{FrameOutput, Mapper, MapperError, Probe, ScanInput};
use crate::geom::Se2;

/// The feeding state of one run.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Feeder {
    file_order: bool,
    range_min: f32,
    /// Last stamp given to the mapper per stream: odometry, gyro, scans.
    clocks: [Option<i64>; 3],
    scans_carry_odometry: bool,
    /// Stamps moved forward so far.
    pub stamps_repaired: u64,
}

impl Feeder {
    /// A feeder; `file_order` repairs stamps that step back, `range_min` (metres) is the
    /// shortest range used.
    pub const fn new(file_order: bool, range_min: f32) -> Self {
        Feeder {
            file_order,
            range_min,
            clocks: [None; 3],
            scans_carry_odometry: false,
            stamps_repaired: 0,
        }
    }

    fn clock(&mut self, stream: usize, t: i64) -> i64 {
        if !self.file_order {
            return t;
        }
        let Some(slot) = self.clocks.get_mut(stream) else {
            return t;
        };
        let c = match *slot {
            Some(last) if t <= last => {
                self.stamps_repaired += 1;
                last.saturating_add(1_000)
            }
            _ => t,
        };
        *slot = Some(c);
        c
    }

    /// A wheel odometry pose stamped `t` ns (ignored once scans carry odometry).
    ///
    /// # Errors
    /// The mapper's rejection (counted there).
    pub fn odometry(&mut self, m: &mut Mapper<'_>, t: i64, pose: Se2) -> Result<(), MapperError> {
        if self.scans_carry_odometry {
            return Ok(());
        }
        let t = self.clock(0, t);
        m.push_odometry(t, pose)
    }

    /// A gyro yaw rate stamped `t` ns.
    ///
    /// # Errors
    /// The mapper's rejection (counted there).
    pub fn gyro(&mut self, m: &mut Mapper<'_>, t: i64, yaw_rate: f64) -> Result<(), MapperError> {
        let t = self.clock(1, t);
        m.push_gyro(t, yaw_rate)
    }

    /// A scan, with the odometry pose its source recorded at its time, if any.
    ///
    /// # Errors
    /// The mapper's rejection (counted there).
    pub fn scan(
        &mut self,
        m: &mut Mapper<'_>,
        scan: &ScanInput<'_>,
        odometry: Option<Se2>,
        deadline_passed: bool,
    ) -> Result<FrameOutput, MapperError> {
        self.scan_probed(m, scan, odometry, deadline_passed, &mut ())
    }

    /// [`Feeder::scan`] through [`Mapper::push_scan_probed`] (the odometry push before it is
    /// not part of any section).
    ///
    /// # Errors
    /// The mapper's rejection (counted there).
    pub fn scan_probed(
        &mut self,
        m: &mut Mapper<'_>,
        scan: &ScanInput<'_>,
        odometry: Option<Se2>,
        deadline_passed: bool,
        probe: &mut impl Probe,
    ) -> Result<FrameOutput, MapperError> {
        let stamp = self.clock(2, scan.stamp);
        if let Some(pose) = odometry {
            self.scans_carry_odometry = true;
            let t = self.clock(0, stamp);
            let _ = m.push_odometry(t, pose);
        }
        let mut input = *scan;
        input.stamp = stamp;
        input.geometry.range_min = input.geometry.range_min.max(self.range_min);
        m.push_scan_probed(&input, deadline_passed, probe)
    }
}
