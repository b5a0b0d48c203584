#!/usr/bin/env python3
"""Draws what Foxglove's Image panel shows of a `shoal run --record` file: one frame of
`/cam0/image_raw` with the tracked features of `/cam0/features` (`foxglove.ImageAnnotations`)
on it, decoded independently of shoal (pip install mcap mcap-ros2-support
mcap-protobuf-support pillow).

Usage: benches/mcap_features_png.py FILE.mcap OUT.png [FRAME_INDEX]
"""
import sys

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory
from mcap_ros2.decoder import DecoderFactory
from PIL import Image, ImageDraw


def main():
    path, out = sys.argv[1], sys.argv[2]
    index = int(sys.argv[3]) if len(sys.argv) > 3 else 100
    images, features = [], {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory(), ProtobufDecoderFactory()])
        topics = ["/cam0/image_raw", "/cam0/features"]
        for _, channel, message, decoded in reader.iter_decoded_messages(topics=topics):
            if channel.topic == "/cam0/image_raw":
                images.append((message.log_time, decoded))
            else:
                features[message.log_time] = decoded.points[0].points
    t, img = images[min(index, len(images) - 1)]
    pic = Image.frombytes("L", (img.width, img.height), bytes(img.data)).convert("RGB")
    draw = ImageDraw.Draw(pic)
    points = features.get(t, [])
    for p in points:
        draw.ellipse([p.x - 3, p.y - 3, p.x + 3, p.y + 3], outline=(25, 230, 50), width=2)
    pic.save(out)
    print(f"frame at {t} ns: {len(points)} tracked features -> {out}")


if __name__ == "__main__":
    main()
