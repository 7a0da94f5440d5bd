"""Writes a ROS 2 bag (MCAP storage) from a CARMEN log with the independent `rosbags` package.

Usage: carmen_to_rosbag.py LOG.clf OUT_DIR [MAX_SCANS]

Front laser lines (FLASER) go to /scan as sensor_msgs/msg/LaserScan and ODOM lines to /odom
as nav_msgs/msg/Odometry, stamped with the lines' IPC time stamps (parsed from the decimal
text into integer nanoseconds). Beam angles follow the old CARMEN convention: 180 degrees
from -90 degrees, ends included for an odd beam count. The bag is a rosbag2 folder with
metadata.yaml and one .mcap file, whose path is printed.
"""
import math
import sys
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore


def stamp_ns(text):
    whole, _, frac = text.partition(".")
    frac = (frac + "000000000")[:9]
    sign = -1 if whole.startswith("-") else 1
    return sign * (abs(int(whole or "0")) * 10**9 + int(frac))


def main():
    log, out = sys.argv[1], Path(sys.argv[2])
    max_scans = int(sys.argv[3]) if len(sys.argv) > 3 else None
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    Time = T["builtin_interfaces/msg/Time"]
    Header = T["std_msgs/msg/Header"]
    LaserScan = T["sensor_msgs/msg/LaserScan"]
    Odometry = T["nav_msgs/msg/Odometry"]
    PoseWithCovariance = T["geometry_msgs/msg/PoseWithCovariance"]
    TwistWithCovariance = T["geometry_msgs/msg/TwistWithCovariance"]
    Pose = T["geometry_msgs/msg/Pose"]
    Point = T["geometry_msgs/msg/Point"]
    Quaternion = T["geometry_msgs/msg/Quaternion"]
    Twist = T["geometry_msgs/msg/Twist"]
    Vector3 = T["geometry_msgs/msg/Vector3"]

    def header(ns, frame):
        return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    scans = odoms = 0
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        c_scan = writer.add_connection("/scan", LaserScan.__msgtype__, typestore=ts)
        c_odom = writer.add_connection("/odom", Odometry.__msgtype__, typestore=ts)
        with open(log) as f:
            for line in f:
                tok = line.split()
                if not tok:
                    continue
                if tok[0] == "FLASER":
                    if max_scans is not None and scans >= max_scans:
                        break
                    n = int(tok[1])
                    ranges = np.array([float(r) for r in tok[2:2 + n]], dtype=np.float32)
                    ns = stamp_ns(tok[2 + n + 6])
                    inc = math.pi / (n - 1) if n % 2 == 1 and n > 1 else math.pi / n
                    a0 = -math.pi / 2
                    msg = LaserScan(
                        header=header(ns, "laser"),
                        angle_min=a0, angle_max=a0 + inc * (n - 1), angle_increment=inc,
                        time_increment=0.0, scan_time=0.0, range_min=0.0, range_max=80.0,
                        ranges=ranges, intensities=np.array([], dtype=np.float32),
                    )
                    writer.write(c_scan, ns, ts.serialize_cdr(msg, LaserScan.__msgtype__))
                    scans += 1
                elif tok[0] == "ODOM":
                    x, y, th, tv, rv = (float(v) for v in tok[1:6])
                    ns = stamp_ns(tok[7])
                    msg = Odometry(
                        header=header(ns, "odom"),
                        child_frame_id="base_link",
                        pose=PoseWithCovariance(
                            pose=Pose(position=Point(x=x, y=y, z=0.0),
                                      orientation=Quaternion(x=0.0, y=0.0, z=math.sin(th / 2),
                                                             w=math.cos(th / 2))),
                            covariance=np.zeros(36)),
                        twist=TwistWithCovariance(
                            twist=Twist(linear=Vector3(x=tv, y=0.0, z=0.0),
                                        angular=Vector3(x=0.0, y=0.0, z=rv)),
                            covariance=np.zeros(36)),
                    )
                    writer.write(c_odom, ns, ts.serialize_cdr(msg, Odometry.__msgtype__))
                    odoms += 1
    mcaps = sorted(out.glob("*.mcap"))
    print(mcaps[0], scans, odoms)


if __name__ == "__main__":
    main()
