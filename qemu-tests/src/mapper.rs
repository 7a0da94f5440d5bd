//! The firmware's mapper mode (`cloi-mapper`): run a `.cloilog` under QEMU and parse its
//! report and pose file (real-time pose per scan, final keyframe poses).

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, ensure, Context, Result};

use crate::stats::Percentiles;
use crate::{field, run_firmware_timeout};

/// One accepted scan of the pose file.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScanLine {
    /// Scan time, ns.
    pub t_ns: i64,
    /// Real-time pose `[x, y, theta]`.
    pub pose: [f64; 3],
    /// The scan became a keyframe.
    pub keyframe: bool,
    /// Instructions of `push_scan`.
    pub push_scan: u64,
    /// Instructions of the back-end step after the scan.
    pub backend: u64,
}

/// One keyframe of the final graph.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KeyframeLine {
    /// Keyframe serial.
    pub serial: u32,
    /// Optimized pose `[x, y, theta]`.
    pub pose: [f64; 3],
}

/// What a mapper run printed and wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct MapperRun {
    /// The `Debug` form of the firmware's `MapperConfig`.
    pub config: String,
    /// Scan records processed (accepted or not).
    pub scans: u64,
    /// Scans the mapper rejected.
    pub rejected: u64,
    /// The `key=value` counters of the `mapper_records=` line (and, localizing, of the
    /// `localized_scans=` line).
    pub counters: BTreeMap<String, u64>,
    /// Instruction percentiles per section (`push_scan`, `frontend_gpe`, `keyframe_scan`, the
    /// parts `frontend`, `gpe`, `keyframe_update`, `loop_search`,
    /// `backend_step`, `backend_working`, `backend_optimizer`).
    pub sections: BTreeMap<String, Percentiles>,
    /// SYS stack high-water mark, bytes.
    pub stack_used_bytes: u64,
    /// Accepted scans.
    pub poses: Vec<ScanLine>,
    /// Final keyframes.
    pub keyframes: Vec<KeyframeLine>,
    /// The firmware's output.
    pub log: String,
}

fn float(s: &str, line: &str) -> Result<f64> {
    s.parse::<f64>()
        .with_context(|| format!("bad number in {line:?}"))
}

/// Parses the pose file (`scan ...` and `keyframe ...` lines, `#` comments).
///
/// # Errors
/// A malformed line.
pub fn parse_pose_file(text: &str) -> Result<(Vec<ScanLine>, Vec<KeyframeLine>)> {
    let (mut scans, mut keyframes) = (Vec::new(), Vec::new());
    for line in text
        .lines()
        .filter(|l| !l.starts_with('#') && !l.is_empty())
    {
        let f: Vec<&str> = line.split_whitespace().collect();
        match f.first().copied() {
            Some("scan") if f.len() == 8 => scans.push(ScanLine {
                t_ns: f[1].parse()?,
                pose: [float(f[2], line)?, float(f[3], line)?, float(f[4], line)?],
                keyframe: f[5] == "1",
                push_scan: f[6].parse()?,
                backend: f[7].parse()?,
            }),
            Some("keyframe") if f.len() == 5 => keyframes.push(KeyframeLine {
                serial: f[1].parse()?,
                pose: [float(f[2], line)?, float(f[3], line)?, float(f[4], line)?],
            }),
            _ => bail!("bad pose-file line {line:?}"),
        }
    }
    Ok((scans, keyframes))
}

/// Runs the mapper firmware (`cloi-mapper`) on `log`, writing its poses to `out` (both opened
/// by QEMU on the host).
///
/// # Errors
/// QEMU fails, the firmware reports an error, or its output or pose file is malformed.
pub fn run_mapper(elf: &Path, log: &Path, out: &Path) -> Result<MapperRun> {
    run_mapper_timeout(elf, log, out, 600)
}

/// [`run_mapper`] with a timeout of `seconds`.
///
/// # Errors
/// As [`run_mapper`].
pub fn run_mapper_timeout(elf: &Path, log: &Path, out: &Path, seconds: u32) -> Result<MapperRun> {
    run_mapper_saving(elf, log, out, None, seconds)
}

/// [`run_mapper_timeout`], the firmware also writing its final map to `save` (`.cloimap`).
///
/// # Errors
/// As [`run_mapper`].
pub fn run_mapper_saving(
    elf: &Path,
    log: &Path,
    out: &Path,
    save: Option<&Path>,
    seconds: u32,
) -> Result<MapperRun> {
    if let Some(save) = save {
        let _ = std::fs::remove_file(save);
    }
    let extra = save.map(|s| format!("save={}", s.display()));
    run_firmware_over(elf, log, out, save, extra.as_deref(), seconds)
}

/// Runs the `cloi-mapper` firmware localizing in the saved map `map` over `log`
/// (`localize=MAP [initial=X,Y,THETA]`, as `cloi localize`), the poses written to `out`; the
/// run's counters include the `localized_scans=` line's.
///
/// # Errors
/// As [`run_mapper`].
pub fn run_localizer(
    elf: &Path,
    log: &Path,
    out: &Path,
    map: &Path,
    initial: Option<[f64; 3]>,
    seconds: u32,
) -> Result<MapperRun> {
    let mut extra = format!("localize={}", map.display());
    if let Some([x, y, theta]) = initial {
        extra.push_str(&format!(" initial={x:e},{y:e},{theta:e}"));
    }
    run_firmware_over(elf, log, out, Some(map), Some(&extra), seconds)
}

