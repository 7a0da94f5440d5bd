//! The shared MCAP files: the `mcap` crate's fixtures (compressed, uncompressed, a zstd chunk
//! with padding, and a truncated file) and a real Nav2 bag.

use std::path::Path;

use cloi_host::dataset::shared_file;
use cloi_host::io::bag_read::{BagReadOptions, BagReader, BagStats, SensorMsg};

fn read_all(path: &Path, strict: bool) -> (Vec<anyhow::Result<SensorMsg>>, BagStats) {
    let mut reader = BagReader::open(
        path,
        BagReadOptions {
            strict,
            ..Default::default()
        },
    )
    .unwrap();
    let msgs = reader.by_ref().map(|m| m.map(|m| m.msg)).collect();
    (msgs, reader.stats().clone())
}

#[test]
fn ros1_fixtures_are_counted_and_skipped() {
    for name in ["compressed.mcap", "uncompressed.mcap"] {
        let Some(path) = shared_file(&format!("mcap/fixtures/{name}")) else {
            return;
        };
        let (msgs, stats) = read_all(&path, true);
        // Both hold ROS 1 messages only: nothing is delivered, all are accounted for.
        assert!(msgs.is_empty(), "{name}");
        assert!(!stats.truncated);
        assert_eq!(stats.topics["/tf"].skipped, 774, "{name}");
        assert_eq!(stats.topics["/tf"].type_name, "tf2_msgs/TFMessage");
        assert_eq!(stats.topics["/diagnostics"].skipped, 52, "{name}");
        assert_eq!(stats.foreign_encoding, 774);
        assert!(
            stats.warnings[0].contains("\"ros1\" encoding"),
            "{:?}",
            stats.warnings
        );
    }
}

#[test]
fn zstd_chunk_with_padding_is_decompressed() {
    let Some(path) = shared_file("mcap/fixtures/zstd_chunk_with_padding.mcap") else {
        return;
    };
    let (msgs, stats) = read_all(&path, false);
    // Its 12 messages sit in a padded zstd chunk and name a channel that has no record.
    assert!(msgs.is_empty());
    assert_eq!(stats.unknown_channel, 12);
    assert!(!stats.truncated);
    let (msgs, _) = read_all(&path, true);
    assert!(msgs.last().unwrap().is_err());
}

#[test]
fn truncated_fixture_warns_or_fails_in_strict_mode() {
    let Some(path) = shared_file("mcap/fixtures/chunk_not_closed.mcap") else {
        return;
    };
    let (msgs, stats) = read_all(&path, false);
    assert!(msgs.is_empty());
    assert!(stats.truncated);
    // The chunk record starts at byte 39 and its length, never written back, is all ones: the
    // reader names that record when it has read the length (byte 48), not the end of the file.
    assert!(
        stats.warnings[0].contains("damaged or truncated near byte 48")
            && stats.warnings[0].contains("opcode 06"),
        "{:?}",
        stats.warnings
    );
    let (msgs, _) = read_all(&path, true);
    let err = msgs.last().unwrap().as_ref().unwrap_err().to_string();
    assert!(err.contains("chunk_not_closed.mcap"), "{err}");
}

#[test]
fn nav2_bag_odometry() {
    let Some(path) = shared_file("mcap/nav2_turtlebot.mcap") else {
        return;
    };
    let (msgs, stats) = read_all(&path, true);
    assert_eq!(stats.topics["/odom"].delivered, 2639);
    assert_eq!(stats.topics["/tf"].delivered, 5422);
    assert_eq!(stats.topics["/amcl_pose"].delivered, 135);
    assert_eq!(stats.out_of_order, 0);
    let odoms: Vec<_> = msgs
        .iter()
        .filter_map(|m| match m.as_ref().unwrap() {
            SensorMsg::Odom(o) => Some(o),
            _ => None,
        })
        .collect();
    assert_eq!(odoms.len(), 2639);
    let first = odoms[0];
    assert_eq!(first.header.frame_id, "odom");
    assert_eq!(first.child_frame_id, "base_link");
    let (x, y, _) = first.pose.pose.to_planar();
    assert!((x + 2.8019166340612314).abs() < 1e-12 && (y - 1.0977901491292252).abs() < 1e-12);
    // Time stamps increase and the robot drives about 34 m in 97 s.
    let mut length = 0.0;
    for w in odoms.windows(2) {
        assert!(w[1].header.stamp >= w[0].header.stamp);
        let (a, b) = (w[0].pose.pose.position, w[1].pose.pose.position);
        length += (b.x - a.x).hypot(b.y - a.y);
    }
    assert!((length - 34.32).abs() < 0.01, "{length}");
}
