//! An iRobot Create 2 encoder stream through the core's frame reader and dead reckoning
//! (`core-nostd/src/sensor/create2.rs`): any bytes decode without a panic, no more frames come
//! out than their shortest length allows, every byte is accounted for, and the pose stays
//! finite whatever counts arrive.
#![no_main]
use cloi_core::sensor::create2::{EncoderOdometry, StreamReader, WheelGeometry};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let mut reader = StreamReader::new();
    let mut odometry = EncoderOdometry::new(WheelGeometry::CREATE2);
    let mut counts = 0u64;
    for &byte in data {
        if let Some(c) = reader.push(byte) {
            counts += 1;
            assert!(odometry.update(c).is_finite());
        }
    }
    let c = reader.counters();
    // The shortest frame with both encoders is 9 bytes; any good frame at least 3.
    assert!(counts <= data.len() as u64 / 9);
    assert!(c.frames <= data.len() as u64 / 3);
    assert!(c.frames - c.frames_ignored == counts);
    assert!(c.skipped_bytes <= data.len() as u64);
});
