//! Replay mode: a recorded `.cloilog` streamed from the host through semihosting.
//!
//! The log is read in fixed [`CHUNK`]-byte `SYS_READ` calls into a static buffer and decoded
//! record by record ([`cloi_core::sensor::log::LogReader`]); each record goes to
//! [`process_event`], whose instruction count (A9 global timer under `-icount shift=0`) is
//! recorded per scan. The per-scan results go to the output file through `SYS_WRITE`, one text
//! line per scan:
//!
//! ```text
//! # t_ns x y theta matched instructions
//! 976052857387156000 0e0 0e0 -2.458e-3 0 184530
//! ```
//!
//! Poses are printed in Rust's shortest round-trip form (`{:e}`), so parsing a line gives back
//! the exact `f64` bits. At the end the firmware prints the instruction percentiles per scan
//! (nearest rank: the `p` quantile is the `ceil(p n)`-th smallest count).

use core::ffi::CStr;
use core::fmt::Write as _;

use cloi_core::replay::{Replay, ReplayConfig, ScanOutcome};
use cloi_core::sensor::log::{ByteSource, LogReader, LogRecord, MIN_READER_BUFFER};
use semihosting::fs::File;
use semihosting::io::{Read as _, Write as _};
use semihosting::println;

use crate::statics::TakeOnce;
use crate::timer;

/// Bytes per `SYS_READ`.
pub const CHUNK: usize = 4096;
/// Scans whose instruction counts are kept for the percentiles (intel.clf has 13,631).
pub const MAX_SCANS: usize = 32_768;
/// Output buffered before each `SYS_WRITE`.
const OUT_BUFFER: usize = 8192;

/// Everything the per-event step keeps between records. The mapper replaces the replay here.
pub struct State {
    replay: Replay,
}

impl State {
    const fn new() -> Self {
        Self {
            replay: Replay::new(ReplayConfig::DEFAULT),
        }
    }
}

/// The one per-record step of the firmware's main loop.
pub fn process_event(state: &mut State, record: &LogRecord<'_>) -> Option<ScanOutcome> {
    state.replay.process(record)
}

static STATE: TakeOnce<State> = TakeOnce::new(State::new());
static READ_BUFFER: TakeOnce<[u8; MIN_READER_BUFFER + CHUNK]> =
    TakeOnce::new([0; MIN_READER_BUFFER + CHUNK]);
static SCAN_INSTRUCTIONS: TakeOnce<[u32; MAX_SCANS]> = TakeOnce::new([0; MAX_SCANS]);
static OUT: TakeOnce<OutBuffer> = TakeOnce::new(OutBuffer {
    bytes: [0; OUT_BUFFER],
    len: 0,
});

/// A semihosting file read in fixed chunks.
pub(crate) struct ChunkedFile(pub(crate) File);

impl ByteSource for ChunkedFile {
    type Error = semihosting::io::Error;

    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let n = buf.len().min(CHUNK);
        self.0.read(&mut buf[..n])
    }
}

/// Text lines collected for the output file.
pub(crate) struct OutBuffer {
    pub(crate) bytes: [u8; OUT_BUFFER],
    pub(crate) len: usize,
}

impl core::fmt::Write for OutBuffer {
    fn write_str(&mut self, s: &str) -> core::fmt::Result {
        let end = self.len + s.len();
        let dst = self.bytes.get_mut(self.len..end).ok_or(core::fmt::Error)?;
        dst.copy_from_slice(s.as_bytes());
        self.len = end;
        Ok(())
    }
}

impl OutBuffer {
    pub(crate) const fn new() -> Self {
        Self {
            bytes: [0; OUT_BUFFER],
            len: 0,
        }
    }

    pub(crate) fn flush_to(&mut self, file: &mut File) -> Result<(), semihosting::io::Error> {
        file.write_all(&self.bytes[..self.len])?;
        self.len = 0;
        Ok(())
    }
}

/// Copies `text` into `buf` with a terminating NUL, for the semihosting calls.
pub(crate) fn c_path<'a>(text: &str, buf: &'a mut [u8; 512]) -> Option<&'a CStr> {
    let bytes = text.as_bytes();
    buf.get_mut(..bytes.len())?.copy_from_slice(bytes);
    *buf.get_mut(bytes.len())? = 0;
    CStr::from_bytes_until_nul(&buf[..=bytes.len()]).ok()
}

