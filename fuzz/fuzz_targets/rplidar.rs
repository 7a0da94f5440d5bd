//! A Slamtec RPLIDAR standard-scan byte stream through the core's node reader and revolution
//! assembly (`core-nostd/src/sensor/rplidar.rs`): any bytes decode without a panic, every node
//! handed out has a valid angle field, and no more nodes come out than five bytes each allow.
#![no_main]
use cloi_core::sensor::ld06::Revolution;
use cloi_core::sensor::rplidar::NodeReader;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let mut reader = NodeReader::new();
    let mut revolution = Revolution::<720>::new();
    let mut out = [0.0f32; 720];
    for &byte in data {
        if let Some(n) = reader.push(byte) {
            assert!(n.angle_q6 < 1 << 15 && n.quality < 64);
            let _ = revolution.point(n.angle_cdeg(), n.distance_mm(), n.start, &mut out);
        }
    }
    let c = reader.counters();
    assert!(c.nodes <= data.len() as u64 / 5);
    assert!(c.nodes * 5 + c.skipped_bytes <= data.len() as u64);
});
