//! What every serial device thread of the live path does with its port: read what arrives
//! until the run stops, and when the device goes away (unplugged, its port closed) open it
//! again every [`REOPEN`] until it answers, telling the device's decoder each time.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::Result;

/// Wait between attempts to open a port that went away.
pub const REOPEN: Duration = Duration::from_millis(250);
/// Longest wait of one read, so that a stop request is seen promptly.
pub const READ_TIMEOUT: Duration = Duration::from_millis(100);

/// An open serial port.
pub type Port = Box<dyn serialport::SerialPort>;

/// What a device thread is told about its port.
#[derive(Debug)]
pub enum PortEvent<'a> {
    /// Bytes read.
    Bytes(&'a [u8]),
    /// A read failed: the device went away (logged here).
    Lost,
    /// The port was opened again after a loss (logged here): what was half decoded is stale.
    Reopened,
}

/// Opens `path` at `baud` with the live path's read timeout.
///
/// # Errors
/// The port cannot be opened.
pub fn open(path: &str, baud: u32) -> Result<Port> {
    Ok(serialport::new(path, baud).timeout(READ_TIMEOUT).open()?)
}

/// Reads `port` until `stop` is set or `handle` breaks off (returns `false`); reopens it with
/// `reopen` after a loss. The port at the end, if one is open.
pub fn read_until_stopped(
    path: &str,
    what: &str,
    port: Port,
    stop: &AtomicBool,
    reopen: &dyn Fn() -> Result<Port>,
    mut handle: impl FnMut(PortEvent<'_>) -> bool,
) -> Option<Port> {
    let mut port = Some(port);
    let mut buf = [0u8; 512];
    let mut last_attempt = Instant::now();
    while !stop.load(Ordering::Acquire) {
        let Some(p) = port.as_mut() else {
            std::thread::sleep(REOPEN.saturating_sub(last_attempt.elapsed()));
            last_attempt = Instant::now();
            if let Ok(p) = reopen() {
                log::warn!("{path}: the {what} answers again");
                port = Some(p);
                if !handle(PortEvent::Reopened) {
                    break;
                }
            }
            continue;
        };
        match p.read(&mut buf) {
            Ok(n) => {
                if !handle(PortEvent::Bytes(&buf[..n])) {
                    break;
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
            Err(e) => {
                log::warn!("{path}: {e}; opening it again until it answers");
                port = None;
                last_attempt = Instant::now();
                if !handle(PortEvent::Lost) {
                    break;
                }
            }
        }
    }
    port
}

/// Changes a device thread's counters (a thread that panicked holding them left them usable).
pub fn update<T>(counters: &std::sync::Mutex<T>, change: &mut dyn FnMut(&mut T)) {
    change(
        &mut counters
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner),
    );
}

/// The host's clock, ns since the Unix epoch: the time stamp of what a device sends.
pub fn now_ns() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
}
