"""Decodes an MCAP ROS 2 bag with two independent readers and prints a JSON summary.

Usage: decode_bag.py BAG.mcap

Both the `rosbags` package and the `mcap` reader (with mcap-ros2-support) decode every message;
the summary has, per topic, the message type, the count, and a few decoded values, so the Rust
test can compare them with what it wrote. The two readers must agree with each other.
"""
import json
import sys
from pathlib import Path

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore


def summarize(topic, msgtype, msg, stamp_ns, out):
    entry = out.setdefault(topic, {"type": msgtype, "count": 0, "stamps": [], "values": []})
    entry["count"] += 1
    entry["stamps"].append(stamp_ns)
    if msgtype.endswith("LaserScan"):
        entry["values"].append({
            "frame": msg.header.frame_id,
            "angle_min": float(msg.angle_min),
            "angle_increment": float(msg.angle_increment),
            "range_max": float(msg.range_max),
            "ranges_sum": float(sum(float(r) for r in msg.ranges if r == r and abs(r) != float("inf"))),
            "n": len(msg.ranges),
            "header_ns": msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec,
        })
    elif msgtype.endswith("Odometry"):
        p = msg.pose.pose
        entry["values"].append({
            "frame": msg.header.frame_id,
            "child": msg.child_frame_id,
            "x": p.position.x, "y": p.position.y,
            "qz": p.orientation.z, "qw": p.orientation.w,
            "vx": msg.twist.twist.linear.x, "wz": msg.twist.twist.angular.z,
        })
    elif msgtype.endswith("TFMessage"):
        entry["values"].append([
            [t.header.frame_id, t.child_frame_id, t.transform.translation.x,
             t.transform.translation.y, t.transform.rotation.z, t.transform.rotation.w]
            for t in msg.transforms
        ])
    elif msgtype.endswith("OccupancyGrid"):
        entry["values"].append({"w": msg.info.width, "h": msg.info.height,
                                "res": float(msg.info.resolution), "cells": len(msg.data),
                                "occupied": int(sum(1 for c in msg.data if c == 100))})
    elif msgtype.endswith("Path"):
        entry["values"].append({"poses": len(msg.poses)})


def with_rosbags(path):
    out = {}
    typestore = get_typestore(Stores.EMPTY)
    with AnyReader([Path(path)], default_typestore=typestore) as reader:
        for conn, stamp, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            summarize(conn.topic, conn.msgtype, msg, stamp, out)
    return out


def with_mcap(path):
    out = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, msg in reader.iter_decoded_messages(log_time_order=True):
            summarize(channel.topic, schema.name, msg, message.log_time, out)
    return out


def main():
    path = sys.argv[1]
    a = with_rosbags(path)
    b = with_mcap(path)
    if json.dumps(a, sort_keys=True) != json.dumps(b, sort_keys=True):
        print("rosbags and mcap disagree", file=sys.stderr)
        for topic in sorted(set(a) | set(b)):
            print(topic, a.get(topic, {}).get("count"), b.get(topic, {}).get("count"), file=sys.stderr)
        sys.exit(1)
    json.dump(a, sys.stdout)


if __name__ == "__main__":
    main()
