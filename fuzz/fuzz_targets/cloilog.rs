//! `.cloilog` files through the core's log reader (`core-nostd/src/sensor/log`): each input as
//! it is, then with the CRC of every record recomputed, so that mutations reach the record
//! decoders instead of stopping at the checksum.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    read_all(data);
    read_all(&cloi_fuzz::with_cloilog_crcs(data));
});

fn read_all(data: &[u8]) {
    let mut buf = vec![0u8; 64 * 1024];
    let Ok(mut reader) = cloi_core::sensor::log::LogReader::new(data, &mut buf) else {
        return;
    };
    // Every record consumes at least its frame overhead, so this ends.
    while let Ok(Some(_)) = reader.next_record() {}
    let _ = reader.header();
}
