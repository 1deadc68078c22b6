"""Contract bags read by an independent reader (rosbags, pure Python): the committed demo bags and a fresh one.

Checks what `ros2 bag play`, Foxglove and rosbags rely on (CONTRACT.md "Bags"): profile `ros2`, `ros2msg`
schemas, `cdr` channels with `offered_qos_profiles` (latched ground truth), the `rosbag2` metadata record,
log time = header stamp, frame ids, encodings, and values that round-trip (pose, instance pixel, GT vertex).
"""
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability
from rosbags.typesys import Stores, get_typestore

from frodo_common.geometry import quat_to_matrix
from frodo_datasets.realcapture import preset_kwargs
from frodo_datasets.synth import SynthConfig, sidecar_path, synthesize

BAGS = Path(__file__).resolve().parents[3] / 'bags'
TYPES = {
    '/camera/color/image_raw': 'sensor_msgs/msg/Image',
    '/camera/color/camera_info': 'sensor_msgs/msg/CameraInfo',
    '/camera/pose': 'geometry_msgs/msg/PoseStamped',
    '/camera/instances': 'sensor_msgs/msg/Image',
    '/slam/points': 'sensor_msgs/msg/PointCloud2',
    '/ground_truth/objects': 'visualization_msgs/msg/MarkerArray',
}
WORLD_TOPICS = {'/camera/pose', '/slam/points'}


@pytest.fixture(scope='module')
def fresh_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp('compat') / 'fresh.mcap'
    synthesize(SynthConfig(scene='walk', objects=3, frames=6, width=96, height=72, seed=4, slam_every=3,
                           min_mask_pixels=5), path)
    return path


@pytest.fixture(scope='module')
def handheld_bag(tmp_path_factory):
    """A bag of the real-capture preset (every condition on), small."""
    path = tmp_path_factory.mktemp('compat') / 'handheld.mcap'
    synthesize(SynthConfig(**{**preset_kwargs('handheld'), 'frames': 6}, objects=3, width=96, height=72, seed=4,
                           slam_every=3, min_mask_pixels=5), path)
    return path


def _bags(fresh_bag):
    return [(BAGS / 'demo_walk.mcap', 50), (BAGS / 'demo_orbit.mcap', 35), (fresh_bag, 6)]


