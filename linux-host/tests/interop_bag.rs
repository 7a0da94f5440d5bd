//! Bags written by `BagWriter` decode with two independent Python readers (rosbags and the
//! mcap reader with mcap-ros2-support), with the values we wrote.

mod common;

use cloi_host::io::bag::{BagCompression, BagWriter};
use cloi_host::io::ros2::{
    Header, LaserScan, MapMetaData, OccupancyGrid, Odometry, Path, Pose, PoseStamped, TfMessage,
    Time, Transform, TransformStamped,
};
use serde_json::Value;

#[test]
fn bag_writer_output_decodes_with_rosbags_and_mcap() {
    let Some(python) = common::venv_python() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    for compression in [
        BagCompression::Zstd,
        BagCompression::Lz4,
        BagCompression::None,
    ] {
        let path = dir.path().join(format!("{compression:?}.mcap"));
        let mut bag = BagWriter::create_with(&path, compression).unwrap();
        let t0 = 1_700_000_000_000_000_000_i64;
        for i in 0..20_i64 {
            let t = t0 + i * 50_000_000;
            let stamp = Time::from_nanos(t);
            let scan = LaserScan {
                header: Header::new(stamp, "laser"),
                angle_min: -1.5,
                angle_max: 1.5,
                angle_increment: 0.5,
                range_min: 0.1,
                range_max: 20.0,
                ranges: vec![1.0, 2.0, f32::INFINITY, 3.0, 4.0, 5.0, i as f32],
                ..Default::default()
            };
            bag.write("/scan", t, &scan).unwrap();
            let mut odom = Odometry {
                header: Header::new(stamp, "odom"),
                child_frame_id: "base_link".into(),
                ..Default::default()
            };
            odom.pose.pose = Pose::planar(0.1 * i as f64, -0.2, 0.05 * i as f64);
            odom.twist.twist.linear.x = 0.3;
            bag.write("/odom", t, &odom).unwrap();
            let tf = TfMessage {
                transforms: vec![TransformStamped {
                    header: Header::new(stamp, "base_link"),
                    child_frame_id: "laser".into(),
                    transform: Transform::planar(0.2, 0.0, 0.0),
                }],
            };
            bag.write("/tf_static", t, &tf).unwrap();
        }
        let grid = OccupancyGrid {
            header: Header::new(Time::from_nanos(t0), "map"),
            info: MapMetaData {
                resolution: 0.05,
                width: 4,
                height: 3,
                ..Default::default()
            },
            data: vec![-1, 0, 100, 0, 0, 100, -1, -1, 0, 0, 0, 100],
        };
        bag.write("/map", t0 + 10_000_000_000, &grid).unwrap();
        let path_msg = Path {
            header: Header::new(Time::from_nanos(t0), "map"),
            poses: vec![PoseStamped::default(); 3],
        };
        bag.write("/path", t0 + 10_000_000_000, &path_msg).unwrap();
        bag.finish().unwrap();

        let out = common::run_python(&python, "decode_bag.py", &[path.as_os_str()]);
        let v: Value = serde_json::from_str(&out).unwrap();
        assert_eq!(v["/scan"]["type"], "sensor_msgs/msg/LaserScan");
        assert_eq!(v["/scan"]["count"], 20);
        assert_eq!(v["/odom"]["count"], 20);
        assert_eq!(v["/tf_static"]["count"], 20);
        let scan7 = &v["/scan"]["values"][7];
        assert_eq!(scan7["n"], 7);
        assert_eq!(scan7["ranges_sum"], 15.0 + 7.0);
        assert_eq!(scan7["frame"], "laser");
        assert_eq!(scan7["header_ns"], t0 + 7 * 50_000_000);
        assert_eq!(v["/scan"]["stamps"][7], t0 + 7 * 50_000_000);
        let odom5 = &v["/odom"]["values"][5];
        assert!((odom5["x"].as_f64().unwrap() - 0.5).abs() < 1e-12);
        assert!((odom5["qz"].as_f64().unwrap() - (0.125_f64).sin()).abs() < 1e-12);
        assert_eq!(odom5["child"], "base_link");
        assert_eq!(v["/tf_static"]["values"][0][0][1], "laser");
        assert_eq!(v["/map"]["values"][0]["cells"], 12);
        assert_eq!(v["/map"]["values"][0]["occupied"], 3);
        assert_eq!(v["/path"]["values"][0]["poses"], 3);
    }
}
