//! The readers stream: peak heap use while reading a log does not grow with its length.
//!
//! A counting global allocator (this test binary only) records the peak of live heap bytes
//! while a CARMEN log (plain and gzip) and its MCAP conversion are read from start to end, once
//! for a log and once for a log ten times longer.
// A global allocator needs `unsafe impl`; it only forwards to the system allocator.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::fmt::Write as _;
use std::io::Write as _;
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};

use cloi_host::io::bag_read::{BagReadOptions, BagReader};
use cloi_host::io::carmen::CarmenReader;
use cloi_host::io::convert::carmen_to_bag;

struct Counting;

static CURRENT: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

fn grew(n: usize) {
    let now = CURRENT.fetch_add(n, Ordering::Relaxed) + n;
    PEAK.fetch_max(now, Ordering::Relaxed);
}

// SAFETY: every call forwards to `System` with the caller's layout and pointer unchanged;
// the counters do not affect the memory handed out.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            grew(layout.size());
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        CURRENT.fetch_sub(layout.size(), Ordering::Relaxed);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            CURRENT.fetch_sub(layout.size(), Ordering::Relaxed);
            grew(new_size);
        }
        p
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Peak heap bytes above the level at the start, while `f` runs.
fn peak_of(f: impl FnOnce()) -> usize {
    let base = CURRENT.load(Ordering::Relaxed);
    PEAK.store(base, Ordering::Relaxed);
    f();
    PEAK.load(Ordering::Relaxed).saturating_sub(base)
}

/// A synthetic CARMEN log: 10 scans (180 beams) and 20 odometry lines per second.
fn write_log(path: &Path, scans: usize) {
    let mut text = String::new();
    let mut file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    for i in 0..scans {
        let t = 1000.0 + i as f64 * 0.1;
        for k in 0..2 {
            let tk = t + 0.05 * k as f64;
            writeln!(file, "ODOM {:.3} 0.0 0.0 0.5 0.0 0.0 {tk:.6} h 0", tk * 0.5).unwrap();
        }
        text.clear();
        let _ = write!(text, "FLASER 180");
        for b in 0..180 {
            let _ = write!(text, " {:.2}", 1.0 + ((i * 7 + b) % 500) as f64 * 0.01);
        }
        let _ = write!(text, " {0:.3} 0 0 {0:.3} 0 0 {1:.6} h 0", t * 0.5, t + 0.01);
        writeln!(file, "{text}").unwrap();
    }
    file.flush().unwrap();
}

fn gzip(path: &Path, out: &Path) {
    let mut enc = flate2::write::GzEncoder::new(
        std::fs::File::create(out).unwrap(),
        flate2::Compression::fast(),
    );
    enc.write_all(&std::fs::read(path).unwrap()).unwrap();
    enc.finish().unwrap();
}

fn read_carmen(path: &Path) -> u64 {
    let mut reader = CarmenReader::open(path, true).unwrap();
    let mut n = 0;
    for r in reader.by_ref() {
        r.unwrap();
        n += 1;
    }
    assert!(reader.stats().warnings.is_empty());
    n
}

fn read_bag(path: &Path) -> u64 {
    let mut reader = BagReader::open(path, BagReadOptions::default()).unwrap();
    let mut n = 0;
    for m in reader.by_ref() {
        m.unwrap();
        n += 1;
    }
    assert_eq!(reader.stats().out_of_order, 0);
    n
}

#[test]
fn reader_memory_is_independent_of_log_length() {
    let dir = tempfile::tempdir().unwrap();
    let mut peaks = Vec::new();
    // Both logs make bags of several chunks: the bag reader holds one whole chunk to check
    // its CRC before using it, so a log smaller than a chunk would understate its peak.
    for scans in [2_000, 20_000] {
        let log = dir.path().join(format!("s{scans}.clf"));
        let gz = dir.path().join(format!("s{scans}.clf.gz"));
        let bag = dir.path().join(format!("s{scans}.mcap"));
        write_log(&log, scans);
        gzip(&log, &gz);
        carmen_to_bag(&log, &bag, true, None).unwrap();

        let mut count = 0;
        let plain = peak_of(|| count = read_carmen(&log));
        assert_eq!(count, 3 * scans as u64);
        let zipped = peak_of(|| count = read_carmen(&gz));
        assert_eq!(count, 3 * scans as u64);
        // A bag has scans, odometry, and a transform per odometry message, plus tf_static;
        // each scan's own odometry pose is one more odometry message and transform.
        let mcap = peak_of(|| count = read_bag(&bag));
        assert_eq!(count, 7 * scans as u64 + 1);
        let size = std::fs::metadata(&log).unwrap().len();
        eprintln!(
            "{scans} scans ({size} bytes): peak heap carmen {plain} B, gzip {zipped} B, mcap {mcap} B"
        );
        peaks.push((size, plain, zipped, mcap));
    }
    let (short, long) = (peaks[0], peaks[1]);
    assert!(long.0 > 9 * short.0);
    // Ten times the input, at most a quarter more memory (plus 64 KiB of slack).
    for (what, a, b) in [
        ("carmen", short.1, long.1),
        ("gzip", short.2, long.2),
        ("mcap", short.3, long.3),
    ] {
        assert!(
            b <= a + a / 4 + 65_536,
            "{what}: peak {b} B for the long log vs {a} B for the short one"
        );
        // And far below the size of the log itself.
        assert!(b < (long.0 / 4) as usize, "{what}: peak {b} B");
    }
}
