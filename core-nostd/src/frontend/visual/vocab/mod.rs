//! Place recognition by a bag of binary words (paper section III-B, visual loop closure): a
//! frame's rotated BRIEF descriptors become a sparse weighted histogram of visual words, and
//! a revisited place is an earlier keyframe whose histogram is close to the current one.
//!
//! One job per file:
//! * [`tree`]: the vocabulary, a tree of Hamming centroids in caller-lent slots, and the
//!   descent that gives a descriptor its word.
//! * [`train`](mod@train): hierarchical k-majority clustering with deterministic seeding, and the
//!   inverse document frequency of each word, over caller-lent scratch.
//! * [`bag`]: a frame's L1-normalised TF-IDF bag in fixed storage, and the similarity of two.
//! * [`database`]: keyframe bags in caller-lent storage and the query for loop candidates,
//!   scored relative to the query's recent neighbours.
//! * [`file`](mod@file): the checked binary file a trained vocabulary is saved to and loaded from.
//!
//! A tree rather than a flat list of words: finding a word costs `branching * depth` Hamming
//! distances (30 for the default 10 x 3) instead of one per word (1000), which is what makes
//! a bag per keyframe affordable on the Cortex-A9. Nothing allocates, recurses or panics.

pub mod bag;
pub mod database;
pub mod file;
pub mod train;
pub mod tree;

pub use bag::{Bag, BagStats, WordWeight, BAG_CAPACITY};
pub use database::{Candidate, Database, DatabaseFull, QueryConfig, QueryResult};
pub use file::{VocabFileError, VocabHeader};
pub use train::TrainStats;
pub use train::{counter_len, document_counter_len, set_weights, train, TrainConfig, TrainError};
pub use tree::{node_count, Node, ShapeError, Vocabulary, MAX_BRANCHING, MAX_DEPTH};

#[cfg(test)]
mod tests;
