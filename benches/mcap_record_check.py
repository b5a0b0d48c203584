#!/usr/bin/env python3
"""Decodes a `shoal run --record` file with an independent implementation (the `mcap` /
`mcap-ros2-support` and `mcap-protobuf-support` Python packages: pip install mcap
mcap-ros2-support mcap-protobuf-support) and prints, per topic, the schema, the message
count and what the first and last messages say, then checks that every topic a viewer needs
is there and decodes: the frames, the IMU, the camera, the tracker's poses, `/tf` and
odometry, the keyframes, the server-map poses and points, the latency (ROS 2 messages), and
the Foxglove-schema topics (transforms, paths, keyframes, features, map points, loops).

Usage: benches/mcap_record_check.py FILE.mcap
Exit code 0 when every check passes.
"""
import sys
from collections import defaultdict

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory

EXPECTED = ["/cam0/image_raw", "/cam0/camera_info", "/shoal/pose", "/tf", "/shoal/keyframe",
            "/shoal/latency_ms", "/shoal/map", "/shoal/odometry", "/shoal/transforms",
            "/shoal/trajectory", "/shoal/keyframes", "/cam0/features", "/shoal/map_points",
            "/shoal/loops"]


def summary(topic, m):
    if topic == "/cam0/image_raw":
        return f"{m.width}x{m.height} {m.encoding}, {len(m.data)} bytes"
    if topic == "/cam0/camera_info":
        return f"K {list(m.k)[:3]}..., D {list(m.d)}"
    if topic == "/imu0":
        return f"gyro {m.angular_velocity.x:.4f} ..., accel {m.linear_acceleration.z:.3f}"
    if topic in ("/tf", "/tf_static"):
        t = m.transforms[0]
        return f"{t.header.frame_id} -> {t.child_frame_id}: {t.transform.translation.x:.4f} ..."
    if topic == "/shoal/map":
        return f"{m.width} points, fields {[f.name for f in m.fields]}, frame {m.header.frame_id}"
    if topic == "/rosout":
        return f"{m.name}: {m.msg}"
    if topic == "/shoal/odometry":
        p = m.pose.pose.position
        return f"{m.header.frame_id} -> {m.child_frame_id}: ({p.x:.4f}, {p.y:.4f}, {p.z:.4f})"
    if topic == "/shoal/transforms":
        t = m.transforms[0]
        return f"{t.parent_frame_id} -> {t.child_frame_id}: {t.translation.x:.4f} ..."
    if topic in ("/shoal/trajectory", "/shoal/server_trajectory", "/shoal/keyframes"):
        return f"{len(m.poses)} poses in {m.frame_id}"
    if topic == "/cam0/features":
        return f"{len(m.points[0].points)} points" if m.points else "none"
    if topic == "/shoal/map_points":
        return f"{len(m.data) // m.point_stride} points in {m.frame_id}"
    if topic == "/shoal/loops":
        lines = m.entities[0].lines
        return f"{len(lines[0].points) // 2 if lines else 0} edges in {m.entities[0].frame_id}"
    if topic == "/shoal/latency_ms":
        return f"{m.data:.3f} ms"
    if hasattr(m, "pose"):
        p = m.pose.position
        return f"{m.header.frame_id}: ({p.x:.4f}, {p.y:.4f}, {p.z:.4f})"
    return type(m).__name__


def main():
    counts = defaultdict(int)
    first, last, schemas = {}, {}, {}
    with open(sys.argv[1], "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory(), ProtobufDecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            counts[channel.topic] += 1
            schemas[channel.topic] = schema.name
            first.setdefault(channel.topic, summary(channel.topic, decoded))
            last[channel.topic] = summary(channel.topic, decoded)
    for topic in sorted(counts):
        print(f"{topic} [{schemas[topic]}] x{counts[topic]}: first {first[topic]}; last {last[topic]}")
    missing = [t for t in EXPECTED if counts[t] == 0]
    print("missing:", missing if missing else "none")
    sys.exit(1 if missing else 0)


if __name__ == "__main__":
    main()
