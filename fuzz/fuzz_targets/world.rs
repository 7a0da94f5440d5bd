//! Simulator world files (`sim/world.rs`).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let _ = cloi_host::sim::world::WorldFile::parse(text, "fuzz.world");
});
