#!/usr/bin/env python3
"""Turns an MCAP file of ROS 2 messages (e.g. `shoal convert --to mcap` output) into a ROS 1
bag with the independent `rosbags` writer (pip install rosbags mcap mcap-ros2-support):
Image, CameraInfo and Imu topics, same stamps and values; bz2 chunks with `--bz2`. Used to
check the ROS 1 reader end to end: the bag replays to the same trajectory as its source.

Usage: benches/mcap_to_ros1_bag.py IN.mcap OUT.bag [--bz2]
"""
import sys

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.rosbag1 import Writer
from rosbags.typesys import Stores, get_typestore

TYPES = {"sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo", "sensor_msgs/msg/Imu"}


def main():
    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]

    def header(h):
        return Header(seq=0, stamp=Time(sec=h.stamp.sec, nanosec=h.stamp.nanosec),
                      frame_id=h.frame_id)

    def convert(name, m):
        if name == "sensor_msgs/msg/Image":
            return T[name](header=header(m.header), height=m.height, width=m.width,
                           encoding=m.encoding, is_bigendian=m.is_bigendian, step=m.step,
                           data=np.frombuffer(bytes(m.data), dtype=np.uint8))
        if name == "sensor_msgs/msg/CameraInfo":
            r = m.roi
            return T[name](header=header(m.header), height=m.height, width=m.width,
                           distortion_model=m.distortion_model, D=np.array(m.d, dtype=float),
                           K=np.array(m.k, dtype=float), R=np.array(m.r, dtype=float),
                           P=np.array(m.p, dtype=float), binning_x=m.binning_x,
                           binning_y=m.binning_y,
                           roi=T["sensor_msgs/msg/RegionOfInterest"](
                               x_offset=r.x_offset, y_offset=r.y_offset, height=r.height,
                               width=r.width, do_rectify=r.do_rectify))
        v3, q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
        o, a, l = m.orientation, m.angular_velocity, m.linear_acceleration
        return T[name](header=header(m.header), orientation=q(x=o.x, y=o.y, z=o.z, w=o.w),
                       orientation_covariance=np.array(m.orientation_covariance, dtype=float),
                       angular_velocity=v3(x=a.x, y=a.y, z=a.z),
                       angular_velocity_covariance=np.array(m.angular_velocity_covariance,
                                                            dtype=float),
                       linear_acceleration=v3(x=l.x, y=l.y, z=l.z),
                       linear_acceleration_covariance=np.array(
                           m.linear_acceleration_covariance, dtype=float))

    w = Writer(sys.argv[2])
    if "--bz2" in sys.argv:
        w.set_compression(Writer.CompressionFormat.BZ2)
    conns = {}
    with w, open(sys.argv[1], "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, m in reader.iter_decoded_messages(log_time_order=True):
            if schema.name not in TYPES:
                continue
            if channel.topic not in conns:
                conns[channel.topic] = w.add_connection(channel.topic, schema.name, typestore=ts)
            w.write(conns[channel.topic], message.log_time,
                    ts.serialize_ros1(convert(schema.name, m), schema.name))


if __name__ == "__main__":
    main()
