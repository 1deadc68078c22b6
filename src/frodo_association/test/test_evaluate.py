"""The evaluation scores a perfect association as perfect, and reads contract bags with ground truth: a
box-world walk written as a bag comes back with the same objects and instance labels."""
import numpy as np

from frodo_association.boxes import canonical_yaw
from frodo_association.core import AssociationConfig
from frodo_association.evaluate import run_scene, scene_from_bag, summarise, upright_box
from frodo_association.synthetic import add_noise, make_scene
from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.bag import BagWriter
from frodo_common.geometry import box_corners
from frodo_detection.core import FilterConfig
from visualization_msgs.msg import MarkerArray

# The 12 triangles of a box whose corners are ordered as frodo_common.geometry.box_corners.
BOX_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


def test_clean_walk_scores_perfect():
    m = summarise([run_scene(make_scene(3, seed=7, n_frames=40), AssociationConfig(), FilterConfig())])
    assert m['purity'] == 1.0 and m['completeness'] == 1.0 and m['center_err_m'] < 0.03


def test_upright_box_recovers_a_yawed_box_from_its_corners():
    center, size, yaw = np.array([1.0, -2.0, 0.4]), np.array([1.4, 0.8, 0.8]), 0.3
    got = upright_box(box_corners(center, size, yaw))
    want_size, want_yaw = canonical_yaw(size, yaw)
    got_size, got_yaw = canonical_yaw(got[1], got[2])
    np.testing.assert_allclose(got[0], center, atol=1e-5)
    np.testing.assert_allclose(got_size, want_size, atol=1e-5)
    assert abs(got_yaw - want_yaw) < 1e-5


def test_scene_from_bag_recovers_objects_and_labels(tmp_path):
    scene = make_scene(3, seed=2, n_frames=12)
    path = tmp_path / 'walk.mcap'
    _write_scene_bag(scene, path)
    read, notes = scene_from_bag(str(path))
    assert len(read.frames) == 12 and len(read.objects) == 3
    for got, want in zip(read.objects, scene.objects):
        assert got.coco_id == want.coco_id
        assert np.allclose(got.center, want.center, atol=1e-3)
        assert np.allclose(np.sort(got.size[:2]), np.sort(want.size[:2]), atol=1e-3)
    labelled = [(read_f.gt.get(lab), gt) for read_f, f in zip(read.frames, scene.frames) for lab, gt in f.gt.items()
                if f.visibility[lab] > 0.5]
    assert np.mean([a == b for a, b in labelled]) > 0.95


def test_scene_from_bag_gives_each_frame_its_depth_image(tmp_path):
    # The trace and the box errors must see the depth the association node sees (CONTRACT v1.1).
    scene = make_scene(2, seed=3, n_frames=6)
    depths = {f.stamp: np.full(f.size[::-1], 1000 + 10 * k, np.uint16) for k, f in enumerate(scene.frames) if k % 2}
    _write_scene_bag(scene, tmp_path / 'walk.mcap', depths)
    read, _ = scene_from_bag(str(tmp_path / 'walk.mcap'))
    for f in read.frames:
        if f.stamp in depths:
            np.testing.assert_array_equal(f.depth, depths[f.stamp])
        else:
            assert f.depth is None


def _write_scene_bag(scene, path, depths=None):
    names = {62: 'chair', 67: 'dining table'}
    with BagWriter(path) as bag:
        f0 = scene.frames[0]
        markers = [conv.mesh_to_marker(o.corners(), BOX_FACES, names[o.coco_id], k, f0.stamp, 'world')
                   for k, o in enumerate(scene.objects)]
        bag.write(topics.GROUND_TRUTH, MarkerArray(markers=markers), f0.stamp)
        for f in scene.frames:
            bag.write(topics.CAMERA_INFO, conv.make_camera_info(f.K, *f.size, f.stamp, 'cam'), f.stamp)
            bag.write(topics.POSE, conv.make_pose_stamped(f.T_world_camera, f.stamp, 'world'), f.stamp)
            bag.write(topics.INSTANCES, conv.numpy_to_image(f.instances, '16UC1', f.stamp, 'cam'), f.stamp)
            if depths and f.stamp in depths:
                bag.write(topics.DEPTH, conv.numpy_to_image(depths[f.stamp], '16UC1', f.stamp, 'cam'), f.stamp)


def test_partial_views_are_labelled_with_the_object_whose_box_holds_them(tmp_path):
    # Instances less than half visible (behind another object): their boxes overlap the object's projected box by
    # less than min_iou, yet lie inside it.
    scene = make_scene(5, seed=5, n_frames=20)
    _write_scene_bag(scene, tmp_path / 'walk.mcap')
    scores = {}
    for min_inside in (0.9, 2.0):                                        # > 1: by IoU alone
        read, _ = scene_from_bag(str(tmp_path / 'walk.mcap'), min_inside=min_inside)
        occluded = [(read_f.gt.get(lab), gt) for read_f, f in zip(read.frames, scene.frames)
                    for lab, gt in f.gt.items() if f.visibility[lab] <= 0.5]
        scores[min_inside] = (sum(a == b for a, b in occluded), sum(a is not None and a != b for a, b in occluded))
    assert scores[0.9][0] > scores[2.0][0] + 4 and scores[0.9][1] == scores[2.0][1]


def test_add_noise_perturbs_a_recorded_scene_like_make_scene():
    scene = make_scene(3, seed=4, n_frames=10)
    assert add_noise(scene, 0) is scene                                  # the clean condition
    noisy = add_noise(scene, 0, mask_noise=2, rot_noise_deg=0.5, trans_noise=0.02, miss_rate=0.5)
    assert len(noisy.frames) == 10 and noisy.objects is scene.objects
    f, g = scene.frames[3], noisy.frames[3]
    assert np.array_equal(g.T_world_camera, f.T_world_camera) and not np.allclose(g.T_world_camera_observed,
                                                                                  f.T_world_camera)
    assert set(g.gt) <= set(f.gt) and set(g.gt) == set(np.unique(g.instances[g.instances > 0]).tolist())
    assert sum(len(fr.gt) for fr in noisy.frames) < sum(len(fr.gt) for fr in scene.frames)   # misses
    again = add_noise(scene, 0, mask_noise=2, rot_noise_deg=0.5, trans_noise=0.02, miss_rate=0.5)
    assert np.array_equal(again.frames[3].instances, g.instances)      # seeded


def test_set_overrides_association_and_evidence_fields_and_rejects_others(tmp_path, capsys):
    import json

    import pytest

    from frodo_association.evaluate import main
    out = tmp_path / 'eval.json'
    assert main(['--seeds', '1', '--objects', '2', '--frames', '10', '--conditions', 'clean', '--no-ablation',
                 '--set', 'landmark_quantile=0.1,min_track_views=4', '--json', str(out)]) == 0
    config = json.loads(out.read_text())['config']
    assert config['landmark_quantile'] == 0.1 and config['min_track_views'] == 4
    with pytest.raises(SystemExit) as stop:
        main(['--seeds', '1', '--set', 'no_such_field=1'])
    assert stop.value.code == 2 and 'no_such_field' in capsys.readouterr().err
