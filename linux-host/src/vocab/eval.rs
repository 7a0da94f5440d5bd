//! Place recognition measured against a ground-truth loop matrix: for every image, the best
//! earlier image outside its recent neighbours, accepted when its normalised score passes a
//! threshold; precision and recall over all thresholds.
//!
//! The matrix is the 8-bit palette BMP of the RTAB-Map samples (`samples_GT.bmp`): the pixel
//! in row `i`, column `j` (from the top left) is white when image `i` shows the place of the
//! earlier image `j`.

use anyhow::{bail, ensure, Result};
use cloi_core::frontend::visual::vocab::{Bag, Candidate, Database, QueryConfig};

/// A square loop matrix: `get(i, j)` when image `i` revisits image `j`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LoopTruth {
    size: usize,
    cells: Vec<bool>,
}

impl LoopTruth {
    /// Images per side.
    pub fn size(&self) -> usize {
        self.size
    }

    /// Whether image `i` revisits image `j` (0-based).
    pub fn get(&self, i: usize, j: usize) -> bool {
        i < self.size && j < self.size && self.cells.get(i * self.size + j) == Some(&true)
    }

    /// Pairs marked.
    pub fn pairs(&self) -> usize {
        self.cells.iter().filter(|&&c| c).count()
    }

    /// Reads an uncompressed 8-bit palette BMP (rows bottom-up or top-down); a pixel counts
    /// when its palette colour is brighter than mid-grey. Every offset and length is checked.
    ///
    /// # Errors
    /// Anything but a square, uncompressed, 8-bit BMP that fits its bytes.
    pub fn from_bmp(bytes: &[u8]) -> Result<Self> {
        let u32_at = |at: usize| -> Result<u32> {
            match bytes.get(at..at + 4) {
                Some(b) => Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                None => bail!("BMP truncated at byte {at}"),
            }
        };
        let u16_at = |at: usize| -> Result<u16> {
            match bytes.get(at..at + 2) {
                Some(b) => Ok(u16::from_le_bytes([b[0], b[1]])),
                None => bail!("BMP truncated at byte {at}"),
            }
        };
        ensure!(bytes.get(..2) == Some(b"BM"), "not a BMP file");
        let data_at = u32_at(10)? as usize;
        let info_len = u32_at(14)? as usize;
        let width = u32_at(18)? as i32;
        let height = u32_at(22)? as i32;
        let bits = u16_at(28)?;
        let compression = u32_at(30)?;
        ensure!(
            bits == 8 && compression == 0,
            "only uncompressed 8-bit BMP is read"
        );
        let colours = match u32_at(46)? {
            0 => 256,
            n => n as usize,
        };
        ensure!(colours <= 256, "BMP palette of {colours} colours");
        let (w, h) = (
            width.unsigned_abs() as usize,
            height.unsigned_abs() as usize,
        );
        ensure!(
            width > 0 && w == h && w <= 10_000,
            "a square loop matrix was expected, not {width} x {height}"
        );
        let palette_at = info_len.saturating_add(14);
        let palette = bytes
            .get(palette_at..palette_at.saturating_add(4 * colours))
            .ok_or_else(|| anyhow::anyhow!("BMP palette truncated"))?;
        let stride = w.div_ceil(4) * 4;
        let pixels = bytes
            .get(data_at..data_at.saturating_add(stride * h))
            .ok_or_else(|| anyhow::anyhow!("BMP pixels truncated"))?;
        let mut cells = vec![false; w * w];
        for (stored, row) in pixels.chunks_exact(stride).enumerate() {
            // Positive height: bottom-up rows.
            let r = if height > 0 { h - 1 - stored } else { stored };
            for (c, &index) in row.iter().take(w).enumerate() {
                let bright = palette
                    .get(4 * usize::from(index)..4 * usize::from(index) + 3)
                    .is_some_and(|bgr| bgr.iter().map(|&v| u32::from(v)).sum::<u32>() > 3 * 128);
                cells[r * w + c] = bright;
            }
        }
        Ok(LoopTruth { size: w, cells })
    }
}

/// The best earlier match of one image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BestMatch {
    /// The query image (0-based).
    pub query: usize,
    /// The best earlier image outside the recent ones.
    pub candidate: Candidate,
    /// Whether the ground truth marks the pair.
    pub correct: bool,
}

/// One point of the precision/recall curve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CurvePoint {
    /// Normalised score a match needs.
    pub threshold: f32,
    /// Matches accepted.
    pub accepted: usize,
    /// Accepted matches the ground truth marks.
    pub correct: usize,
    /// `correct / accepted` (1 when none is accepted).
    pub precision: f64,
    /// `correct / positives`.
    pub recall: f64,
}

