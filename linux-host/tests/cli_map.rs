//! `cloi map` as a user runs it: the simulated home by default, every output written,
//! deterministic runs identical, and bad input rejected and counted without a crash.

use std::fmt::Write as _;
use std::path::Path;
use std::process::Command;

fn cloi(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(args)
        .output()
        .expect("cloi runs")
}

fn report(dir: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(dir.join("report.json")).expect("report.json");
    serde_json::from_str(&text).expect("valid JSON")
}

fn tum_rows(path: &Path) -> Vec<Vec<f64>> {
    std::fs::read_to_string(path)
        .expect("trajectory")
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            l.split_whitespace()
                .map(|v| v.parse().expect("number"))
                .collect()
        })
        .collect()
}

#[test]
fn simulated_home_writes_every_output_and_repeats_bit_for_bit() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let run = |name: &str| {
        let dir = tmp.path().join(name);
        let out = cloi(&[
            "map",
            "--deterministic",
            "--quiet",
            "--sim-duration",
            "40",
            "--out",
            dir.to_str().expect("utf-8"),
        ]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        dir
    };
    let a = run("a");
    for f in [
        "map.pgm",
        "map.yaml",
        "map.png",
        "result.mcap",
        "trajectory.tum",
        "gpe.tum",
        "graph.g2o",
        "report.json",
    ] {
        assert!(a.join(f).is_file(), "{f} missing");
    }
    // result.mcap: the map at the start and the end, the path, one pose per scan.
    let bytes = std::fs::read(a.join("result.mcap")).expect("result.mcap");
    let mut topics = std::collections::BTreeMap::<String, usize>::new();
    for m in mcap::MessageStream::new(&bytes).expect("an MCAP file") {
        *topics
            .entry(m.expect("message").channel.topic.clone())
            .or_default() += 1;
    }
    let scans = std::fs::read_to_string(a.join("trajectory.tum"))
        .expect("trajectory")
        .lines()
        .filter(|l| !l.starts_with('#'))
        .count();
    assert_eq!(topics.get("/map"), Some(&2), "{topics:?}");
    assert_eq!(topics.get("/trajectory"), Some(&1), "{topics:?}");
    assert_eq!(topics.get("/pose"), Some(&scans), "{topics:?}");
    let r = report(&a);
    for key in [
        "scans",
        "keyframes",
        "nodes",
        "edges",
        "loop_closures",
        "data_seconds",
        "wall_seconds",
        "peak_heap_bytes",
        "gpe_max_jump_m",
        "gpe_rate_hz",
    ] {
        assert!(r.get(key).is_some(), "report lacks {key}: {r}");
    }
    let scans = r["scans"].as_u64().expect("scans");
    let rejected = r["scans_rejected"].as_u64().expect("rejected");
    assert!(scans > 50, "{r}");
    assert!(r["keyframes"].as_u64().expect("keyframes") > 10, "{r}");
    assert!(r["data_seconds"].as_f64().expect("seconds") > 30.0, "{r}");
    assert!(r["peak_heap_bytes"].as_u64().expect("heap") > 0, "{r}");
    assert!(r["gpe_max_jump_m"].as_f64().expect("jump") < 0.05, "{r}");
    assert_eq!(r["profile"], "home");
    // One pose per accepted scan, in both trajectories.
    let traj = tum_rows(&a.join("trajectory.tum"));
    assert_eq!(traj.len() as u64, scans - rejected);
    assert_eq!(tum_rows(&a.join("gpe.tum")).len(), traj.len());
    assert!(traj.iter().all(|row| row.len() == 8));
    // The map image has the size the YAML says and is not blank.
    let yaml = std::fs::read_to_string(a.join("map.yaml")).expect("yaml");
    assert!(yaml.contains("image: map.pgm"), "{yaml}");
    let pgm = std::fs::read(a.join("map.pgm")).expect("pgm");
    assert!(pgm.starts_with(b"P5\n"));
    assert!(
        pgm.iter().skip(20).any(|&v| v == 0),
        "no occupied cell in the map"
    );
    // graph.g2o has every node and its edges.
    let g2o = std::fs::read_to_string(a.join("graph.g2o")).expect("g2o");
    let vertices = g2o.lines().filter(|l| l.starts_with("VERTEX_SE2")).count();
    assert_eq!(vertices as u64, r["nodes"].as_u64().expect("nodes"));
    let b = run("b");
    for f in ["trajectory.tum", "gpe.tum", "graph.g2o", "map.pgm"] {
        assert_eq!(
            std::fs::read(a.join(f)).expect("a"),
            std::fs::read(b.join(f)).expect("b"),
            "{f} differs between two deterministic runs"
        );
    }
}

