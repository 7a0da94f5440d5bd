//! CARMEN log lines (`io/carmen.rs`), lenient and strict.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    for strict in [false, true] {
        let reader = cloi_host::io::carmen::reader_from_bytes(data.to_vec(), "fuzz.clf", strict);
        for item in reader {
            if item.is_err() {
                break;
            }
        }
    }
});
