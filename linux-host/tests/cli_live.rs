//! `cloi run` against devices: the emulated LD06 or RPLIDAR (and Create 2 base) of `cloi
//! emulate` on pseudo-terminals (issue 18). Mapped live from scans alone or with the base's
//! wheel odometry; damaged packets and a device that goes away are counted while the run goes
//! on; the recording of a run maps again with `cloi map`; Ctrl-C (SIGINT) ends a run with
//! every output written; a device that is not there is a clear error.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A running emulator and the terminal it sends on (and its base's, if it emulates one).
struct Emulator {
    child: Child,
    path: String,
    base: Option<String>,
}

impl Emulator {
    /// Waits for the emulator to end; what it says it sent (`sent N turns[ and M base
    /// frames]`), as the numbers N and M (M is 0 without a base).
    fn sent(mut self) -> (u64, u64) {
        use std::io::Read;
        let mut text = String::new();
        let mut stderr = self.child.stderr.take().expect("stderr");
        stderr
            .read_to_string(&mut text)
            .expect("the emulator's stderr");
        let _ = self.child.wait();
        let line = text
            .lines()
            .find_map(|l| l.strip_prefix("sent "))
            .unwrap_or_else(|| panic!("no `sent` line in {text:?}"));
        let words: Vec<&str> = line.split_whitespace().collect();
        let number = |i: usize| words.get(i).and_then(|w| w.parse().ok());
        (number(0).expect("turns"), number(3).unwrap_or(0))
    }
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
        .stderr(Stdio::piped())
        .spawn()
        .expect("the emulator starts");
    let mut stdout = BufReader::new(child.stdout.take().expect("stdout"));
    let mut terminal = |name: &str| {
        let mut line = String::new();
        stdout
            .read_line(&mut line)
            .expect("the emulator prints its terminal");
        line.trim()
            .strip_prefix(&format!("{name} on "))
            .expect("`KIND on PATH`")
            .to_owned()
    };
    let path = terminal(kind);
    let base = args.contains(&"--base").then(|| terminal("create2"));
    Emulator { child, path, base }
}

fn report(out: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(out.join("report.json")).expect("report.json");
    serde_json::from_str(&text).expect("json")
}

/// Whether `bad` of `good + bad` is one in `n`, give or take one (the run starts and ends
/// anywhere in the emulator's count).
fn one_in(n: u64, good: u64, bad: u64) -> bool {
    let k = n - 1;
    bad > 0 && bad * k <= good + k && good <= bad * k + k
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
    assert!(one_in(10, good, bad), "{device}");
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

/// The poses of a TUM trajectory file: (stamp ns, x, y, yaw).
fn tum_poses(path: &Path) -> Vec<(i64, f64, f64, f64)> {
    let text = std::fs::read_to_string(path).expect("trajectory");
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| {
            let v: Vec<f64> = l
                .split_whitespace()
                .map(|x| x.parse().expect("number"))
                .collect();
            let yaw = 2.0 * v[6].atan2(v[7]);
            ((v[0] * 1e9).round() as i64, v[1], v[2], yaw)
        })
        .collect()
}

/// The motion from `a` to `b` in `a`'s frame: (distance, heading change).
fn motion(a: (f64, f64, f64), b: (f64, f64, f64)) -> (f64, f64) {
    let turn = (b.2 - a.2).sin().atan2((b.2 - a.2).cos());
    ((b.0 - a.0).hypot(b.1 - a.1), turn)
}