/// Ray-cast ranges in a 6 m x 4 m room with a box, 181 beams over 180 degrees.
fn room_scan(x: f64, y: f64, th: f64) -> Vec<f64> {
    let walls = [
        [0.0, 0.0, 6.0, 0.0],
        [6.0, 0.0, 6.0, 4.0],
        [6.0, 4.0, 0.0, 4.0],
        [0.0, 4.0, 0.0, 0.0],
        [2.5, 1.5, 3.5, 1.5],
        [3.5, 1.5, 3.5, 2.5],
        [3.5, 2.5, 2.5, 2.5],
        [2.5, 2.5, 2.5, 1.5],
    ];
    (0..181)
        .map(|i| {
            let a = th - std::f64::consts::FRAC_PI_2 + (i as f64).to_radians();
            let (dx, dy) = (a.cos(), a.sin());
            walls
                .iter()
                .filter_map(|w| {
                    let (ex, ey) = (w[2] - w[0], w[3] - w[1]);
                    let den = dx * ey - dy * ex;
                    if den.abs() < 1e-12 {
                        return None;
                    }
                    let (qx, qy) = (w[0] - x, w[1] - y);
                    let t = (qx * ey - qy * ex) / den;
                    let u = (qx * dy - qy * dx) / den;
                    (t > 0.0 && (0.0..=1.0).contains(&u)).then_some(t)
                })
                .fold(f64::INFINITY, f64::min)
        })
        .collect()
}

#[test]
fn bad_scans_in_a_log_are_rejected_and_counted() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut log = String::from("# synthetic log\nPARAM robot_frontlaser_offset 0.0 nohost 0\n");
    let mut t = 1000.0;
    let line = |log: &mut String, ranges: &str, n: usize, x: f64, t: f64| {
        writeln!(
            log,
            "FLASER {n} {ranges} {x} 1.0 0.0 {x} 1.0 0.0 {t:.6} host {t:.6}"
        )
        .expect("write");
    };
    for i in 0..60 {
        let x = 1.0 + 0.05 * i as f64;
        let r = room_scan(x, 1.0, 0.0);
        let text: Vec<String> = r.iter().map(|v| format!("{v:.3}")).collect();
        line(&mut log, &text.join(" "), 181, x, t);
        match i {
            // A scan of NaN ranges only.
            10 => line(&mut log, &vec!["nan"; 181].join(" "), 181, x, t + 0.01),
            // A time stamp going backwards.
            20 => line(&mut log, &text.join(" "), 181, x, t - 5.0),
            // An empty scan.
            30 => line(&mut log, "", 0, x, t + 0.02),
            _ => {}
        }
        t += 0.1;
    }
    // A scan with some NaN beams is used.
    let mut r: Vec<String> = room_scan(4.0, 1.0, 0.0)
        .iter()
        .map(|v| format!("{v:.3}"))
        .collect();
    r[5] = "nan".into();
    r[6] = "nan".into();
    line(&mut log, &r.join(" "), 181, 4.0, t);
    let path = tmp.path().join("bad.clf");
    std::fs::write(&path, log).expect("write log");
    let run = |name: &str, stamps: &str| {
        let dir = tmp.path().join(name);
        let out = cloi(&[
            "map",
            path.to_str().expect("utf-8"),
            "--profile",
            "home",
            "--deterministic",
            "--quiet",
            "--stamps",
            stamps,
            "--out",
            dir.to_str().expect("utf-8"),
        ]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        dir
    };
    // The mapper rejects and counts the scan stamped in the past.
    let dir = run("reject", "reject");
    let r = report(&dir);
    let m = &r["mapper"];
    assert_eq!(r["scans"].as_u64(), Some(64), "{r}");
    assert_eq!(r["scans_rejected"].as_u64(), Some(3), "{r}");
    assert_eq!(m["scans_out_of_order"].as_u64(), Some(1), "{r}");
    assert_eq!(m["scans_empty"].as_u64(), Some(2), "{r}");
    assert!(m["beams_invalid"].as_u64().expect("beams") >= 183, "{r}");
    assert_eq!(tum_rows(&dir.join("trajectory.tum")).len(), 61);
    // The robot drove 3 m along x: the trajectory follows.
    let traj = tum_rows(&dir.join("trajectory.tum"));
    let (first, last) = (&traj[0], &traj[traj.len() - 1]);
    let dx = last[1] - first[1];
    assert!((dx - 3.0).abs() < 0.1, "travelled {dx} m");
    // In file order (the default) it is kept, under its own stamp, and the repair counted.
    let dir = run("file-order", "file-order");
    let r = report(&dir);
    assert_eq!(r["scans_rejected"].as_u64(), Some(2), "{r}");
    assert_eq!(r["stamps_repaired"].as_u64(), Some(2), "{r}");
    let traj = tum_rows(&dir.join("trajectory.tum"));
    assert_eq!(traj.len(), 62);
    assert!(
        traj.iter().any(|row| (row[0] - 997.0).abs() < 0.005),
        "stamp kept"
    );
}

