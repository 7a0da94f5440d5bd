//! `.cloilog` files through the core's log reader (`core-nostd/src/sensor/log`).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let mut buf = vec![0u8; 64 * 1024];
    let Ok(mut reader) = cloi_core::sensor::log::LogReader::new(data, &mut buf) else {
        return;
    };
    let _ = reader.header();
    // Every record consumes at least its frame overhead, so this ends.
    while let Ok(Some(_)) = reader.next_record() {}
});
