//! Golden tests of `cloi map` on real logs, against the GMapping reference with the metric of
//! `cloi eval ref` (in the laser's frame, as the reference poses are):
//! * the whole `mit-csail.clf` (1,988 scans, 7 minutes): the relation error of the final
//!   trajectory beats GMapping's published 0.049 m, and two deterministic runs are identical;
//! * the whole `fr079.clf` (4,934 scans, 18 minutes): beats GMapping's published 0.061 m;
//! * a cut of `intel.clf` (the first 4,000 scans, 13 minutes, with its first big loops): the
//!   error stays under its golden bound, and the two-thread schedule and a deliberately
//!   delayed back-end keep the real-time pose free of jumps;
//! * the whole `intel.clf` (13,631 scans, 45 minutes), with the preset and with more loop
//!   candidates per keyframe (a perturbation that used to bend the map to 0.73 m): both stay
//!   under the error intel had before the loop-search window was taken from the submap's
//!   anchor (0.0515 m);
//! * the whole process of `cloi map` on the whole `intel.clf` stays under each profile's
//!   memory ceiling (its proven static footprint plus 24 MiB);
//! * a soak: four hours of the simulated home (68,000 scans, the graph pruned throughout) keep
//!   the process's resident memory flat from the middle of the run to its end;
//! * each of the three whole logs converted to a ROS 2 bag (`cloi convert`: messages in stamp
//!   order, as a robot delivers them) maps within 10 % of the relation error of the same log
//!   read from the `.clf`, without odometry gaps. The bag of intel differs from its `.clf` in
//!   order, not only in form: about 500 of its scans bear stamps earlier than the line before
//!   them, so the bag delivers them in another order than the log (which the `.clf` run keeps,
//!   repairing the stamps). On the whole log that costs 7 %; on the 4,000-scan cut above, 17 %,
//!   and the `.clf` itself with its lines sorted by stamp gives the bag's result to the bit.
//!
//! Release mode: `cargo test --release -p cloi-host --features golden --test golden_map`.

use std::mem::size_of;
use std::path::Path;
use std::process::Command;
use std::time::Instant;

use cloi_core::profile::{AirportResources, HomeResources, OfficeResources, AIRPORT, HOME, OFFICE};
use cloi_core::Se2;
use cloi_host::eval::relations::{relations_from_reference, score, PlanarTrajectory};
use cloi_host::io::convert::carmen_to_bag;
use cloi_host::map::output::proc_status_bytes;

