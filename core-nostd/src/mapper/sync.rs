//! Holding scans until the motion sensors cover them (the front-end's seed, paper section III:
//! the wheel odometry, fused with the gyro, predicts the motion between scans).
//!
//! A recorded log may interleave its streams as the logger wrote them; a robot's drivers and a
//! bag deliver them in stamp order, so a scan stamped `t` arrives before the odometry sample
//! that follows `t`. Pushed at once, such a scan could only be seeded by extrapolating the
//! last odometry, which fails after any gap longer than the extrapolation limit. The gate
//! below instead decides, per scan, when it may go to the mapper:
//! * **covered**: the newest wheel sample and the newest gyro sample are at or after the end
//!   of the scan's sweep, so the seed is an interpolation. A stream counts only once the input
//!   has shown it has one (a sample arrived): a LiDAR-only input, or the scans before the
//!   first odometry sample, never wait;
//! * **waited long enough**: the input's data time (the newest stamp seen on any stream) has
//!   run `wait_ns` past the end of the sweep without cover; the mapper then seeds as it can
//!   (counted). Drivers use [`SYNC_WAIT_NS`];
//! * **no room**: a new scan finds all `SYNC_SLOTS` taken; the oldest goes first (counted).
//!
//! Scans leave in the order they came. The gate keeps only stamps: the caller (host or
//! firmware) keeps each held scan's data, in a queue of at most [`SYNC_SLOTS`] scans, and
//! pushes the oldest one whenever [`ScanGate::release`] names it. A scan that carries its own
//! odometry (CARMEN laser lines) is covered by definition and never waits.

use heapless::Deque;

/// Scans the gate holds at most (the caller's queue needs room for as many).
pub const SYNC_SLOTS: usize = 8;

/// The wait drivers give a scan for odometry to cover it, in data time: five periods of a
/// 10 Hz wheel odometry, the slowest rate a service robot's base reports (ROS base drivers
/// publish at 20 to 50 Hz, the CARMEN robots logged about 10 Hz). In stamp order the covering
/// sample normally comes within one period; a stream silent for five has dropped samples,
/// and waiting longer would only delay the real-time pose of every scan behind this one.
pub const SYNC_WAIT_NS: i64 = 500_000_000;

/// What the caller does with a scan it offers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Admit {
    /// Push it now (nothing older is held and the sensors cover it).
    Now,
    /// Keep it; [`ScanGate::release`] will name it.
    Held,
    /// The queue was full: push the oldest held scan now (it leaves without cover, counted),
    /// then keep this one.
    HeldAfterOldest,
}

/// Why a held scan left the gate.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Released {
    /// Odometry (and gyro) cover its sweep.
    Covered,
    /// The data time ran past the wait without cover.
    Waited,
    /// The input ended.
    Drained,
}

/// Counters of the gate.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SyncStats {
    /// Scans that had to wait for cover.
    pub held: u64,
    /// Held scans released without cover after the wait.
    pub waited: u64,
    /// Held scans released without cover because the queue was full.
    pub evicted: u64,
    /// Scans that had to wait but had more beams than a held slot takes (rejected).
    pub too_long: u64,
}

/// The gate's state: coverage of the motion streams and the stamps of the held scans.
#[derive(Clone, Debug)]
pub struct ScanGate {
    wait_ns: i64,
    wheel: Option<i64>,
    gyro: Option<i64>,
    data_time: Option<i64>,
    /// End of each held scan's sweep, ns (its stamp when the beams carry no time).
    held: Deque<i64, SYNC_SLOTS>,
    /// Counters.
    pub stats: SyncStats,
}

fn later(a: Option<i64>, t: i64) -> Option<i64> {
    Some(a.map_or(t, |a| a.max(t)))
}

impl ScanGate {
    /// A gate that waits at most `wait_ns` of data time for cover.
    pub const fn new(wait_ns: i64) -> Self {
        ScanGate {
            wait_ns,
            wheel: None,
            gyro: None,
            data_time: None,
            held: Deque::new(),
            stats: SyncStats {
                held: 0,
                waited: 0,
                evicted: 0,
                too_long: 0,
            },
        }
    }

    /// A wheel odometry sample stamped `t` ns arrived.
    pub fn wheel(&mut self, t: i64) {
        self.wheel = later(self.wheel, t);
        self.data_time = later(self.data_time, t);
    }

    /// A gyro sample stamped `t` ns arrived.
    pub fn gyro(&mut self, t: i64) {
        self.gyro = later(self.gyro, t);
        self.data_time = later(self.data_time, t);
    }

    /// Scans waiting.
    pub fn len(&self) -> usize {
        self.held.len()
    }

    /// No scan waiting.
    pub fn is_empty(&self) -> bool {
        self.held.is_empty()
    }

    fn covered(&self, end: i64) -> bool {
        if end == i64::MIN {
            return true;
        }
        let wheel = self.wheel.is_none_or(|w| w >= end);
        let gyro = self.gyro.is_none_or(|g| g >= end);
        wheel && gyro
    }

    /// Whether a scan stamped `stamp` ns whose sweep ends at `end` ns may go to the mapper at
    /// once (nothing older held, and covered or carrying its own odometry); the data time
    /// advances either way. [`ScanGate::admit`] gives the same answer as [`Admit::Now`].
    pub fn passes(&mut self, stamp: i64, end: i64, own_odometry: bool) -> bool {
        self.data_time = later(self.data_time, stamp);
        self.held.is_empty() && (own_odometry || self.covered(end.max(stamp)))
    }

