//! How sensor events reach the mapper, shared by every driver (the `cloi map` host, the
//! firmware) so that they feed it identically:
//! * **odometry on scans**: a source whose scans carry the odometry at their own time (CARMEN
//!   logs) gives the most exact seed; once a scan does, separate odometry events are ignored
//!   (they are logged at other times and would only be interpolated);
//! * **scans before their odometry** (bags, live drivers: stamp order): the front-end seeds
//!   ICP with the wheel odometry (and gyro) interpolated at the scan's time (paper III-B.2),
//!   which needs a motion sample after that time. A scan no sample covers yet waits in the
//!   [`ScanGate`] of module `sync` until one does or its bounded wait runs out; scans leave in
//!   arrival order. A scan carrying its own odometry is covered on arrival;
//! * **stamps that step back**: with `file_order`, the input's order is taken as the true one
//!   (a log whose stamps jitter, like intel.clf's) and such a stamp is moved to 1 µs after the
//!   previous one of its stream (counted); without it, the mapper rejects the event (counted);
//! * **shortest range**: the configured one applies when the scan's own is shorter.
//!
//! # Where held scans live
//! A [`ScanInput`] only borrows its ranges, and the borrow ends when the driver's call
//! returns, so a scan that waits must be copied. The copy goes into [`ScanSlots`], a
//! fixed-capacity ring of [`SYNC_SLOTS`] scans of up to [`MAX_POINTS`] beams each that the
//! caller lends to the feeder (about 35 kB: a heap box on the host, a static on the firmware,
//! never the stack). Keeping the queue in the core rather than in each driver means the host
//! and the firmware hold, release and evict scans by the same code. A scan that waits but has
//! more beams than a slot holds is rejected and counted ([`SyncStats::too_long`]). A scan that
//! needs no wait goes to the mapper at once, without a copy.
//!
//! # Driving it
//! Images (`image`) go to the camera stage at once. After every event (`odometry`, `gyro`, `scan`), the driver calls [`Feeder::next`] until it
//! gives `None`: each call pushes at most one released scan. At the end of the input,
//! [`Feeder::finish`] until `None` pushes what is still held. Every pushed scan comes back as
//! a [`Pushed`] with the source's own stamp, so the driver can step its back-end and record
//! outputs per scan.

use super::sync::{Admit, ScanGate, SyncStats, SYNC_SLOTS, SYNC_WAIT_NS};
use super::{FrameOutput, ImageOutput, Mapper, MapperError, Probe, ScanInput};
use crate::frontend::scan::{BeamGeometry, MAX_POINTS};
use crate::geom::Se2;
use crate::sensor::ImageView;

/// One scan held by the feeder.
#[derive(Clone, Copy, Debug)]
struct Slot {
    ranges: [f32; MAX_POINTS],
    beams: usize,
    /// Stamp given to the mapper (after any repair), ns.
    stamp: i64,
    /// The source's own stamp, ns.
    original: i64,
    geometry: BeamGeometry,
    mounting: Se2,
}

impl Slot {
    const EMPTY: Slot = Slot {
        ranges: [0.0; MAX_POINTS],
        beams: 0,
        stamp: 0,
        original: 0,
        geometry: BeamGeometry {
            angle_min: 0.0,
            angle_increment: 0.0,
            range_min: 0.0,
            range_max: 0.0,
            time_increment: 0.0,
        },
        mounting: Se2::IDENTITY,
    };
}

/// Storage for the scans a [`Feeder`] holds: a ring of [`SYNC_SLOTS`] scans, oldest first.
#[derive(Clone, Debug)]
pub struct ScanSlots {
    slots: [Slot; SYNC_SLOTS],
    head: usize,
    len: usize,
}

impl Default for ScanSlots {
    fn default() -> Self {
        Self::new()
    }
}

impl ScanSlots {
    /// Empty storage.
    pub const fn new() -> Self {
        ScanSlots {
            slots: [Slot::EMPTY; SYNC_SLOTS],
            head: 0,
            len: 0,
        }
    }

