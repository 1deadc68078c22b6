"""Fused-stage placement: a decoded shape lands in its 3D box with the box height as scale (Sec. 5.3 init)."""
import numpy as np
import pytest
import trimesh

from frodo_optim.core import fused_estimate, place_from_box


def _normalised_box_shape(extents):
    return trimesh.creation.box(extents=extents)


def test_scale_is_box_height_and_centre_matches():
    shape = _normalised_box_shape([0.6, 0.4, 1.0])
    T, scale, yaw = place_from_box(shape, center=[2.0, 1.0, 0.45], size=[0.54, 0.36, 0.9], yaw=0.3)
    assert scale == pytest.approx(0.9)
    placed = shape.copy().apply_transform(T)
    assert np.allclose(placed.bounding_box_oriented.centroid, [2.0, 1.0, 0.45], atol=1e-9)
    assert yaw == pytest.approx(0.3)


def test_footprint_axes_are_swapped_when_they_fit_better():
    shape = _normalised_box_shape([0.4, 0.8, 1.0])  # long along y
    _, _, yaw = place_from_box(shape, center=[0, 0, 0.5], size=[1.6, 0.8, 1.0], yaw=0.0)  # box long along x
    assert yaw == pytest.approx(np.pi / 2)


def test_fused_estimate_world_mesh_and_box():
    shape = _normalised_box_shape([0.5, 0.5, 1.0])
    est = fused_estimate(3, 'chair', 62, np.zeros(64), 5, shape, (np.array([1.0, 0, 0.4]), np.array([0.4, 0.4, 0.8]), 0.0))
    lo, hi = est.mesh_world.bounds
    assert np.allclose(lo, [0.8, -0.2, 0.0]) and np.allclose(hi, [1.2, 0.2, 0.8])
    assert np.allclose(est.box.size, [0.4, 0.4, 0.8]) and est.stage == 'fused'


def test_state_table_to_json_records():
    from frodo_optim.states import STATES_DTYPE, states_to_records
    table = np.zeros(1, dtype=STATES_DTYPE)
    table[0] = (7, 67, 1, 12, 1.3, np.eye(4).ravel(), [1, 2, 0.4, 1.2, 0.8, 0.75, 0.1], np.ones(64), 0.5, 5)
    record = states_to_records(table)[7]
    assert record['class'] == 'dining table' and record['stage'] == 'sparse' and record['num_views'] == 12
    assert record['stage_reason'] == 'dense not better than sparse'
    assert record['pose'] == np.eye(4).tolist() and record['box']['size'] == [1.2, 0.8, 0.75]
