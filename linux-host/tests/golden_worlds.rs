//! The CI cut of the generated-building benchmark (`bench/generalize.sh --quick`, issue 15):
//! five buildings from seeds fixed before any result was seen (three small, two medium, two
//! without a gyro), one lap each, mapped by `cloi map --sim-world` in the deterministic
//! schedule and scored with `cloi eval ate` against the simulator's exact ground truth.
//!
//! Bounds (issue 15's targets for generated worlds): no building above 0.3 m final ATE RMSE,
//! median at most 0.05 m, p90 at most 0.10 m (nearest rank; with five runs, the worst). One
//! more target of the issue is not met yet and so not asserted: no wrong loop closure acting
//! on the map (`bench/generalize.sh` counts them; gen:205:m:nogyro keeps one).
//!
//! Release mode: `cargo test --release -p cloi-host --features golden --test golden_worlds`.

use std::path::Path;
use std::process::Command;

const WORLDS: [&str; 5] = [
    "gen:101:s",
    "gen:105:s:nogyro",
    "gen:109:s",
    "gen:201:m",
    "gen:205:m:nogyro",
];

fn cloi(args: &[&str]) -> String {
    let o = Command::new(env!("CARGO_BIN_EXE_cloi"))
        .args(args)
        .output()
        .expect("cloi runs");
    assert!(
        o.status.success(),
        "cloi {args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8(o.stdout).expect("utf-8")
}

fn ate_rmse(trajectory: &Path, reference: &Path) -> f64 {
    let text = cloi(&[
        "eval",
        "ate",
        "--trajectory",
        trajectory.to_str().expect("utf-8"),
        "--reference",
        reference.to_str().expect("utf-8"),
    ]);
    let v: serde_json::Value = serde_json::from_str(&text).expect("json");
    v["translation_m"]["rmse"].as_f64().expect("rmse")
}

/// Simulates one lap of `world` for its ground truth, maps the same simulation and returns
/// the final and real-time ATE RMSE.
fn run(world: &str, dir: &Path) -> (f64, f64) {
    let seed = world.split(':').nth(1).expect("seed");
    run_session(world, "0", seed, "office", false, dir)
}

/// [`run`] of mapping session `session` of `world` (its changes up to it applied) with the
/// simulator's seed `seed` and the memory profile `profile`; from the simulation's bag when
/// `from_bag` (as a robot's recording arrives), else from the simulator directly.
fn run_session(
    world: &str,
    session: &str,
    seed: &str,
    profile: &str,
    from_bag: bool,
    dir: &Path,
) -> (f64, f64) {
    let bag = dir.join("sim.mcap");
    let sim = cloi(&[
        "sim",
        "--world",
        world,
        "--session",
        session,
        "--sensors",
        "L",
        "--laps",
        "1",
        "--seed",
        seed,
        "--out",
        bag.to_str().expect("utf-8"),
    ]);
    let duration = sim
        .lines()
        .find_map(|l| l.strip_prefix("duration: ")?.strip_suffix(" s"))
        .expect("the simulator prints the lap's duration");
    let out = dir.join("map");
    let out_dir = out.to_str().expect("utf-8");
    if from_bag {
        let input = bag.to_str().expect("utf-8");
        cloi(&[
            "-q",
            "map",
            input,
            "--profile",
            profile,
            "--deterministic",
            "--out",
            out_dir,
        ]);
    } else {
        cloi(&[
            "-q",
            "map",
            "--sim-world",
            world,
            "--sim-duration",
            duration,
            "--sim-seed",
            seed,
            "--sim-session",
            session,
            "--profile",
            profile,
            "--deterministic",
            "--out",
            out_dir,
        ]);
    }
    let truth = dir.join("sim.gt.tum");
    (
        ate_rmse(&out.join("trajectory.tum"), &truth),
        ate_rmse(&out.join("gpe.tum"), &truth),
    )
}

#[test]
fn generated_buildings_map_within_the_generalization_bounds() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut finals = Vec::new();
    for world in WORLDS {
        let dir = tmp.path().join(world.replace(':', "_"));
        std::fs::create_dir_all(&dir).expect("dir");
        let (fin, rt) = run(world, &dir);
        println!("{world}: final ATE RMSE {fin:.3} m, real-time {rt:.3} m");
        finals.push((fin, world));
    }
    for &(fin, world) in &finals {
        assert!(fin <= 0.3, "{world} failed: final ATE RMSE {fin} m");
    }
    let mut sorted: Vec<f64> = finals.iter().map(|f| f.0).collect();
    sorted.sort_by(f64::total_cmp);
    let rank = |q: f64| sorted[((q * sorted.len() as f64) as usize).min(sorted.len() - 1)];
    let (median, p90) = (rank(0.5), rank(0.9));
    println!("median {median:.3} m, p90 {p90:.3} m");
    assert!(
        median <= 0.05,
        "median final ATE RMSE {median} m: {finals:?}"
    );
    assert!(p90 <= 0.10, "p90 final ATE RMSE {p90} m: {finals:?}");
}

