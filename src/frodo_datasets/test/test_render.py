"""Ray-cast renderer: geometry of labels/depth, projection convention, textures, shadows, determinism."""
import time

import numpy as np
import pytest
import trimesh

from frodo_common.geometry import invert_transform, look_at, project_points
from frodo_datasets.render import TEXTURE_KINDS, Light, Material, RenderObject, Renderer, intrinsics, render

W, H = 160, 120


def _floor():
    floor = trimesh.creation.box((6.0, 6.0, 0.02))
    floor.apply_translation((0, 0, -0.01))
    return RenderObject(floor, Material(kind='checker', scale=2.0), label=0)


def _box(centre, size=(0.5, 0.5, 0.8), label=1, material=None):
    mesh = trimesh.creation.box(size)
    mesh.apply_translation(centre)
    return RenderObject(mesh, material or Material(color=(0.8, 0.2, 0.2)), label=label)


def test_labels_align_with_depth_and_projection():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.4)
    sphere.apply_translation((0.3, 0.2, 0.5))
    objects = [RenderObject(sphere, Material(kind='noise', seed=3), label=5), _box((-0.8, 0.5, 0.4), label=9)]
    K = intrinsics(W, H, 60.0)
    T = look_at((0.5, -3.0, 1.5), (0.0, 0.0, 0.4))
    out = render(objects, K, T, W, H)
    assert out.rgb.shape == (H, W, 3) and out.rgb.dtype == np.uint8
    assert out.labels.dtype == np.uint16 and out.depth.dtype == np.float32
    # No room geometry: a pixel has depth exactly where it has a label.
    assert np.array_equal(out.labels > 0, out.depth > 0)
    assert set(np.unique(out.labels)) == {0, 5, 9}
    # The sphere point nearest to the camera projects to a pixel of label 5 with that point's z-depth.
    eye = T[:3, 3]
    centre = np.array([0.3, 0.2, 0.5])
    near = centre + 0.4 * (eye - centre) / np.linalg.norm(eye - centre)
    uv, z = project_points(K, invert_transform(T), near[None])
    u, v = np.round(uv[0]).astype(int)
    assert out.labels[v, u] == 5
    assert out.depth[v, u] == pytest.approx(z[0], abs=0.01)
    # Background pixels are black by default.
    assert np.all(out.rgb[out.labels == 0] == 0)


def test_depth_is_z_along_optical_axis():
    plane = trimesh.creation.box((20.0, 20.0, 0.01))
    plane.apply_translation((0, 0, -0.005))
    K = intrinsics(W, H, 70.0)
    T = look_at((0.0, 0.0, 2.0), (0.0, 1e-3, 0.0), up=(0.0, 1.0, 0.0))
    out = render([RenderObject(plane, Material(), 1)], K, T, W, H, shadows=False)
    assert np.allclose(out.depth, 2.0, atol=1e-3)  # fronto-parallel plane: constant z-depth, not ray length


def test_deterministic_and_materials():
    rng = np.random.default_rng(0)
    objects = [_floor()] + [_box((i - 2.0, 0.0, 0.4), label=i + 1, material=Material.random(rng, kinds=[k]))
                            for i, k in enumerate(TEXTURE_KINDS)]
    renderer = Renderer(objects)
    K, T = intrinsics(W, H), look_at((0.0, -4.0, 2.0), (0.0, 0.0, 0.4))
    a, b = renderer.render(K, T, W, H), renderer.render(K, T, W, H)
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.labels, b.labels)
    assert Material.random(np.random.default_rng(1)) == Material.random(np.random.default_rng(1))
    # Solid textures depend on the 3D point only; non-plain kinds vary over a surface.
    pts = np.random.default_rng(2).uniform(-1, 1, (500, 3))
    for kind in TEXTURE_KINDS:
        m = Material(color=(0.9, 0.9, 0.9), color2=(0.1, 0.1, 0.1), kind=kind, seed=4)
        albedo = m.albedo(pts)
        assert albedo.shape == (500, 3) and np.all((albedo >= 0) & (albedo <= 1))
        assert np.array_equal(albedo, m.albedo(pts))
        assert (albedo.std() > 0.05) == (kind != 'plain')
    with pytest.raises(ValueError, match='texture kind'):
        Material(kind='marble')


def test_shadows_darken_the_floor_under_an_object():
    objects = [_floor(), _box((0.0, 0.0, 1.0), size=(1.0, 1.0, 0.1))]  # a slab hovering over the floor
    for o in objects:
        o.material = Material(color=(0.8, 0.8, 0.8))
    K, T = intrinsics(W, H), look_at((2.5, -2.5, 1.2), (0.0, 0.0, 0.0))
    light = Light(direction=(0.0, 0.0, -1.0), intensity=0.7)
    lit = render(objects, K, T, W, H, light=light, shadows=False)
    shadowed = render(objects, K, T, W, H, light=light, shadows=True)
    uv, _ = project_points(K, invert_transform(T), np.array([[0.0, 0.0, 0.0]]))
    u, v = np.round(uv[0]).astype(int)
    assert shadowed.labels[v, u] == 0 and shadowed.depth[v, u] > 0  # floor visible below the slab
    assert int(shadowed.rgb[v, u, 0]) < int(lit.rgb[v, u, 0]) - 60
    # A point light far above behaves like the directional light.
    point = render(objects, K, T, W, H, light=Light(position=(0.0, 0.0, 1000.0), intensity=0.7))
    assert abs(int(point.rgb[v, u, 0]) - int(shadowed.rgb[v, u, 0])) <= 2


def test_background_and_errors():
    K, T = intrinsics(W, H), look_at((0.0, -4.0, 2.0), (0.0, 0.0, 0.4))
    out = render([_box((0, 0, 0.4))], K, T, W, H, background=(0.0, 0.0, 1.0))
    assert np.all(out.rgb[out.labels == 0] == [0, 0, 255])
    image = np.full((H, W, 3), 77, np.uint8)
    out = render([_box((0, 0, 0.4))], K, T, W, H, background=image)
    assert np.all(out.rgb[out.labels == 0] == 77)
    with pytest.raises(ValueError, match='background'):
        render([_box((0, 0, 0.4))], K, T, W, H, background=np.zeros((2, 2, 3), np.uint8))
    with pytest.raises(ValueError, match='at least one object'):
        Renderer([])


def test_speed_320x240():
    renderer = Renderer([_floor(), _box((0, 0, 0.4)), _box((1, 0.5, 0.4), label=2)])
    K, T = intrinsics(320, 240), look_at((0.0, -4.0, 2.0), (0.0, 0.0, 0.4))
    renderer.render(K, T, 320, 240)
    start = time.perf_counter()
    renderer.render(K, T, 320, 240)
    assert time.perf_counter() - start < 1.0