#[test]
fn unreadable_input_is_an_error_with_its_name() {
    let out = cloi(&["map", "/no/such/file.clf", "--quiet"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("/no/such/file.clf"));
}

#[test]
fn json_goes_to_stdout_alone_and_the_summary_to_stderr() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("out");
    let out = cloi(&[
        "map",
        "--deterministic",
        "--json",
        "--sim-duration",
        "5",
        "--out",
        dir.to_str().expect("utf-8"),
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let printed: serde_json::Value =
        serde_json::from_slice(&out.stdout).expect("stdout is one JSON document");
    assert_eq!(printed["scans"], report(&dir)["scans"]);
    assert!(
        stderr.contains("mapped ") && stderr.contains("report.json"),
        "{stderr}"
    );
    // Quiet: nothing on stdout without --json, no summary on stderr.
    let out = cloi(&[
        "map",
        "-q",
        "--deterministic",
        "--sim-duration",
        "5",
        "--out",
        dir.to_str().expect("utf-8"),
    ]);
    assert!(out.status.success());
    assert!(out.stdout.is_empty());
    assert!(!String::from_utf8_lossy(&out.stderr).contains("mapped "));
}

#[test]
fn an_input_without_scans_says_what_to_check() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let log = tmp.path().join("odom-only.clf");
    std::fs::write(
        &log,
        "ODOM 0 0 0 0 0 0 1.0 h 1.0\nODOM 0.1 0 0 0 0 0 1.1 h 1.1\n",
    )
    .expect("write log");
    let out = cloi(&[
        "map",
        log.to_str().expect("utf-8"),
        "-q",
        "--deterministic",
        "--out",
        tmp.path().join("out").to_str().expect("utf-8"),
    ]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("no laser scan") && stderr.contains("--laser"),
        "{stderr}"
    );
}

/// Runs `cloi map` on 40 s of the simulated home with `CLOI_MAP_INJECT_FAULT=<thread>`, and
/// returns its exit status and stderr, or fails if it has not ended within two minutes.
fn map_with_injected_fault(thread: &str) -> (std::process::ExitStatus, String) {
    use std::io::Read as _;
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut child = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(["map", "--quiet", "--sim-duration", "40", "--out"])
        .arg(tmp.path().join("out"))
        .env("CLOI_MAP_INJECT_FAULT", thread)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("cloi starts");
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    let status = loop {
        if let Some(status) = child.try_wait().expect("wait") {
            break status;
        }
        if std::time::Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("cloi map with a failing {thread} thread hangs");
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    };
    let mut stderr = String::new();
    child
        .stderr
        .take()
        .expect("stderr")
        .read_to_string(&mut stderr)
        .expect("stderr text");
    (status, stderr)
}

#[test]
fn threaded_run_stops_with_an_error_when_either_thread_fails() {
    for thread in ["frontend", "backend"] {
        let (status, stderr) = map_with_injected_fault(thread);
        assert!(!status.success(), "{thread}: exit 0\n{stderr}");
        let name = if thread == "frontend" {
            "front-end"
        } else {
            "back-end"
        };
        assert!(
            stderr.contains(&format!("injected {name} failure")),
            "{thread}: the panic message is missing\n{stderr}"
        );
    }
}

#[test]
fn report_says_whether_the_run_is_bit_reproducible() {
    let tmp = tempfile::tempdir().expect("tempdir");
    for (flag, expected) in [
        (None, "threaded"),
        (Some("--deterministic"), "deterministic"),
    ] {
        let dir = tmp.path().join(expected);
        let mut args = vec!["map", "--quiet", "--sim-duration", "20"];
        args.extend(flag);
        args.extend(["--out", dir.to_str().expect("utf-8")]);
        let out = cloi(&args);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert_eq!(report(&dir)["reproducibility"], expected);
    }
}

/// The visible files of an output folder with their contents (report.json as its scan count:
/// its wall time and memory differ between runs).
fn output_set(dir: &Path) -> std::collections::BTreeMap<String, Vec<u8>> {
    let mut set = std::collections::BTreeMap::new();
    let Ok(entries) = std::fs::read_dir(dir) else {
        return set;
    };
    for e in entries {
        let e = e.expect("entry");
        let name = e.file_name().to_string_lossy().into_owned();
        if name.starts_with('.') {
            continue;
        }
        let bytes = std::fs::read(e.path()).expect("readable output");
        let bytes = if name == "report.json" {
            let v: serde_json::Value = serde_json::from_slice(&bytes).expect("complete report");
            v["scans"].to_string().into_bytes()
        } else {
            bytes
        };
        set.insert(name, bytes);
    }
    set
}

/// A deterministic map of `seconds` of the simulated home into `dir`.
fn map_home(seconds: &str, dir: &Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_cloi"));
    c.args([
        "map",
        "--deterministic",
        "--quiet",
        "--sim-duration",
        seconds,
        "--out",
    ])
    .arg(dir)
    .stdout(std::process::Stdio::null())
    .stderr(std::process::Stdio::piped());
    c
}

#[test]
fn a_killed_rerun_never_mixes_old_and_new_outputs() {
    let tmp = tempfile::tempdir().expect("tempdir");
    // The two complete sets, for reference.
    let (ref_a, ref_b) = (tmp.path().join("a"), tmp.path().join("b"));
    assert!(map_home("10", &ref_a).status().expect("runs").success());
    let started = std::time::Instant::now();
    assert!(map_home("12", &ref_b).status().expect("runs").success());
    let whole = started.elapsed();
    let (a, b) = (output_set(&ref_a), output_set(&ref_b));
    assert_ne!(a, b);
    assert!(
        a.contains_key("report.json") && a.len() >= 8,
        "{:?}",
        a.keys()
    );

    let out = tmp.path().join("out");
    assert!(map_home("10", &out).status().expect("runs").success());
    // SIGKILL at moments spread over the run, more of them near its end, where the outputs
    // are written.
    let mut seen_new = false;
    for i in 0..12u32 {
        let frac = if i < 4 {
            f64::from(i) / 4.0
        } else {
            0.75 + f64::from(i - 4) * 0.04
        };
        let mut child = map_home("12", &out).spawn().expect("starts");
        std::thread::sleep(whole.mul_f64(frac));
        let _ = child.kill();
        let _ = child.wait();
        let now = output_set(&out);
        // The old set, the new one, or, when the kill cut the commit short, part of one of
        // them without report.json: never files of both runs.
        let part_of = |set: &std::collections::BTreeMap<String, Vec<u8>>| {
            now.iter().all(|(name, bytes)| set.get(name) == Some(bytes))
        };
        let whole = now == a || now == b;
        let cut = !now.contains_key("report.json") && (part_of(&a) || part_of(&b));
        assert!(
            whole || cut,
            "killed at {frac:.2} of the run: files of both runs {:?}",
            now.keys()
        );
        seen_new |= now == b;
    }
    // Finally let it finish: the new set replaces the old one.
    assert!(map_home("12", &out).status().expect("runs").success());
    assert_eq!(output_set(&out), b);
    println!("the kill landed after the commit in some runs: {seen_new}");
}

#[test]
fn a_full_disk_is_a_clear_error_and_keeps_the_previous_outputs() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("out");
    assert!(map_home("10", &out).status().expect("runs").success());
    let before = output_set(&out);
    // A file-size limit makes every write past 4 KiB fail as a full disk does (EFBIG, with
    // SIGXFSZ ignored, in place of ENOSPC): the same error path, without a small filesystem.
    let script = "trap '' XFSZ; ulimit -f 4; exec \"$0\" map --deterministic --quiet \
         --sim-duration 12 --out \"$1\"";
    let o = Command::new("bash")
        .args(["-c", script, env!("CARGO_BIN_EXE_cloi")])
        .arg(&out)
        .output()
        .expect("bash runs");
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "exit 0 on a full disk: {stderr}");
    assert!(
        stderr.contains("writing") && stderr.contains("File too large"),
        "{stderr}"
    );
    assert_eq!(output_set(&out), before, "the previous outputs changed");
}

