//! Relation files of the Freiburg/CARMEN benchmark (`eval/relations.rs`).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = cloi_fuzz::scratch_file("relations", data);
    let _ = cloi_host::eval::relations::load_relations(&path);
});
