//! A frame as a bag of words: the sparse TF-IDF vector of its descriptors' words, L1
//! normalised, and the similarity of two bags.
//!
//! Each descriptor adds its word's weight (the word's inverse document frequency) to the
//! word's entry, so an entry is `count * idf`; dividing by the sum of the entries makes the
//! term frequency's denominator and the frame's feature count drop out. Words every training
//! image holds weigh 0 and are left out, as they tell nothing about the place.
//!
//! The similarity of two L1-normalised bags `a` and `b` is `1 - |a - b|_1 / 2`, in `[0, 1]`,
//! 1 for equal bags and 0 for bags without a common word. For non-negative entries
//! `|x - y| = x + y - 2 min(x, y)`, so it equals the sum over common words of the smaller
//! entry, which one merge of the two sorted entry lists gives.

use super::super::brief::Descriptor;
use super::tree::Vocabulary;

/// Most distinct words a bag holds: one per feature of a frame
/// ([`MAX_FEATURES`](super::super::frame::MAX_FEATURES)).
pub const BAG_CAPACITY: usize = 256;

/// One entry of a bag.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct WordWeight {
    /// The word.
    pub word: u32,
    /// Its normalised TF-IDF weight.
    pub weight: f32,
}

/// What [`Bag::transform`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct BagStats {
    /// Descriptors that added weight.
    pub used: usize,
    /// Descriptors whose word weighs 0 (or that a malformed tree could not place).
    pub uninformative: usize,
    /// Descriptors dropped because the bag was full.
    pub dropped: usize,
}

/// A sparse bag of words in fixed storage, sorted by word.
#[derive(Clone, Debug)]
pub struct Bag {
    entries: [WordWeight; BAG_CAPACITY],
    len: usize,
}

impl Default for Bag {
    fn default() -> Self {
        Self::new()
    }
}

impl Bag {
    /// An empty bag.
    pub const fn new() -> Self {
        Bag {
            entries: [WordWeight {
                word: 0,
                weight: 0.0,
            }; BAG_CAPACITY],
            len: 0,
        }
    }

    /// The entries, by increasing word.
    pub fn entries(&self) -> &[WordWeight] {
        self.entries.get(..self.len).unwrap_or(&[])
    }

    /// Distinct words held.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether no word is held.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Replaces the bag with the L1-normalised TF-IDF bag of `descriptors` under `vocab`.
    pub fn transform(&mut self, vocab: &Vocabulary<'_>, descriptors: &[Descriptor]) -> BagStats {
        self.len = 0;
        let mut stats = BagStats::default();
        for d in descriptors {
            let Some(word) = vocab.word(d) else {
                stats.uninformative += 1;
                continue;
            };
            let weight = vocab.weight(word);
            if !(weight > 0.0 && weight.is_finite()) {
                stats.uninformative += 1;
                continue;
            }
            if self.add(word, weight) {
                stats.used += 1;
            } else {
                stats.dropped += 1;
            }
        }
        let total: f32 = self.entries().iter().map(|e| e.weight).sum();
        if total > 0.0 {
            for e in self.entries.iter_mut().take(self.len) {
                e.weight /= total;
            }
        }
        stats
    }

    /// Adds `weight` to `word`'s entry, inserting it in order; false when the bag is full.
    fn add(&mut self, word: u32, weight: f32) -> bool {
        let held = self.entries.get(..self.len).unwrap_or(&[]);
        match held.binary_search_by_key(&word, |e| e.word) {
            Ok(i) => {
                if let Some(e) = self.entries.get_mut(i) {
                    e.weight += weight;
                }
                true
            }
            Err(i) => {
                if self.len >= BAG_CAPACITY {
                    return false;
                }
                self.entries.copy_within(i..self.len, i + 1);
                if let Some(e) = self.entries.get_mut(i) {
                    *e = WordWeight { word, weight };
                }
                self.len += 1;
                true
            }
        }
    }

    /// The similarity of two normalised bags, `1 - |a - b|_1 / 2`: 1 for equal bags, 0 when
    /// no word is shared.
    pub fn score(&self, other: &Bag) -> f32 {
        let (a, b) = (self.entries(), other.entries());
        let (mut i, mut j) = (0, 0);
        let mut sum = 0.0f32;
        while let (Some(x), Some(y)) = (a.get(i), b.get(j)) {
            match x.word.cmp(&y.word) {
                core::cmp::Ordering::Less => i += 1,
                core::cmp::Ordering::Greater => j += 1,
                core::cmp::Ordering::Equal => {
                    sum += x.weight.min(y.weight);
                    i += 1;
                    j += 1;
                }
            }
        }
        sum.clamp(0.0, 1.0)
    }
}
