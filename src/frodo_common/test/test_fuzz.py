"""Property-based fuzzing (hypothesis) of the bag reader and the message conversions: whatever the bytes,
they either give valid data or fail with the module's own error (BagError / ConversionError), never with
another exception. Derandomised and bounded (max_examples), so the run is deterministic and short."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from geometry_msgs.msg import Pose
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField

from frodo_common import conversions as c
from frodo_common.bag import BagError, BagReader, BagWriter

FUZZ = settings(max_examples=80, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
STAMP0 = 1_700_000_000_000_000_000


@pytest.fixture(scope='module')
def bag_bytes(tmp_path_factory) -> tuple[bytes, set[tuple[str, int, bytes]]]:
    """A small valid bag (several chunks) and the (topic, log time, data) of each of its messages."""
    path = tmp_path_factory.mktemp('fuzz') / 'a.mcap'
    with BagWriter(path, chunk_size=1024) as bag:
        for i in range(12):
            stamp = STAMP0 + i * 100_000_000
            bag.write('/camera/pose', c.make_pose_stamped(np.eye(4), stamp, 'world'), stamp)
            bag.write('/camera/color/image_raw', c.numpy_to_image(np.full((6, 8, 3), i, np.uint8), 'rgb8', stamp,
                                                                  'cam'), stamp)
    originals = {(m.topic, m.log_time_ns, m.data) for m in BagReader(path).messages()}
    assert len(originals) == 24
    return path.read_bytes(), originals


def _read(tmp_path, data: bytes):
    path = tmp_path / 'fuzzed.mcap'
    path.write_bytes(data)
    try:
        reader = BagReader(path)
    except BagError:
        return None
    return reader, list(reader.messages())


@FUZZ
@given(flips=st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(1, 255)), min_size=1, max_size=8),
       cut=st.one_of(st.none(), st.floats(0, 1)))
def test_damaged_bags_yield_only_original_messages_or_a_bag_error(tmp_path, bag_bytes, flips, cut):
    data, originals = bag_bytes
    damaged = bytearray(data)
    for where, xor in flips:
        damaged[int(where * len(damaged))] ^= xor
    if cut is not None:
        damaged = damaged[: int(cut * len(damaged))]
    result = _read(tmp_path, bytes(damaged))
    if result is None:
        return
    reader, messages = result
    assert {(m.topic, m.log_time_ns, m.data) for m in messages} <= originals
    assert [m.log_time_ns for m in messages] == sorted(m.log_time_ns for m in messages)
    if len(messages) < len(originals):
        assert reader.problems  # what was lost is said


@FUZZ
@given(tail=st.binary(max_size=400))
def test_random_bytes_after_the_mcap_magic_never_crash_the_reader(tmp_path, tail):
    result = _read(tmp_path, b'\x89MCAP0\r\n' + tail)
    if result is not None:
        assert isinstance(result[1], list)


ENCODINGS = st.sampled_from(['rgb8', 'bgr8', 'rgba8', 'bgra8', 'mono8', '8UC1', 'mono16', '16UC1', '32FC1',
                             'yuv422', '', '64FC1'])


@FUZZ
@given(width=st.integers(0, 12000), height=st.integers(0, 40), step=st.integers(0, 50000),
       encoding=ENCODINGS, big=st.booleans(), extra=st.integers(-5, 5))
def test_image_conversion_returns_a_consistent_array_or_a_conversion_error(width, height, step, encoding, big, extra):
    size = max(0, min(step * height + extra, 200_000))
    msg = Image(width=width, height=height, step=step, encoding=encoding, is_bigendian=int(big),
                data=bytes(size))
    try:
        arr = c.image_to_numpy(msg)
    except c.ConversionError:
        return
    assert arr.shape[:2] == (height, width) and max(width, height) <= c.MAX_IMAGE_SIDE
    try:
        rgb = c.image_to_rgb(msg)
    except c.ConversionError:
        assert encoding not in c.COLOUR_ENCODINGS + c.CONVERTED_COLOUR_ENCODINGS
        return
    assert rgb.shape == (height, width, 3) and rgb.dtype == np.uint8


FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=64)


@FUZZ
@given(k=st.lists(FLOATS, min_size=9, max_size=9), d=st.lists(FLOATS, max_size=5),
       width=st.integers(0, 20000), height=st.integers(0, 20000))
def test_camera_info_gives_a_pinhole_matrix_or_a_conversion_error(k, d, width, height):
    msg = CameraInfo(k=k, d=d, width=width, height=height)
    try:
        K = c.camera_info_to_K(msg)
    except c.ConversionError:
        return
    assert np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1])


@FUZZ
@given(values=st.lists(FLOATS, min_size=7, max_size=7))
def test_poses_give_a_rigid_transform_or_a_conversion_error(values):
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = values[:3]
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = values[3:]
    try:
        T = c.pose_to_matrix(pose)
    except c.ConversionError:
        return
    R = T[:3, :3]
    assert np.all(np.isfinite(T)) and np.allclose(R @ R.T, np.eye(3), atol=1e-6)
    assert np.isclose(np.linalg.det(R), 1.0, atol=1e-6)


FIELD = st.builds(lambda name, offset, datatype, count: PointField(name=name, offset=offset, datatype=datatype,
                                                                    count=count),
                  st.sampled_from(['x', 'y', 'z', 'label', 'code']), st.integers(0, 64), st.integers(0, 9),
                  st.integers(0, 4))


@FUZZ
@given(fields=st.lists(FIELD, max_size=4), point_step=st.integers(0, 64), width=st.integers(0, 50),
       height=st.integers(0, 3), size=st.integers(0, 4000), big=st.booleans())
def test_clouds_give_a_table_or_a_conversion_error(fields, point_step, width, height, size, big):
    msg = PointCloud2(fields=fields, point_step=point_step, width=width, height=height, is_bigendian=big,
                      row_step=point_step * width, data=bytes(size))
    try:
        table = c.cloud_to_table(msg)
    except c.ConversionError:
        return
    assert len(table) == width * height