/// The evaluation of a sequence.
#[derive(Debug, Clone)]
pub struct Evaluation {
    /// Each image's best match (images without an eligible earlier one are left out).
    pub matches: Vec<BestMatch>,
    /// Images that revisit an eligible earlier image: what recall counts against.
    pub positives: usize,
    /// The curve, by decreasing threshold (one point per distinct score).
    pub curve: Vec<CurvePoint>,
}

impl Evaluation {
    /// The largest recall at precision 1, with its threshold (`None` when the best-scored
    /// match is already wrong).
    pub fn recall_at_full_precision(&self) -> Option<CurvePoint> {
        self.curve
            .iter()
            .filter(|p| p.accepted > 0 && p.correct == p.accepted)
            .max_by(|a, b| a.recall.total_cmp(&b.recall))
            .copied()
    }
}

/// Queries every bag of `bags` (one per image, in order) against the earlier ones with
/// `recent` neighbours as the reference, and scores the best matches against `truth`.
///
/// # Errors
/// The matrix and the bags disagree on the image count.
pub fn evaluate(bags: &[Bag], truth: &LoopTruth, recent: usize) -> Result<Evaluation> {
    ensure!(
        bags.len() == truth.size(),
        "{} images but a {1}x{1} ground truth",
        bags.len(),
        truth.size()
    );
    let mut storage = vec![Bag::new(); bags.len()];
    let mut db = Database::new(&mut storage);
    let cfg = QueryConfig {
        recent,
        min_normalised: 0.0,
        ..QueryConfig::default()
    };
    let mut matches = Vec::new();
    let mut positives = 0;
    for (i, bag) in bags.iter().enumerate() {
        let eligible = i.saturating_sub(recent);
        if (0..eligible).any(|j| truth.get(i, j)) {
            positives += 1;
        }
        let mut out = [Candidate::default(); 1];
        if db.query(bag, &cfg, &mut out).candidates == 1 {
            matches.push(BestMatch {
                query: i,
                candidate: out[0],
                correct: truth.get(i, out[0].entry),
            });
        }
        db.add(bag)
            .map_err(|_| anyhow::anyhow!("database storage full"))?;
    }
    let mut sorted = matches.clone();
    sorted.sort_by(|a, b| b.candidate.normalised.total_cmp(&a.candidate.normalised));
    let mut curve = Vec::new();
    let (mut accepted, mut correct) = (0, 0);
    for (k, m) in sorted.iter().enumerate() {
        accepted += 1;
        correct += usize::from(m.correct);
        // One point per distinct score: ties are accepted together.
        if sorted
            .get(k + 1)
            .is_some_and(|n| n.candidate.normalised == m.candidate.normalised)
        {
            continue;
        }
        curve.push(CurvePoint {
            threshold: m.candidate.normalised,
            accepted,
            correct,
            precision: correct as f64 / accepted as f64,
            recall: if positives == 0 {
                0.0
            } else {
                correct as f64 / positives as f64
            },
        });
    }
    Ok(Evaluation {
        matches,
        positives,
        curve,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 4x4 8-bit BMP, bottom-up, grey palette, with `white` pixels (row, column from the
    /// top left).
    fn bmp(white: &[(usize, usize)]) -> Vec<u8> {
        let mut b = Vec::new();
        b.extend_from_slice(b"BM");
        b.extend_from_slice(&(54u32 + 1024 + 16).to_le_bytes());
        b.extend_from_slice(&[0; 4]);
        b.extend_from_slice(&(54u32 + 1024).to_le_bytes());
        b.extend_from_slice(&40u32.to_le_bytes());
        b.extend_from_slice(&4i32.to_le_bytes());
        b.extend_from_slice(&4i32.to_le_bytes());
        b.extend_from_slice(&1u16.to_le_bytes());
        b.extend_from_slice(&8u16.to_le_bytes());
        b.extend_from_slice(&[0; 24]);
        for v in 0..=255u8 {
            b.extend_from_slice(&[v, v, v, 0]);
        }
        for stored in 0..4 {
            let r = 3 - stored;
            for c in 0..4 {
                b.push(if white.contains(&(r, c)) { 255 } else { 0 });
            }
        }
        b
    }

    #[test]
    fn the_loop_matrix_is_read_top_down_and_damage_is_refused() {
        let bytes = bmp(&[(2, 0), (3, 1)]);
        let t = LoopTruth::from_bmp(&bytes).unwrap();
        assert_eq!(t.size(), 4);
        assert_eq!(t.pairs(), 2);
        assert!(t.get(2, 0) && t.get(3, 1) && !t.get(0, 2) && !t.get(9, 9));
        for len in 0..bytes.len() {
            assert!(LoopTruth::from_bmp(&bytes[..len]).is_err(), "{len}");
        }
    }
}
