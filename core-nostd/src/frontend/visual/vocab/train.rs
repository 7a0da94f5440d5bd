//! Training a vocabulary: hierarchical k-majority clustering of binary descriptors under the
//! Hamming distance, then the inverse document frequency of each word.
//!
//! The tree is built level by level without recursion. The training descriptors are reordered
//! in place so that every cluster's descriptors are contiguous, in slot order; a slot's range
//! is then the running sum of the sizes of the slots before it on its level, so no per-slot
//! ranges are stored. Each cluster is split by k-majority:
//! * **seeding**: the first centre is a descriptor drawn by a SplitMix64 generator seeded from
//!   the configuration's seed and the cluster's position; each next one is drawn with
//!   probability proportional to the squared distance to the nearest centre so far (the
//!   k-means++ rule), so equal inputs give equal trees on every target;
//! * **iterations**: assign each descriptor to its nearest centre (the lower index on a tie),
//!   count the set bits of each cluster, and set a centre's bit when more than half of its
//!   members have it; stop when no centre changes or after [`TrainConfig::iterations`];
//! * a cluster with at most `branching` descriptors gives one child per descriptor, and an
//!   empty child stays absent.
//!
//! The caller lends the bit counters (`branching * 256` words, [`counter_len`]), so firmware
//! could train with the storage it has; nothing here allocates.

use super::super::brief::{Descriptor, BITS};
use super::tree::{level_len, level_start, node_count, Node, Vocabulary, MAX_BRANCHING};

/// Training parameters.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct TrainConfig {
    /// Children per slot (2 to 16).
    pub branching: usize,
    /// Levels below the root (1 to 6); the vocabulary has up to `branching^depth` words.
    pub depth: usize,
    /// Most assignment rounds per cluster.
    pub iterations: usize,
    /// Seed of the centre draws.
    pub seed: u64,
}

impl Default for TrainConfig {
    /// Branching 10 and depth 3: a thousand words, about 20 training descriptors per word for
    /// a hundred images of 200 features; deeper trees left most words with a handful.
    fn default() -> Self {
        TrainConfig {
            branching: 10,
            depth: 3,
            iterations: 10,
            seed: 0x434C_4F69_564F_4342, // "CLOiVOCB"
        }
    }
}

/// What a training did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct TrainStats {
    /// Training descriptors.
    pub descriptors: usize,
    /// Clusters split.
    pub clusters: usize,
    /// Clusters that stopped at the iteration cap rather than at a fixed point.
    pub unconverged: usize,
    /// Present leaves: the words a descriptor can get.
    pub words: usize,
}

/// Why a training or weighting failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum TrainError {
    /// Branching or depth outside the supported range.
    BadShape,
    /// The node slice is shorter than the tree.
    StorageTooSmall,
    /// The counters are shorter than [`counter_len`] (or [`document_counter_len`]).
    ScratchTooSmall,
    /// No training descriptor, or no training image.
    Empty,
}

/// Bit counters [`train`] needs for `branching`.
pub const fn counter_len(branching: usize) -> usize {
    branching * BITS
}

/// Counters [`set_weights`] needs for a vocabulary of `words` words.
pub const fn document_counter_len(words: usize) -> usize {
    2 * words
}

