//! The `cloi map` input layer on the whole shared CARMEN logs (release mode, feature
//! `golden`): every scan and odometry line becomes an event, intel.clf's stamps that step
//! back pass through and are counted, the laser mountings come from the right place, and a
//! bag converted from a log gives the same scans with the mounting from `/tf_static`.

use std::time::Instant;

use cloi_host::dataset::shared_file;
use cloi_host::io::convert::carmen_to_bag;
use cloi_host::map::input::{open_input, InputOptions, InputStats, SensorEvent};

fn read_all(path: &std::path::Path) -> (Vec<i64>, InputStats, usize) {
    let mut stream = open_input(path, &InputOptions::default()).unwrap();
    let mut scan_stamps = Vec::new();
    let mut nan = 0;
    for event in stream.by_ref() {
        if let SensorEvent::Scan(s) = event.unwrap() {
            scan_stamps.push(s.t_ns);
            nan += s.ranges.iter().filter(|r| r.is_nan()).count();
        }
    }
    (scan_stamps, stream.stats(), nan)
}

#[test]
fn shared_logs_become_event_streams() {
    // (file, FLASER lines, ODOM lines, laser offset x, where it comes from)
    for (name, scans, odoms, offset_x, source) in [
        ("carmen/intel.clf", 13_631u64, 26_915u64, 0.0, "PARAM"),
        ("carmen/fr079.clf", 4_934, 8_951, -0.04, "PARAM"),
        ("carmen/mit-csail.clf", 1_988, 0, 0.0, "laser line"),
    ] {
        let Some(log) = shared_file(name) else {
            return;
        };
        let started = Instant::now();
        let (stamps, stats, _) = read_all(&log);
        let wall = started.elapsed().as_secs_f64();
        eprintln!(
            "{name}: {} events in {wall:.2} s, {:.0} data-s per wall-s, {} stamps back, {} \
             odometry from scan lines",
            stats.scans + stats.odometry + stats.gyro,
            stats.data_seconds() / wall,
            stats.backwards_stamps,
            stats.odometry_from_scans
        );
        assert_eq!(stats.scans, scans, "{name}");
        assert_eq!(stamps.len() as u64, scans);
        assert_eq!(stats.odometry - stats.odometry_from_scans, odoms, "{name}");
        assert_eq!(stats.gyro, 0);
        assert_eq!(stats.skipped, 0, "{name}");
        let offset = stats.laser_offset.unwrap();
        assert!((offset.x - offset_x).abs() < 1e-4, "{name}: {offset:?}");
        assert!(offset.y.abs() < 1e-4 && offset.theta.abs() < 1e-4);
        assert_eq!(stats.laser_offset_source.as_deref(), Some(source), "{name}");
        if odoms == 0 {
            // mit-csail: every scan brings its own odometry.
            assert_eq!(stats.odometry_from_scans, scans);
        }
        let backwards = stamps.windows(2).filter(|w| w[1] < w[0]).count() as u64;
        assert!(stats.backwards_stamps >= backwards);
        if name.contains("intel") {
            // intel.clf's clock steps back on about 1,200 lines (scans and ODOM).
            assert!(
                (1_000..1_500).contains(&stats.backwards_stamps),
                "{}",
                stats.backwards_stamps
            );
            assert!(
                (stats.data_seconds() - 2_691.0).abs() < 5.0,
                "{}",
                stats.data_seconds()
            );
        }
    }
}

#[test]
fn converted_bag_gives_the_same_scans() {
    let Some(log) = shared_file("carmen/fr079.clf") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let bag = dir.path().join("fr079.mcap");
    carmen_to_bag(&log, &bag, true, None).unwrap();
    let (from_log, log_stats, _) = read_all(&log);
    let (from_bag, bag_stats, _) = read_all(&bag);
    assert_eq!(bag_stats.scans, log_stats.scans);
    let mut sorted = from_log.clone();
    sorted.sort_unstable();
    assert_eq!(from_bag, sorted, "the bag delivers scans in time order");
    assert_eq!(bag_stats.laser_offset_source.as_deref(), Some("tf_static"));
    let offset = bag_stats.laser_offset.unwrap();
    assert!((offset.x + 0.04).abs() < 1e-9, "{offset:?}");
}
