"""A bag with image_transport's compressed topics (compressedDepth png and rvl 16-bit, jpeg colour)
replays like its raw twin."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from replays import replay_in_process
from rvl_encoder import rvl_payload

from senfunet_ros.bagio import open_bag, write_sequence_bag

PARAMS = "senfunet:\n  ros__parameters:\n    working_width: 64\n    voxel_size_m: 0.04\n    band_m: 0.4\n"
COMPRESSED_TOPICS = ("    tof:\n      depth_topic: /tof/depth/compressedDepth\n"
                     "    stereo:\n      color_topic: /stereo/color/compressed\n")


def _compressed_copy(src: Path, dst: Path) -> None:
    """/tof/depth (16UC1) -> /tof/depth/compressedDepth (png and rvl in turn), /stereo/color (rgb8) ->
    /stereo/color/compressed (jpeg), written the way image_transport's plugins do; everything else
    as it is."""
    import cv2
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    CompressedImage = store.types["sensor_msgs/msg/CompressedImage"]
    with open_bag(src) as reader, Writer(dst, version=9) as writer:
        conns = {}
        depth_images = 0
        for msg in reader.messages():
            topic, msgtype, data = msg.topic, msg.msgtype, msg.data
            if topic in ("/tof/depth", "/stereo/color"):
                image = store.deserialize_cdr(msg.data, msgtype)
                pixels = np.asarray(image.data, np.uint8)
                if topic == "/tof/depth":
                    assert image.encoding == "16UC1"
                    raw = pixels.view("<u2").reshape(image.height, image.width)
                    codec = ("png", "rvl")[depth_images % 2]
                    depth_images += 1
                    encoded = rvl_payload(raw) if codec == "rvl" else cv2.imencode(".png", raw)[1].tobytes()
                    payload = np.frombuffer(bytes(12) + encoded, np.uint8)  # ConfigHeader, then the image
                    fmt, topic = f"16UC1; compressedDepth {codec}", "/tof/depth/compressedDepth"
                else:
                    rgb = pixels.reshape(image.height, image.width, 3)
                    _, jpg = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
                    payload, fmt, topic = jpg.reshape(-1), "rgb8; jpeg compressed bgr8", "/stereo/color/compressed"
                msgtype = "sensor_msgs/msg/CompressedImage"
                data = store.serialize_cdr(CompressedImage(header=image.header, format=fmt, data=payload), msgtype)
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(conns[topic], msg.log_time_ns, data)


def test_compressed_bag_replays_like_the_raw_one(tmp_path: Path) -> None:
    import json

    from senfunet_core.learning import simulator as sim
    from senfunet_core.ply import read_ply

    seq = sim.simulate_sequence(sim.make_scene(4), 4, duration_s=1.0, width=128, height=128, tof_rate_hz=8,
                                stereo_rate_hz=8)
    raw_bag = write_sequence_bag(seq, tmp_path / "raw")
    compressed = tmp_path / "compressed"
    _compressed_copy(raw_bag, compressed)
    (tmp_path / "raw.yaml").write_text(PARAMS)
    (tmp_path / "c.yaml").write_text(PARAMS + COMPRESSED_TOPICS)
    # in this process: two replay processes spent most of their time loading torch and the kernels
    ref, got = (replay_in_process(bag, tmp_path / out, tmp_path / p, compare=True)
                for bag, out, p in ((raw_bag, "ref", "raw.yaml"), (compressed, "got", "c.yaml")))
    assert ref.returncode == 0 and got.returncode == 0, ref.stderr + got.stderr
    stats = json.loads((tmp_path / "got" / "stats.json").read_text())
    assert stats["topics"]["/tof/depth/compressedDepth"]["type"] == "sensor_msgs/msg/CompressedImage"
    assert stats["topics"]["/stereo/color/compressed"]["undecodable"] == 0
    assert ref.stdout.splitlines()[:2] == got.stdout.splitlines()[:2]  # every frame fused in both
    assert all(c["dropped_total"] == 0 for c in stats["sensors"].values())
    # ToF depth is lossless (png or rvl of the same millimetres): its mesh is the same bytes
    assert (tmp_path / "ref" / "tof.ply").read_bytes() == (tmp_path / "got" / "tof.ply").read_bytes()
    a, b = read_ply(tmp_path / "ref" / "mesh.ply"), read_ply(tmp_path / "got" / "mesh.ply")
    assert a.n_faces > 100 and abs(a.n_faces - b.n_faces) <= 0.05 * a.n_faces  # jpeg colour: stereo features move
