extern crate std;

use std::vec::Vec;

use super::super::brief::Descriptor;
use super::super::synth::Rng;
use super::file::{self, VocabFileError};
use super::*;

fn random_descriptor(rng: &mut Rng) -> Descriptor {
    let mut d = Descriptor::default();
    for w in &mut d.0 {
        *w = rng.next_u64() as u32;
    }
    d
}

/// `d` with `flips` random bits flipped (possibly the same bit twice).
fn perturbed(d: &Descriptor, flips: usize, rng: &mut Rng) -> Descriptor {
    let mut out = *d;
    for _ in 0..flips {
        let b = (rng.next_u64() % 256) as usize;
        out.0[b / 32] ^= 1 << (b % 32);
    }
    out
}

/// A trained vocabulary's slots.
fn trained(cfg: &TrainConfig, descriptors: &[Descriptor], docs: &[&[Descriptor]]) -> Vec<Node> {
    let mut nodes = std::vec![Node::EMPTY; node_count(cfg.branching, cfg.depth).unwrap()];
    let mut scratch = descriptors.to_vec();
    let mut counters = std::vec![0u32; counter_len(cfg.branching)];
    train(cfg, &mut scratch, &mut counters, &mut nodes).unwrap();
    let words = Vocabulary::new(cfg.branching, cfg.depth, &nodes)
        .unwrap()
        .word_count();
    let mut doc_counters = std::vec![0u32; document_counter_len(words)];
    set_weights(
        cfg.branching,
        cfg.depth,
        &mut nodes,
        docs.iter().copied(),
        &mut doc_counters,
    )
    .unwrap();
    nodes
}

#[test]
fn k_majority_recovers_separable_clusters() {
    let mut rng = Rng::new(5);
    let protos: Vec<Descriptor> = (0..4).map(|_| random_descriptor(&mut rng)).collect();
    // 60 copies of each prototype with 12 bits flipped: a bit is wrong in about 5% of the
    // copies, so the majority is the prototype itself.
    let mut data = Vec::new();
    for p in &protos {
        for _ in 0..60 {
            data.push(perturbed(p, 12, &mut rng));
        }
    }
    let cfg = TrainConfig {
        branching: 4,
        depth: 1,
        ..TrainConfig::default()
    };
    let mut nodes = std::vec![Node::EMPTY; 4];
    let mut counters = std::vec![0u32; counter_len(4)];
    let mut shuffled = data.clone();
    let stats = train(&cfg, &mut shuffled, &mut counters, &mut nodes).unwrap();
    assert_eq!(stats.clusters, 1);
    assert_eq!(stats.unconverged, 0, "{stats:?}");
    assert_eq!(stats.words, 4);
    for p in &protos {
        assert_eq!(
            nodes.iter().filter(|n| n.centroid == *p).count(),
            1,
            "every prototype is exactly one centroid"
        );
    }
    assert!(nodes.iter().all(|n| n.size == 60));
    // The reordered descriptors are grouped by cluster, in slot order.
    for (slot, n) in nodes.iter().enumerate() {
        for d in &shuffled[slot * 60..(slot + 1) * 60] {
            assert!(d.hamming(&n.centroid) <= 12);
        }
    }
    // Every copy of a prototype gets that prototype's word, in a deeper tree too.
    let cfg = TrainConfig {
        branching: 4,
        depth: 3,
        ..TrainConfig::default()
    };
    let docs: Vec<&[Descriptor]> = data.chunks(60).collect();
    let nodes = trained(&cfg, &data, &docs);
    let vocab = Vocabulary::new(4, 3, &nodes).unwrap();
    for (i, chunk) in data.chunks(60).enumerate() {
        for d in chunk {
            let w = vocab.word(d).unwrap();
            // The first level separates the prototypes: words of different prototypes
            // lie under different first-level slots.
            let first = w as usize / 16;
            let others = data
                .chunks(60)
                .enumerate()
                .filter(|(j, _)| *j != i)
                .flat_map(|(_, c)| c.iter());
            for o in others {
                assert_ne!(vocab.word(o).unwrap() as usize / 16, first);
            }
        }
    }
}

