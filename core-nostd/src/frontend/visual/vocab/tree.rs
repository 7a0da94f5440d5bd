//! The vocabulary tree: binary words as the leaves of a complete tree of Hamming centroids,
//! laid out level by level in one caller-lent slice of [`Node`]s.
//!
//! The root is implicit. Level `l` (1 to `depth`) holds `branching^l` slots, stored after the
//! slots of the levels above it; the children of slot `j` of level `l` are slots
//! `j * branching .. (j + 1) * branching` of level `l + 1`. A slot whose cluster received no
//! training descriptor is absent (`size == 0`) and is never descended into. A word is the slot
//! index of a leaf within the last level, so words are `0 .. branching^depth`.

use super::super::brief::Descriptor;

/// Largest branching factor a vocabulary may have (the training's bit counters are sized by
/// it, and a file claiming more is refused).
pub const MAX_BRANCHING: usize = 16;
/// Deepest tree a vocabulary may have.
pub const MAX_DEPTH: usize = 6;
/// Most slots a vocabulary may have (a file claiming more is refused before anything is read).
pub const MAX_NODES: usize = 1 << 20;

/// One slot of the tree.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Node {
    /// The bitwise majority of the training descriptors of this cluster.
    pub centroid: Descriptor,
    /// Training descriptors that fell in this cluster; 0 marks an absent slot.
    pub size: u32,
    /// For a leaf, the word's inverse document frequency `ln(N / n_w)` (`N` training images,
    /// `n_w` of them containing the word); 0 for inner slots.
    pub weight: f32,
}

impl Node {
    /// An absent slot.
    pub const EMPTY: Node = Node {
        centroid: Descriptor([0; 8]),
        size: 0,
        weight: 0.0,
    };

    /// Whether a training descriptor reached this slot.
    pub fn is_present(&self) -> bool {
        self.size > 0
    }
}

/// `branching^level`, or `None` past [`MAX_NODES`].
pub fn level_len(branching: usize, level: usize) -> Option<usize> {
    let mut n: usize = 1;
    for _ in 0..level {
        n = n.checked_mul(branching).filter(|&n| n <= MAX_NODES)?;
    }
    Some(n)
}

/// Slots of a tree of `branching` and `depth` (levels 1 to `depth`), or `None` when the shape
/// is outside `2..=MAX_BRANCHING`, `1..=MAX_DEPTH` or over [`MAX_NODES`].
pub fn node_count(branching: usize, depth: usize) -> Option<usize> {
    if !(2..=MAX_BRANCHING).contains(&branching) || !(1..=MAX_DEPTH).contains(&depth) {
        return None;
    }
    let mut total: usize = 0;
    for l in 1..=depth {
        total = total
            .checked_add(level_len(branching, l)?)
            .filter(|&t| t <= MAX_NODES)?;
    }
    Some(total)
}

/// Index of the first slot of `level` (1-based) in the node slice.
pub(crate) fn level_start(branching: usize, level: usize) -> usize {
    (1..level)
        .map(|l| level_len(branching, l).unwrap_or(0))
        .sum()
}

/// Why a vocabulary cannot be formed over some storage.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ShapeError {
    /// Branching or depth outside the supported range.
    BadShape,
    /// The node slice is shorter than the tree needs.
    StorageTooSmall,
}

/// A trained vocabulary over borrowed nodes.
#[derive(Clone, Copy, Debug)]
pub struct Vocabulary<'a> {
    branching: usize,
    depth: usize,
    nodes: &'a [Node],
}

impl<'a> Vocabulary<'a> {
    /// The vocabulary of `branching` and `depth` held by the first [`node_count`] slots of
    /// `nodes`.
    ///
    /// # Errors
    /// An unsupported shape, or `nodes` too short for it.
    pub fn new(branching: usize, depth: usize, nodes: &'a [Node]) -> Result<Self, ShapeError> {
        let n = node_count(branching, depth).ok_or(ShapeError::BadShape)?;
        let nodes = nodes.get(..n).ok_or(ShapeError::StorageTooSmall)?;
        Ok(Vocabulary {
            branching,
            depth,
            nodes,
        })
    }

    /// Children per slot.
    pub fn branching(&self) -> usize {
        self.branching
    }

    /// Levels below the root.
    pub fn depth(&self) -> usize {
        self.depth
    }

    /// Every slot, level by level.
    pub fn nodes(&self) -> &'a [Node] {
        self.nodes
    }

    /// Number of possible words (`branching^depth`).
    pub fn word_count(&self) -> usize {
        level_len(self.branching, self.depth).unwrap_or(0)
    }

    /// The leaf of word `w`.
    pub fn leaf(&self, w: u32) -> Option<&'a Node> {
        let start = level_start(self.branching, self.depth);
        self.nodes.get(start.checked_add(w as usize)?)
    }

    /// The weight of word `w` (0 for an unknown word).
    pub fn weight(&self, w: u32) -> f32 {
        self.leaf(w).map_or(0.0, |n| n.weight)
    }

    /// The word of `d`: from the root, the nearest present child (the lower index on a tie)
    /// at each level, `depth` Hamming comparisons per level. `None` when a present slot has no
    /// present child (a malformed tree).
    pub fn word(&self, d: &Descriptor) -> Option<u32> {
        let mut parent = 0usize;
        let mut start = 0usize;
        for level in 1..=self.depth {
            let first = parent.checked_mul(self.branching)?;
            let slots = self
                .nodes
                .get(start.checked_add(first)?..start.checked_add(first + self.branching)?)?;
            let (best, _) = nearest(slots, d)?;
            parent = first + best;
            start += level_len(self.branching, level)?;
        }
        u32::try_from(parent).ok()
    }
}

/// The index and distance of the present slot nearest to `d` (the first on a tie).
pub(crate) fn nearest(slots: &[Node], d: &Descriptor) -> Option<(usize, u32)> {
    let mut best: Option<(usize, u32)> = None;
    for (i, n) in slots.iter().enumerate() {
        if !n.is_present() {
            continue;
        }
        let dist = n.centroid.hamming(d);
        if best.is_none_or(|(_, b)| dist < b) {
            best = Some((i, dist));
        }
    }
    best
}