    /// A scan stamped `stamp` ns whose sweep ends at `end` ns arrived; `own_odometry` when it
    /// carries the odometry pose at its time.
    pub fn admit(&mut self, stamp: i64, end: i64, own_odometry: bool) -> Admit {
        if self.passes(stamp, end, own_odometry) {
            return Admit::Now;
        }
        let end = end.max(stamp);
        // A scan with its own odometry needs no cover, only its turn.
        let end = if own_odometry { i64::MIN } else { end };
        let admit = if self.held.is_full() {
            let _ = self.held.pop_front();
            self.stats.evicted += 1;
            Admit::HeldAfterOldest
        } else {
            Admit::Held
        };
        self.stats.held += 1;
        // Room was made above.
        let _ = self.held.push_back(end);
        admit
    }

    /// The oldest held scan if it may go to the mapper now, with the reason; the caller pushes
    /// it (its stamp is the caller's to keep) and calls again until `None`.
    pub fn release(&mut self) -> Option<Released> {
        let end = *self.held.front()?;
        let why = if self.covered(end) {
            Released::Covered
        } else if self
            .data_time
            .is_some_and(|d| d.saturating_sub(end) > self.wait_ns)
        {
            self.stats.waited += 1;
            Released::Waited
        } else {
            return None;
        };
        let _ = self.held.pop_front();
        Some(why)
    }

    /// At the end of the input: the oldest held scan, released without further wait.
    pub fn drain(&mut self) -> Option<Released> {
        if let Some(why) = self.release() {
            return Some(why);
        }
        self.held.pop_front().map(|_| Released::Drained)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: i64 = 1_000_000;

    #[test]
    fn scan_waits_for_the_odometry_after_it() {
        let mut g = ScanGate::new(500 * MS);
        g.wheel(0);
        assert_eq!(g.admit(10 * MS, 10 * MS, false), Admit::Held);
        assert_eq!(g.release(), None);
        g.wheel(20 * MS);
        assert_eq!(g.release(), Some(Released::Covered));
        assert!(g.is_empty());
        // Covered on arrival: straight through.
        assert_eq!(g.admit(15 * MS, 15 * MS, false), Admit::Now);
        assert_eq!(g.stats.held, 1);
    }

    #[test]
    fn streams_not_seen_yet_do_not_hold_scans() {
        let mut g = ScanGate::new(500 * MS);
        // No motion stream yet (a LiDAR-only input, or scans before the first sample).
        assert!(g.passes(0, 0, false));
        assert_eq!(g.admit(10 * MS, 10 * MS, false), Admit::Now);
        g.wheel(5 * MS);
        assert!(!g.passes(20 * MS, 20 * MS, false));
        assert_eq!(g.admit(20 * MS, 20 * MS, false), Admit::Held);
        assert_eq!(g.stats.held, 1);
    }

    #[test]
    fn gyro_must_cover_too_once_it_exists() {
        let mut g = ScanGate::new(500 * MS);
        g.gyro(0);
        g.wheel(50 * MS);
        assert_eq!(g.admit(40 * MS, 45 * MS, false), Admit::Held);
        assert_eq!(g.release(), None);
        g.gyro(46 * MS);
        assert_eq!(g.release(), Some(Released::Covered));
    }

    #[test]
    fn sweep_end_decides_not_the_stamp() {
        let mut g = ScanGate::new(500 * MS);
        g.wheel(100 * MS);
        assert_eq!(g.admit(90 * MS, 190 * MS, false), Admit::Held);
        g.wheel(180 * MS);
        assert_eq!(g.release(), None);
        g.wheel(200 * MS);
        assert_eq!(g.release(), Some(Released::Covered));
    }

    #[test]
    fn bounded_wait_in_data_time() {
        let mut g = ScanGate::new(100 * MS);
        g.wheel(-MS);
        assert_eq!(g.admit(0, 0, false), Admit::Held);
        assert_eq!(g.admit(50 * MS, 50 * MS, false), Admit::Held);
        assert_eq!(g.release(), None);
        assert_eq!(g.admit(101 * MS, 101 * MS, false), Admit::Held);
        assert_eq!(g.release(), Some(Released::Waited));
        assert_eq!(g.release(), None);
        assert_eq!(g.stats.waited, 1);
        assert_eq!(g.drain(), Some(Released::Drained));
        assert_eq!(g.drain(), Some(Released::Drained));
        assert_eq!(g.drain(), None);
    }

    #[test]
    fn full_queue_releases_the_oldest_in_order() {
        let mut g = ScanGate::new(i64::MAX);
        g.wheel(-MS);
        for k in 0..SYNC_SLOTS as i64 {
            assert_eq!(g.admit(k * MS, k * MS, false), Admit::Held);
        }
        assert_eq!(g.admit(100 * MS, 100 * MS, false), Admit::HeldAfterOldest);
        assert_eq!(g.stats.evicted, 1);
        assert_eq!(g.release(), None);
        g.wheel(MS);
        assert_eq!(g.release(), Some(Released::Covered));
        assert_eq!(g.len(), SYNC_SLOTS - 1);
    }

    #[test]
    fn scan_with_its_own_odometry_never_waits_unless_behind_others() {
        let mut g = ScanGate::new(500 * MS);
        g.wheel(0);
        assert_eq!(g.admit(10 * MS, 10 * MS, true), Admit::Now);
        assert_eq!(g.admit(20 * MS, 20 * MS, false), Admit::Held);
        assert_eq!(g.admit(30 * MS, 30 * MS, true), Admit::Held);
        g.wheel(25 * MS);
        assert_eq!(g.release(), Some(Released::Covered));
        assert_eq!(g.release(), Some(Released::Covered));
        assert_eq!(g.release(), None);
    }
}
