//! `cloi run` against a device: the emulated LD06 of `cloi emulate ld06` on a pseudo-terminal
//! (issue 18). Mapped live from scans alone; damaged packets and a device that goes away are
//! counted while the run goes on; the recording of a run maps again with `cloi map`; Ctrl-C
//! (SIGINT) ends a run with every output written; a device that is not there is a clear error.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A running emulator and the terminal it sends on.
struct Emulator {
    child: Child,
    path: String,
}

impl Drop for Emulator {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn emulate(args: &[&str]) -> Emulator {
    emulate_kind("ld06", args)
}

fn emulate_kind(kind: &str, args: &[&str]) -> Emulator {
    let mut child = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(["emulate", kind, "--world", "home"])
        .args(args)
        .stdout(Stdio::piped())
        .spawn()
        .expect("the emulator starts");
    let mut line = String::new();
    BufReader::new(child.stdout.take().expect("stdout"))
        .read_line(&mut line)
        .expect("the emulator prints its terminal");
    let path = line
        .trim()
        .strip_prefix(&format!("{kind} on "))
        .expect("`KIND on PATH`")
        .to_owned();
    Emulator { child, path }
}

fn report(out: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(out.join("report.json")).expect("report.json");
    serde_json::from_str(&text).expect("json")
}

fn check_outputs(out: &Path, r: &serde_json::Value) {
    let scans = r["scans"].as_u64().expect("scans");
    assert_eq!(r["device"]["scans"].as_u64(), Some(scans), "{r}");
    let poses = std::fs::read_to_string(out.join("trajectory.tum")).expect("trajectory");
    let poses = poses.lines().filter(|l| !l.starts_with('#')).count();
    assert_eq!(poses as u64, scans);
    for f in [
        "map.png",
        "map.pgm",
        "map.yaml",
        "gpe.tum",
        "graph.g2o",
        "result.mcap",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    // Walls were mapped: the picture has occupied (dark) cells.
    let pgm = std::fs::read(out.join("map.pgm")).expect("pgm");
    assert!(pgm.iter().rev().take(pgm.len() / 2).any(|&v| v < 50));
}

#[test]
fn an_emulated_ld06_is_mapped_live_and_damage_and_loss_are_counted() {
    // Four seconds of data with one packet in ten damaged, then the terminal closes.
    let emulator = emulate(&["--duration", "4", "--corrupt-every", "10"]);
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("live");
    let recording = tmp.path().join("run.mcap");
    let o = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(["run", "--lidar", &format!("ld06:{}", emulator.path)])
        .args(["--lidar-offset", "0.1,0,0", "--duration", "7", "--record"])
        .arg(&recording)
        .arg("--out")
        .arg(&out)
        .output()
        .expect("cloi run");
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    let r = report(&out);
    println!("{}", r["device"]);
    let device = &r["device"];
    let n = |k: &str| device[k].as_u64().expect(k);
    assert!(n("scans") >= 10, "{device}");
    // One packet in ten: each fails its CRC and none is taken for a good one.
    let (good, bad) = (n("packets"), n("crc_errors"));
    assert!(
        bad > 0 && bad * 9 <= good + 9 && good <= bad * 9 + 9,
        "{device}"
    );
    // The emulator's end is a device that went away; the run waited and ended on time.
    assert!(n("read_errors") >= 1, "{device}");
    assert!(stderr.contains("damaged packets"), "{stderr}");
    check_outputs(&out, &r);
    // The recording holds every scan, with the mounting, and maps again.
    assert_eq!(n("recorded"), n("scans"), "{device}");
    let again = tmp.path().join("again");
    let o = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(["-q", "map"])
        .arg(&recording)
        .args(["--deterministic", "--profile", "home", "--out"])
        .arg(&again)
        .output()
        .expect("cloi map");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let replay = report(&again);
    assert_eq!(replay["scans"].as_u64(), Some(n("scans")), "{replay}");
    assert_eq!(replay["scans_rejected"].as_u64(), Some(0), "{replay}");
    assert_eq!(
        replay["input"]["laser_offset"],
        serde_json::json!([0.1, 0.0, 0.0]),
        "{replay}"
    );
}

#[test]
fn an_emulated_rplidar_is_asked_to_scan_and_mapped() {
    // One node in fifty with its check bit broken: the reader finds the node grid again.
    let emulator = emulate_kind("rplidar", &["--duration", "60", "--corrupt-every", "50"]);
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("live");
    let o = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args([
            "-q",
            "run",
            "--lidar",
            &format!("rplidar:{}", emulator.path),
        ])
        .args(["--duration", "5", "--out"])
        .arg(&out)
        .output()
        .expect("cloi run");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = report(&out);
    let device = &r["device"];
    let n = |k: &str| device[k].as_u64().expect(k);
    // The emulator streams only after the scan request: every node came after it.
    assert!(
        n("scans") >= 10 && n("nodes") >= 300 * n("scans"),
        "{device}"
    );
    assert!(n("skipped_bytes") > 0 && n("packets") == 0, "{device}");
    check_outputs(&out, &r);
}

#[test]
fn a_device_that_comes_back_is_opened_again_and_mapping_resumes() {
    // The run reads a link; the first device's data ends after 3 s, then the link points at a
    // second device (a LiDAR unplugged and plugged in again under the same name).
    let tmp = tempfile::tempdir().expect("tempdir");
    let link = tmp.path().join("ld06");
    let first = emulate(&["--duration", "3"]);
    std::os::unix::fs::symlink(&first.path, &link).expect("link");
    let out = tmp.path().join("live");
    let run = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(["-q", "run", "--lidar"])
        .arg(format!("ld06:{}", link.display()))
        .args(["--duration", "9", "--out"])
        .arg(&out)
        .spawn()
        .expect("cloi run");
    std::thread::sleep(Duration::from_secs(4));
    let second = emulate(&["--duration", "60", "--seed", "2"]);
    std::fs::remove_file(&link).expect("unlink");
    std::os::unix::fs::symlink(&second.path, &link).expect("link again");
    let status = run.wait_with_output().expect("cloi run ends").status;
    assert!(status.success(), "{status}");
    drop(first);
    let r = report(&out);
    let device = &r["device"];
    assert!(device["read_errors"].as_u64() >= Some(1), "{device}");
    assert!(device["reopened"].as_u64() >= Some(1), "{device}");
    // Scans from both devices: more than the first one's three seconds at 10 Hz hold.
    assert!(device["scans"].as_u64() > Some(35), "{device}");
    check_outputs(&out, &r);
}

#[test]
fn sigint_ends_a_live_run_with_every_output() {
    let emulator = emulate(&["--duration", "120"]);
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("live");
    let mut run = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args([
            "-q",
            "run",
            "--lidar",
            &format!("ld06:{}", emulator.path),
            "--out",
        ])
        .arg(&out)
        .spawn()
        .expect("cloi run");
    std::thread::sleep(Duration::from_secs(4));
    let kill = Command::new("kill")
        .args(["-INT", &run.id().to_string()])
        .status()
        .expect("kill");
    assert!(kill.success());
    let stopped = Instant::now();
    let status = loop {
        if let Some(s) = run.try_wait().expect("wait") {
            break s;
        }
        assert!(
            stopped.elapsed() < Duration::from_secs(30),
            "no exit after SIGINT"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(status.success(), "{status}");
    let r = report(&out);
    assert!(r["scans"].as_u64().expect("scans") >= 5, "{r}");
    check_outputs(&out, &r);
}

#[test]
fn a_missing_device_is_a_clear_error() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let o = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args([
            "run",
            "--lidar",
            "ld06:/dev/cloi-no-such-port",
            "--duration",
            "1",
        ])
        .arg("--out")
        .arg(tmp.path())
        .output()
        .expect("cloi run");
    assert!(!o.status.success());
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(
        stderr.contains("opening the LiDAR's serial port /dev/cloi-no-such-port"),
        "{stderr}"
    );
}
