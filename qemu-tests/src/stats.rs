//! Instruction percentiles over the scans of a firmware run, computed on the host exactly as
//! the firmware computes them, so a test can check the printed figures against the pose file.

/// Nearest-rank instruction percentiles over a run's scans.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct Percentiles {
    /// Scans counted.
    pub n: u64,
    /// Fewest instructions.
    pub min: u64,
    /// Median.
    pub median: u64,
    /// 99th percentile.
    pub p99: u64,
    /// Most instructions.
    pub max: u64,
}

impl Percentiles {
    /// Nearest-rank percentiles of `counts` (the `ceil(p n)`-th smallest), as the firmware
    /// computes them.
    pub fn of(counts: &[u64]) -> Self {
        let mut v = counts.to_vec();
        v.sort_unstable();
        let q = |percent: usize| {
            let rank = (percent * v.len()).div_ceil(100).clamp(1, v.len().max(1));
            v.get(rank - 1).copied().unwrap_or(0)
        };
        Self {
            n: v.len() as u64,
            min: q(0),
            median: q(50),
            p99: q(99),
            max: q(100),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_use_the_nearest_rank() {
        let counts: Vec<u64> = (1..=200).collect();
        let p = Percentiles::of(&counts);
        assert_eq!(
            (p.n, p.min, p.median, p.p99, p.max),
            (200, 1, 100, 198, 200)
        );
        assert_eq!(Percentiles::of(&[]).max, 0);
    }
}