fn map(log: &Path, out: &Path, extra: &[&str]) -> serde_json::Value {
    let mut args = vec![
        "map",
        log.to_str().expect("utf-8"),
        "--quiet",
        "--out",
        out.to_str().expect("utf-8"),
    ];
    args.extend_from_slice(extra);
    let o = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(&args)
        .output()
        .expect("cloi runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = std::fs::read_to_string(out.join("report.json")).expect("report");
    serde_json::from_str(&text).expect("json")
}

/// The relation error of `dir/trajectory.tum` in the laser's frame (the reference holds the
/// laser's poses; the mounting is the one `cloi map` reports).
fn relation_error(
    dir: &Path,
    report: &serde_json::Value,
    reference: &Path,
    min_pairs: usize,
) -> f64 {
    let o = &report["input"]["laser_offset"];
    let laser = Se2::new(
        o[0].as_f64().expect("laser x"),
        o[1].as_f64().expect("laser y"),
        o[2].as_f64().expect("laser theta"),
    );
    let traj = PlanarTrajectory::load_tum(&dir.join("trajectory.tum"))
        .expect("trajectory")
        .in_sensor_frame(&laser);
    let reference = PlanarTrajectory::load_reference(reference).expect("reference");
    let rels = relations_from_reference(&reference, 1.0);
    let s = score(&traj, &rels, 0.0).expect("score");
    assert!(s.pairs_used > min_pairs, "{s:?}");
    s.trans_mean_m
}

#[test]
fn csail_beats_gmapping_and_repeats_exactly() {
    let Some(log) = cloi_host::dataset::shared_file("carmen/mit-csail.clf") else {
        return;
    };
    let Some(reference) =
        cloi_host::dataset::shared_file("carmen/mit-csail.gfs_reference_poses.txt")
    else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    let ra = map(&log, &a, &["--deterministic"]);
    map(&log, &b, &["--deterministic"]);
    for f in ["trajectory.tum", "gpe.tum", "graph.g2o", "map.pgm"] {
        assert_eq!(
            std::fs::read(a.join(f)).expect("a"),
            std::fs::read(b.join(f)).expect("b"),
            "{f} differs between two deterministic runs"
        );
    }
    let err = relation_error(&a, &ra, &reference, 500);
    println!("mit-csail: relation error {err:.4} m, report {ra}");
    // Measured 0.0412 m (2026-12-05); GMapping's published figure is the bound.
    assert!(err < 0.049, "relation error {err} m");
    assert!(ra["gpe_max_jump_m"].as_f64().expect("jump") < 0.05, "{ra}");
}

#[test]
fn fr079_beats_gmapping() {
    let Some(log) = cloi_host::dataset::shared_file("carmen/fr079.clf") else {
        return;
    };
    let Some(reference) = cloi_host::dataset::shared_file("carmen/fr079.gfs_reference_poses.txt")
    else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let a = tmp.path().join("a");
    let ra = map(&log, &a, &["--deterministic"]);
    // The one log of the three whose laser is off the robot's centre (0.04 m behind it).
    assert_eq!(ra["input"]["laser_offset"][0].as_f64(), Some(-0.04), "{ra}");
    let err = relation_error(&a, &ra, &reference, 500);
    println!("fr079: relation error {err:.4} m, report {ra}");
    // Measured 0.0372 m (2026-12-05); GMapping's published figure is the bound.
    assert!(err < 0.061, "relation error {err} m");
    assert!(ra["gpe_max_jump_m"].as_f64().expect("jump") < 0.05, "{ra}");
}

#[test]
fn intel_cut_stays_within_its_bound_and_has_no_jumps() {
    let Some(log) = cloi_host::dataset::shared_file("carmen/intel.clf") else {
        return;
    };
    let Some(reference) = cloi_host::dataset::shared_file("carmen/intel.gfs_reference_poses.txt")
    else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let a = tmp.path().join("a");
    let cut = ["--max-scans", "4000"];
    let ra = map(&log, &a, &[&cut[..], &["--deterministic"]].concat());
    let err = relation_error(&a, &ra, &reference, 500);
    println!("intel first 4000 scans: relation error {err:.4} m, report {ra}");
    // Measured 0.0422 m (2026-12-05); about 10 % margin. A cut that misses its first big loops
    // (as when the loop-search window shrinks after every local closure) scores 0.6 m.
    assert!(err < 0.046, "relation error {err} m");
    assert_eq!(ra["stamps_repaired"].as_u64(), Some(494), "{ra}");
    assert!(ra["gpe_max_jump_m"].as_f64().expect("jump") < 0.05, "{ra}");

    // Two threads, and a back-end held back by 30 s of data: no jumps either.
    for (i, extra) in [&[][..], &["--backend-delay", "30"][..]].iter().enumerate() {
        let dir = tmp.path().join(format!("t{i}"));
        let r = map(&log, &dir, &[&cut[..], extra].concat());
        assert!(r["gpe_max_jump_m"].as_f64().expect("jump") < 0.05, "{r}");
        assert_eq!(r["scans"], ra["scans"]);
    }
}

#[test]
fn intel_stays_consistent_when_loop_search_changes() {
    let Some(log) = cloi_host::dataset::shared_file("carmen/intel.clf") else {
        return;
    };
    let Some(reference) = cloi_host::dataset::shared_file("carmen/intel.gfs_reference_poses.txt")
    else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let five = tmp.path().join("five.toml");
    std::fs::write(&five, "[loop_closure]\nmax_candidates = 5\n").expect("config");
    for (name, extra) in [
        ("preset", vec!["--deterministic"]),
        (
            "5 candidates",
            vec!["--deterministic", "--config", five.to_str().expect("utf-8")],
        ),
    ] {
        let dir = tmp.path().join(name.replace(' ', "-"));
        let r = map(&log, &dir, &extra);
        let err = relation_error(&dir, &r, &reference, 5000);
        println!("intel ({name}): relation error {err:.4} m, report {r}");
        // Measured 0.0375 m (preset) and 0.0374 m (5 candidates) on 2026-12-05; the bound is
        // the preset's figure before the loop-search window followed each submap's anchor.
        assert!(err < 0.0515, "{name}: relation error {err} m");
        assert!(r["gpe_max_jump_m"].as_f64().expect("jump") < 0.05, "{r}");
        if name == "preset" {
            assert_within_memory_ceiling(&r, OFFICE.name, size_of::<OfficeResources>());
        }
    }
}

/// The whole process's peak resident memory (what `cloi map` reports, read after every
/// output but the report was written) is at most the profile's proven static footprint plus
/// 24 MiB for the host: input buffers, the map image and the output files.
fn assert_within_memory_ceiling(report: &serde_json::Value, profile: &str, footprint: usize) {
    let peak = report["peak_rss_bytes"]
        .as_u64()
        .expect("peak_rss_bytes on Linux");
    let ceiling = footprint as u64 + (24 << 20);
    println!(
        "{profile}: peak RSS {:.1} MiB, ceiling {:.1} MiB (footprint {:.1} MiB)",
        peak as f64 / 1048576.0,
        ceiling as f64 / 1048576.0,
        footprint as f64 / 1048576.0
    );
    assert!(
        peak <= ceiling,
        "{profile}: peak RSS {peak} B above {ceiling} B"
    );
}

/// The largest shared log mapped in the two other profiles stays within their memory
/// ceilings too (office: the intel test above). Measured 2026-12-03: home 27.3 MiB (ceiling
/// 34.4), office 64.9 (68.6), airport 155.9 (182.0); before the pools
/// were allocated on the heap element by element, 186, 220 and 333 MiB.
#[test]
fn intel_maps_within_each_profiles_memory_ceiling() {
    let Some(log) = cloi_host::dataset::shared_file("carmen/intel.clf") else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    for (spec, footprint) in [
        (HOME, size_of::<HomeResources>()),
        (AIRPORT, size_of::<AirportResources>()),
    ] {
        let dir = tmp.path().join(spec.name);
        let r = map(&log, &dir, &["--profile", spec.name]);
        assert_within_memory_ceiling(&r, spec.name, footprint);
    }
}

/// A soak (issue 19): `cloi map` over four hours of the simulated home in the home profile,
/// its resident memory sampled every 50 ms. Mapping a place for longer must not cost more
/// memory: from the middle of the run (the graph has been pruned for an hour by then) to 95 %
/// of it (the last samples hold the outputs being composed), the resident memory may not grow
/// by more than 1 MiB, which is what keeping 32 bytes per scan of the second half would
/// take. The whole run stays within the home ceiling. `bench/soak.sh --hours 24` is the long
/// version (office: +0.00 MiB over the second half).
#[test]
fn four_hours_of_the_home_keep_memory_flat() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("soak");
    let mut child = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(["map", "--sim-world", "home", "--sim-duration", "14400"])
        .args(["--profile", "home", "--deterministic", "--quiet", "--out"])
        .arg(&out)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("cloi runs");
    let mut samples = Vec::new();
    let status = loop {
        if let Some(status) = child.try_wait().expect("wait") {
            break status;
        }
        if let Some(rss) = proc_status_bytes(&child.id().to_string(), "VmRSS") {
            samples.push(rss);
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    };
    let mut stderr = String::new();
    if let Some(mut e) = child.stderr.take() {
        std::io::Read::read_to_string(&mut e, &mut stderr).expect("stderr");
    }
    assert!(status.success(), "{stderr}");
    let text = std::fs::read_to_string(out.join("report.json")).expect("report");
    let report: serde_json::Value = serde_json::from_str(&text).expect("json");
    let pruned = report["mapper"]["nodes_pruned"]
        .as_u64()
        .expect("nodes_pruned");
    let n = samples.len();
    assert!(n >= 100, "only {n} samples of the run");
    let (half, end) = (n / 2, n * 95 / 100);
    let at_half = samples[half];
    let most = samples[half..=end].iter().copied().max().expect("samples");
    let mib = |b: u64| b as f64 / 1048576.0;
    println!(
        "soak: {} scans, {pruned} nodes pruned, {n} samples, RSS {:.2} MiB at 50 %, at most \
         {:.2} MiB up to 95 %, {:.2} MiB at 95 %",
        report["scans"],
        mib(at_half),
        mib(most),
        mib(samples[end])
    );
    assert!(pruned > 5_000, "the soak must prune: {pruned} nodes");
    assert!(
        most <= at_half + (1 << 20),
        "resident memory grew from {at_half} B to {most} B in the second half"
    );
    assert_within_memory_ceiling(&report, HOME.name, size_of::<HomeResources>());
}

#[test]
fn bags_map_within_ten_percent_of_their_logs() {
    for name in ["mit-csail", "fr079", "intel"] {
        let Some(log) = cloi_host::dataset::shared_file(&format!("carmen/{name}.clf")) else {
            return;
        };
        let Some(reference) =
            cloi_host::dataset::shared_file(&format!("carmen/{name}.gfs_reference_poses.txt"))
        else {
            return;
        };
        let started = Instant::now();
        let tmp = tempfile::tempdir().expect("tempdir");
        let bag = tmp.path().join(format!("{name}.mcap"));
        carmen_to_bag(&log, &bag, true, None).expect("conversion");
        let extra = ["--deterministic"];
        let (from_log, from_bag) = (tmp.path().join("clf"), tmp.path().join("bag"));
        // The two runs side by side (deterministic: timing cannot change their results).
        let (rl, rb) = std::thread::scope(|s| {
            let clf = s.spawn(|| map(&log, &from_log, &extra));
            let rb = map(&bag, &from_bag, &extra);
            (clf.join().expect("the .clf run"), rb)
        });
        let el = relation_error(&from_log, &rl, &reference, 500);
        let eb = relation_error(&from_bag, &rb, &reference, 500);
        println!(
            "{name}: relation error .clf {el:.4} m, bag {eb:.4} m ({:.1} s), bag sync {}, \
             bag mapper {}",
            started.elapsed().as_secs_f64(),
            rb["sync"],
            rb["mapper"]
        );
        // The bag carries the mounting (tf_static) and every scan the log has.
        assert_eq!(
            rb["input"]["laser_offset"], rl["input"]["laser_offset"],
            "{name}"
        );
        assert_eq!(rb["scans"], rl["scans"], "{name}");
        // Every scan was seeded by odometry around its time, none after a give-up.
        assert_eq!(
            rb["mapper"]["odometry_gaps"].as_u64(),
            Some(0),
            "{name}: {rb}"
        );
        assert_eq!(rb["sync"]["waited"].as_u64(), Some(0), "{name}: {rb}");
        assert_eq!(rb["sync"]["evicted"].as_u64(), Some(0), "{name}: {rb}");
        assert!(
            eb <= 1.1 * el,
            "{name}: bag relation error {eb} m, .clf {el} m"
        );
    }
}
