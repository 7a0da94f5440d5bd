//! Helpers for the QEMU tests: build the bare-metal firmware, run it under
//! `qemu-system-arm -icount`, and parse what it prints.
//!
//! The tests themselves are in `tests/`; `qemu-tests/run` is the one command that runs all of
//! them, including `cloi-core`'s unit tests under `qemu-arm -cpu cortex-a9`.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context, Result};

/// Root of the workspace.
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The firmware crate's folder.
pub fn firmware_dir() -> PathBuf {
    workspace_root().join("armv7-target").join("firmware")
}

/// Bare-metal target of the firmware (hard float; core is built from source).
pub const FIRMWARE_TARGET: &str = "armv7a-none-eabihf";

/// Builds the firmware binaries in release mode and returns the workload ELF's path.
///
/// # Errors
/// Cargo fails or the ELF is missing.
pub fn build_firmware() -> Result<PathBuf> {
    let dir = firmware_dir();
    let status = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()))
        .current_dir(&dir)
        .env("RUSTC_BOOTSTRAP", "1")
        // Do not inherit the outer build's target dir or flags.
        .env_remove("CARGO_TARGET_DIR")
        .env_remove("RUSTFLAGS")
        .env_remove("CARGO_ENCODED_RUSTFLAGS")
        .args([
            "build",
            "--release",
            "-Zbuild-std=core",
            "--target",
            FIRMWARE_TARGET,
        ])
        .status()
        .context("running cargo to build the firmware")?;
    if !status.success() {
        bail!("firmware build failed ({status})");
    }
    let elf = firmware_elf("cloi-firmware");
    for bin in [&elf, &firmware_elf("cloi-mapper")] {
        if !bin.is_file() {
            bail!("firmware ELF {} missing after the build", bin.display());
        }
    }
    Ok(elf)
}

/// The robot computer's Linux target (Cortex-A9, hard float).
pub const LINUX_TARGET: &str = "armv7-unknown-linux-gnueabihf";

/// Builds the `cloi` binary in release mode for `target` (`None`: the host) with this
/// workspace's cargo settings (the ARM linker of `.cargo/config.toml`) and returns its path.
///
/// # Errors
/// Cargo fails or the binary is missing.
pub fn build_cloi(target: Option<&str>) -> Result<PathBuf> {
    let root = workspace_root();
    let mut cmd = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
    cmd.current_dir(&root)
        .env_remove("RUSTFLAGS")
        .env_remove("CARGO_ENCODED_RUSTFLAGS")
        .args([
            "build",
            "--release",
            "--locked",
            "-p",
            "cloi-host",
            "--bin",
            "cloi",
        ]);
    if let Some(t) = target {
        cmd.args(["--target", t]);
    }
    let status = cmd.status().context("running cargo to build cloi")?;
    if !status.success() {
        bail!("cloi build failed ({status})");
    }
    let dir =
        std::env::var_os("CARGO_TARGET_DIR").map_or_else(|| root.join("target"), PathBuf::from);
    let bin = match target {
        Some(t) => dir.join(t).join("release").join("cloi"),
        None => dir.join("release").join("cloi"),
    };
    if !bin.is_file() {
        bail!("{} missing after the build", bin.display());
    }
    Ok(bin)
}

/// Path of a firmware binary after [`build_firmware`]: `cloi-firmware` (the fixed workload)
/// or `cloi-mapper` (the mapper on a `.cloilog` streamed through semihosting).
pub fn firmware_elf(name: &str) -> PathBuf {
    firmware_dir()
        .join("target")
        .join(FIRMWARE_TARGET)
        .join("release")
        .join(name)
}

/// The QEMU command line for the Cortex-A9 board with exact instruction counting.
pub fn qemu_command(elf: &Path) -> Command {
    let mut cmd = Command::new("qemu-system-arm");
    cmd.args([
        "-M",
        "vexpress-a9",
        "-cpu",
        "cortex-a9",
        "-m",
        "1024M",
        "-nographic",
        "-semihosting",
        "-audiodev",
        "none,id=noaudio",
        "-global",
        "pl041.audiodev=noaudio",
        "-icount",
        "shift=0,sleep=off",
        "-kernel",
    ])
    .arg(elf);
    cmd
}