/// Runs the firmware over `log` with `log= out=` and the `extra` arguments, checking that
/// `log`, `out` and `other` have no spaces; parses what it printed and its pose file.
fn run_firmware_over(
    elf: &Path,
    log: &Path,
    out: &Path,
    other: Option<&Path>,
    extra: Option<&str>,
    seconds: u32,
) -> Result<MapperRun> {
    for p in [log, out].into_iter().chain(other) {
        let s = p.to_string_lossy();
        ensure!(
            !s.contains(' '),
            "semihosting paths must not contain spaces: {s}"
        );
    }
    let _ = std::fs::remove_file(out);
    let mut args = format!("log={} out={}", log.display(), out.display());
    if let Some(extra) = extra {
        args.push(' ');
        args.push_str(extra);
    }
    let text = run_firmware_timeout(elf, &args, seconds)?;
    let mut run = MapperRun {
        config: String::new(),
        scans: 0,
        rejected: 0,
        counters: BTreeMap::new(),
        sections: BTreeMap::new(),
        stack_used_bytes: 0,
        poses: Vec::new(),
        keyframes: Vec::new(),
        log: text.clone(),
    };
    let mut ok = false;
    let number = |line: &str, key: &str| -> Result<u64> {
        field(line, key)
            .and_then(|v| v.parse().ok())
            .with_context(|| format!("no {key}= in {line:?}"))
    };
    for line in text.lines() {
        if let Some(c) = line.strip_prefix("config=") {
            c.clone_into(&mut run.config);
        } else if line.starts_with("mapper_records=") || line.starts_with("localized_scans=") {
            for kv in line.split_whitespace() {
                if let Some((k, v)) = kv.split_once('=') {
                    run.counters.insert(k.to_owned(), v.parse()?);
                }
            }
            if line.starts_with("mapper_records=") {
                run.scans = number(line, "mapper_scans")?;
                run.rejected = number(line, "mapper_rejected")?;
            }
        } else if let Some(name) = field(line, "stat") {
            run.sections.insert(
                name.to_owned(),
                Percentiles {
                    n: number(line, "n")?,
                    min: number(line, "min")?,
                    median: number(line, "median")?,
                    p99: number(line, "p99")?,
                    max: number(line, "max")?,
                },
            );
        } else if field(line, "stack_used_bytes").is_some() {
            run.stack_used_bytes = number(line, "stack_used_bytes")?;
        } else if field(line, "status") == Some("ok") {
            ok = true;
        }
    }
    if !ok {
        bail!("the mapper firmware did not end with status=ok:\n{text}");
    }
    let poses = std::fs::read_to_string(out)
        .with_context(|| format!("reading the firmware's pose file {}", out.display()))?;
    (run.poses, run.keyframes) = parse_pose_file(&poses)?;
    Ok(run)
}

/// Runs the `cloi-mapper` firmware with `load=MAP`: it reads the saved map into the `home`
/// profile's static pools. Returns the `map_*` fields it printed (`map_nodes`, `map_edges`,
/// `map_submaps`, `map_next_serial`, `map_load_instructions`, `map_checksum`).
///
/// # Errors
/// QEMU missing or failing, a path with a space, or a run that did not end with `status=ok`.
pub fn load_map_firmware(elf: &Path, map: &Path) -> Result<BTreeMap<String, String>> {
    let s = map.to_string_lossy();
    ensure!(
        !s.contains(' '),
        "semihosting paths must not contain spaces: {s}"
    );
    let text = run_firmware_timeout(elf, &format!("load={s}"), 120)?;
    if !text.lines().any(|l| field(l, "status") == Some("ok")) {
        bail!("the map firmware did not end with status=ok:\n{text}");
    }
    Ok(text
        .split_whitespace()
        .filter_map(|kv| kv.split_once('='))
        .filter(|(k, _)| k.starts_with("map_"))
        .map(|(k, v)| (k.to_owned(), v.to_owned()))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pose_file_lines_parse_exactly() {
        let text = "# scan ...\nscan 5 1e-1 -2.5e0 3.0000000000000004e0 1 42 7\n\
                    # keyframe ...\nkeyframe 3 1e-1 0e0 -1e0\n";
        let (s, k) = parse_pose_file(text).unwrap();
        assert_eq!(s[0].pose[0].to_bits(), 0.1f64.to_bits());
        assert_eq!(s[0].pose[2].to_bits(), 3.000_000_000_000_000_4f64.to_bits());
        assert!(s[0].keyframe && s[0].push_scan == 42 && s[0].backend == 7 && s[0].t_ns == 5);
        assert_eq!((k[0].serial, k[0].pose[2]), (3, -1.0));
        assert!(parse_pose_file("scan 1 2 3\n").is_err());
    }
}
