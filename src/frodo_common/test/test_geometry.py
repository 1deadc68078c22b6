"""Geometry helpers: quaternions, similarity inverses, projection and rays agree with each other."""
import numpy as np
import pytest

from frodo_common import geometry as g


def test_quaternion_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[3] >= 0 else -q
        R = g.quat_to_matrix(q)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.allclose(g.matrix_to_quat(R), q, atol=1e-9)


def test_invalid_quaternion_raises():
    with pytest.raises(ValueError):
        g.quat_to_matrix([0, 0, 0, 0])


def test_similarity_inverse():
    T = g.make_transform(g.yaw_matrix(0.7), [1, 2, 3], scale=2.5)
    assert np.allclose(g.invert_transform(T) @ T, np.eye(4))


def test_projection_and_rays_are_consistent():
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    T_wc = g.look_at([3.0, 1.0, 1.5], [0.0, 0.0, 0.5])
    point = np.array([[0.2, -0.1, 0.6]])
    uv, depth = g.project_points(K, g.invert_transform(T_wc), point)
    assert depth[0] > 0
    origin, direction = g.pixel_rays(K, T_wc, uv)
    to_point = point[0] - origin
    assert np.allclose(direction[0], to_point / np.linalg.norm(to_point), atol=1e-9)


def test_look_at_is_optical_frame():
    T = g.look_at([0, -2, 1], [0, 0, 1])
    assert np.allclose(T[:3, 2], [0, 1, 0])   # z forward
    assert np.allclose(T[:3, 1], [0, 0, -1])  # y down (world up is -y)


def test_box_corners_and_iou():
    corners = g.box_corners([0, 0, 0.5], [2, 1, 1], np.pi / 2)
    assert np.allclose(corners.min(0), [-0.5, -1, 0]) and np.allclose(corners.max(0), [0.5, 1, 1])
    assert g.box_iou_2d([0, 0, 2, 2], [1, 0, 3, 2]) == pytest.approx(1 / 3)
    assert g.box_iou_2d([0, 0, 1, 1], [2, 2, 3, 3]) == 0.0


def test_a_box_is_the_same_only_as_an_identical_one():
    Box3D = g.Box3D
    box = Box3D([1.0, 2.0, 0.4], [0.5, 0.6, 0.8], 0.1)
    assert box.same_as(Box3D(box.center.copy(), box.size.copy(), 0.1))
    assert not box.same_as(Box3D(box.center + [1e-9, 0, 0], box.size, 0.1))
    assert not box.same_as(Box3D(box.center, box.size, 0.1 + 1e-12))
    assert not box.same_as(Box3D(box.center, box.size * 1.01, 0.1))


def test_backproject_pixels_inverts_project_points():
    rng = np.random.default_rng(4)
    K = np.array([[420.0, 0.0, 161.0], [0.0, 410.0, 118.0], [0.0, 0.0, 1.0]])
    T_wc = g.look_at([1.0, -2.0, 1.4], [0.2, 0.5, 0.6])
    points = rng.uniform([-0.5, 0.0, 0.0], [1.0, 1.5, 1.2], (50, 3))
    uv, z = g.project_points(K, g.invert_transform(T_wc), points)
    np.testing.assert_allclose(g.backproject_pixels(K, T_wc, uv[:, 0], uv[:, 1], z), points, atol=1e-9)


def test_bearing_span_is_the_smallest_arc_holding_every_point():
    """Across the +-180 degree seam too; NaN rows left out; one point gives 0."""
    centre = np.array([1.0, -2.0, 0.4])

    def around(degrees):
        a = np.radians(degrees)
        return np.c_[1.0 + 2.5 * np.cos(a), -2.0 + 2.5 * np.sin(a), np.full(len(a), 1.4)]

    assert g.bearing_span(around([10, 20, 40]), centre) == pytest.approx(30.0)
    assert g.bearing_span(around([170, -170, 175]), centre) == pytest.approx(20.0)
    assert g.bearing_span(around([0, 120, 240]), centre) == pytest.approx(240.0)
    assert g.bearing_span(np.r_[around([10, 40]), [[np.nan, 0.0, 1.0]]], centre) == pytest.approx(30.0)
    assert g.bearing_span(around([10]), centre) == 0.0