#[test]
fn training_is_deterministic_and_refuses_bad_inputs() {
    let mut rng = Rng::new(11);
    let data: Vec<Descriptor> = (0..500).map(|_| random_descriptor(&mut rng)).collect();
    let cfg = TrainConfig {
        branching: 5,
        depth: 2,
        ..TrainConfig::default()
    };
    let docs: Vec<&[Descriptor]> = data.chunks(50).collect();
    assert_eq!(trained(&cfg, &data, &docs), trained(&cfg, &data, &docs));

    let mut nodes = std::vec![Node::EMPTY; 30];
    let mut counters = std::vec![0u32; counter_len(5)];
    let mut d = data.clone();
    let bad = TrainConfig {
        branching: 1,
        ..cfg
    };
    assert_eq!(
        train(&bad, &mut d, &mut counters, &mut nodes),
        Err(TrainError::BadShape)
    );
    assert_eq!(
        train(&cfg, &mut d, &mut counters, &mut nodes[..29]),
        Err(TrainError::StorageTooSmall)
    );
    assert_eq!(
        train(&cfg, &mut d, &mut counters[..10], &mut nodes),
        Err(TrainError::ScratchTooSmall)
    );
    assert_eq!(
        train(&cfg, &mut [], &mut counters, &mut nodes),
        Err(TrainError::Empty)
    );
    // Fewer descriptors than branches: one word each.
    let few = &mut data[..3].to_vec();
    let stats = train(&cfg, few, &mut counters, &mut nodes).unwrap();
    assert_eq!(stats.words, 3);
}

/// Ten "places", each with 120 descriptors of its own plus 30 seen everywhere; a frame of a
/// place is its descriptors with a few bits of noise.
struct Places {
    places: Vec<Vec<Descriptor>>,
}

impl Places {
    fn new(rng: &mut Rng) -> Self {
        let common: Vec<Descriptor> = (0..30).map(|_| random_descriptor(rng)).collect();
        let places = (0..10)
            .map(|_| {
                let mut p: Vec<Descriptor> = (0..120).map(|_| random_descriptor(rng)).collect();
                p.extend_from_slice(&common);
                p
            })
            .collect();
        Places { places }
    }

    fn frame(&self, place: usize, rng: &mut Rng) -> Vec<Descriptor> {
        self.places[place]
            .iter()
            .map(|d| perturbed(d, 6, rng))
            .collect()
    }
}

/// Ten places, one frame of each, and a vocabulary of 8 x 3 trained on those frames.
fn ten_places(rng: &mut Rng) -> (Places, Vec<Vec<Descriptor>>, Vec<Node>) {
    let places = Places::new(rng);
    let frames: Vec<Vec<Descriptor>> = (0..10).map(|p| places.frame(p, rng)).collect();
    let all: Vec<Descriptor> = frames.iter().flatten().copied().collect();
    let docs: Vec<&[Descriptor]> = frames.iter().map(Vec::as_slice).collect();
    let cfg = TrainConfig {
        branching: 8,
        depth: 3,
        ..TrainConfig::default()
    };
    let nodes = trained(&cfg, &all, &docs);
    (places, frames, nodes)
}

