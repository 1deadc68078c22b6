"""Room composer and camera trajectories: support plane, free footprints, determinism, views of the objects."""
import numpy as np
import pytest

from frodo_common.geometry import invert_transform, project_points
from frodo_datasets.render import Renderer, intrinsics
from frodo_datasets.scene import footprints_overlap, compose_scene, orbit_trajectory, trajectory, walk_trajectory


@pytest.fixture(scope='module')
def walk_scene():
    return compose_scene(4, ('chair', 'dining table'), seed=3, layout='walk')


def test_objects_stand_on_the_floor_without_overlap(walk_scene):
    scene = walk_scene
    assert [o.class_name for o in scene.objects] == ['chair', 'dining table', 'chair', 'dining table']
    assert [o.coco_id for o in scene.objects] == [62, 67, 62, 67]
    assert [o.id for o in scene.objects] == [1, 2, 3, 4]
    half = np.asarray(scene.room_size) / 2
    for o in scene.objects:
        world = o.mesh_world
        assert world.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)  # on the support plane z = 0
        assert np.all(np.abs(world.vertices[:, :2]) < half)          # inside the room
        R = o.T_world_object[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3)) and np.allclose(R[:, 2], [0, 0, 1])  # upright, yaw only
        # Canonical frame: origin at the bounding-box centre, so T_world_object holds the box centre.
        assert np.allclose(o.mesh.bounds.mean(axis=0), 0.0, atol=1e-9)
        assert o.T_world_object[2, 3] == pytest.approx(o.mesh.extents[2] / 2)
    for i, a in enumerate(scene.objects):
        for b in scene.objects[i + 1:]:
            assert not footprints_overlap(a.footprint, b.footprint, 0.0)


def test_deterministic(walk_scene):
    again = compose_scene(4, ('chair', 'dining table'), seed=3, layout='walk')
    for a, b in zip(walk_scene.objects, again.objects):
        assert np.array_equal(a.mesh_world.vertices, b.mesh_world.vertices) and a.material == b.material
    other = compose_scene(4, ('chair', 'dining table'), seed=4, layout='walk')
    assert not np.allclose(other.objects[0].T_world_object, walk_scene.objects[0].T_world_object)
    poses = walk_trajectory(walk_scene, 20, seed=1)
    assert all(np.array_equal(p, q) for p, q in zip(poses, walk_trajectory(walk_scene, 20, seed=1)))


def test_walk_sees_every_object_with_truncation(walk_scene):
    scene = walk_scene
    w, h = 160, 120
    K = intrinsics(w, h)
    poses = trajectory(scene, 'walk', 30, seed=0)
    half = np.asarray(scene.room_size) / 2
    renderer = Renderer(scene.render_objects())
    seen, truncated = set(), 0
    for T in poses:
        assert np.all(np.abs(T[:2, 3]) < half) and 1.3 <= T[2, 3] <= 1.65
        labels = renderer.render(K, T, w, h, shadows=False).labels
        ids = set(np.unique(labels).tolist()) - {0}
        seen |= ids
        border = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
        truncated += bool(set(border.tolist()) - {0})
    assert seen == {o.id for o in scene.objects}
    assert truncated >= 3
    # Smooth path: consecutive camera centres are close.
    steps = np.linalg.norm(np.diff([T[:3, 3] for T in poses], axis=0), axis=1)
    assert steps.max() < 3 * np.median(steps) + 0.05


def test_orbit_looks_at_the_object():
    scene = compose_scene(1, ('chair',), seed=5, layout='orbit')
    obj = scene.objects[0]
    assert np.allclose(obj.T_world_object[:2, 3], 0.0)  # the orbit's first object sits at the centre
    poses = orbit_trajectory(scene, 35, seed=0)
    assert len(poses) == 35
    K = intrinsics(160, 120)
    centre = obj.mesh_world.bounds.mean(axis=0)
    azimuths = []
    for T in poses:
        assert 1.2 <= T[2, 3] <= 1.6
        uv, z = project_points(K, invert_transform(T), centre[None])
        assert z[0] > 0 and 0.25 * 160 < uv[0, 0] < 0.75 * 160 and 0.2 * 120 < uv[0, 1] < 0.8 * 120
        azimuths.append(np.arctan2(T[1, 3], T[0, 3]))
    span = np.degrees(np.abs(np.unwrap(azimuths)[-1] - np.unwrap(azimuths)[0]))
    assert span > 300


def test_errors():
    with pytest.raises(ValueError, match='layout'):
        compose_scene(2, layout='maze')
    with pytest.raises(ValueError, match='n_objects'):
        compose_scene(0)
