//! A Hokuyo SCIP 2.0 byte stream through the core's scan reader and parameter lines
//! (`core-nostd/src/sensor/urg.rs`): any bytes decode without a panic, a scan never holds more
//! steps than the reader's storage or than the bytes could carry, and every line is counted.
#![no_main]
use cloi_core::sensor::urg::{ScanReader, UrgParams, MAX_STEPS};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let mut reader = ScanReader::new();
    let mut params = UrgParams::default();
    let mut scans = 0u64;
    for line in data.split(|&b| b == b'\n') {
        let _ = params.take_line(line);
    }
    let _ = params.usable();
    for &byte in data {
        if let Some(scan) = reader.push(byte) {
            scans += 1;
            assert!(scan.steps <= MAX_STEPS && scan.steps == reader.ranges_mm().len());
            // Three characters a distance.
            assert!(scan.steps * 3 <= data.len());
        }
    }
    let c = reader.counters();
    assert_eq!(c.scans, scans);
    assert!(c.lines <= data.len() as u64);
});