/// The simulated home's route has a 100 s LiDAR outage (its fault schedule); with seed 102 of
/// its second session the dead reckoning across it ends 1.7 m and 21 degrees off, beyond any
/// window, so the two halves of the lap are joined only by the far search, along a corridor
/// where the confirming keyframes' matches slide (no evidence either way, not a refutation).
/// One lap recorded and mapped as a new map, as the bench's `alone` run of session 2
/// (`bench/lifelong.py --fresh`): 2.17 m final ATE before the far search counted only real
/// evidence (mapped from the simulator directly, the same lap happens to rejoin by a windowed
/// loop: 0.10 m either way).
#[test]
fn a_home_whose_lidar_fails_for_100_s_is_joined_again_by_the_far_search() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (fin, rt) = run_session("home", "2", "102", "home", true, tmp.path());
    println!("home session 2, seed 102: final ATE RMSE {fin:.3} m, real-time {rt:.3} m");
    let report: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(tmp.path().join("map/report.json")).expect("report"),
    )
    .expect("json");
    assert!(
        report["mapper"]["far_confirmed"].as_u64() >= Some(1),
        "{:#}",
        report["mapper"]
    );
    assert!(fin <= 0.3, "final ATE RMSE {fin} m");
}

/// Headings of a TUM file (stamp, yaw), in file order.
fn headings(path: &Path) -> Vec<(f64, f64)> {
    cloi_host::io::tum::read_tum(path)
        .expect("tum")
        .iter()
        .map(|p| (p.t, p.q.euler_angles().2))
        .collect()
}

/// The guide robot (a 30 m LiDAR at 1 Hz, the airport profile) drives 390 m along a single
/// straight wall, 3 m from it, and back. The wall fixes the heading at every scan; the local
/// point map must not turn it: refilled from 10 cm submap cells, the wall's staircase let the
/// real-time heading drift 21 degrees by the far end (0.04 degrees a scan); restarted from the
/// scan itself, the largest error is 0.7 to 1.2 degrees (simulator seeds 1 to 4).
#[test]
fn the_guide_robots_heading_holds_along_one_long_wall() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let world = tmp.path().join("wall.toml");
    std::fs::write(
        &world,
        "name = \"one wall\"\nceiling_height = 3.0\nrobot = \"guide\"\n\n[[wall]]\n\
         points = [[0, 0], [400, 0]]\n\n[route]\nstart = [5, 3]\n\
         legs = [{ type = \"waypoints\", points = [[395, 3]] }]\n",
    )
    .expect("world file");
    let bag = tmp.path().join("wall.mcap");
    let (world, bag_path) = (world.to_str().expect("utf-8"), bag.to_str().expect("utf-8"));
    cloi(&[
        "sim",
        "--world",
        world,
        "--sensors",
        "L",
        "--laps",
        "1",
        "--seed",
        "1",
        "--out",
        bag_path,
    ]);
    let out = tmp.path().join("map");
    let out_dir = out.to_str().expect("utf-8");
    cloi(&[
        "-q",
        "map",
        bag_path,
        "--profile",
        "airport",
        "--deterministic",
        "--out",
        out_dir,
    ]);
    let truth = headings(&tmp.path().join("wall.gt.tum"));
    let estimate = headings(&out.join("gpe.tum"));
    let (g0, e0) = (truth[0].1, estimate[0].1);
    let mut worst: f64 = 0.0;
    for &(t, h) in &estimate {
        let i = truth.partition_point(|g| g.0 < t).min(truth.len() - 1);
        let e = (h - e0) - (truth[i].1 - g0);
        worst = worst.max(e.sin().atan2(e.cos()).abs().to_degrees());
    }
    println!(
        "one wall: largest real-time heading error {worst:.2} deg over {} scans",
        estimate.len()
    );
    assert!(estimate.len() > 900, "{} scans mapped", estimate.len());
    assert!(worst <= 2.0, "real-time heading off by {worst:.2} deg");
}

