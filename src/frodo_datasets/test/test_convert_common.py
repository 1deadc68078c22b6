"""Converter building blocks: keyframe selection, intrinsics scaling, depth registration, gravity alignment,
landmarks from depth and from ORB features (on rendered views with known geometry)."""
import numpy as np
import pytest

from frodo_common.geometry import invert_transform, look_at
from frodo_datasets.convert.common import (backproject, register_depth, scale_intrinsics, select_keyframes,
                                           valid_pose)
from frodo_datasets.convert.fixtures import render_sequence
from frodo_datasets.convert.gravity import align_floor, align_up, camera_up, fit_floor, rotation_to_z
from frodo_datasets.convert.landmarks import DepthLandmarks, FeatureLandmarks, VoxelMap
from frodo_datasets.render import intrinsics


def test_keyframes_spread_evenly_every_and_max():
    assert select_keyframes(100, views=5) == [0, 25, 50, 74, 99]
    assert select_keyframes(10, every=3) == [0, 3, 6, 9]
    assert select_keyframes(10, every=2, views=3) == [0, 4, 8]
    assert select_keyframes(10, max_frames=4) == [0, 1, 2, 3]
    assert select_keyframes(3, views=35) == [0, 1, 2]
    with pytest.raises(ValueError):
        select_keyframes(10, every=0)


def test_valid_pose_rejects_inf_nan_and_non_rigid():
    assert valid_pose(np.eye(4))
    assert not valid_pose(np.full((4, 4), -np.inf))
    bad = np.eye(4)
    bad[0, 3] = np.nan
    assert not valid_pose(bad) and not valid_pose(np.diag([2.0, 1, 1, 1])) and not valid_pose(None)


def test_scaled_intrinsics_project_the_same_point():
    K = intrinsics(1296, 968, 60)
    K2 = scale_intrinsics(K, (1296, 968), (640, 480))
    X = np.array([0.3, -0.2, 2.0])
    uv = K @ X / X[2]
    uv2 = K2 @ X / X[2]
    # pixel centres: u' + 0.5 = (u + 0.5) * s
    assert np.allclose(uv2[0] + 0.5, (uv[0] + 0.5) * 640 / 1296)
    assert np.allclose(uv2[1] + 0.5, (uv[1] + 0.5) * 480 / 968)


def _plane_depth(K, size, z0=2.0, slope=0.1):
    w, h = size
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    # plane z = z0 + slope * y (camera frame): z = z0 / (1 - slope * (v - cy) / fy)
    return (z0 / (1 - slope * (v - K[1, 2]) / K[1, 1])).astype(np.float32)


def test_register_depth_by_intrinsics_and_by_extrinsics():
    K_d = intrinsics(80, 60, 70)
    depth = _plane_depth(K_d, (80, 60))
    K_c = intrinsics(160, 120, 60)
    out = register_depth(depth, K_d, K_c, (160, 120))
    expected = _plane_depth(K_c, (160, 120))
    assert np.allclose(out, expected, rtol=0.03)
    # a depth camera 5 cm to the right: splatted depth is the same plane seen from the colour camera
    T = np.eye(4)
    T[0, 3] = 0.05
    out2 = register_depth(depth, K_d, K_c, (160, 120), T)
    valid = out2 > 0
    assert valid.mean() > 0.3 and np.allclose(out2[valid], expected[valid], rtol=0.03)


def test_rotation_to_z_and_align_up():
    for up in ([0, 1, 0], [0, 0, -1], [1, 2, 3], [0, 0, 1]):
        R = rotation_to_z(np.array(up, float))
        assert np.allclose(R @ (np.array(up) / np.linalg.norm(up)), [0, 0, 1])
        assert np.allclose(R.T @ R, np.eye(3)) and np.linalg.det(R) == pytest.approx(1)
    assert np.allclose(align_up([0, 1, 0])[:3, :3] @ [0, 1, 0], [0, 0, 1])


def test_floor_fit_picks_the_lowest_large_horizontal_plane():
    rng = np.random.default_rng(0)
    # dataset world with y up: floor y = -1 (4000 pts), table top y = -0.25 (2500 pts), a wall x = 2
    floor = np.c_[rng.uniform(-3, 3, 4000), np.full(4000, -1.0), rng.uniform(-3, 3, 4000)]
    table = np.c_[rng.uniform(-0.5, 0.5, 2500), np.full(2500, -0.25), rng.uniform(-0.5, 0.5, 2500)]
    wall = np.c_[np.full(3000, 2.0), rng.uniform(-1, 1.6, 3000), rng.uniform(-3, 3, 3000)]
    pts = np.concatenate([floor, table, wall]) + rng.normal(0, 0.005, (9500, 3))
    cams = [look_at(np.array([x, 0.5, -2.0]), np.array([0, -0.5, 0]), up=(0, 1, 0)) for x in (-1, 0, 1)]
    up = camera_up(cams)
    plane = fit_floor(pts, up, np.array([T[:3, 3] for T in cams]))
    assert np.degrees(np.arccos(plane.normal @ [0, 1, 0])) < 1.0 and plane.d == pytest.approx(1.0, abs=0.01)
    T = align_floor(plane)
    aligned = floor @ T[:3, :3].T + T[:3, 3]
    assert np.allclose(aligned[:, 2], 0, atol=0.02)


def test_voxel_map_counts_views_not_points():
    vm = VoxelMap(0.1)
    vm.add_view(np.array([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [1.05, 0, 0]]))
    vm.add_view(np.array([[0.03, 0.03, 0.03]]))
    two = vm.points(min_views=2)
    assert len(two) == 1 and np.allclose(two[0], 0.02)
    assert len(vm.points(1)) == 2


@pytest.fixture(scope='module')
def views():
    return render_sequence(frames=6, width=160, height=120, seed=3, layout='orbit')


def test_depth_landmarks_lie_on_the_surface(views):
    lm = DepthLandmarks(stride=6, voxel=0.05, min_views=2)
    for T, d in zip(views.poses, views.depth):
        lm.add(d, views.K, T)
    pts = lm.points()
    assert len(pts) > 50
    # every landmark re-projects onto a rendered surface within the voxel size
    T = views.poses[0]
    cam = pts @ invert_transform(T)[:3, :3].T + invert_transform(T)[:3, 3]
    uv = cam @ views.K.T
    uv = uv[:, :2] / uv[:, 2:]
    inside = (cam[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < 159.5) & (uv[:, 1] >= 0) & (uv[:, 1] < 119.5)
    d = views.depth[0][np.round(uv[inside, 1]).astype(int), np.round(uv[inside, 0]).astype(int)]
    front = np.abs(d - cam[inside, 2])
    assert np.median(front) < 0.03
    assert len(backproject(views.depth[0], views.K, T, stride=8)) > 0


def test_feature_landmarks_triangulate_onto_the_surface():
    views = render_sequence(frames=24, width=160, height=120, seed=3, layout='orbit')  # 15 degrees apart
    poses, rgbs, depths = views.poses[:6], views.rgb[:6], views.depth[:6]
    lm = FeatureLandmarks(voxel=0.02)
    for T, rgb in zip(poses, rgbs):
        lm.add(rgb, views.K, T)
    pts = lm.points()
    assert lm.pairs == 5 and len(pts) >= 30
    # distance to the nearest depth back-projection of the views (dense surface samples)
    surface = np.concatenate([backproject(d, views.K, T, stride=1) for T, d in zip(poses, depths)])
    from scipy.spatial import cKDTree
    dist, _ = cKDTree(surface).query(pts)
    assert np.median(dist) < 0.05