#[test]
fn an_emulated_create2_gives_the_live_map_its_wheel_odometry() {
    // Fourteen seconds of data (the robot drives 3 m and turns); one LiDAR packet and one base
    // frame in twenty damaged.
    let emulator = emulate(&[
        "--duration",
        "14",
        "--corrupt-every",
        "20",
        "--base",
        "create2",
    ]);
    let base = emulator.base.clone().expect("the base's terminal");
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("live");
    let recording = tmp.path().join("run.mcap");
    let o = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(["run", "--lidar", &format!("ld06:{}", emulator.path)])
        .args(["--odom", &format!("create2:{base}"), "--duration", "16"])
        .arg("--record")
        .arg(&recording)
        .arg("--out")
        .arg(&out)
        .output()
        .expect("cloi run");
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    let r = report(&out);
    println!("{}", r["base"]);
    let b = &r["base"];
    let n = |k: &str| b[k].as_u64().expect(k);
    // The simulator measures the wheels at 50 Hz: a frame each time.
    assert!(n("poses") >= 600, "{b}");
    // Every good frame the emulator sent was read (the last may be cut as its terminal
    // closes) and every damaged one was refused. A refused frame is searched again from its
    // second byte, so an encoder byte that happens to equal the header is refused too: the
    // checksum errors are at least the damaged frames, at most all their bytes.
    let (sent, damaged) = {
        let (_, frames) = emulator.sent();
        (frames, frames / 20)
    };
    let (good, bad) = (n("frames"), n("checksum_errors"));
    assert!(
        good + damaged <= sent && good + damaged + 1 >= sent,
        "{sent} sent: {b}"
    );
    let frame_bytes = cloi_core::sensor::create2::ENCODER_FRAME_LEN as u64;
    assert!(
        bad >= damaged && bad <= damaged * frame_bytes,
        "{sent} sent: {b}"
    );
    assert_eq!(n("poses"), good, "{b}");
    assert!(n("read_errors") >= 1, "{b}");
    assert!(stderr.contains("damaged frames"), "{stderr}");
    check_outputs(&out, &r);
    // Every pose reached the mapper, none was refused, and the scans were covered by them
    // (the first scan may come before the first frame).
    assert_eq!(r["input"]["odometry"].as_u64(), Some(n("poses")), "{r}");
    assert_eq!(r["mapper"]["odometry_rejected"].as_u64(), Some(0), "{r}");
    assert!(r["mapper"]["odometry_gaps"].as_u64() <= Some(2), "{r}");
    // Each live scan's latency was measured (its figures are the note's, not a test's).
    let latency = &r["live_latency_ms"];
    let ms = |k: &str| latency[k].as_f64().expect(k);
    assert!(
        ms("median") <= ms("p99") && ms("p99") <= ms("max"),
        "{latency}"
    );

    // The recording holds both streams; the wheels' motion over the run is the LiDAR's: the
    // encoder geometry, the turning direction and both devices' time stamps agree (within the
    // simulated wheel odometry's own error: its heading drifts by up to 0.2 rad in 10 s).
    assert_eq!(n("recorded"), n("poses"), "{b}");
    let events = cloi_host::map::input::open_input(&recording, &Default::default())
        .expect("the recording opens");
    let odom: Vec<(i64, f64, f64, f64)> = events
        .filter_map(|e| match e.expect("event") {
            cloi_host::map::input::SensorEvent::Odometry { t_ns, pose } => {
                Some((t_ns, pose.x, pose.y, pose.theta))
            }
            _ => None,
        })
        .collect();
    assert_eq!(odom.len() as u64, n("poses"));
    let traj = tum_poses(&out.join("trajectory.tum"));
    let at = |t: i64| {
        let o = odom
            .iter()
            .min_by_key(|o| (o.0 - t).abs())
            .expect("odometry");
        (o.1, o.2, o.3)
    };
    let (first, last) = (traj[2], traj[traj.len() - 1]);
    let lidar = motion((first.1, first.2, first.3), (last.1, last.2, last.3));
    let wheels = motion(at(first.0), at(last.0));
    println!("LiDAR {lidar:?}, wheels {wheels:?}");
    assert!(
        lidar.0 > 2.0 && lidar.1.abs() > 0.6,
        "the robot moved and turned: {lidar:?}"
    );
    assert!(
        (lidar.0 - wheels.0).abs() < 0.05 * lidar.0 + 0.05 && (lidar.1 - wheels.1).abs() < 0.3,
        "LiDAR {lidar:?}, wheels {wheels:?}"
    );
}

#[test]
fn an_emulated_hokuyo_is_asked_for_its_parameters_and_mapped() {
    // One scan in ten with a damaged line: dropped whole and counted.
    let emulator = emulate_kind("urg", &["--duration", "60", "--corrupt-every", "10"]);
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("live");
    let recording = tmp.path().join("run.mcap");
    let o = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(["-q", "run", "--lidar", &format!("urg:{}", emulator.path)])
        .args(["--duration", "5", "--record"])
        .arg(&recording)
        .arg("--out")
        .arg(&out)
        .output()
        .expect("cloi run");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = report(&out);
    let device = &r["device"];
    let n = |k: &str| device[k].as_u64().expect(k);
    assert!(n("scans") >= 10, "{device}");
    // Each damaged scan fails one line's check and is dropped; none is taken whole.
    let (good, bad) = (n("scans"), n("crc_errors"));
    assert!(
        one_in(10, good, bad) && bad == n("revolutions_dropped"),
        "{device}"
    );
    check_outputs(&out, &r);
    // The scans are the device's own: 682 steps over 240 degrees from its parameters (`PP`),
    // at most 5.6 m, as the recording shows.
    let scans: Vec<cloi_host::map::input::ScanEvent> =
        cloi_host::map::input::open_input(&recording, &Default::default())
            .expect("the recording opens")
            .filter_map(|e| match e.expect("event") {
                cloi_host::map::input::SensorEvent::Scan(s) => Some(s),
                _ => None,
            })
            .collect();
    assert_eq!(scans.len() as u64, good);
    let s = &scans[0];
    let last = s.angle_min + s.angle_increment * (s.ranges.len() - 1) as f32;
    assert_eq!(s.ranges.len(), 682);
    assert!(
        (s.angle_min.to_degrees() + 119.53).abs() < 0.01,
        "{}",
        s.angle_min
    );
    assert!((last.to_degrees() - 119.88).abs() < 0.01, "{last}");
    assert_eq!((s.range_min, s.range_max), (0.02, 5.6));
    assert!(s.ranges.iter().filter(|r| r.is_finite()).count() > 300);
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
    // The devices are opened gyro, base, LiDAR: the first missing one is named.
    for (device, said) in [
        (
            ["--lidar-offset", "0,0,0"],
            "opening the LiDAR's serial port /dev/cloi-no-such-port",
        ),
        (
            ["--odom", "create2:/dev/cloi-no-such-base"],
            "opening the base's serial port /dev/cloi-no-such-base",
        ),
        (
            ["--imu", "mpu6050:/dev/cloi-no-such-i2c"],
            "opening the I2C device /dev/cloi-no-such-i2c",
        ),
    ] {
        let o = Command::new(env!("CARGO_BIN_EXE_cloi"))
            .args(["run", "--lidar", "ld06:/dev/cloi-no-such-port"])
            .args(device)
            .args(["--duration", "1", "--out"])
            .arg(tmp.path())
            .output()
            .expect("cloi run");
        assert!(!o.status.success());
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(stderr.contains(said), "{stderr}");
    }
}