/// One mapping session of the lifelong soak: session `k` driven in the home's world of
/// session `world` (its changes up to it applied) for 600 s, extending the map of session
/// `k - 1` (`cloi map --load`) and saved for the next. Returns the final ATE RMSE, the saved
/// map's size in bytes and the run's report.
fn soak_session(k: u32, world: u32, dir: &Path) -> (f64, u64, serde_json::Value) {
    let path = |name: String| dir.join(name).to_str().expect("utf-8").to_owned();
    let bag = path(format!("s{k}.mcap"));
    let (world, seed) = (world.to_string(), (100 + k).to_string());
    cloi(&[
        "sim",
        "--world",
        "home",
        "--session",
        &world,
        "--seed",
        &seed,
        "--sensors",
        "L",
        "--duration",
        "600",
        "--quiet",
        "--out",
        &bag,
    ]);
    let (map, out) = (path(format!("s{k}.cloimap")), path(format!("s{k}")));
    let mut args = vec![
        "-q",
        "map",
        &bag,
        "--deterministic",
        "--save",
        &map,
        "--out",
        &out,
    ];
    let previous = path(format!("s{}.cloimap", k.saturating_sub(1)));
    if k == 0 {
        args.extend(["--profile", "home"]);
    } else {
        args.extend(["--load", &previous, "--initial-pose", "0,0,0"]);
    }
    cloi(&args);
    std::fs::remove_file(&bag).expect("the session's bag");
    let out = Path::new(&out);
    let ate = ate_rmse(
        &out.join("trajectory.tum"),
        &dir.join(format!("s{k}.gt.tum")),
    );
    let bytes = std::fs::metadata(&map).expect("the saved map").len();
    let report =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).expect("report"))
            .expect("json");
    (ate, bytes, report)
}