/// A bag with a camera (the simulator's sensor set C+L) is mapped with its images tracked:
/// every image reaches the camera stage, a textured home ceiling gives the features and
/// frame-to-frame matches the visual odometry needs, and the LiDAR map is the same as with
/// the images left out (with a LiDAR, camera frames do not join the graph yet).
#[test]
fn a_bag_with_a_camera_has_its_images_tracked_and_the_lidar_map_unchanged() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let bag = tmp.path().join("cl.mcap");
    let sim = cloi(&[
        "sim",
        "--world",
        "home",
        "--duration",
        "15",
        "--sensors",
        "C+L",
        "--seed",
        "5",
        "--out",
        bag.to_str().expect("utf-8"),
    ]);
    assert!(
        sim.status.success(),
        "{}",
        String::from_utf8_lossy(&sim.stderr)
    );
    let map = |name: &str, extra: &[&str]| {
        let dir = tmp.path().join(name);
        let mut args = vec![
            "map",
            bag.to_str().expect("utf-8"),
            "--deterministic",
            "--quiet",
        ];
        args.extend_from_slice(extra);
        args.extend_from_slice(&["--out", dir.to_str().expect("utf-8")]);
        let out = cloi(&args);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        dir
    };
    let with = map("with", &[]);
    let without = map("without", &["--no-images"]);
    let r = report(&with);
    let cams = &r["cameras"];
    let track = &cams["tracks"][0];
    eprintln!("{cams:#}");
    // The simulated camera runs at 10 Hz over 15 s.
    let frames = track["frames"].as_u64().expect("frames");
    assert!((140..=151).contains(&frames), "{frames} frames");
    assert_eq!(track["out_of_order"], 0);
    assert_eq!(track["unreadable"], 0);
    assert_eq!(cams["refused"], 0);
    // The home ceiling test (camera_frontend_sim) finds 45-62 features per frame.
    let features = track["features_mean"].as_f64().expect("features");
    assert!(features >= 40.0, "{features} features per frame");
    let tracked = track["tracked_mean"].as_f64().expect("tracked");
    assert!(tracked >= 0.4 * features, "{tracked} of {features} tracked");
    assert!(report(&without).get("cameras").is_none());
    for f in ["trajectory.tum", "gpe.tum", "graph.g2o"] {
        let a = std::fs::read(with.join(f)).expect("output");
        let b = std::fs::read(without.join(f)).expect("output");
        assert!(a == b, "{f} differs with the images");
    }
}

