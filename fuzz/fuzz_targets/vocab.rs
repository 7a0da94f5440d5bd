//! Place-recognition vocabulary files (`cloi vocab train`) through the core's reader
//! (`core-nostd/src/frontend/visual/vocab/file.rs`) into fixed storage: each input as it is,
//! then with its trailing CRC recomputed, so that mutations reach the shape, weight and tree
//! checks instead of stopping at the checksum. A vocabulary that is read then turns a few
//! fixed descriptors into a bag, which must come out normalised.
#![no_main]
use cloi_core::frontend::visual::vocab::{file, Bag, Node};
use cloi_core::frontend::visual::Descriptor;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    read(data);
    read(&cloi_fuzz::with_vocab_crc(data));
});

/// Slots of the fuzzed reads: a 16 x 3 tree (4,368 slots) and every smaller one fit, so a
/// larger claim exercises `StorageTooSmall`.
const NODES: usize = 4368;
/// Descriptors turned into a bag.
const DESCRIPTORS: usize = 24;

fn read(data: &[u8]) {
    let mut nodes = vec![Node::EMPTY; NODES];
    let Ok((vocab, header)) = file::read(data, &mut nodes) else {
        return;
    };
    assert_eq!(vocab.nodes().len(), header.nodes);
    let descriptors = fixed_descriptors();
    let mut bag = Bag::new();
    let stats = bag.transform(&vocab, &descriptors);
    assert_eq!(
        stats.used + stats.uninformative + stats.dropped,
        DESCRIPTORS
    );
    let entries = bag.entries();
    assert!(entries.windows(2).all(|w| w[0].word < w[1].word));
    assert!(entries
        .iter()
        .all(|e| e.weight.is_finite() && e.weight >= 0.0));
    let score = bag.score(&bag);
    assert!((0.0..=1.0).contains(&score), "self-score {score}");
}

/// All zeros, all ones, alternating bits, then a fixed pseudo-random sequence.
fn fixed_descriptors() -> [Descriptor; DESCRIPTORS] {
    let mut out = [Descriptor([0; 8]); DESCRIPTORS];
    out[1] = Descriptor([u32::MAX; 8]);
    out[2] = Descriptor([0xAAAA_AAAA; 8]);
    let mut state: u32 = 0x9E37_79B9;
    for d in out.iter_mut().skip(3) {
        for w in d.0.iter_mut() {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            *w = state;
        }
    }
    out
}
