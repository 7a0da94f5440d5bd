//! The firmware's replay mode: run a `.cloilog` under QEMU, parse its report and pose file, and
//! run the identical core calls on the host for comparison.

use std::path::Path;

use anyhow::{bail, ensure, Context, Result};
use cloi_core::replay::{Replay, ReplayConfig, ScanOutcome};
use cloi_core::sensor::log::{LogReader, MIN_READER_BUFFER};

use crate::{field, run_firmware_raw};

/// Instruction percentiles over the scans of a replay (nearest rank).
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

/// One line of the firmware's pose file.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseLine {
    /// Scan time, ns.
    pub t_ns: i64,
    /// Pose `[x, y, theta]`.
    pub pose: [f64; 3],
    /// ICP matched.
    pub matched: bool,
    /// Instructions of the scan's step.
    pub instructions: u64,
}

/// What a replay run printed and wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct ReplayRun {
    /// Scans processed.
    pub scans: u64,
    /// Scans whose match failed.
    pub unmatched: u64,
    /// Percentiles printed by the firmware.
    pub instructions: Percentiles,
    /// SYS stack high-water mark, bytes.
    pub stack_used_bytes: u64,
    /// The per-scan lines of the pose file.
    pub poses: Vec<PoseLine>,
    /// The firmware's output.
    pub log: String,
}

fn number(line: &str, key: &str) -> Result<u64> {
    field(line, key)
        .and_then(|v| v.parse().ok())
        .with_context(|| format!("no {key}= in {line:?}"))
}

/// Parses the pose file (`# ...` comment, then `t_ns x y theta matched instructions`).
///
/// # Errors
/// A malformed line.
pub fn parse_poses(text: &str) -> Result<Vec<PoseLine>> {
    let mut out = Vec::new();
    for line in text
        .lines()
        .filter(|l| !l.starts_with('#') && !l.is_empty())
    {
        let f: Vec<&str> = line.split_whitespace().collect();
        ensure!(f.len() == 6, "bad pose line {line:?}");
        let float = |s: &str| {
            s.parse::<f64>()
                .with_context(|| format!("bad number in {line:?}"))
        };
        out.push(PoseLine {
            t_ns: f[0].parse()?,
            pose: [float(f[1])?, float(f[2])?, float(f[3])?],
            matched: f[4] == "1",
            instructions: f[5].parse()?,
        });
    }
    Ok(out)
}

/// Runs the replay firmware (`cloi-replay`) on `log`, writing its poses to `out` (both opened by QEMU on the host).
///
/// # Errors
/// QEMU fails, the firmware reports an error, or its output or pose file is malformed.
pub fn run_replay(elf: &Path, log: &Path, out: &Path) -> Result<ReplayRun> {
    for p in [log, out] {
        let s = p.to_string_lossy();
        ensure!(
            !s.contains(' '),
            "semihosting paths must not contain spaces: {s}"
        );
    }
    let _ = std::fs::remove_file(out);
    let text = run_firmware_raw(elf, &format!("log={} out={}", log.display(), out.display()))?;
    let mut run = ReplayRun {
        scans: 0,
        unmatched: 0,
        instructions: Percentiles::default(),
        stack_used_bytes: 0,
        poses: Vec::new(),
        log: text.clone(),
    };
    let mut ok = false;
    for line in text.lines() {
        if field(line, "replay_scans").is_some() {
            run.scans = number(line, "replay_scans")?;
            run.unmatched = number(line, "replay_unmatched")?;
        } else if line.starts_with("scan_instructions ") {
            run.instructions = Percentiles {
                n: number(line, "n")?,
                min: number(line, "min")?,
                median: number(line, "median")?,
                p99: number(line, "p99")?,
                max: number(line, "max")?,
            };
        } else if field(line, "stack_used_bytes").is_some() {
            run.stack_used_bytes = number(line, "stack_used_bytes")?;
        } else if field(line, "status") == Some("ok") {
            ok = true;
        }
    }
    if !ok {
        bail!("replay did not end with status=ok:\n{text}");
    }
    let poses = std::fs::read_to_string(out)
        .with_context(|| format!("reading the firmware's pose file {}", out.display()))?;
    run.poses = parse_poses(&poses)?;
    Ok(run)
}

/// The same replay on this machine: the same decoder and the same per-event calls as the
/// firmware's `process_event`, on the same bytes.
///
/// # Errors
/// The log is damaged.
pub fn host_replay(log: &[u8]) -> Result<Vec<ScanOutcome>> {
    let mut buf = vec![0u8; MIN_READER_BUFFER];
    let mut reader = LogReader::new(log, &mut buf).map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut replay = Box::new(Replay::new(ReplayConfig::DEFAULT));
    let mut out = Vec::new();
    while let Some(record) = reader.next_record().map_err(|e| anyhow::anyhow!("{e}"))? {
        out.extend(replay.process(&record));
    }
    Ok(out)
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

    #[test]
    fn pose_lines_parse_exactly() {
        let text =
            "# t_ns x y theta matched instructions\n5 1e-1 -2.5e0 3.0000000000000004e0 1 42\n";
        let p = parse_poses(text).unwrap();
        assert_eq!(p[0].pose[0].to_bits(), 0.1f64.to_bits());
        assert_eq!(p[0].pose[2].to_bits(), 3.000_000_000_000_000_4f64.to_bits());
        assert!(p[0].matched && p[0].instructions == 42 && p[0].t_ns == 5);
        assert!(parse_poses("1 2 3\n").is_err());
    }
}
