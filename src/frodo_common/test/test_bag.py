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


# ---------------------------------------------------------------- bad input
import pytest  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from mcap.writer import Writer  # noqa: E402

from frodo_common.bag import BagError  # noqa: E402

STAMP0 = 1_700_000_000_000_000_000


@pytest.mark.parametrize('content, message', [
    (b'hello, this is not a bag at all\n' * 10, 'is not an MCAP file'),
    (b'', 'is empty'),
    (b'SQLite format 3\x00' + bytes(100), r'rosbag2 SQLite \(.db3\) bag'),
    (b'#ROSBAG V2.0\n' + bytes(100), 'ROS 1 bag'),
])
def test_files_that_are_not_mcap_are_rejected_at_once(tmp_path, content, message):
    path = tmp_path / 'garbage.mcap'
    path.write_bytes(content)
    with pytest.raises(BagError, match=message):
        BagReader(path)


def test_an_mcap_of_another_profile_is_rejected(tmp_path):
    path = tmp_path / 'other.mcap'
    with open(path, 'wb') as f:
        writer = Writer(f)
        writer.start(profile='protobuf', library='test')
        writer.finish()
    with pytest.raises(BagError, match="profile is 'protobuf'"):
        BagReader(path)


def test_a_bag_directory_resolves_to_its_mcap(tmp_path):
    _write(tmp_path / 'bag' / 'bag_0.mcap', frames=2)
    assert BagReader(tmp_path / 'bag').topics()['/camera/pose'][1] == 2
    (tmp_path / 'empty').mkdir()
    with pytest.raises(BagError, match='0 .mcap files'):
        BagReader(tmp_path / 'empty')


def test_a_corrupt_chunk_in_the_middle_is_skipped_and_reading_goes_on(tmp_path):
    path = tmp_path / 'a.mcap'
    with BagWriter(path, chunk_size=4096) as bag:
        for i in range(60):
            stamp = STAMP0 + i * 100_000_000
            bag.write('/camera/pose', c.make_pose_stamped(np.eye(4), stamp, 'world'), stamp)
            bag.write('/camera/color/image_raw',
                      c.numpy_to_image(np.random.default_rng(i).integers(0, 255, (24, 32, 3), np.uint8), 'rgb8',
                                       stamp, 'cam'), stamp)
    with open(path, 'rb') as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda ci: ci.chunk_start_offset)
    assert len(chunks) >= 5
    middle = chunks[len(chunks) // 2]
    data = bytearray(path.read_bytes())
    at = middle.chunk_start_offset + middle.chunk_length // 2
    data[at:at + 8] = bytes(b ^ 0xFF for b in data[at:at + 8])
    bad = tmp_path / 'bad.mcap'
    bad.write_bytes(bytes(data))
    reader = BagReader(bad)
    kept = list(reader.messages())
    assert 0 < len(kept) < 120
    assert kept[-1].log_time_ns == STAMP0 + 59 * 100_000_000  # messages after the damaged chunk were read
    assert any('1 damaged chunk(s) skipped' in p for p in reader.problems), reader.problems


def test_unknown_schema_encoding_out_of_order_and_duplicate_stamps(tmp_path):
    path = tmp_path / 'a.mcap'
    with BagWriter(path) as bag:
        for i in (0, 2, 1, 1, 3):  # stored out of order, stamp 1 twice
            stamp = STAMP0 + i * 100_000_000
            bag.write('/camera/pose', c.make_pose_stamped(np.eye(4), stamp, 'world'), stamp)
        json_schema = bag._writer.register_schema('Thing', 'jsonschema', b'{}')
        channel = bag._writer.register_channel('/json/thing', 'json', json_schema)
        bag._writer.add_message(channel, log_time=STAMP0, data=b'{}', publish_time=STAMP0)
    reader = BagReader(path)
    stamps = [m.log_time_ns for m in reader.messages()]
    assert stamps == [STAMP0 + i * 100_000_000 for i in range(4)]
    text = '\n'.join(reader.problems)
    assert '/camera/pose: 1 message(s) with an already seen stamp dropped' in text
    assert 'out of log-time order' in text
    assert "1 message(s) on /json/thing (encoding 'json'" in text
    assert reader.missing_topics(['/camera/pose', '/camera/color/image_raw']) == ['/camera/color/image_raw']
