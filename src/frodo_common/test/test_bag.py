"""Bags written by BagWriter read back with our reader and with the independent rosbags reader."""
from pathlib import Path

import numpy as np
import yaml
from rosbags.highlevel import AnyReader

from frodo_common import conversions as c
from frodo_common.bag import BagReader, BagWriter, qos_yaml


def _write(path: Path, frames: int = 20) -> None:
    with BagWriter(path) as bag:
        bag.add_topic('/frodo/objects', 'visualization_msgs/msg/MarkerArray', qos_yaml(transient_local=True, depth=1))
        for i in range(frames):
            stamp = 1_700_000_000_000_000_000 + i * 100_000_000
            bag.write('/camera/color/image_raw',
                      c.numpy_to_image(np.full((48, 64, 3), i, np.uint8), 'rgb8', stamp, 'cam'), stamp)
            bag.write('/camera/pose', c.make_pose_stamped(np.eye(4), stamp, 'world'), stamp)


def test_round_trip_with_rosbags(tmp_path):
    path = tmp_path / 'a.mcap'
    _write(path)
    reader = BagReader(path)
    assert reader.topics()['/camera/pose'] == ('geometry_msgs/msg/PoseStamped', 20)
    assert not reader.problems and reader.profile == 'ros2'
    meta = yaml.safe_load(reader.metadata['rosbag2']['serialized_metadata'])['rosbag2_bagfile_information']
    assert meta['message_count'] == 40 and meta['version'] == 9
    with AnyReader([path]) as independent:
        counts = {con.topic: con.msgcount for con in independent.connections}
        assert counts['/camera/color/image_raw'] == 20
        for con, log_time, raw in independent.messages():
            msg = independent.deserialize(raw, con.msgtype)
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == log_time


def test_truncated_bag_keeps_readable_messages(tmp_path):
    path = tmp_path / 'a.mcap'
    _write(path, frames=200)
    data = path.read_bytes()
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(data[: int(len(data) * 0.6)])
    reader = BagReader(cut)
    kept = list(reader.messages())
    assert 0 < len(kept) < 400
    assert reader.problems and 'damaged' in reader.problems[0]
    assert kept[0].decode().header.frame_id in ('cam', 'world')
