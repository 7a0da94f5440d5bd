//! toro pose graphs (`graph_io/toro.rs`).
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = cloi_host::graph_io::read_toro(text, Path::new("fuzz.toro"));
    }
});
