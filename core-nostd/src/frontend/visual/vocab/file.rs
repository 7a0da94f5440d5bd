//! The vocabulary file: what `cloi vocab train` writes and a robot loads, so a trained
//! vocabulary travels as bytes and is checked before any of it is used.
//!
//! Layout, little-endian:
//!
//! | bytes | field |
//! |---|---|
//! | 8 | magic `CLOIVOCB` |
//! | 2 | version (1) |
//! | 1 | branching (2 to 16) |
//! | 1 | depth (1 to 6) |
//! | 4 | slot count: must equal the count of a complete tree of that shape |
//! | 2 | descriptor bits (256) |
//! | 2 | reserved (0) |
//! | 4 | training images (the `N` of the weights) |
//! | 40 per slot | centroid (8 words of 32 bits), cluster size (u32), weight (f32) |
//! | 4 | CRC-32 (IEEE) of every byte before it |
//!
//! Reading checks the length against the header before anything else, then the CRC, then
//! every value (weights from 0 to [`MAX_WEIGHT`], and a tree in which the root and every present
//! inner slot have a present child, so every descriptor gets a word). No input panics.

use super::super::brief::{Descriptor, BITS};
use super::tree::{level_len, level_start, node_count, Node, Vocabulary};

/// The first bytes of a vocabulary file.
pub const MAGIC: [u8; 8] = *b"CLOIVOCB";
/// The format version written.
pub const VERSION: u16 = 1;
/// Bytes before the slots.
pub const HEADER_LEN: usize = 24;
/// Bytes per slot.
pub const NODE_LEN: usize = 40;
/// Bytes of the trailing CRC.
pub const CRC_LEN: usize = 4;
/// Largest weight a file may hold: a weight is an inverse document frequency `ln(N / n_w)`
/// with at most `N = 2^32` training images (`ln 2^32` is 22.18), and a bound keeps a bag's sum
/// of weights finite (huge finite weights overflow it to infinity, and the bag to NaN).
pub const MAX_WEIGHT: f32 = 22.2;

/// The size of the file of a vocabulary of `nodes` slots.
pub const fn file_len(nodes: usize) -> usize {
    HEADER_LEN + nodes * NODE_LEN + CRC_LEN
}

/// Why a vocabulary file was not written or not read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum VocabFileError {
    /// Shorter than a header.
    Truncated,
    /// Not a vocabulary file.
    BadMagic,
    /// A version this build does not read.
    UnsupportedVersion(u16),
    /// Branching, depth, slot count or descriptor size outside what is supported, or a
    /// reserved field not 0.
    BadShape,
    /// The length differs from the one the header implies.
    WrongLength {
        /// Bytes the header implies.
        expected: usize,
        /// Bytes given.
        actual: usize,
    },
    /// The CRC does not match: the file is damaged.
    BadCrc,
    /// A weight is not finite, negative or over [`MAX_WEIGHT`], or the tree has a dead end.
    BadValue,
    /// The caller's slots (when reading) or bytes (when writing) are too few.
    StorageTooSmall,
}

/// What a file's header says.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct VocabHeader {
    /// Children per slot.
    pub branching: usize,
    /// Levels below the root.
    pub depth: usize,
    /// Slots.
    pub nodes: usize,
    /// Training images.
    pub documents: u32,
}

/// Writes `vocab` (trained on `documents` images) to the start of `out`; returns the bytes
/// written ([`file_len`] of its slot count).
///
/// # Errors
/// [`VocabFileError::StorageTooSmall`] when `out` is too short.
pub fn write(
    vocab: &Vocabulary<'_>,
    documents: u32,
    out: &mut [u8],
) -> Result<usize, VocabFileError> {
    let nodes = vocab.nodes();
    let len = file_len(nodes.len());
    let out = out.get_mut(..len).ok_or(VocabFileError::StorageTooSmall)?;
    let mut at = 0usize;
    let mut put = |bytes: &[u8]| {
        if let Some(dst) = out.get_mut(at..at + bytes.len()) {
            dst.copy_from_slice(bytes);
        }
        at += bytes.len();
    };
    put(&MAGIC);
    put(&VERSION.to_le_bytes());
    put(&[vocab.branching() as u8, vocab.depth() as u8]);
    put(&(nodes.len() as u32).to_le_bytes());
    put(&(BITS as u16).to_le_bytes());
    put(&0u16.to_le_bytes());
    put(&documents.to_le_bytes());
    for n in nodes {
        for w in n.centroid.0 {
            put(&w.to_le_bytes());
        }
        put(&n.size.to_le_bytes());
        put(&n.weight.to_bits().to_le_bytes());
    }
    let crc = crc32fast::hash(out.get(..len - CRC_LEN).unwrap_or(&[]));
    if let Some(dst) = out.get_mut(len - CRC_LEN..) {
        dst.copy_from_slice(&crc.to_le_bytes());
    }
    Ok(len)
}