    /// Copies `scan` (stamped `stamp` for the mapper, `original` by its source) behind the
    /// others; `false` when the ring is full or the scan has more beams than a slot.
    fn push_back(&mut self, scan: &ScanInput<'_>, original: i64) -> bool {
        if self.len >= SYNC_SLOTS || scan.ranges.len() > MAX_POINTS {
            return false;
        }
        let Some(slot) = self.slots.get_mut((self.head + self.len) % SYNC_SLOTS) else {
            return false;
        };
        let Some(dst) = slot.ranges.get_mut(..scan.ranges.len()) else {
            return false;
        };
        dst.copy_from_slice(scan.ranges);
        slot.beams = scan.ranges.len();
        slot.stamp = scan.stamp;
        slot.original = original;
        slot.geometry = scan.geometry;
        slot.mounting = scan.mounting;
        self.len += 1;
        true
    }

    /// The oldest scan, as the mapper takes it, with its source's stamp.
    fn front(&self) -> Option<(ScanInput<'_>, i64)> {
        if self.len == 0 {
            return None;
        }
        let slot = self.slots.get(self.head)?;
        let input = ScanInput {
            stamp: slot.stamp,
            ranges: slot.ranges.get(..slot.beams)?,
            geometry: slot.geometry,
            mounting: slot.mounting,
        };
        Some((input, slot.original))
    }

    fn pop_front(&mut self) {
        if self.len > 0 {
            self.head = (self.head + 1) % SYNC_SLOTS;
            self.len -= 1;
        }
    }

    /// Scans held.
    pub fn len(&self) -> usize {
        self.len
    }

    /// No scan held.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

/// A scan the feeder gave to the mapper (or rejected itself), with its source's stamp.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pushed {
    /// The source's own stamp, ns (the mapper's may have been moved forward in file order).
    pub stamp: i64,
    /// What the mapper made of it.
    pub result: Result<FrameOutput, MapperError>,
}

/// The feeding state of one run.
#[derive(Debug)]
pub struct Feeder<'s> {
    file_order: bool,
    range_min: f32,
    /// Last stamp given to the mapper per stream: odometry, gyro, scans.
    clocks: [Option<i64>; 3],
    scans_carry_odometry: bool,
    gate: ScanGate,
    held: &'s mut ScanSlots,
    /// Stamps moved forward so far.
    pub stamps_repaired: u64,
}

impl<'s> Feeder<'s> {
    /// A feeder; `file_order` repairs stamps that step back, `range_min` (metres) is the
    /// shortest range used, `held` keeps the scans that wait for odometry (emptied here).
    pub fn new(file_order: bool, range_min: f32, held: &'s mut ScanSlots) -> Self {
        *held = ScanSlots::new();
        Feeder {
            file_order,
            range_min,
            clocks: [None; 3],
            scans_carry_odometry: false,
            gate: ScanGate::new(SYNC_WAIT_NS),
            held,
            stamps_repaired: 0,
        }
    }

    /// Counters of the wait for odometry.
    pub fn sync_stats(&self) -> SyncStats {
        self.gate.stats
    }