/// A camera-only bag (`--sensors C`) is mapped from its images with the calibration of the
/// simulator's sidecar: every image a frame of `trajectory.tum`, the dead reckoning beside it
/// in `odometry.tum`, the scans of a bag that has them left out; without a calibration, and
/// for two cameras, the run is refused with the reason.
#[test]
fn a_camera_only_bag_maps_from_its_images_and_needs_a_calibration() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let bag = tmp.path().join("c.mcap");
    let bag_path = bag.to_str().expect("utf-8");
    let sim = cloi(&[
        "sim",
        "--world",
        "home",
        "--duration",
        "8",
        "--sensors",
        "C",
        "--seed",
        "5",
        "--out",
        bag_path,
    ]);
    assert!(
        sim.status.success(),
        "{}",
        String::from_utf8_lossy(&sim.stderr)
    );
    let out = tmp.path().join("out");
    let out_path = out.to_str().expect("utf-8");
    let run = |extra: &[&str]| {
        let mut args = vec![
            "map",
            bag_path,
            "--deterministic",
            "--quiet",
            "--out",
            out_path,
        ];
        args.extend_from_slice(extra);
        cloi(&args)
    };
    let ok = run(&["--sensors", "C"]);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let lines = |f: &str| {
        std::fs::read_to_string(out.join(f))
            .expect("output")
            .lines()
            .filter(|l| !l.starts_with('#'))
            .count()
    };
    let visual = &report(&out)["visual"];
    let frames = visual["frames"].as_u64().expect("frames") as usize;
    assert!(frames >= 70, "{visual:#}");
    assert_eq!(lines("trajectory.tum"), frames);
    assert_eq!(lines("gpe.tum"), frames);
    assert_eq!(lines("odometry.tum"), frames);
    assert!(visual["frame_nodes"].as_u64() >= Some(2), "{visual:#}");
    let two = run(&["--sensors", "2C"]);
    assert!(!two.status.success());
    assert!(String::from_utf8_lossy(&two.stderr).contains("2C"));
    std::fs::remove_file(tmp.path().join("c.sim.json")).expect("the sidecar");
    let bare = run(&["--sensors", "C"]);
    assert!(!bare.status.success());
    let why = String::from_utf8_lossy(&bare.stderr);
    assert!(why.contains("--camera-calibration"), "{why}");
}

