#!/usr/bin/env python3
"""Writes the small ROS 1 bag `datasets/tests/data/small_ros1.bag` with an independent
writer (the `rosbags` Python package: pip install rosbags), for the ROS 1 reader's tests:

- `/cam0/image_raw`: 10 `sensor_msgs/Image` mono8 64x48 at 20 Hz from T0, pixel (x, y) of
  frame k = (x * 5 + y * 3 + 7 * k) ^ (x * y) mod 256, header stamps = the bag times;
- `/cam0/image_raw/compressed`: none (the raw topic is what a replay takes);
- `/cam0/camera_info`: one `sensor_msgs/CameraInfo` (plumb_bob, fx 50, fy 51, cx 32, cy 24,
  D = [-0.1, 0.01, 0.001, -0.002, 0]);
- `/imu0`: `sensor_msgs/Imu` at 200 Hz from T0 - 20 ms, gyro (0.01 k, 0.2, -0.3), accel
  (0.1, 9.81, 0.001 k) for sample k;
- chunks compressed with bz2 when `--bz2` is given (the EuRoC bags' choice), else plain.

Usage: benches/make_ros1_bag.py OUT.bag [--bz2]
"""
import sys

import numpy as np
from rosbags.rosbag1 import Writer
from rosbags.typesys import Stores, get_typestore

W, H = 64, 48
T0 = 1_403_636_580_013_555_456
PERIOD = 50_000_000
FRAMES = 10


def main():
    out = sys.argv[1]
    ts = get_typestore(Stores.ROS1_NOETIC)
    Image = ts.types["sensor_msgs/msg/Image"]
    Info = ts.types["sensor_msgs/msg/CameraInfo"]
    Imu = ts.types["sensor_msgs/msg/Imu"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    Quat = ts.types["geometry_msgs/msg/Quaternion"]
    Vec3 = ts.types["geometry_msgs/msg/Vector3"]
    Roi = ts.types["sensor_msgs/msg/RegionOfInterest"]

    def header(t, frame, seq=0):
        return Header(seq=seq, stamp=Time(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000),
                      frame_id=frame)

    w = Writer(out)
    if "--bz2" in sys.argv:
        w.set_compression(Writer.CompressionFormat.BZ2)
    with w:
        c_img = w.add_connection("/cam0/image_raw", Image.__msgtype__, typestore=ts)
        c_info = w.add_connection("/cam0/camera_info", Info.__msgtype__, typestore=ts)
        c_imu = w.add_connection("/imu0", Imu.__msgtype__, typestore=ts)
        msgs = []
        info = Info(header=header(T0, "cam0"), height=H, width=W, distortion_model="plumb_bob",
                    D=np.array([-0.1, 0.01, 0.001, -0.002, 0.0]),
                    K=np.array([50.0, 0, 32, 0, 51, 24, 0, 0, 1]),
                    R=np.eye(3).flatten(), P=np.array([50.0, 0, 32, 0, 0, 51, 24, 0, 0, 0, 1, 0]),
                    binning_x=0, binning_y=0,
                    roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
        msgs.append((T0, c_info, ts.serialize_ros1(info, Info.__msgtype__)))
        for k in range(FRAMES):
            t = T0 + k * PERIOD
            px = np.array([((x * 5 + y * 3 + 7 * k) ^ (x * y)) % 256 for y in range(H)
                           for x in range(W)], dtype=np.uint8)
            img = Image(header=header(t, "cam0", k), height=H, width=W, encoding="mono8",
                        is_bigendian=0, step=W, data=px)
            msgs.append((t, c_img, ts.serialize_ros1(img, Image.__msgtype__)))
        for k in range(int((FRAMES * PERIOD + 20_000_000) / 5_000_000)):
            t = T0 - 20_000_000 + k * 5_000_000
            m = Imu(header=header(t, "imu0", k), orientation=Quat(x=0, y=0, z=0, w=1),
                    orientation_covariance=np.array([-1.0] + [0.0] * 8),
                    angular_velocity=Vec3(x=0.01 * k, y=0.2, z=-0.3),
                    angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=Vec3(x=0.1, y=9.81, z=0.001 * k),
                    linear_acceleration_covariance=np.zeros(9))
            msgs.append((t, c_imu, ts.serialize_ros1(m, Imu.__msgtype__)))
        for t, c, data in sorted(msgs, key=lambda m: m[0]):
            w.write(c, t, data)


if __name__ == "__main__":
    main()
