//! What a run keeps per scan until its end, kept off the heap: a long run (a soak of a day, a
//! robot that maps for hours) must not grow the process with every scan.
//!
//! * [`ScanSpool`]: each accepted scan's record in an anonymous temporary file, read back once
//!   in order when the run writes its trajectories (a scan's final pose is known only after the
//!   last optimization).
//! * [`Latency`]: the wall time per scan as a histogram of fixed size, whose percentiles are
//!   exact to its bin width (1 %).

use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, SeekFrom, Write};

use anyhow::{Context, Result};
use cloi_core::geom::Se2;

/// One accepted scan: its time, reference keyframe, front-end motion since it, and outputs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanRecord {
    /// Stamp, ns.
    pub stamp: i64,
    /// Serial of the keyframe the scan hangs off.
    pub reference: u32,
    /// Front-end pose of that keyframe.
    pub reference_frontend: Se2,
    /// Front-end motion from the keyframe to the scan.
    pub rel: Se2,
    /// The real-time (GPE) pose.
    pub gpe: Se2,
    /// The front-end pose.
    pub frontend: Se2,
}

/// Bytes of one record in the spool.
const RECORD_BYTES: usize = 8 + 4 + 4 * 3 * 8;

impl ScanRecord {
    fn encode(&self) -> [u8; RECORD_BYTES] {
        let mut b = [0u8; RECORD_BYTES];
        b[..8].copy_from_slice(&self.stamp.to_le_bytes());
        b[8..12].copy_from_slice(&self.reference.to_le_bytes());
        let poses = [self.reference_frontend, self.rel, self.gpe, self.frontend];
        for (k, p) in poses.iter().enumerate() {
            for (j, v) in [p.x, p.y, p.theta].iter().enumerate() {
                let at = 12 + (3 * k + j) * 8;
                b[at..at + 8].copy_from_slice(&v.to_le_bytes());
            }
        }
        b
    }

    fn decode(b: &[u8; RECORD_BYTES]) -> Self {
        let f = |at: usize| {
            let mut v = [0u8; 8];
            v.copy_from_slice(&b[at..at + 8]);
            f64::from_le_bytes(v)
        };
        let pose = |k: usize| {
            let at = 12 + 3 * k * 8;
            Se2::new(f(at), f(at + 8), f(at + 16))
        };
        let mut stamp = [0u8; 8];
        stamp.copy_from_slice(&b[..8]);
        let mut reference = [0u8; 4];
        reference.copy_from_slice(&b[8..12]);
        ScanRecord {
            stamp: i64::from_le_bytes(stamp),
            reference: u32::from_le_bytes(reference),
            reference_frontend: pose(0),
            rel: pose(1),
            gpe: pose(2),
            frontend: pose(3),
        }
    }
}

/// The records of a run, in an anonymous temporary file (removed by the system however the
/// process ends).
#[derive(Debug)]
pub struct ScanSpool {
    file: BufWriter<File>,
    len: u64,
}

impl ScanSpool {
    /// An empty spool.
    ///
    /// # Errors
    /// No temporary file could be created.
    pub fn new() -> Result<Self> {
        let file = tempfile::tempfile().context("creating the scan spool (a temporary file)")?;
        Ok(ScanSpool {
            file: BufWriter::new(file),
            len: 0,
        })
    }

    /// Appends `r`.
    ///
    /// # Errors
    /// A write error (a full disk).
    pub fn push(&mut self, r: &ScanRecord) -> Result<()> {
        self.file
            .write_all(&r.encode())
            .context("writing the scan spool")?;
        self.len += 1;
        Ok(())
    }

    /// Records so far.
    pub fn len(&self) -> u64 {
        self.len
    }

    /// Whether no record was pushed.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The records in the order they were pushed.
    ///
    /// # Errors
    /// A write or seek error.
    pub fn into_records(self) -> Result<SpoolRecords> {
        let mut file = self
            .file
            .into_inner()
            .map_err(|e| e.into_error())
            .context("writing the scan spool")?;
        file.seek(SeekFrom::Start(0))
            .context("rewinding the scan spool")?;
        Ok(SpoolRecords {
            file: BufReader::new(file),
            left: self.len,
        })
    }
}

/// Iterator over a spool's records (see [`ScanSpool::into_records`]).
#[derive(Debug)]
pub struct SpoolRecords {
    file: BufReader<File>,
    left: u64,
}

