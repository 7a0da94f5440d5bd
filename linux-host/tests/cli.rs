//! The `cloi` binary as a user meets it: help, version, errors.

use std::process::Command;

fn cloi(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(args)
        .output()
        .expect("cloi runs")
}

#[test]
fn help_lists_the_subcommands() {
    let out = cloi(&["--help"]);
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("Usage: cloi"), "{text}");
    assert!(text.contains("budget"), "{text}");
}

#[test]
fn version_is_the_package_version() {
    let out = cloi(&["--version"]);
    assert!(out.status.success());
    assert_eq!(
        String::from_utf8_lossy(&out.stdout).trim(),
        format!("cloi {}", env!("CARGO_PKG_VERSION"))
    );
}

#[test]
fn unknown_subcommand_fails_with_a_message() {
    let out = cloi(&["no-such-command"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("no-such-command"));
}

#[test]
fn budget_prints_every_profile() {
    let out = cloi(&["budget"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    for profile in ["home", "office", "airport"] {
        assert!(
            text.contains(&format!("{profile} ")),
            "{profile} missing:\n{text}"
        );
    }
    assert!(!text.contains("OVER"), "{text}");
}

#[test]
fn a_missing_file_is_a_clear_error_and_a_failure() {
    let out = cloi(&["budget", "--elf", "/nonexistent/firmware.elf"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.starts_with("error: "), "{err}");
    assert!(err.contains("/nonexistent/firmware.elf"), "{err}");
}