/// A SplitMix64 step.
fn splitmix(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The index and distance of the centre nearest to `d` (the first on a tie).
fn nearest_centre(centres: &[Descriptor], d: &Descriptor) -> (usize, u32) {
    let mut best = (0, u32::MAX);
    for (i, c) in centres.iter().enumerate() {
        let dist = c.hamming(d);
        if dist < best.1 {
            best = (i, dist);
        }
    }
    best
}

/// Builds the tree of `cfg` into `nodes` from `descriptors` (reordered in place), with
/// `counters` (at least [`counter_len`]) as scratch. Leaf weights are left at 0: call
/// [`set_weights`] next.
///
/// # Errors
/// An unsupported shape, too short storage or scratch, or no descriptor.
pub fn train(
    cfg: &TrainConfig,
    descriptors: &mut [Descriptor],
    counters: &mut [u32],
    nodes: &mut [Node],
) -> Result<TrainStats, TrainError> {
    let (k, depth) = (cfg.branching, cfg.depth);
    let n = node_count(k, depth).ok_or(TrainError::BadShape)?;
    let nodes = nodes.get_mut(..n).ok_or(TrainError::StorageTooSmall)?;
    let counters = counters
        .get_mut(..counter_len(k))
        .ok_or(TrainError::ScratchTooSmall)?;
    if descriptors.is_empty() {
        return Err(TrainError::Empty);
    }
    let total = u32::try_from(descriptors.len()).map_err(|_| TrainError::StorageTooSmall)?;
    nodes.fill(Node::EMPTY);
    let mut stats = TrainStats {
        descriptors: descriptors.len(),
        ..TrainStats::default()
    };
    for level in 1..=depth {
        let parents = level_len(k, level - 1).ok_or(TrainError::BadShape)?;
        let parent_start = level_start(k, level - 1);
        let child_start = level_start(k, level);
        let mut offset = 0usize;
        for p in 0..parents {
            let size = if level == 1 {
                total
            } else {
                nodes.get(parent_start + p).map_or(0, |n| n.size)
            };
            if size == 0 {
                continue;
            }
            let end = offset + size as usize;
            let (Some(members), Some(children)) = (
                descriptors.get_mut(offset..end),
                nodes.get_mut(child_start + p * k..child_start + (p + 1) * k),
            ) else {
                return Err(TrainError::StorageTooSmall);
            };
            let mut state = cfg.seed ^ ((level as u64) << 48) ^ (p as u64);
            let converged = split(members, children, counters, cfg.iterations, &mut state);
            stats.clusters += 1;
            stats.unconverged += usize::from(!converged);
            offset = end;
        }
    }
    let leaves = nodes.get(level_start(k, depth)..).unwrap_or(&[]);
    stats.words = leaves.iter().filter(|n| n.is_present()).count();
    Ok(stats)
}

/// Splits `members` into `children` (their centroids and sizes) and reorders `members` by
/// child. Returns whether the centres reached a fixed point.
fn split(
    members: &mut [Descriptor],
    children: &mut [Node],
    counters: &mut [u32],
    iterations: usize,
    state: &mut u64,
) -> bool {
    let k = children.len().min(MAX_BRANCHING);
    if members.len() <= k {
        for (d, c) in members.iter().zip(children.iter_mut()) {
            *c = Node {
                centroid: *d,
                size: 1,
                weight: 0.0,
            };
        }
        return true;
    }
    let mut centres = [Descriptor::default(); MAX_BRANCHING];
    let used = seed_centres(members, centres.get_mut(..k).unwrap_or(&mut []), state);
    let centres = centres.get_mut(..used).unwrap_or(&mut []);
    let mut converged = false;
    for _ in 0..iterations {
        if !update_centres(members, centres, counters) {
            converged = true;
            break;
        }
    }
    // Reorder by nearest centre, one pass per centre over what is left.
    let centres: &[Descriptor] = centres;
    let mut placed = 0usize;
    for (c, child) in children.iter_mut().enumerate().take(centres.len()) {
        let Some(&centre) = centres.get(c) else {
            break;
        };
        let rest = members.get_mut(placed..).unwrap_or(&mut []);
        let mut front = 0usize;
        for i in 0..rest.len() {
            let Some(d) = rest.get(i) else { break };
            if nearest_centre(centres, d).0 == c {
                rest.swap(front, i);
                front += 1;
            }
        }
        placed += front;
        if front > 0 {
            *child = Node {
                centroid: centre,
                size: u32::try_from(front).unwrap_or(u32::MAX),
                weight: 0.0,
            };
        }
    }
    converged
}

/// Draws up to `centres.len()` centres from `members` (k-means++ rule on squared Hamming
/// distances). Returns how many were drawn: fewer when the members hold fewer distinct
/// descriptors.
fn seed_centres(members: &[Descriptor], centres: &mut [Descriptor], state: &mut u64) -> usize {
    let Some(first) = members.get((splitmix(state) % members.len().max(1) as u64) as usize) else {
        return 0;
    };
    let Some(slot) = centres.first_mut() else {
        return 0;
    };
    *slot = *first;
    let mut used = 1;
    while used < centres.len() {
        let chosen = centres.get(..used).unwrap_or(&[]);
        let weight = |d: &Descriptor| u64::from(nearest_centre(chosen, d).1).pow(2);
        let total: u64 = members.iter().map(weight).sum();
        if total == 0 {
            break;
        }
        let mut r = splitmix(state) % total;
        let mut pick = None;
        for d in members {
            let w = weight(d);
            if r < w {
                pick = Some(*d);
                break;
            }
            r -= w;
        }
        let (Some(d), Some(slot)) = (pick, centres.get_mut(used)) else {
            break;
        };
        *slot = d;
        used += 1;
    }
    used
}

/// One k-majority round: assigns every member to its nearest centre and moves each centre to
/// the bitwise majority of its members (a centre without members stays). Returns whether a
/// centre changed.
fn update_centres(
    members: &[Descriptor],
    centres: &mut [Descriptor],
    counters: &mut [u32],
) -> bool {
    counters.fill(0);
    let mut sizes = [0u32; MAX_BRANCHING];
    for d in members {
        let (c, _) = nearest_centre(centres, d);
        if let Some(s) = sizes.get_mut(c) {
            *s += 1;
        }
        let Some(bits) = counters.get_mut(c * BITS..(c + 1) * BITS) else {
            continue;
        };
        for (w, word) in d.0.iter().enumerate() {
            let mut rest = *word;
            while rest != 0 {
                let b = rest.trailing_zeros() as usize;
                if let Some(n) = bits.get_mut(w * 32 + b) {
                    *n += 1;
                }
                rest &= rest - 1;
            }
        }
    }
    let mut changed = false;
    for (c, centre) in centres.iter_mut().enumerate() {
        let size = sizes.get(c).copied().unwrap_or(0);
        let Some(bits) = counters.get(c * BITS..(c + 1) * BITS) else {
            continue;
        };
        if size == 0 {
            continue;
        }
        let mut next = Descriptor::default();
        for (i, &n) in bits.iter().enumerate() {
            if 2 * u64::from(n) > u64::from(size) {
                if let Some(w) = next.0.get_mut(i / 32) {
                    *w |= 1 << (i % 32);
                }
            }
        }
        changed |= next != *centre;
        *centre = next;
    }
    changed
}

/// Sets each leaf's weight to its inverse document frequency over `documents` (the
/// descriptors of each training image), with `counters` (at least [`document_counter_len`] of
/// the vocabulary's word count) as scratch. A present word no document holds gets the largest
/// weight, `ln(N)`. Returns the number of documents.
///
/// # Errors
/// An unsupported shape, too short storage or scratch, or no document.
pub fn set_weights<'d>(
    branching: usize,
    depth: usize,
    nodes: &mut [Node],
    documents: impl IntoIterator<Item = &'d [Descriptor]>,
    counters: &mut [u32],
) -> Result<usize, TrainError> {
    let vocab = Vocabulary::new(branching, depth, nodes).map_err(|e| match e {
        super::tree::ShapeError::BadShape => TrainError::BadShape,
        super::tree::ShapeError::StorageTooSmall => TrainError::StorageTooSmall,
    })?;
    let words = vocab.word_count();
    let counters = counters
        .get_mut(..document_counter_len(words))
        .ok_or(TrainError::ScratchTooSmall)?;
    counters.fill(0);
    let (seen, last) = counters.split_at_mut(words);
    let mut docs = 0u32;
    for doc in documents {
        docs = docs.saturating_add(1);
        for d in doc {
            let Some(w) = vocab.word(d) else { continue };
            let (Some(s), Some(l)) = (seen.get_mut(w as usize), last.get_mut(w as usize)) else {
                continue;
            };
            // `last` holds the 1-based number of the last document that had the word.
            if *l != docs {
                *l = docs;
                *s += 1;
            }
        }
    }
    if docs == 0 {
        return Err(TrainError::Empty);
    }
    let start = level_start(branching, depth);
    let leaves = nodes.get_mut(start..start + words).unwrap_or(&mut []);
    for (leaf, &n) in leaves.iter_mut().zip(seen.iter()) {
        leaf.weight = if leaf.is_present() {
            libm::logf(docs as f32 / n.max(1) as f32)
        } else {
            0.0
        };
    }
    Ok(docs as usize)
}