/// Maps 40 s of the simulated home into `dir`, saving the map to `file`.
fn save_home(dir: &Path, file: &Path) {
    let out = map_home("40", dir)
        .arg("--save")
        .arg(file)
        .output()
        .expect("cloi runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn a_saved_map_reads_back_whole_and_a_damaged_one_is_refused_with_its_reason() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (dir, file) = (tmp.path().join("run"), tmp.path().join("home.cloimap"));
    save_home(&dir, &file);
    let shown = tmp.path().join("shown");
    let show = |path: &Path, out: Option<&Path>| {
        let mut c = Command::new(env!("CARGO_BIN_EXE_cloi"));
        c.arg("show-map").arg(path);
        if let Some(o) = out {
            c.arg("--out").arg(o);
        }
        c.output().expect("cloi runs")
    };
    let o = show(&file, Some(&shown));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).expect("JSON");
    let r = report(&dir);
    assert_eq!(summary["nodes"], r["nodes"]);
    assert_eq!(summary["edges"], r["edges"]);
    assert_eq!(summary["loop_edges"], r["loop_edges"]["in_graph"]);
    assert_eq!(summary["submaps"], r["mapper"]["submaps"]);
    assert_eq!(summary["grid"]["resolution_m"], 0.05);
    // The grid composed from the file alone is the run's own map, byte for byte.
    for f in ["map.pgm", "map.yaml"] {
        assert_eq!(
            std::fs::read(shown.join(f)).expect("shown"),
            std::fs::read(dir.join(f)).expect("mapped"),
            "{f}"
        );
    }
    let bytes = std::fs::read(&file).expect("map file");
    let damaged = tmp.path().join("damaged.cloimap");
    let mut flipped = bytes.clone();
    flipped[bytes.len() / 2] ^= 0x10;
    let mut version = bytes.clone();
    version[8] = 9;
    for (what, b, reason) in [
        ("truncated", &bytes[..bytes.len() - 100], "truncated"),
        ("flipped", &flipped[..], "corrupt"),
        ("version", &version[..], "version 9"),
        ("empty", &[][..], "truncated"),
    ] {
        std::fs::write(&damaged, b).expect("write");
        let o = show(&damaged, None);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.contains(reason), "{what}: {err}");
        assert!(!err.contains("panicked"), "{what}: {err}");
    }
}

/// Distances, ascending, from each pose of `track` stamped `from` or later to the pose of
/// `reference` at the same time (within 0.1 s; TUM rows).
fn distances_after(track: &[Vec<f64>], reference: &[Vec<f64>], from: f64) -> Vec<f64> {
    let mut d: Vec<f64> = track
        .iter()
        .filter(|g| g[0] >= from)
        .filter_map(|g| {
            let m = reference
                .iter()
                .min_by(|a, b| (a[0] - g[0]).abs().total_cmp(&(b[0] - g[0]).abs()))?;
            ((m[0] - g[0]).abs() < 0.1).then(|| (m[1] - g[1]).hypot(m[2] - g[2]))
        })
        .collect();
    d.sort_by(f64::total_cmp);
    d
}

