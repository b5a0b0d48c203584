#!/usr/bin/env python3
"""Cross-check shoal's MCAP reader and writer against an independent implementation, the
`mcap` / `mcap-ros2-support` Python packages (pip install mcap mcap-ros2-support).

1. Writes a ROS 2 bag with `mcap_ros2.writer.Writer` (zstd chunks): mono8 frames stamped
   with their FIRST-row time (the camera-driver convention), an rgb8 topic, a CameraInfo
   and a 200 Hz IMU.
2. Runs `shoal convert --to mcap BAG OUT --calib CAL` with t_r = 10 ms, t_d = 3 ms.
3. Decodes OUT with `mcap_ros2`'s decoder (shoal's ros2msg schemas and CDR, read by another
   implementation) and checks: the same pixels, each frame stamped stamp + t_r/2 + t_d
   (middle row, IMU clock), the same IMU samples, the CameraInfo's K and D, and the `shoal`
   metadata record saying `time_convention = middle_row`.

Usage: benches/mcap_ros2_check.py [--shoal target/release/shoal] [--keep DIR]
Prints one line per check and `N passed, M failed`.
"""
import argparse
import os
import subprocess
import sys
import tempfile

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer

SEP = "=" * 80 + "\n"
TIME = "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
HEADER = "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
IMAGE = ("std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
         "uint8 is_bigendian\nuint32 step\nuint8[] data\n" + SEP + HEADER + SEP + TIME)
CAMERA_INFO = ("std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
               "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\n"
               "uint32 binning_y\nsensor_msgs/RegionOfInterest roi\n" + SEP + HEADER + SEP + TIME
               + SEP + "MSG: sensor_msgs/RegionOfInterest\nuint32 x_offset\nuint32 y_offset\n"
               "uint32 height\nuint32 width\nbool do_rectify\n")
VEC3 = "float64 x\nfloat64 y\nfloat64 z\n"
IMU = ("std_msgs/Header header\ngeometry_msgs/Quaternion orientation\n"
       "float64[9] orientation_covariance\ngeometry_msgs/Vector3 angular_velocity\n"
       "float64[9] angular_velocity_covariance\ngeometry_msgs/Vector3 linear_acceleration\n"
       "float64[9] linear_acceleration_covariance\n" + SEP + HEADER + SEP + TIME + SEP
       + "MSG: geometry_msgs/Quaternion\nfloat64 x\nfloat64 y\nfloat64 z\nfloat64 w\n" + SEP
       + "MSG: geometry_msgs/Vector3\n" + VEC3)

W, H = 64, 48
T0 = 1_600_000_000_123_000_000
PERIOD = 50_000_000
FRAMES = 40
T_R, T_D = 10_000_000, 3_000_000


def stamp(t):
    return {"sec": t // 1_000_000_000, "nanosec": t % 1_000_000_000}


def mono(k):
    return bytes(((x * 5 + y * 3 + 7 * k) ^ (x * y)) % 256 for y in range(H) for x in range(W))


def write_bag(path):
    with open(path, "wb") as f:
        w = Writer(f)
        img = w.register_msgdef("sensor_msgs/msg/Image", IMAGE)
        info = w.register_msgdef("sensor_msgs/msg/CameraInfo", CAMERA_INFO)
        imu = w.register_msgdef("sensor_msgs/msg/Imu", IMU)
        hdr = lambda t, fid: {"stamp": stamp(t), "frame_id": fid}
        w.write_message("/camera/camera_info", info, {
            "header": hdr(T0, "cam"), "height": H, "width": W, "distortion_model": "plumb_bob",
            "d": [-0.2, 0.05, 0.001, 0.002, 0.0], "k": [50.0, 0, 32.0, 0, 51.0, 24.0, 0, 0, 1.0],
            "r": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], "p": [0.0] * 12, "binning_x": 0,
            "binning_y": 0, "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0,
                                    "do_rectify": False}}, log_time=T0, publish_time=T0)
        for k in range(FRAMES):
            for j in range(10):
                t = T0 + k * PERIOD + j * PERIOD // 10
                n = 10 * k + j
                w.write_message("/imu/data", imu, {
                    "header": hdr(t, "imu"),
                    "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                    "orientation_covariance": [-1.0] + [0.0] * 8,
                    "angular_velocity": {"x": 0.001 * n, "y": -0.5, "z": 0.25},
                    "angular_velocity_covariance": [0.0] * 9,
                    "linear_acceleration": {"x": 0.1, "y": 0.01 * n, "z": 9.81},
                    "linear_acceleration_covariance": [0.0] * 9}, log_time=t, publish_time=t)
            t = T0 + k * PERIOD
            # A second image topic (rgb8): the mono one must be chosen with --image-topic.
            w.write_message("/camera/image_rgb", img, {
                "header": hdr(t, "cam"), "height": H, "width": W, "encoding": "rgb8",
                "is_bigendian": 0, "step": 3 * W, "data": bytes(3 * W * H)},
                log_time=t + 1_000_000, publish_time=t + 1_000_000)
            w.write_message("/camera/image_mono", img, {
                "header": hdr(t, "cam"), "height": H, "width": W, "encoding": "mono8",
                "is_bigendian": 0, "step": W, "data": mono(k)},
                log_time=t + 1_000_000, publish_time=t + 1_000_000)
        w.finish()


