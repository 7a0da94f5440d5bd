//! ROS 2 MCAP bags with CDR messages through the streaming bag reader (`io/bag_read.rs`).
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    use cloi_host::io::bag_read::{BagReadOptions, BagReader};
    let input: Box<dyn std::io::Read> = Box::new(std::io::Cursor::new(data.to_vec()));
    let reader = BagReader::from_reader(input, Path::new("fuzz.mcap"), BagReadOptions::default());
    for item in reader {
        if item.is_err() {
            break;
        }
    }
});