    /// Scans waiting for odometry now.
    pub fn held(&self) -> usize {
        self.held.len()
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

    /// A wheel odometry pose stamped `t` ns (ignored once scans carry odometry). Then call
    /// [`Feeder::next`] until `None`.
    ///
    /// # Errors
    /// The mapper's rejection (counted there).
    pub fn odometry(&mut self, m: &mut Mapper<'_>, t: i64, pose: Se2) -> Result<(), MapperError> {
        if self.scans_carry_odometry {
            return Ok(());
        }
        let t = self.clock(0, t);
        m.push_odometry(t, pose)?;
        self.gate.wheel(t);
        Ok(())
    }

    /// A gyro yaw rate stamped `t` ns. Then call [`Feeder::next`] until `None`.
    ///
    /// # Errors
    /// The mapper's rejection (counted there).
    pub fn gyro(&mut self, m: &mut Mapper<'_>, t: i64, yaw_rate: f64) -> Result<(), MapperError> {
        let t = self.clock(1, t);
        m.push_gyro(t, yaw_rate)?;
        self.gate.gyro(t);
        Ok(())
    }

    /// Camera `camera`'s image `view`, stamped `t` ns, to the mapper's camera stage. Images wait
    /// for nothing: they are tracked against the camera's previous image on arrival, and one
    /// whose stamp does not advance is rejected (counted per camera) rather than repaired,
    /// since a camera's frames are not interpolated. With the visual odometry
    /// ([`Mapper::push_image`]), the image's pose comes back in [`ImageOutput::frame`].
    ///
    /// # Errors
    /// The mapper's rejection (see [`Mapper::push_image`]).
    pub fn image(
        &mut self,
        m: &mut Mapper<'_>,
        camera: u8,
        t: i64,
        view: &ImageView<'_>,
        deadline_passed: bool,
    ) -> Result<ImageOutput, MapperError> {
        m.push_image(camera, t, view, deadline_passed)
    }

    /// A scan, with the odometry pose its source recorded at its time, if any. Gives the scan
    /// pushed by this call: this one when nothing needs to wait, or the oldest held one when
    /// the queue was full (then this one is held); `None` when this one is held. Then call
    /// [`Feeder::next`] until `None`.
    pub fn scan(
        &mut self,
        m: &mut Mapper<'_>,
        scan: &ScanInput<'_>,
        odometry: Option<Se2>,
        deadline_passed: bool,
    ) -> Option<Pushed> {
        self.scan_probed(m, scan, odometry, deadline_passed, &mut ())
    }

    /// [`Feeder::scan`] through [`Mapper::push_scan_probed`] (the odometry push before it is
    /// not part of any section).
    pub fn scan_probed(
        &mut self,
        m: &mut Mapper<'_>,
        scan: &ScanInput<'_>,
        odometry: Option<Se2>,
        deadline_passed: bool,
        probe: &mut impl Probe,
    ) -> Option<Pushed> {
        let original = scan.stamp;
        let stamp = self.clock(2, scan.stamp);
        let own_odometry = odometry.is_some();
        if let Some(pose) = odometry {
            self.scans_carry_odometry = true;
            let t = self.clock(0, stamp);
            if m.push_odometry(t, pose).is_ok() {
                self.gate.wheel(t);
            }
        }
        let mut input = *scan;
        input.stamp = stamp;
        input.geometry.range_min = input.geometry.range_min.max(self.range_min);
        // The odometry must cover the whole sweep: the last beam is corrected with it too.
        let seconds = input.geometry.sweep_seconds(input.ranges.len());
        let end = stamp.saturating_add(libm::round(seconds * 1e9) as i64);
        if self.gate.passes(stamp, end, own_odometry) {
            return Some(Pushed {
                stamp: original,
                result: m.push_scan_probed(&input, deadline_passed, probe),
            });
        }
        if input.ranges.len() > MAX_POINTS {
            self.gate.stats.too_long += 1;
            return Some(Pushed {
                stamp: original,
                result: Err(MapperError::TooManyBeams),
            });
        }
        match self.gate.admit(stamp, end, own_odometry) {
            // `passes` said no, so the gate holds it.
            Admit::Now | Admit::Held => {
                let _ = self.held.push_back(&input, original);
                None
            }
            Admit::HeldAfterOldest => {
                let pushed = self.push_front(m, deadline_passed, probe);
                let _ = self.held.push_back(&input, original);
                pushed
            }
        }
    }

    fn push_front(
        &mut self,
        m: &mut Mapper<'_>,
        deadline_passed: bool,
        probe: &mut impl Probe,
    ) -> Option<Pushed> {
        let (input, stamp) = self.held.front()?;
        let result = m.push_scan_probed(&input, deadline_passed, probe);
        self.held.pop_front();
        Some(Pushed { stamp, result })
    }

    /// The oldest held scan, pushed to the mapper if odometry now covers it or its wait ran
    /// out; `None` when none may go yet.
    pub fn next(&mut self, m: &mut Mapper<'_>, deadline_passed: bool) -> Option<Pushed> {
        self.next_probed(m, deadline_passed, &mut ())
    }

    /// [`Feeder::next`] through [`Mapper::push_scan_probed`].
    pub fn next_probed(
        &mut self,
        m: &mut Mapper<'_>,
        deadline_passed: bool,
        probe: &mut impl Probe,
    ) -> Option<Pushed> {
        self.gate.release()?;
        self.push_front(m, deadline_passed, probe)
    }

    /// At the end of the input: the oldest held scan, pushed without further wait; `None` when
    /// none is left.
    pub fn finish(&mut self, m: &mut Mapper<'_>, deadline_passed: bool) -> Option<Pushed> {
        self.finish_probed(m, deadline_passed, &mut ())
    }

    /// [`Feeder::finish`] through [`Mapper::push_scan_probed`].
    pub fn finish_probed(
        &mut self,
        m: &mut Mapper<'_>,
        deadline_passed: bool,
        probe: &mut impl Probe,
    ) -> Option<Pushed> {
        self.gate.drain()?;
        self.push_front(m, deadline_passed, probe)
    }
}