/// Nearest-rank quantile `percent / 100` of sorted values: the `ceil(p n)`-th smallest.
pub(crate) fn quantile(sorted: &[u32], percent: usize) -> u32 {
    let n = sorted.len();
    let rank = (percent * n).div_ceil(100).clamp(1, n.max(1));
    sorted.get(rank - 1).copied().unwrap_or(0)
}

/// Runs the replay of `log_path`, writing poses to `out_path`. Returns an error message.
pub fn run(log_path: &str, out_path: &str) -> Result<(), &'static str> {
    let (Some(state), Some(read_buffer), Some(counts), Some(out)) = (
        STATE.take(),
        READ_BUFFER.take(),
        SCAN_INSTRUCTIONS.take(),
        OUT.take(),
    ) else {
        return Err("replay started twice");
    };
    let mut path = [0u8; 512];
    let log_c = c_path(log_path, &mut path).ok_or("log path too long")?;
    let file = File::open(log_c).map_err(|_| "cannot open the log (SYS_OPEN)")?;
    let log_bytes = file.metadata().map(|m| m.len()).unwrap_or(0);
    let out_c = c_path(out_path, &mut path).ok_or("output path too long")?;
    let mut out_file = File::create(out_c).map_err(|_| "cannot create the output (SYS_OPEN)")?;
    println!("mode=replay log={log_path} log_bytes={log_bytes} chunk_bytes={CHUNK}");
    let _ = writeln!(out, "# t_ns x y theta matched instructions");

    let mut reader =
        LogReader::new(ChunkedFile(file), read_buffer).map_err(|_| "read buffer too small")?;
    let (mut scans, mut records) = (0usize, 0u64);
    let (mut process_total, mut decode_total) = (0u64, 0u64);
    loop {
        let t0 = timer::ticks();
        let next = reader.next_record();
        let t1 = timer::ticks();
        decode_total += (t1 - t0) * timer::INSTRUCTIONS_PER_TICK;
        let record = match next {
            Ok(Some(record)) => record,
            Ok(None) => break,
            Err(e) => {
                println!("replay_error=\"{e}\"");
                return Err("the log is damaged or unreadable");
            }
        };
        records += 1;
        let start = timer::ticks();
        let outcome = core::hint::black_box(process_event(state, &record));
        let end = timer::ticks();
        let instructions = (end - start) * timer::INSTRUCTIONS_PER_TICK;
        process_total += instructions;
        let Some(o) = outcome else { continue };
        if let Some(slot) = counts.get_mut(scans) {
            *slot = u32::try_from(instructions).unwrap_or(u32::MAX);
        }
        scans += 1;
        if out.len + 256 > OUT_BUFFER {
            out.flush_to(&mut out_file)
                .map_err(|_| "cannot write the output (SYS_WRITE)")?;
        }
        let _ = writeln!(
            out,
            "{} {:e} {:e} {:e} {} {}",
            o.stamp.as_nanos(),
            o.pose.x,
            o.pose.y,
            o.pose.theta,
            u8::from(o.matched),
            instructions
        );
    }
    out.flush_to(&mut out_file)
        .map_err(|_| "cannot write the output (SYS_WRITE)")?;
    drop(out_file);

    let stats = state.replay.stats();
    println!(
        "replay_records={records} replay_scans={} replay_odometry={} replay_unmatched={} \
         replay_keyframes={} replay_rejected={}",
        stats.scans, stats.odometry, stats.unmatched, stats.keyframes, stats.rejected
    );
    let kept = scans.min(MAX_SCANS);
    let sorted = &mut counts[..kept];
    sorted.sort_unstable();
    println!(
        "scan_instructions n={kept} min={} median={} p99={} max={} mean={}",
        quantile(sorted, 0),
        quantile(sorted, 50),
        quantile(sorted, 99),
        quantile(sorted, 100),
        if kept > 0 {
            sorted.iter().map(|&c| u64::from(c)).sum::<u64>() / kept as u64
        } else {
            0
        }
    );
    println!("event_instructions_total={process_total} decode_instructions_total={decode_total}");
    if scans > MAX_SCANS {
        println!("scans_not_in_percentiles={}", scans - MAX_SCANS);
    }
    Ok(())
}