#[test]
fn a_saved_home_is_localized_in_by_another_run_from_a_given_pose_and_from_nowhere() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (dir, file) = (tmp.path().join("map"), tmp.path().join("home.cloimap"));
    save_home(&dir, &file);
    let mapped = tum_rows(&dir.join("trajectory.tum"));
    let localize = |name: &str, initial: Option<&str>| {
        let out_dir = tmp.path().join(name);
        let mut c = Command::new(env!("CARGO_BIN_EXE_cloi"));
        // The same route with another draw of the sensor noise.
        c.arg("localize")
            .arg(&file)
            .args(["--deterministic", "--quiet", "--sim-duration", "40"])
            .args(["--sim-seed", "7", "--out"])
            .arg(&out_dir);
        if let Some(p) = initial {
            c.arg("--initial-pose").arg(p);
        }
        let out = c.output().expect("cloi runs");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        (report(&out_dir), tum_rows(&out_dir.join("gpe.tum")))
    };
    for (name, initial) in [("given", Some("0,0,0")), ("global", None)] {
        let (r, gpe) = localize(name, initial);
        let l = &r["localization"];
        eprintln!("{name}: {l:#}");
        // Nothing was added to the map.
        assert_eq!(r["keyframes"], 0);
        assert_eq!(l["lost"], 0, "{name}");
        let fraction = l["localized_fraction"].as_f64().expect("fraction");
        let fix = l["time_to_first_fix_s"].as_f64().expect("a fix");
        if initial.is_some() {
            assert_eq!(fraction, 1.0);
        } else {
            assert!(fix <= 5.0, "first fix after {fix} s");
            assert!(fraction >= 0.85, "{fraction}");
        }
        // Once localized, the pose is where the map's own run was at that time (its scans
        // come within 0.1 s of each other).
        let errors = distances_after(&gpe, &mapped, gpe[0][0] + fix + 0.5);
        assert!(
            errors.len() > 100,
            "{name}: {} poses compared",
            errors.len()
        );
        let (median, worst) = (errors[errors.len() / 2], errors[errors.len() - 1]);
        eprintln!("{name}: against the map's run median {median:.3} m, max {worst:.3} m");
        assert!(median < 0.05 && worst < 0.12, "{name}: {median} {worst}");
    }
}

#[test]
fn a_later_session_extends_a_saved_home_and_saves_the_grown_map() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (dir, file) = (tmp.path().join("map"), tmp.path().join("home.cloimap"));
    save_home(&dir, &file);
    let first = report(&dir);
    // What one session driving the whole 60 s makes of it: the reference the second session's
    // poses are compared with.
    let whole = tmp.path().join("whole");
    let o = map_home("60", &whole).output().expect("cloi runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let reference = tum_rows(&whole.join("trajectory.tum"));
    // The second session: the same route for 60 s with another draw of the sensor noise, found
    // in the map by searching it whole, then mapping on past where the first session ended.
    let (out_dir, grown) = (tmp.path().join("second"), tmp.path().join("grown.cloimap"));
    let o = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(["map", "--deterministic", "--quiet", "--sim-duration", "60"])
        .args(["--sim-seed", "7", "--load"])
        .arg(&file)
        .arg("--save")
        .arg(&grown)
        .arg("--out")
        .arg(&out_dir)
        .output()
        .expect("cloi runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = report(&out_dir);
    let (session, l) = (&r["session"], &r["localization"]);
    eprintln!("{session:#} {l:#}");
    assert_eq!(session["joined"], true);
    // Its keyframes continue the map's serials, and the map grew by them.
    let first_serial = session["first_serial"].as_u64().expect("a serial");
    assert!(first_serial > 0 && first_serial <= first["keyframes"].as_u64().expect("count"));
    assert!(r["keyframes"].as_u64().expect("count") > 50, "{r:#}");
    assert!(r["nodes"].as_u64() > first["nodes"].as_u64(), "{r:#}");
    let fix = l["time_to_first_fix_s"].as_f64().expect("a fix");
    assert!(fix <= 5.0, "first fix after {fix} s");
    // After the join the session's poses are where the single session put them (its scans
    // come within 0.1 s of each other).
    let ours = tum_rows(&out_dir.join("trajectory.tum"));
    let errors = distances_after(&ours, &reference, ours[0][0] + fix + 0.5);
    assert!(errors.len() > 200, "{} poses compared", errors.len());
    let (median, worst) = (errors[errors.len() / 2], errors[errors.len() - 1]);
    eprintln!("against one session: median {median:.3} m, max {worst:.3} m");
    assert!(median < 0.05 && worst < 0.15, "{median} {worst}");
    // The grown map reads back with every node of the run.
    let o = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .arg("show-map")
        .arg(&grown)
        .output()
        .expect("cloi runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).expect("JSON");
    assert_eq!(summary["nodes"], r["nodes"]);
}