/// One measured section of a firmware run.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SectionRun {
    /// Section name.
    pub name: String,
    /// Guest instructions (timer ticks x 10).
    pub instructions: u64,
    /// Checksum as raw f64 bits.
    pub result_bits: u64,
}

/// Everything a firmware run printed that the tests check.
#[derive(Clone, Debug, PartialEq, Eq, Default)]
pub struct FirmwareRun {
    /// The sections, in order.
    pub sections: Vec<SectionRun>,
    /// SYS stack high-water mark, bytes.
    pub stack_used_bytes: u64,
    /// The raw output.
    pub log: String,
}

/// Runs the firmware once with a semihosting command line (QEMU `-append`; empty for none)
/// under a timeout, and returns what it printed.
///
/// # Errors
/// QEMU cannot be started, times out or exits non-zero.
pub fn run_firmware_raw(elf: &Path, cmdline: &str) -> Result<String> {
    run_firmware_timeout(elf, cmdline, 600)
}

/// [`run_firmware_raw`] with a timeout of `seconds` (the full-log benchmarks run longer).
///
/// # Errors
/// As [`run_firmware_raw`].
pub fn run_firmware_timeout(elf: &Path, cmdline: &str, seconds: u32) -> Result<String> {
    let mut qemu = qemu_command(elf);
    if !cmdline.is_empty() {
        qemu.arg("-append").arg(cmdline);
    }
    let out = Command::new("timeout")
        .arg(seconds.to_string())
        .arg(qemu.get_program())
        .args(qemu.get_args())
        .output()
        .context("starting qemu-system-arm (is it installed? run scripts/setup)")?;
    let log = String::from_utf8_lossy(&out.stdout).into_owned();
    if !out.status.success() {
        bail!(
            "firmware run failed ({}):\n{log}\n{}",
            out.status,
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(log)
}

/// Runs the firmware's fixed workload once (with a timeout) and parses its output.
///
/// # Errors
/// QEMU cannot be started, times out, exits non-zero, or the output is malformed.
pub fn run_firmware(elf: &Path) -> Result<FirmwareRun> {
    parse_log(&run_firmware_raw(elf, "")?)
}

fn field<'a>(line: &'a str, key: &str) -> Option<&'a str> {
    line.split_whitespace()
        .find_map(|kv| kv.strip_prefix(key)?.strip_prefix('='))
}

/// Parses the firmware's `key=value` output.
///
/// # Errors
/// A section line is malformed, or the run did not end with `status=ok`.
pub fn parse_log(log: &str) -> Result<FirmwareRun> {
    let mut run = FirmwareRun {
        log: log.to_owned(),
        ..FirmwareRun::default()
    };
    let mut ok = false;
    for line in log.lines() {
        if let Some(name) = field(line, "section") {
            let instructions = field(line, "instructions")
                .and_then(|v| v.parse().ok())
                .with_context(|| format!("bad instructions in {line:?}"))?;
            let result_bits = field(line, "result")
                .and_then(|v| u64::from_str_radix(v, 16).ok())
                .with_context(|| format!("bad result in {line:?}"))?;
            run.sections.push(SectionRun {
                name: name.to_owned(),
                instructions,
                result_bits,
            });
        } else if let Some(v) = field(line, "stack_used_bytes") {
            run.stack_used_bytes = v
                .parse()
                .with_context(|| format!("bad stack in {line:?}"))?;
        } else if field(line, "status") == Some("ok") {
            ok = true;
        }
    }
    if !ok {
        bail!("firmware did not report status=ok:\n{log}");
    }
    Ok(run)
}

pub mod mapper;
pub mod stats;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_a_run() {
        let log = "firmware=x\nsection=a ticks=2 instructions=20 result=3ff0000000000000\n\
                   stack_used_bytes=512\nstatus=ok\n";
        let run = parse_log(log).unwrap();
        assert_eq!(run.sections[0].instructions, 20);
        assert_eq!(f64::from_bits(run.sections[0].result_bits), 1.0);
        assert_eq!(run.stack_used_bytes, 512);
        assert!(parse_log("status=panic\n").is_err());
    }
}
