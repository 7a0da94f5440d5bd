//! Instruction statistics over the scans of a run: per-scan counts kept in fixed arrays and
//! their nearest-rank percentiles, computed as the QEMU tests compute them on the host.

/// Scans whose instruction counts are kept for the percentiles (intel.clf has 13,631).
pub const MAX_SCANS: usize = 32_768;

/// Nearest-rank quantile `percent / 100` of sorted values: the `ceil(p n)`-th smallest.
pub(crate) fn quantile(sorted: &[u32], percent: usize) -> u32 {
    let n = sorted.len();
    let rank = (percent * n).div_ceil(100).clamp(1, n.max(1));
    sorted.get(rank - 1).copied().unwrap_or(0)
}