/// A little-endian `u32` at `at`.
fn u32_at(bytes: &[u8], at: usize) -> Option<u32> {
    let b = bytes.get(at..at.checked_add(4)?)?;
    Some(u32::from_le_bytes([
        *b.first()?,
        *b.get(1)?,
        *b.get(2)?,
        *b.get(3)?,
    ]))
}

/// A little-endian `u16` at `at`.
fn u16_at(bytes: &[u8], at: usize) -> Option<u16> {
    let b = bytes.get(at..at.checked_add(2)?)?;
    Some(u16::from_le_bytes([*b.first()?, *b.get(1)?]))
}

/// The header of `bytes`, checked against the length of `bytes` and against the CRC.
///
/// # Errors
/// Any of [`VocabFileError`] but `BadValue` and `StorageTooSmall`.
pub fn read_header(bytes: &[u8]) -> Result<VocabHeader, VocabFileError> {
    let head = bytes.get(..HEADER_LEN).ok_or(VocabFileError::Truncated)?;
    if head.get(..8) != Some(&MAGIC[..]) {
        return Err(VocabFileError::BadMagic);
    }
    let field16 = |at| u16_at(head, at).ok_or(VocabFileError::Truncated);
    let field32 = |at| u32_at(head, at).ok_or(VocabFileError::Truncated);
    let version = field16(8)?;
    if version != VERSION {
        return Err(VocabFileError::UnsupportedVersion(version));
    }
    let branching = usize::from(*head.get(10).ok_or(VocabFileError::Truncated)?);
    let depth = usize::from(*head.get(11).ok_or(VocabFileError::Truncated)?);
    let claimed = field32(12)? as usize;
    let expected_nodes = node_count(branching, depth).ok_or(VocabFileError::BadShape)?;
    if claimed != expected_nodes || usize::from(field16(16)?) != BITS || field16(18)? != 0 {
        return Err(VocabFileError::BadShape);
    }
    let expected = file_len(expected_nodes);
    if bytes.len() != expected {
        return Err(VocabFileError::WrongLength {
            expected,
            actual: bytes.len(),
        });
    }
    let body = bytes
        .get(..expected - CRC_LEN)
        .ok_or(VocabFileError::Truncated)?;
    let stored = u32_at(bytes, expected - CRC_LEN).ok_or(VocabFileError::Truncated)?;
    if crc32fast::hash(body) != stored {
        return Err(VocabFileError::BadCrc);
    }
    Ok(VocabHeader {
        branching,
        depth,
        nodes: expected_nodes,
        documents: field32(20)?,
    })
}

/// Reads a vocabulary file into `nodes` (at least the header's slot count) and returns the
/// vocabulary over them with the header.
///
/// # Errors
/// Any of [`VocabFileError`]; `nodes` may then hold part of the file.
pub fn read<'n>(
    bytes: &[u8],
    nodes: &'n mut [Node],
) -> Result<(Vocabulary<'n>, VocabHeader), VocabFileError> {
    let header = read_header(bytes)?;
    let slots = nodes
        .get_mut(..header.nodes)
        .ok_or(VocabFileError::StorageTooSmall)?;
    let records = bytes
        .get(HEADER_LEN..HEADER_LEN + header.nodes * NODE_LEN)
        .ok_or(VocabFileError::Truncated)?;
    for (slot, rec) in slots.iter_mut().zip(records.chunks_exact(NODE_LEN)) {
        let mut centroid = Descriptor::default();
        for (i, w) in centroid.0.iter_mut().enumerate() {
            *w = u32_at(rec, 4 * i).ok_or(VocabFileError::Truncated)?;
        }
        let size = u32_at(rec, 32).ok_or(VocabFileError::Truncated)?;
        let weight = f32::from_bits(u32_at(rec, 36).ok_or(VocabFileError::Truncated)?);
        if !(0.0..=MAX_WEIGHT).contains(&weight) {
            return Err(VocabFileError::BadValue);
        }
        *slot = Node {
            centroid,
            size,
            weight,
        };
    }
    check_tree(header.branching, header.depth, slots)?;
    let vocab = Vocabulary::new(header.branching, header.depth, nodes)
        .map_err(|_| VocabFileError::BadShape)?;
    Ok((vocab, header))
}

/// Whether the root and every present inner slot have a present child.
fn check_tree(branching: usize, depth: usize, nodes: &[Node]) -> Result<(), VocabFileError> {
    let has_child = |level: usize, slot: usize| {
        let start = level_start(branching, level + 1) + slot * branching;
        nodes
            .get(start..start + branching)
            .is_some_and(|c| c.iter().any(Node::is_present))
    };
    if !has_child(0, 0) {
        return Err(VocabFileError::BadValue);
    }
    for level in 1..depth {
        let start = level_start(branching, level);
        let len = level_len(branching, level).ok_or(VocabFileError::BadShape)?;
        let slots = nodes
            .get(start..start + len)
            .ok_or(VocabFileError::Truncated)?;
        for (j, n) in slots.iter().enumerate() {
            if n.is_present() && !has_child(level, j) {
                return Err(VocabFileError::BadValue);
            }
        }
    }
    Ok(())
}
