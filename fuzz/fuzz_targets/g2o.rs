//! g2o pose graphs (`graph_io/g2o.rs`).
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = cloi_host::graph_io::read_g2o(text, Path::new("fuzz.g2o"));
    }
});