/// The CI cut of the lifelong soak (`bench/lifelong.py --sessions 100 --duration 600 --cycle
/// 3`, issue 17): ten sessions of ten minutes in the home, each extending the map the one
/// before saved, while the home's three sets of changes (furniture moved, a door closed,
/// clutter) come and go. Ten sessions fill the home profile's node pool once, so the graph is
/// pruned on the way. Every session joins the saved map, no keyframe is dropped for want of
/// room, the pruning shrinks the saved file, no session fails (final ATE above 0.3 m), and the
/// last session is no worse than 1.2 times the first that extended a map (session 1; session
/// 0 maps an empty world from scratch and is not the same kind of run).
#[test]
fn a_home_mapped_in_ten_sessions_stays_bounded_and_right() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut sessions = Vec::new();
    for k in 0..10u32 {
        let world = if k == 0 { 0 } else { (k - 1) % 3 + 1 };
        let (ate, bytes, r) = soak_session(k, world, tmp.path());
        let m = &r["mapper"];
        let count = |key: &str| m[key].as_u64().unwrap_or_else(|| panic!("{key}: {m:#}"));
        let (prunes, dropped) = (count("prunes"), count("keyframes_dropped"));
        println!(
            "session {k} (world {world}): final ATE RMSE {ate:.3} m, map file {bytes} B, \
             prunes {prunes}, keyframes dropped {dropped}"
        );
        if k > 0 {
            assert_eq!(r["session"]["joined"].as_bool(), Some(true), "session {k}");
        }
        assert_eq!(dropped, 0, "session {k} dropped keyframes");
        assert!(ate <= 0.3, "session {k} failed: final ATE RMSE {ate} m");
        sessions.push((ate, bytes, prunes));
    }
    let pruned: Vec<usize> = (1..sessions.len()).filter(|&k| sessions[k].2 > 0).collect();
    assert!(!pruned.is_empty(), "the pool never filled: {sessions:?}");
    for &k in &pruned {
        assert!(
            sessions[k].1 < sessions[k - 1].1,
            "session {k} pruned but its map grew: {sessions:?}"
        );
    }
    let (first, last) = (sessions[1].0, sessions[sessions.len() - 1].0);
    assert!(
        last <= 1.2 * first,
        "session 9's final ATE {last} m against session 1's {first} m"
    );
}

/// Sensor set C (one ceiling-tilted fisheye, wheels and gyro, no LiDAR) through the real
/// `cloi map --sensors C` path: the first 120 s of the home's route, simulated with seed 21
/// (fixed before any result was seen) and mapped from its bag, the camera's calibration taken
/// from the simulator's sidecar. Without visual loop closure the map is the visual odometry's
/// trajectory of keyframes. Over seeds 21 to 25 of this cut the final ATE RMSE was 0.102,
/// 0.130, 0.160, 0.107 and 0.075 m, the wheel+gyro dead reckoning's of the same runs
/// (`odometry.tum`) 0.101, 0.133, 0.190, 0.247 and 0.084 m: better or level, not by a margin
/// to assert on one seed. So the test asserts every image posed (the odometry covers each), a
/// frame node per visual keyframe, and this seed's run (0.102 m) within 0.15 m, final and
/// real-time alike (the worst of the five seeds is 0.160 m).
#[test]
fn a_camera_only_home_run_maps_from_its_bag() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let bag = tmp.path().join("sim.mcap");
    let bag_path = bag.to_str().expect("utf-8");
    cloi(&[
        "sim",
        "--world",
        "home",
        "--sensors",
        "C",
        "--duration",
        "120",
        "--seed",
        "21",
        "--quiet",
        "--out",
        bag_path,
    ]);
    let out = tmp.path().join("map");
    cloi(&[
        "-q",
        "map",
        bag_path,
        "--sensors",
        "C",
        "--deterministic",
        "--out",
        out.to_str().expect("utf-8"),
    ]);
    let truth = tmp.path().join("sim.gt.tum");
    let camera = ate_rmse(&out.join("trajectory.tum"), &truth);
    let realtime = ate_rmse(&out.join("gpe.tum"), &truth);
    let wheels = ate_rmse(&out.join("odometry.tum"), &truth);
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).expect("report"))
            .expect("json");
    let visual = &report["visual"];
    println!(
        "home, sensor set C, seed 21, 120 s: final ATE RMSE {camera:.3} m, real-time \
         {realtime:.3} m, wheel+gyro {wheels:.3} m; {visual:#}"
    );
    assert!(visual["frame_nodes"].as_u64() >= Some(100), "{visual:#}");
    assert_eq!(visual["frames_without_odometry"].as_u64(), Some(0));
    assert_eq!(
        visual["frame_nodes"].as_u64(),
        visual["keyframes"].as_u64(),
        "{visual:#}"
    );
    assert!(camera <= 0.15, "final ATE RMSE {camera} m");
    assert!(realtime <= 0.15, "real-time ATE RMSE {realtime} m");
}
