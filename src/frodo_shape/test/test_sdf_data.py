"""SDF sampling (paper Sec. 4 training data): signs and distances on shapes with known SDFs."""
import numpy as np
import trimesh

from frodo_shape.sdf_data import (SamplingConfig, cached_samples, inside, inside_check, sample_sdf, signed_distance,
                                  winding_number)


def test_sphere_signed_distance_matches_analytic():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    pts = np.random.default_rng(0).uniform(-1, 1, (2000, 3))
    sd = signed_distance(sphere, pts, n_dense=20000)
    exact = np.linalg.norm(pts, axis=1) - 0.5
    assert np.all(np.sign(sd[np.abs(exact) > 0.01]) == np.sign(exact[np.abs(exact) > 0.01]))
    assert np.abs(sd - exact).max() < 0.005  # tessellation error of the icosphere


def test_union_of_overlapping_boxes_is_inside_where_boxes_overlap():
    # Two overlapping closed boxes concatenated (not boolean-unioned): ray parity alone says "outside" in
    # the overlap; splitting into bodies gets it right.
    a = trimesh.creation.box((0.6, 0.2, 0.2))
    b = trimesh.creation.box((0.2, 0.6, 0.2))
    mesh = trimesh.util.concatenate([a, b])
    pts = np.array([[0.0, 0.0, 0.0], [0.25, 0.0, 0.0], [0.0, 0.25, 0.0], [0.25, 0.25, 0.0]])
    assert inside(mesh, pts).tolist() == [True, True, True, False]
    box = trimesh.creation.box((0.6, 0.4, 0.2))
    d = signed_distance(box, np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.3]]), n_dense=5000)
    np.testing.assert_allclose(d, [-0.1, 0.2], atol=1e-6)


def test_winding_number_of_open_mesh_part():
    box = trimesh.creation.box((0.5, 0.5, 0.5))
    w = winding_number(box, np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(w, [1.0, 0.0], atol=1e-6)


def test_inside_check_agrees_on_closed_parts_and_flags_an_open_tube():
    # A table of two closed boxes (top and pedestal, concatenated): the inside test matches the exact volume.
    top = trimesh.creation.box((1.0, 0.6, 0.1))
    top.apply_translation((0.0, 0.0, 0.35))
    table = trimesh.util.concatenate([top, trimesh.creation.box((0.1, 0.1, 0.6))])
    check = inside_check(table)
    exact = (1.0 * 0.6 * 0.1 + 0.1 * 0.1 * 0.6) / (1.0 * 0.6 * 0.7)  # bounding box 1.0 x 0.6 x 0.7
    assert check['consistent'] and np.isclose(check['reference_fraction'], exact)
    assert abs(check['inside_fraction'] - exact) < 0.02
    # A box with its two x faces missing: an open tube whose winding number calls most of its hollow inside,
    # while its voxelisation (open to the outside) fills nothing but the walls.
    box = trimesh.creation.box((1.0, 0.6, 0.4))
    tube = trimesh.Trimesh(box.vertices, box.faces[np.abs(box.face_normals[:, 0]) < 0.5])
    check = inside_check(tube)
    assert not tube.is_volume and not check['consistent']
    assert check['inside_fraction'] > 0.3 and check['reference_fraction'] < 0.1


def test_samples_have_both_signs_and_are_cached(tmp_path):
    cfg = SamplingConfig(n_near=1000, n_uniform=200, n_surface=256, n_dense=5000)
    box = trimesh.creation.box((0.8, 0.6, 0.4))
    s = sample_sdf(box, cfg, seed=1)
    assert s.points.shape == (1200, 3) and s.sdf.shape == (1200,) and s.surface.shape == (256, 3)
    assert 0.2 < (s.sdf < 0).mean() < 0.8
    c1 = cached_samples(box, cfg, tmp_path, seed=1)
    assert len(list(tmp_path.glob('*.npz'))) == 1
    c2 = cached_samples(box, cfg, tmp_path, seed=1)
    np.testing.assert_array_equal(c1.sdf, c2.sdf)
    np.testing.assert_array_equal(c1.sdf, s.sdf)
