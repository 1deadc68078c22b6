"""Tracing why objects are (not) published (`evaluate.trace_objects`, `Associator.publish_blocker`) and the SLAM
maps a bag's frames carry (`evaluate.scene_from_bag`)."""
from dataclasses import replace

import numpy as np

from frodo_association.config import AssociationConfig
from frodo_association.evaluate import run_scene, scene_from_bag
from frodo_association.synthetic import make_scene
from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.bag import BagWriter
from frodo_detection.core import FilterConfig
from visualization_msgs.msg import MarkerArray

BOX_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


def test_trace_names_published_objects_and_the_failed_publishing_condition():
    scene = make_scene(3, seed=7, n_frames=40)
    res = run_scene(scene, AssociationConfig(), FilterConfig(), trace=True)
    assert len(res.trace) == 3 and all('published as' in line for line in res.trace)
    strict = run_scene(scene, replace(AssociationConfig(), min_track_views=1000), FilterConfig(), trace=True)
    assert len(strict.trace) == 3
    assert all('not published' in line and '< min_track_views 1000' in line for line in strict.trace)
    # The end of the input (run_scene settles) publishes objects still in view however long the window.
    windowed = run_scene(scene, replace(AssociationConfig(), confirm_window=1000), FilterConfig(), trace=True)
    assert all('published as' in line for line in windowed.trace)
    far = run_scene(scene, replace(AssociationConfig(), confirm_distance=1e-4), FilterConfig(), trace=True)
    assert all('consistent detections in' in line and 'confirm_distance 0.0001 m' in line for line in far.trace)


def test_bag_frames_carry_the_latest_slam_map_stamped_no_later(tmp_path):
    scene = make_scene(2, seed=3, n_frames=6)
    path = tmp_path / 'walk.mcap'
    names = {62: 'chair', 67: 'dining table'}
    maps = {scene.frames[1].stamp: np.zeros((4, 3)), scene.frames[4].stamp: np.ones((7, 3))}
    with BagWriter(path) as bag:
        f0 = scene.frames[0]
        bag.write(topics.GROUND_TRUTH, MarkerArray(markers=[
            conv.mesh_to_marker(o.corners(), BOX_FACES, names[o.coco_id], k, f0.stamp, 'world')
            for k, o in enumerate(scene.objects)]), f0.stamp)
        for f in scene.frames:
            bag.write(topics.CAMERA_INFO, conv.make_camera_info(f.K, *f.size, f.stamp, 'cam'), f.stamp)
            bag.write(topics.POSE, conv.make_pose_stamped(f.T_world_camera, f.stamp, 'world'), f.stamp)
            bag.write(topics.INSTANCES, conv.numpy_to_image(f.instances, '16UC1', f.stamp, 'cam'), f.stamp)
            if f.stamp in maps:
                bag.write(topics.SLAM_POINTS, conv.xyz_to_cloud(maps[f.stamp], f.stamp, 'world'), f.stamp)
    read, notes = scene_from_bag(str(path))
    assert [None if f.landmarks is None else len(f.landmarks) for f in read.frames] == [None, 4, 4, 4, 7, 7]
    assert '2 SLAM maps' in notes[-1]


def _raise_bottoms(scene, fraction: float) -> None:
    """Cut the lower `fraction` of every instance's mask in every frame (masks that miss legs)."""
    for frame in scene.frames:
        for label in np.unique(frame.instances[frame.instances > 0]):
            rows = np.nonzero((frame.instances == label).any(1))[0]
            cut = int(round(rows.max() - fraction * (rows.max() - rows.min())))
            frame.instances[cut + 1:][frame.instances[cut + 1:] == label] = 0


def test_trace_says_what_fixed_a_misplaced_objects_depth(monkeypatch):
    from functools import partial
    from frodo_association import evaluate
    # every published object traced as misplaced (far 0), to read the evidence the trace gives
    monkeypatch.setattr(evaluate, 'trace_objects', partial(evaluate.trace_objects, far=0.0))
    scene = make_scene(2, seed=3, n_frames=30)
    gaps = {}
    for fraction in (0.0, 0.5):
        if fraction:
            _raise_bottoms(scene, fraction)
        lines = run_scene(scene, AssociationConfig(), FilterConfig(), trace=True).trace
        published = [line for line in lines if 'published as' in line]
        assert published and all('(placement: seen over ' in line for line in published)
        gaps[fraction] = [float(line.split('detection bottoms ')[1].split(' ')[0]) for line in published]
        spreads = [float(line.split('seen over ')[1].split(' ')[0]) for line in published]
        assert all(s > 5 for s in spreads)     # a walk past the objects
    assert all(abs(g) < 0.1 for g in gaps[0.0])          # masks reach the floor contact
    assert all(0.35 < g < 0.65 for g in gaps[0.5])       # half the height hidden at the bottom


def test_along_view_error_is_the_signed_offset_away_from_the_cameras(monkeypatch):
    from frodo_association import evaluate
    seen = {}

    def keep(assoc, scene, gt, tracks, match, **kwargs):
        seen.update(assoc=assoc, gt=gt)
        return []
    monkeypatch.setattr(evaluate, 'trace_objects', keep)
    scene = make_scene(1, seed=5, n_frames=20)
    run_scene(scene, AssociationConfig(), FilterConfig(), trace=True)
    assoc, rows = seen['assoc'], np.nonzero(seen['gt'] == 0)[0]
    obj = scene.objects[0]
    T = assoc.frames.T_camera_world[assoc.rows.frame[rows]]
    cams = np.einsum('fij,fj->fi', -np.transpose(T[:, :3, :3], (0, 2, 1)), T[:, :3, 3])
    look = obj.center[:2] - cams[:, :2]
    view = (look / np.linalg.norm(look, axis=1, keepdims=True)).mean(0)     # mean unit direction to the object
    view /= np.linalg.norm(view)
    away = obj.center + 0.3 * np.array([view[0], view[1], 0.0])
    across = obj.center + 0.3 * np.array([-view[1], view[0], 0.0])
    assert abs(evaluate.along_view_error(assoc, rows, obj, away) - 0.3) < 0.02
    assert abs(evaluate.along_view_error(assoc, rows, obj, 2 * obj.center - away) + 0.3) < 0.02
    assert abs(evaluate.along_view_error(assoc, rows, obj, across)) < 0.02
