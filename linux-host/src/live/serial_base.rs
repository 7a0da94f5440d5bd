//! A robot base on a serial port as a wheel-odometry source: a thread asks an iRobot Create 2
//! (or a Roomba 600 series) for its encoder stream, decodes the frames with the core's parser
//! ([`cloi_core::sensor::create2`]) and sends each frame's dead-reckoned pose on as an
//! odometry event, stamped with the host's clock when the frame arrived.
//!
//! The interface is opened in its passive mode: the robot is read, never driven. The stream is
//! paused when the run ends. Checksum failures, bytes between frames and frames without both
//! encoder counts are counted; a device that goes away is opened (and asked for its stream)
//! again, the dead reckoning going on from the pose it had (the wheels' motion while it was
//! away is lost, as a gap in the odometry).

use std::io::Write;
use std::sync::atomic::AtomicBool;
use std::sync::mpsc::SyncSender;
use std::sync::{Arc, Mutex};

use anyhow::{Context, Result};
use cloi_core::sensor::create2::{
    EncoderOdometry, StreamCounters, StreamReader, WheelGeometry, PAUSE_STREAM,
    START_ENCODER_STREAM,
};
use serde::Serialize;

use super::port::{self, Port, PortEvent};
use super::record::{self, SharedRecorder};
use crate::map::input::SensorEvent;

/// What the base's thread met, for the run's report.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct BaseCounters {
    /// Bytes read from the port.
    pub bytes: u64,
    /// Frames whose checksum held.
    pub frames: u64,
    /// Frames whose checksum failed.
    pub checksum_errors: u64,
    /// Bytes skipped while looking for a frame.
    pub skipped_bytes: u64,
    /// Good frames without both encoder counts.
    pub frames_ignored: u64,
    /// Encoder steps too large to be motion (the robot's counters were reset).
    pub counter_resets: u64,
    /// Odometry poses sent on.
    pub poses: u64,
    /// Reads that failed (the device went away).
    pub read_errors: u64,
    /// Times the port was opened again after a failure.
    pub reopened: u64,
    /// Poses written to the recording.
    pub recorded: u64,
}

/// Where to read the base.
#[derive(Clone, Debug)]
pub struct SerialBase {
    /// Device path.
    pub path: String,
    /// Serial speed.
    pub baud: u32,
    /// The run's recording.
    pub recorder: Arc<SharedRecorder>,
}

impl SerialBase {
    /// Opens the port and asks for the encoder stream.
    fn open(&self) -> Result<Port> {
        let mut port = port::open(&self.path, self.baud)?;
        port.write_all(&START_ENCODER_STREAM)?;
        Ok(port)
    }

    /// Opens the port (a clear error if it cannot be) and starts the thread that reads it and
    /// sends its poses on `tx` until `stop` is set; `counters` follows what it met.
    ///
    /// # Errors
    /// The port cannot be opened, or the thread cannot be started.
    pub fn start(
        self,
        tx: SyncSender<Result<SensorEvent>>,
        stop: Arc<AtomicBool>,
        counters: Arc<Mutex<BaseCounters>>,
    ) -> Result<std::thread::JoinHandle<Result<()>>> {
        let port = self
            .open()
            .with_context(|| format!("opening the base's serial port {}", self.path))?;
        std::thread::Builder::new()
            .name("cloi-base".into())
            .spawn(move || {
                let port = self.read_until_stopped(port, &tx, &stop, &counters);
                if let Some(mut p) = port {
                    // Best effort: the device may be gone.
                    let _ = p.write_all(&PAUSE_STREAM);
                }
                Ok(())
            })
            .context("starting the base's thread")
    }

    fn read_until_stopped(
        &self,
        port: Port,
        tx: &SyncSender<Result<SensorEvent>>,
        stop: &AtomicBool,
        counters: &Mutex<BaseCounters>,
    ) -> Option<Port> {
        let count = |f: &mut dyn FnMut(&mut BaseCounters)| port::update(counters, f);
        let mut reader = StreamReader::new();
        let mut odometry = EncoderOdometry::new(WheelGeometry::CREATE2);
        let mut last_stamp = i64::MIN;
        let handle = |event: PortEvent<'_>| {
            let bytes = match event {
                PortEvent::Bytes(bytes) => bytes,
                PortEvent::Lost => {
                    count(&mut |c| c.read_errors += 1);
                    return true;
                }
                PortEvent::Reopened => {
                    count(&mut |c| c.reopened += 1);
                    reader = StreamReader::new();
                    odometry.restart();
                    return true;
                }
            };
            let (before, jumps) = (reader.counters(), odometry.jumps());
            let mut poses = Vec::new();
            for &b in bytes {
                if let Some(counts) = reader.push(b) {
                    poses.push(odometry.update(counts));
                }
            }
            let (after, resets) = (reader.counters(), odometry.jumps() - jumps);
            count(&mut |c| {
                c.bytes += bytes.len() as u64;
                add(c, before, after);
                c.counter_resets += resets;
                c.poses += poses.len() as u64;
            });
            // Frames read together arrived together: one stamp, nudged apart to stay in order.
            let now = port::now_ns();
            for pose in poses {
                let t_ns = now.max(last_stamp.saturating_add(1));
                last_stamp = t_ns;
                if record::record(&self.recorder, |r| r.odometry(t_ns, pose)) {
                    count(&mut |c| c.recorded += 1);
                }
                if tx.send(Ok(SensorEvent::Odometry { t_ns, pose })).is_err() {
                    return false;
                }
            }
            true
        };
        port::read_until_stopped(&self.path, "base", port, stop, &|| self.open(), handle)
    }
}

/// Adds what the reader met between two readings of its counters.
fn add(c: &mut BaseCounters, before: StreamCounters, after: StreamCounters) {
    c.frames += after.frames - before.frames;
    c.checksum_errors += after.checksum_errors - before.checksum_errors;
    c.skipped_bytes += after.skipped_bytes - before.skipped_bytes;
    c.frames_ignored += after.frames_ignored - before.frames_ignored;
}
