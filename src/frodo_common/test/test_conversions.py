"""Message conversions round-trip and reject bad input with ConversionError."""
import numpy as np
import pytest
from visualization_msgs.msg import Marker

from frodo_common import conversions as c
from frodo_common.geometry import make_transform, yaw_matrix


def test_image_round_trip_and_bgr():
    rgb = np.random.default_rng(1).integers(0, 255, (5, 7, 3), dtype=np.uint8)
    msg = c.numpy_to_image(rgb, 'rgb8', 123, 'cam')
    assert np.array_equal(c.image_to_rgb(msg), rgb)
    bgr = c.numpy_to_image(rgb[..., ::-1], 'bgr8', 123, 'cam')
    assert np.array_equal(c.image_to_rgb(bgr), rgb)
    labels = np.arange(35, dtype=np.uint16).reshape(5, 7) * 300
    assert np.array_equal(c.image_to_numpy(c.numpy_to_image(labels, '16UC1', 0, 'cam')), labels)


def test_image_errors():
    msg = c.numpy_to_image(np.zeros((4, 4, 3), np.uint8), 'rgb8', 0, 'cam')
    msg.data = msg.data[:10]
    with pytest.raises(c.ConversionError, match='too short'):
        c.image_to_numpy(msg)
    msg = c.numpy_to_image(np.zeros((4, 4), np.uint16), '16UC1', 0, 'cam')
    with pytest.raises(c.ConversionError, match='rgb8 or bgr8'):
        c.image_to_rgb(msg)
    msg.encoding = 'yuv422'
    with pytest.raises(c.ConversionError, match='unsupported'):
        c.image_to_numpy(msg)


def test_pose_round_trip_and_nan():
    T = make_transform(yaw_matrix(0.3), [1, -2, 0.5])
    assert np.allclose(c.pose_to_matrix(c.make_pose_stamped(T, 5, 'world').pose), T)
    msg = c.make_pose_stamped(T, 5, 'world')
    msg.pose.position.x = float('nan')
    with pytest.raises(c.ConversionError, match='NaN'):
        c.pose_to_matrix(msg.pose)


def test_camera_info():
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    assert np.allclose(c.camera_info_to_K(c.make_camera_info(K, 640, 480, 0, 'cam')), K)
    with pytest.raises(c.ConversionError):
        c.camera_info_to_K(c.make_camera_info(np.zeros((3, 3)), 640, 480, 0, 'cam'))


def test_table_round_trip_with_vector_field():
    table = np.zeros(3, dtype=[('object_id', '<i4'), ('label', '<u2'), ('code', '<f4', (64,))])
    table['object_id'] = [4, -1, 7]
    table['label'] = [62 * 256 + 1, 67 * 256 + 2, 62 * 256 + 3]
    table['code'] = np.random.default_rng(0).normal(size=(3, 64))
    out = c.cloud_to_table(c.table_to_cloud(table, 9, 'world'))
    for name in table.dtype.names:
        assert np.array_equal(out[name], table[name])


def test_xyz_cloud_drops_nan():
    pts = np.array([[0, 1, 2], [np.nan, 0, 0], [3, 4, 5]], dtype=float)
    assert np.allclose(c.cloud_to_xyz(c.xyz_to_cloud(pts, 0, 'world')), pts[[0, 2]])


def test_mesh_and_box_markers():
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    faces = np.array([[0, 1, 2], [0, 1, 3]])
    marker = c.mesh_to_marker(verts, faces, 'chair', 3, 0, 'world')
    assert marker.type == Marker.TRIANGLE_LIST and marker.ns == 'chair' and marker.id == 3
    tri, tri_faces = c.marker_to_mesh(marker)
    assert np.allclose(tri[tri_faces], verts[faces])
    box = c.box_to_marker([1, 2, 0.4], [0.5, 0.6, 0.8], 0.25, 'chair', 3, 0, 'world')
    center, size, yaw = c.marker_to_box(box)
    assert np.allclose(center, [1, 2, 0.4]) and np.allclose(size, [0.5, 0.6, 0.8]) and yaw == pytest.approx(0.25)


# ---------------------------------------------------------------- bad input (issue 12)
def test_colour_encodings_are_converted_or_rejected_with_a_reason():
    rgb = np.random.default_rng(2).integers(0, 255, (4, 6, 3), dtype=np.uint8)
    bgra = np.concatenate([rgb[..., ::-1], np.full((4, 6, 1), 255, np.uint8)], axis=2)
    assert np.array_equal(c.image_to_rgb(c.numpy_to_image(bgra, 'bgra8', 0, 'cam')), rgb)
    grey = rgb[..., 0]
    assert np.array_equal(c.image_to_rgb(c.numpy_to_image(grey, 'mono8', 0, 'cam')), np.stack([grey] * 3, axis=2))
    labels = c.numpy_to_image(np.zeros((4, 6), np.uint16), '16UC1', 0, 'cam')
    with pytest.raises(c.ConversionError, match='instance or depth image on the colour topic'):
        c.image_to_rgb(labels)


def test_step_and_size_mismatches_are_rejected():
    msg = c.numpy_to_image(np.zeros((4, 6, 3), np.uint8), 'rgb8', 0, 'cam')
    padded = c.numpy_to_image(np.zeros((4, 6, 3), np.uint8), 'rgb8', 0, 'cam')
    padded.step, padded.data = 20, bytes(80)  # rows padded to 20 bytes: valid
    assert c.image_to_rgb(padded).shape == (4, 6, 3)
    msg.step = 10
    with pytest.raises(c.ConversionError, match='shorter than a row'):
        c.image_to_numpy(msg)
    msg.step, msg.data = 18, bytes(18 * 4 + 5)
    with pytest.raises(c.ConversionError, match='too short or too long'):
        c.image_to_numpy(msg)
    wide = c.numpy_to_image(np.zeros((2, 10000), np.uint8), 'mono8', 0, 'cam')
    with pytest.raises(c.ConversionError, match='larger than 8192 pixels'):
        c.image_to_numpy(wide)
    with pytest.raises(c.ConversionError, match='image is 640x480 but camera_info is 320x240'):
        c.check_same_size((640, 480), (320, 240), 'image', 'camera_info')


def test_non_unit_quaternions_and_inf_poses_are_rejected():
    T = make_transform(yaw_matrix(0.3), [1, -2, 0.5])
    msg = c.make_pose_stamped(T, 5, 'world')
    msg.pose.orientation.w *= 1.001  # rounding: normalised
    assert np.allclose(c.pose_to_matrix(msg.pose)[:3, :3], T[:3, :3], atol=1e-3)
    msg.pose.orientation.w *= 2.0
    with pytest.raises(c.ConversionError, match='has norm .* not 1'):
        c.pose_to_matrix(msg.pose)
    msg = c.make_pose_stamped(T, 5, 'world')
    msg.pose.position.z = float('inf')
    with pytest.raises(c.ConversionError, match='NaN or inf'):
        c.pose_to_matrix(msg.pose)


@pytest.mark.parametrize('K, match', [
    ([[0.0, 0, 320], [0, 500, 240], [0, 0, 1]], 'fx, fy must be finite and > 0'),
    ([[500.0, 0, 320], [0, float('nan'), 240], [0, 0, 1]], 'fx, fy must be finite'),
    ([[500.0, 0, 320], [0, 500, 240], [0, 0, 0]], 'last row must be 0 0 1'),
])
def test_unusable_camera_info_is_rejected(K, match):
    with pytest.raises(c.ConversionError, match=match):
        c.camera_info_to_K(c.make_camera_info(np.array(K), 640, 480, 0, 'cam'))