CALIB = f"""format = "shoal-calibration"
version = 1

[camera]
model = "pinhole-radtan"
resolution = [{W}, {H}]
intrinsics = [50.0, 51.0, 32.0, 24.0]
distortion = [-0.2, 0.05, 0.001, 0.002]
rate_hz = 20.0
readout_ns = {T_R}.0
time_offset_ns = {T_D}.0
t_bs = [[0.0, -1.0, 0.0, 0.05], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]

[imu]
gyroscope_noise_density = 0.0002
gyroscope_random_walk = 2e-5
accelerometer_noise_density = 0.002
accelerometer_random_walk = 0.003
"""


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--shoal", default="target/release/shoal")
    ap.add_argument("--keep", default=None)
    a = ap.parse_args()
    d = a.keep or tempfile.mkdtemp(prefix="mcap_ros2_check_")
    os.makedirs(d, exist_ok=True)
    bag, out, cal = (os.path.join(d, n) for n in ("python_bag.mcap", "shoal.mcap", "cal.toml"))
    write_bag(bag)
    with open(cal, "w") as f:
        f.write(CALIB)
    subprocess.run([a.shoal, "convert", "--to", "mcap", bag, out, "--calib", cal,
                    "--image-topic", "/camera/image_mono"], check=True)
    results = []

    def check(name, ok, detail=""):
        results.append(ok)
        print(("PASS " if ok else "FAIL ") + name + ("" if ok else f": {detail}"))

    frames, imu, infos = [], [], []
    with open(out, "rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        meta = {m.name: m.metadata for m in r.iter_metadata()}
        for schema, channel, message, msg in r.iter_decoded_messages():
            t = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            if channel.topic == "/cam0/image_raw":
                frames.append((t, msg.encoding, bytes(msg.data), message.log_time))
            elif channel.topic == "/imu0":
                imu.append((t, msg.angular_velocity.x, msg.linear_acceleration.y))
            elif channel.topic == "/cam0/camera_info":
                infos.append(msg)
    check("shoal metadata: middle_row",
          meta.get("shoal", {}).get("time_convention") == "middle_row", meta)
    check("frame count", len(frames) == FRAMES, len(frames))
    want_t = [T0 + k * PERIOD + T_R // 2 + T_D for k in range(FRAMES)]
    check("frame stamps = first-row stamp + t_r/2 + t_d", [f[0] for f in frames] == want_t,
          [f[0] for f in frames[:3]])
    check("log time = stamp", all(f[0] == f[3] for f in frames))
    check("mono8 pixels identical",
          all(f[1] == "mono8" and f[2] == mono(k) for k, f in enumerate(frames)))
    want_imu = [(T0 + k * PERIOD + j * PERIOD // 10, 0.001 * (10 * k + j), 0.01 * (10 * k + j))
                for k in range(FRAMES) for j in range(10)]
    check("IMU samples identical (times unchanged)", imu == want_imu, imu[:2])
    ok_info = len(infos) == 1 and list(infos[0].k) == [50.0, 0, 32.0, 0, 51.0, 24.0, 0, 0, 1.0] \
        and list(infos[0].d)[:4] == [-0.2, 0.05, 0.001, 0.002]
    check("CameraInfo K and D", ok_info, infos[:1])
    failed = results.count(False)
    print(f"{len(results) - failed} passed, {failed} failed")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
