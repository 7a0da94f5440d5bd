//! An LD06 / LD19 serial byte stream through the core's packet reader and revolution assembly
//! (`core-nostd/src/sensor/ld06.rs`): any bytes, cut anywhere, decode without a panic, and
//! every packet handed out has its angles below a full turn.
#![no_main]
use cloi_core::sensor::ld06::{PacketReader, Revolution};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let mut reader = PacketReader::new();
    let mut revolution = Revolution::<720>::new();
    let mut out = [0.0f32; 720];
    for &byte in data {
        if let Some(p) = reader.push(byte) {
            assert!(p.start_cdeg < 36_000 && p.end_cdeg < 36_000);
            let _ = revolution.add(&p, &mut out);
        }
    }
    let c = reader.counters();
    assert!(c.packets <= data.len() as u64 / 47);
});
