#!/usr/bin/env python3
"""Decodes a `shoal run --record` file with an independent implementation (the `mcap` /
`mcap-ros2-support` Python packages: pip install mcap mcap-ros2-support) and prints, per
topic, the schema, the message count and what the first and last messages say, then checks
that every topic a viewer needs is there and decodes: the frames, the IMU, the camera, the
tracker's poses and `/tf`, the keyframes, the server-map poses and points, the latency.

Usage: benches/mcap_record_check.py FILE.mcap
Exit code 0 when every check passes.
"""
import sys
from collections import defaultdict

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

EXPECTED = ["/cam0/image_raw", "/cam0/camera_info", "/shoal/pose", "/tf", "/shoal/keyframe",
            "/shoal/latency_ms", "/shoal/map"]


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
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
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