#[test]
fn a_bag_scores_one_against_itself_and_less_against_a_changed_frame() {
    let mut rng = Rng::new(3);
    let (places, frames, nodes) = ten_places(&mut rng);
    let vocab = Vocabulary::new(8, 3, &nodes).unwrap();

    let bag_of = |d: &[Descriptor]| {
        let mut b = Bag::new();
        let stats = b.transform(&vocab, d);
        assert_eq!(stats.dropped, 0);
        b
    };
    let a = bag_of(&frames[0]);
    assert!(!a.is_empty());
    let total: f32 = a.entries().iter().map(|e| e.weight).sum();
    assert!((total - 1.0).abs() < 1e-5, "L1 norm {total}");
    assert!(a.entries().windows(2).all(|w| w[0].word < w[1].word));
    assert!((a.score(&a) - 1.0).abs() < 1e-5, "{}", a.score(&a));

    // The same place seen again: high; half of it replaced by another place: lower; another
    // place: lower still (512 words for 1300 random descriptors: unrelated ones share some).
    let again = bag_of(&places.frame(0, &mut rng));
    let mut mixed = frames[0][..60].to_vec();
    mixed.extend_from_slice(&frames[1][..60]);
    let mixed = bag_of(&mixed);
    let other = bag_of(&frames[1]);
    let (s_again, s_mixed, s_other) = (a.score(&again), a.score(&mixed), a.score(&other));
    assert!(s_again > 0.6 && s_again < 1.0, "{s_again}");
    assert!(s_mixed < s_again && s_mixed > s_other, "{s_mixed}");
    assert!(s_other < 0.3, "{s_other}");
    assert!((a.score(&mixed) - mixed.score(&a)).abs() < 1e-6);
    assert_eq!(a.score(&Bag::new()), 0.0);
}

#[test]
fn the_database_finds_the_revisited_place() {
    let mut rng = Rng::new(8);
    let (places, _, nodes) = ten_places(&mut rng);
    let vocab = Vocabulary::new(8, 3, &nodes).unwrap();

    // A route through places 0..9, two frames each, then back at place 2.
    let mut storage = std::vec![Bag::new(); 21];
    let mut db = Database::new(&mut storage);
    let mut bag = Bag::new();
    for p in 0..10 {
        for _ in 0..2 {
            bag.transform(&vocab, &places.frame(p, &mut rng));
            db.add(&bag).unwrap();
        }
    }
    // The recent neighbours (place 9) are another place here, so the reference is the score
    // of unrelated frames and a true revisit scores several times it.
    let cfg = QueryConfig {
        recent: 2,
        min_normalised: 3.0,
        min_reference: 0.02,
    };
    let mut out = [Candidate::default(); 3];
    bag.transform(&vocab, &places.frame(2, &mut rng));
    let r = db.query(&bag, &cfg, &mut out);
    assert_eq!(r.candidates, 2, "{r:?} {out:?}");
    assert!([4, 5].contains(&out[0].entry) && [4, 5].contains(&out[1].entry));
    assert!(out[0].score >= out[1].score);
    // Frames of the last place are its recent neighbours, not candidates.
    bag.transform(&vocab, &places.frame(9, &mut rng));
    assert_eq!(db.query(&bag, &cfg, &mut out).candidates, 0);
    // Full storage refuses the next keyframe.
    db.add(&bag).unwrap();
    assert_eq!(db.add(&bag), Err(DatabaseFull));
    assert_eq!(db.len(), 21);
}