def _read(path: Path):
    store = get_typestore(Stores.ROS2_JAZZY)
    with AnyReader([path], default_typestore=store) as reader:
        conns = {c.topic: c for c in reader.connections}
        msgs = [(c.topic, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]
    return conns, msgs


def test_demo_bags_exist_and_are_small():
    for name in ('demo_walk.mcap', 'demo_orbit.mcap'):
        assert (BAGS / name).is_file(), f'{name} missing: see bags/README.md to regenerate'
        assert (BAGS / name).stat().st_size < 5e6


def test_mcap_profile_schemas_and_metadata(fresh_bag, handheld_bag):
    for path, frames in _bags(fresh_bag) + [(handheld_bag, 6)]:
        with open(path, 'rb') as f:
            reader = make_reader(f)
            assert reader.get_header().profile == 'ros2'
            summary = reader.get_summary()
            assert {s.encoding for s in summary.schemas.values()} == {'ros2msg'}
            assert {c.message_encoding for c in summary.channels.values()} == {'cdr'}
            for c in summary.channels.values():
                assert summary.schemas[c.schema_id].name == TYPES[c.topic]
                yaml.safe_load(c.metadata['offered_qos_profiles'])
            records = {m.name: m.metadata for m in reader.iter_metadata()}
            info = yaml.safe_load(records['rosbag2']['serialized_metadata'])['rosbag2_bagfile_information']
            assert info['version'] == 9 and info['storage_identifier'] == 'mcap'
            assert info['message_count'] == summary.statistics.message_count


def test_rosbags_reads_topics_stamps_and_values(fresh_bag, handheld_bag):
    for path, frames in _bags(fresh_bag) + [(handheld_bag, 6)]:
        conns, msgs = _read(path)
        assert {t: c.msgtype for t, c in conns.items()} == TYPES
        counts = {t: c.msgcount for t, c in conns.items()}
        for topic in ('/camera/color/image_raw', '/camera/color/camera_info', '/camera/pose', '/camera/instances'):
            assert counts[topic] == frames
        assert counts['/ground_truth/objects'] == 1 and counts['/slam/points'] >= 1
        qos = conns['/ground_truth/objects'].ext.offered_qos_profiles[0]
        assert qos.durability == QosDurability.TRANSIENT_LOCAL and qos.depth == 1
        assert all(c.ext.offered_qos_profiles for c in conns.values())
        first_image = next(i for i, m in enumerate(msgs) if m[0] == '/camera/color/image_raw')
        assert any(m[0] == '/camera/color/camera_info' for m in msgs[:first_image])
        assert any(m[0] == '/ground_truth/objects' for m in msgs[:first_image])
        for topic, log_ns, msg in msgs:
            header = msg.markers[0].header if topic == '/ground_truth/objects' else msg.header
            assert header.stamp.sec * 10**9 + header.stamp.nanosec == log_ns
            world = topic in WORLD_TOPICS or topic == '/ground_truth/objects'
            assert header.frame_id == ('world' if world else 'camera_color_optical_frame')
            if topic == '/camera/color/image_raw':
                assert msg.encoding == 'rgb8' and msg.step == 3 * msg.width
            elif topic == '/camera/instances':
                assert msg.encoding == '16UC1' and msg.is_bigendian == 0 and msg.step == 2 * msg.width
            elif topic == '/camera/color/camera_info':
                assert msg.distortion_model == 'plumb_bob' and msg.k[0] > 0
            elif topic == '/slam/points':
                assert [(f.name, f.offset, f.datatype) for f in msg.fields] == [('x', 0, 7), ('y', 4, 7), ('z', 8, 7)]
            elif topic == '/ground_truth/objects':
                assert all(m.type == 11 and len(m.points) % 3 == 0 and m.ns in ('chair', 'dining table')
                           for m in msg.markers)
        stamps = [t for topic, t, _ in msgs if topic == '/camera/color/image_raw']
        assert stamps == sorted(stamps) and len(set(stamps)) == frames


def test_round_trip_values_against_the_sidecar(fresh_bag):
    for path, frames in _bags(fresh_bag):
        gt = json.loads(sidecar_path(path).read_text())
        _, msgs = _read(path)
        poses = [m for topic, _, m in msgs if topic == '/camera/pose']
        # A pose: the published matrix (no pose noise in these bags) is the true one.
        T = np.asarray(gt['frames'][frames // 2]['T_world_camera'])
        p = poses[frames // 2].pose
        assert np.allclose([p.position.x, p.position.y, p.position.z], T[:3, 3], atol=1e-9)
        assert np.allclose(quat_to_matrix([p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]),
                           T[:3, :3], atol=1e-9)
        # An instance pixel: high byte = a ground-truth class id, low byte in 1..255.
        inst = next(m for topic, _, m in msgs if topic == '/camera/instances')
        pixels = np.frombuffer(bytes(inst.data), '<u2').reshape(inst.height, inst.width)
        coco = {o['coco_id'] for o in gt['scene']['objects']}
        values = np.unique(pixels[pixels > 0])
        assert len(values) and all((v >> 8) in coco and 1 <= (v & 0xFF) <= 255 for v in values)
        # A ground-truth vertex: the lowest point of each object is on the floor, inside its footprint.
        markers = next(m for topic, _, m in msgs if topic == '/ground_truth/objects').markers
        assert [m.id for m in markers] == [o['id'] for o in gt['scene']['objects']]
        for m, obj in zip(markers, gt['scene']['objects']):
            v = np.array([[q.x, q.y, q.z] for q in m.points])
            assert v[:, 2].min() == pytest.approx(0.0, abs=1e-6)
            centre = np.asarray(obj['T_world_object'])[:3, 3]
            assert np.linalg.norm(v.mean(axis=0)[:2] - centre[:2]) < max(obj['extents'][:2])