impl Iterator for SpoolRecords {
    type Item = Result<ScanRecord>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.left == 0 {
            return None;
        }
        self.left -= 1;
        let mut b = [0u8; RECORD_BYTES];
        Some(
            self.file
                .read_exact(&mut b)
                .map(|()| ScanRecord::decode(&b))
                .context("reading the scan spool"),
        )
    }
}

/// Wall time per scan, µs, as counts in logarithmic bins of 1 % from [`Latency::FLOOR_US`]
/// up; the exact maximum is kept beside them.
#[derive(Debug, Clone)]
pub struct Latency {
    counts: Vec<u64>,
    total: u64,
    max: f64,
}

impl Default for Latency {
    fn default() -> Self {
        Self::new()
    }
}

impl Latency {
    /// Lower edge of the first bin, µs (everything below falls into it).
    pub const FLOOR_US: f64 = 0.1;
    /// Ratio of a bin's upper edge to its lower edge.
    const RATIO: f64 = 1.01;
    /// Bins: from 0.1 µs to beyond 1,000 s (everything above falls into the last).
    const BINS: usize = 2_800;

    /// No samples.
    pub fn new() -> Self {
        Latency {
            counts: vec![0; Self::BINS],
            total: 0,
            max: 0.0,
        }
    }

    /// Adds one time, µs (a non-finite or negative one counts as zero).
    pub fn add(&mut self, us: f64) {
        let us = if us.is_finite() { us.max(0.0) } else { 0.0 };
        let bin = ((us / Self::FLOOR_US).max(1.0).ln() / Self::RATIO.ln()) as usize;
        if let Some(c) = self.counts.get_mut(bin.min(Self::BINS - 1)) {
            *c += 1;
        }
        self.total += 1;
        self.max = self.max.max(us);
    }

    /// The `q` quantile (0..=1), µs: the upper edge of the bin that holds it (at most 1 %
    /// above the exact value), never above the maximum; `None` without samples.
    pub fn quantile(&self, q: f64) -> Option<f64> {
        if self.total == 0 {
            return None;
        }
        let rank = ((self.total - 1) as f64 * q.clamp(0.0, 1.0)).round() as u64;
        let mut seen = 0;
        for (bin, &c) in self.counts.iter().enumerate() {
            seen += c;
            if seen > rank {
                let upper = Self::FLOOR_US * Self::RATIO.powi(bin as i32 + 1);
                return Some(upper.min(self.max));
            }
        }
        Some(self.max)
    }

    /// The largest time, µs; `None` without samples.
    pub fn max(&self) -> Option<f64> {
        (self.total > 0).then_some(self.max)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_come_back_in_order_and_bit_exact() {
        let mut spool = ScanSpool::new().unwrap();
        let r = |k: i64| ScanRecord {
            stamp: -5 + k * 1_000_000_007,
            reference: k as u32 * 3,
            reference_frontend: Se2::new(0.1 * k as f64, -1e-300, 3.0),
            rel: Se2::new(f64::MIN_POSITIVE, 2.5, -0.25),
            gpe: Se2::new(1e12, -7.0, 1.0 / 3.0),
            frontend: Se2::new(k as f64, k as f64 * 0.5, -(k as f64)),
        };
        for k in 0..10_000 {
            spool.push(&r(k)).unwrap();
        }
        assert_eq!(spool.len(), 10_000);
        let back: Vec<ScanRecord> = spool.into_records().unwrap().map(Result::unwrap).collect();
        assert_eq!(back.len(), 10_000);
        for (k, b) in back.iter().enumerate() {
            assert_eq!(*b, r(k as i64));
        }
    }

    #[test]
    fn latency_quantiles_are_within_a_bin_of_the_exact_ones() {
        let mut l = Latency::new();
        assert_eq!(l.quantile(0.5), None);
        let mut exact: Vec<f64> = (0..10_001)
            .map(|i| 1.0 + (i as f64 * 0.37) % 5_000.0)
            .collect();
        for &v in &exact {
            l.add(v);
        }
        l.add(f64::NAN);
        exact.push(0.0);
        exact.sort_by(f64::total_cmp);
        for q in [0.0, 0.1, 0.5, 0.9, 0.99, 1.0] {
            let want = exact[((exact.len() - 1) as f64 * q).round() as usize];
            let got = l.quantile(q).unwrap();
            assert!(
                got >= want && got <= want.max(Latency::FLOOR_US) * 1.0101,
                "q {q}: {got} vs {want}"
            );
        }
        assert_eq!(l.max(), exact.last().copied());
    }
}