#[test]
fn a_vocabulary_file_round_trips_and_damage_is_refused() {
    let mut rng = Rng::new(21);
    let data: Vec<Descriptor> = (0..400).map(|_| random_descriptor(&mut rng)).collect();
    let docs: Vec<&[Descriptor]> = data.chunks(40).collect();
    let cfg = TrainConfig {
        branching: 4,
        depth: 3,
        ..TrainConfig::default()
    };
    let nodes = trained(&cfg, &data, &docs);
    let vocab = Vocabulary::new(4, 3, &nodes).unwrap();
    let mut bytes = std::vec![0u8; file::file_len(nodes.len())];
    assert_eq!(
        file::write(&vocab, 10, &mut bytes[..10]),
        Err(VocabFileError::StorageTooSmall)
    );
    assert_eq!(file::write(&vocab, 10, &mut bytes), Ok(bytes.len()));

    let mut back = std::vec![Node::EMPTY; nodes.len()];
    let (read, header) = file::read(&bytes, &mut back).unwrap();
    assert_eq!(header.documents, 10);
    assert_eq!((read.branching(), read.depth()), (4, 3));
    assert_eq!(read.nodes(), &nodes[..]);
    for d in &data {
        assert_eq!(read.word(d), vocab.word(d));
    }

    let mut small = std::vec![Node::EMPTY; nodes.len() - 1];
    assert_eq!(
        file::read(&bytes, &mut small).unwrap_err(),
        VocabFileError::StorageTooSmall
    );
    // Every truncation, a byte more, and every single flipped byte are refused.
    for len in 0..bytes.len() {
        assert!(
            file::read(&bytes[..len], &mut back).is_err(),
            "length {len}"
        );
    }
    let mut longer = bytes.clone();
    longer.push(0);
    assert!(matches!(
        file::read(&longer, &mut back),
        Err(VocabFileError::WrongLength { .. })
    ));
    for i in 0..bytes.len() {
        let mut bad = bytes.clone();
        bad[i] ^= 0x10;
        assert!(file::read(&bad, &mut back).is_err(), "byte {i}");
    }
    let mut bad = bytes.clone();
    bad[0] = b'X';
    assert_eq!(
        file::read(&bad, &mut back).unwrap_err(),
        VocabFileError::BadMagic
    );
    let mut bad = bytes.clone();
    bad[8] = 2;
    assert_eq!(
        file::read(&bad, &mut back).unwrap_err(),
        VocabFileError::UnsupportedVersion(2)
    );
    let mut bad = bytes.clone();
    bad[10] = 200;
    assert_eq!(
        file::read(&bad, &mut back).unwrap_err(),
        VocabFileError::BadShape
    );
    let mut bad = bytes.clone();
    let n = bad.len();
    bad[n - 5] ^= 1;
    assert_eq!(
        file::read(&bad, &mut back).unwrap_err(),
        VocabFileError::BadCrc
    );
    // A well-formed file whose weight is negative, re-sealed with a valid CRC.
    let mut bad = bytes.clone();
    let at = file::HEADER_LEN + 36;
    bad[at..at + 4].copy_from_slice(&(-1.0f32).to_bits().to_le_bytes());
    let crc = crc32fast::hash(&bad[..n - 4]);
    bad[n - 4..].copy_from_slice(&crc.to_le_bytes());
    assert_eq!(
        file::read(&bad, &mut back).unwrap_err(),
        VocabFileError::BadValue
    );
    // Weights past ln(2^32), re-sealed: huge finite ones once summed a bag to infinity and
    // its weights to NaN (fuzz/regressions/vocab/huge-weights-nan-bag.cloivocab).
    for w in [f32::MAX, f32::NAN, f32::INFINITY, file::MAX_WEIGHT * 1.01] {
        let mut bad = bytes.clone();
        let leaf = nodes.len() - 1;
        let at = file::HEADER_LEN + leaf * file::NODE_LEN + 36;
        bad[at..at + 4].copy_from_slice(&w.to_bits().to_le_bytes());
        let crc = crc32fast::hash(&bad[..n - 4]);
        bad[n - 4..].copy_from_slice(&crc.to_le_bytes());
        assert_eq!(
            file::read(&bad, &mut back).unwrap_err(),
            VocabFileError::BadValue,
            "weight {w}"
        );
    }
    // The largest trained weight, ln(2^32) for one image in 2^32, is read.
    assert!(libm::logf(u32::MAX as f32) <= file::MAX_WEIGHT);
    // A tree whose first-level slots are all absent, re-sealed: a dead end.
    let mut bad = bytes.clone();
    for s in 0..4 {
        let at = file::HEADER_LEN + s * file::NODE_LEN + 32;
        bad[at..at + 4].copy_from_slice(&0u32.to_le_bytes());
    }
    let crc = crc32fast::hash(&bad[..n - 4]);
    bad[n - 4..].copy_from_slice(&crc.to_le_bytes());
    assert_eq!(
        file::read(&bad, &mut back).unwrap_err(),
        VocabFileError::BadValue
    );
}
