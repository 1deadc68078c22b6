"""Association core (paper Sec. 5.1, supplement Algorithm 1 and "Detection Pruning"): segments from boxes,
DP-means over segments with stable ids, merges and same-frame exclusivity, box fitting and pruning."""
from dataclasses import replace

import numpy as np
import pytest

from frodo_association.core import (AssociationConfig, Associator, Box3D, box_segments, clip_segments_to_heights,
                                    depth_intervals, detections_from_instances, fit_box, lsq_center,
                                    point_segment_distance, project_boxes, prune_detections)
from frodo_association.segments import merge_segment_groups
from frodo_association.synthetic import BoxObject, make_scene, render_instances
from frodo_common.geometry import invert_transform, look_at, project_points

CHAIR = 62
K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
SIZE = (320, 240)


def _box_of(center, size, yaw, T_world_camera):
    corners = Box3D(np.asarray(center, float), np.asarray(size, float), yaw).corners()
    uv, _ = project_points(K, invert_transform(T_world_camera), corners)
    return np.array([*uv.min(0), *uv.max(0)])


def _run(scene, cfg=None):
    assoc = Associator(cfg or AssociationConfig())
    updates = []
    for f in scene.frames:
        labels, boxes = detections_from_instances(f.instances)
        updates.append(assoc.add_frame(f.stamp, f.K, f.T_world_camera_observed, f.size, labels, boxes))
        updates.append(assoc.refine_boxes())
    return assoc, updates


def _gt_of_rows(assoc, scene):
    return np.array([scene.frames[f].gt.get(int(lab), -1) for f, lab in zip(assoc.rows.frame, assoc.rows.label)])


def test_depth_interval_is_metric_size_over_angular_extent():
    # A 0.8 m object spanning 80 px at f = 300 is 3 m away; the size range maps to a depth range.
    boxes = np.array([[100.0, 50.0, 140.0, 130.0]])
    d = depth_intervals(boxes, K, np.array([[0.8, 0.8]]), margin=0.0, min_depth=0.1, max_depth=50.0)
    assert d[0] == pytest.approx([3.0, 3.0])
    d = depth_intervals(boxes, K, np.array([[0.4, 1.2]]), margin=0.1, min_depth=0.1, max_depth=50.0)
    assert d[0] == pytest.approx([1.5 * 0.9, 4.5 * 1.1])


def test_segment_lies_on_the_box_centre_ray_at_the_interval_depths():
    T = look_at([3.0, -2.0, 1.5], [0.0, 0.0, 0.5])
    boxes = np.array([[100.0, 50.0, 140.0, 130.0], [10.0, 20.0, 60.0, 40.0]])
    seg = box_segments(boxes, K, T, np.array([[0.4, 1.2], [0.5, 2.0]]), margin=0.0, min_depth=0.1, max_depth=50.0)
    uv, depth = project_points(K, invert_transform(T), seg.reshape(-1, 3))
    centres = np.repeat((boxes[:, :2] + boxes[:, 2:]) / 2, 2, axis=0)
    assert np.allclose(uv, centres, atol=1e-6)
    assert depth.reshape(2, 2) == pytest.approx(depth_intervals(boxes, K, np.array([[0.4, 1.2], [0.5, 2.0]]),
                                                                0.0, 0.1, 50.0))


def test_point_segment_distance_interior_and_ends():
    seg = np.array([[[0.0, 0, 0], [2.0, 0, 0]]])
    pts = np.array([[1.0, 1.0, 0.0], [-3.0, 0.0, 4.0], [2.0, 0.0, 0.0], [5.0, 4.0, 0.0]])
    assert point_segment_distance(pts, seg)[0] == pytest.approx([1.0, 5.0, 0.0, 5.0])


def test_lsq_center_intersection_midpoint_and_clamping():
    rng = np.random.default_rng(0)
    p = np.array([0.3, -0.2, 0.5])
    dirs = rng.normal(size=(5, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    segs = np.stack([p - dirs * rng.uniform(0.5, 2, (5, 1)), p + dirs * rng.uniform(0.5, 2, (5, 1))], axis=1)
    assert lsq_center(segs, prior_weight=1e-6) == pytest.approx(p, abs=1e-4)
    assert lsq_center(segs[:1]) == pytest.approx(segs[0].mean(0))
    # Two crossing lines whose intersection lies beyond the end of one segment: the centre minimises the
    # distances to the segments (not the lines): brute force over a grid agrees.
    segs = np.array([[[0.0, 0, 0], [1.0, 0, 0]], [[2.0, -1, 0], [2.0, 1, 0]]])
    x = lsq_center(segs, prior_weight=1e-9)
    assert x == pytest.approx([1.5, 0.0, 0.0], abs=1e-6)
    cost = lambda q: np.sum(point_segment_distance(q[None], segs) ** 2)       # noqa: E731
    assert cost(x) <= min(cost(x + d) for d in np.eye(3) * 1e-3) + 1e-12


def test_merge_segment_groups_follows_the_dp_means_objective():
    # Four near-parallel rays (a narrow baseline) towards one point, 0.4 m apart at their midpoints: a leader
    # sweep splits them 3 + 1, and the singleton keeps its centre on its own segment. One centre fits all four
    # within the penalty, and sum d^2 + penalty^2 per group falls by merging: one group.
    target = np.array([0.0, 2.0, 0.5])
    eyes = np.array([[x, 0.0, 1.4] for x in (-0.2, -0.1, 0.0, 0.1)])
    ends = np.array([[-0.15, 0.0, 0.0], [0.0, 0.05, 0.0], [0.1, -0.05, 0.0], [0.05, 0.4, 0.0]])
    segs = np.stack([eyes + 0.5 * (target - eyes), eyes + 1.6 * (target - eyes) + ends], axis=1)
    group = np.array([0, 0, 0, 1])
    merged, centres = merge_segment_groups(segs, group, np.arange(4), penalty=0.4)
    assert list(merged) == [0, 0, 0, 0] and centres.shape == (1, 3)
    assert point_segment_distance(centres, segs)[:, 0].max() < 0.4
    # Detections of one frame are two objects: never merged, whatever the geometry.
    assert list(merge_segment_groups(segs, group, np.array([0, 1, 2, 2]), penalty=0.4)[0]) == [0, 0, 0, 1]
    # Two groups 2 m apart stay apart (a merged centre would be farther than the penalty from their segments);
    # unassigned segments (-1) are left alone and the ids come back consecutive.
    far = segs + np.array([2.0, 0.0, 0.0])
    both = np.concatenate([segs[:2], far[:2], segs[2:3]])
    out, centres = merge_segment_groups(both, np.array([3, 3, 5, 5, -1]), np.arange(5), penalty=0.4)
    assert list(out) == [0, 0, 1, 1, -1] and len(centres) == 2
    # No segment in any group (every cluster of the class without a reliable detection; realwalk-tune2-8508 raised
    # here once): nothing to merge, no centre.
    out, centres = merge_segment_groups(both, np.full(5, -1), np.arange(5), penalty=0.4)
    assert list(out) == [-1] * 5 and centres.shape == (0, 3)


def test_dp_means_recovers_the_objects_from_noisy_detections():
    scene = make_scene(5, seed=3, n_frames=40, mask_noise=2, rot_noise_deg=0.5, trans_noise=0.02)
    assoc, _ = _run(scene)
    tracks = assoc.confirmed_tracks()
    assert len(tracks) == 5
    gt = _gt_of_rows(assoc, scene)
    majority = []
    for t in tracks:
        members = gt[assoc.rows.assign == t.object_id]
        counts = np.bincount(members[members >= 0], minlength=5)
        assert counts.max() / counts.sum() > 0.95
        majority.append(counts.argmax())
    assert sorted(majority) == [0, 1, 2, 3, 4]


def test_ids_stable_under_incremental_updates():
    scene = make_scene(4, seed=1, n_frames=40)
    assoc, updates = _run(scene)
    gt = _gt_of_rows(assoc, scene)
    id_of: dict[int, int] = {}                 # ground-truth object -> its track id
    for t in assoc.confirmed_tracks():
        objs = np.unique(gt[assoc.rows.assign == t.object_id])
        assert len(objs) == 1
        id_of[int(objs[0])] = t.object_id
    assert len(id_of) == 4 and assoc.merges == 0
    # Ids published with a frame only ever go from -1 (cluster not yet published) to the final id.
    first = np.concatenate([u.table['object_id'] for u in updates if u.table is not None])
    final = np.concatenate([assoc.frame_table(int(s))['object_id'] for s in assoc.frames.stamp])
    assert np.all((first == -1) | (first == final)) and np.mean(first == final) > 0.6
    for g, oid in id_of.items():
        assert np.all(final[gt == g] == oid)


def _views(center, n=8, radius=3.0, height=1.5, sweep=np.pi):
    angles = np.linspace(0, sweep, n)
    return [look_at([center[0] + radius * np.cos(a), center[1] + radius * np.sin(a), height], center) for a in angles]


def test_merge_keeps_the_older_id_and_resolves_same_frame_duplicates():
    cfg = AssociationConfig(min_track_views=1, min_hit_ratio=0.0, confirm_window=1, full_pass_every=0)
    assoc = Associator(cfg)
    a, b = np.array([0.0, 0.0, 0.45]), np.array([1.2, 0.0, 0.45])
    size = (0.5, 0.5, 0.9)
    T = look_at([0.6, -3.0, 1.4], [0.6, 0.0, 0.4])
    lab = [CHAIR * 256 + 1, CHAIR * 256 + 2]
    assoc.add_frame(1, K, T, SIZE, lab, [_box_of(a, size, 0.0, T), _box_of(b, size, 0.0, T)])
    assert sorted(assoc.tracks) == [0, 1]
    assoc.tracks[1].center = assoc.tracks[0].center + [0.1, 0.0, 0.0]      # drift together
    removed, dirty = assoc.merge_close()
    assert removed == {1: 0} and list(assoc.tracks) == [0] and dirty == {0}
    assert assoc.rows.assign.tolist() in ([0, -1], [-1, 0])               # one detection per frame and object


def test_same_frame_detections_never_join_one_cluster():
    assoc = Associator(AssociationConfig(min_track_views=1, min_hit_ratio=0.0, confirm_window=1))
    a = np.array([0.0, 0.0, 0.45])
    for k, T in enumerate(_views(a, n=3)):
        assoc.add_frame(k, K, T, SIZE, [CHAIR * 256 + 1], [_box_of(a, (0.5, 0.5, 0.9), 0.0, T)])
    # A frame with the chair twice (a split mask): both boxes are near the cluster, only one may join it.
    T = _views(a, n=5)[3]
    box = _box_of(a, (0.5, 0.5, 0.9), 0.0, T)
    assoc.add_frame(10, K, T, SIZE, [CHAIR * 256 + 1, CHAIR * 256 + 2], [box, box + [2, 0, 2, 0]])
    ids = assoc.frame_table(10)['object_id']
    assert sorted(ids.tolist()) == [-1, 0]


@pytest.mark.parametrize('floor', [None, 0.0])
def test_box_fit_recovers_a_known_box(floor):
    gt = Box3D(np.array([0.4, -0.3, 0.45]), np.array([0.6, 0.45, 0.9]), 0.3)
    views = _views(gt.center, n=10, sweep=1.5 * np.pi)
    T_cw = np.stack([invert_transform(T) for T in views])
    boxes = np.stack([_box_of(gt.center, gt.size, gt.yaw, T) for T in views])
    fit = fit_box(np.repeat(K[None], len(views), 0), T_cw, boxes, np.ones((len(views), 4), bool), (0.35, 1.3),
                  gt.center + [0.15, -0.1, 0.1], floor_height=floor, size_prior_weight=1e-3, anchor_weight=1e-3)
    assert fit.center == pytest.approx(gt.center, abs=0.01)
    assert fit.size == pytest.approx(gt.size, abs=0.01)
    assert fit.yaw == pytest.approx(gt.yaw, abs=np.radians(1.0))


def test_pruning_rejects_small_occluded_and_overlapping_detections():
    cfg = AssociationConfig(min_box_width=24, min_box_height=24, occlusion_iou=0.6, overlap_iou=0.4)
    own = np.array([100.0, 50.0, 160.0, 170.0])
    other = np.array([200.0, 60.0, 280.0, 160.0])
    dets = np.array([own,                                   # clean: kept
                     [100.0, 50.0, 110.0, 60.0],            # too small (24 px at 640x480 = 12 px here)
                     [100.0, 50.0, 160.0, 110.0],           # lower half occluded: IoU 0.5
                     own,                                   # the same box but over the other object (below)
                     [-0.5, 50.0, 40.0, 170.0]])            # truncated by the border (its projection is not)
    obj = np.array([[own, other]] * 5)
    obj[3, 1] = [90.0, 40.0, 170.0, 180.0]
    obj[4, 0] = [-60.0, 50.0, 40.0, 170.0]
    kept = prune_detections(dets, np.zeros(5, int), obj, np.ones((5, 2), bool), np.array([SIZE] * 5, float), cfg)
    assert kept.tolist() == [True, False, False, False, False]


def test_project_boxes_marks_objects_behind_the_camera():
    T = look_at([0.0, -3.0, 1.0], [0.0, 0.0, 1.0])
    corners = np.stack([Box3D(np.array([0.0, 0.0, 1.0]), np.ones(3) * 0.5, 0.0).corners(),
                        Box3D(np.array([0.0, -4.0, 1.0]), np.ones(3) * 0.5, 0.0).corners()])
    boxes, valid = project_boxes(K[None], invert_transform(T)[None], corners)
    assert valid[0].tolist() == [True, False]
    assert boxes[0, 0, 0] < 159.5 < boxes[0, 0, 2]


def test_unknown_classes_and_invalid_boxes_are_not_associated():
    assoc = Associator()
    T = look_at([0.0, -3.0, 1.4], [0.0, 0.0, 0.4])
    box = _box_of([0, 0, 0.45], (0.5, 0.5, 0.9), 0.0, T)
    table = assoc.add_frame(5, K, T, SIZE, [1 * 256 + 1, CHAIR * 256 + 2], [box, [np.nan] * 4]).table
    assert table['object_id'].tolist() == [-1, -1] and np.isnan(table['x']).all()
    assert assoc.tracks == {} and table['label'].tolist() == [257, CHAIR * 256 + 2]


def test_segments_are_cut_to_plausible_centre_heights():
    segs = np.array([[[0.0, 0, 2.0], [4.0, 0, -2.0]],      # crosses the band 0.1..0.7
                     [[0.0, 0, 0.5], [1.0, 0, 0.5]],        # flat, inside
                     [[0.0, 0, 3.0], [1.0, 0, 2.0]]])       # entirely above: unchanged
    out = clip_segments_to_heights(segs, np.full(3, 0.1), np.full(3, 0.7))
    assert np.allclose(out[0], [[1.3, 0, 0.7], [1.9, 0, 0.1]])
    assert np.array_equal(out[1], segs[1]) and np.array_equal(out[2], segs[2])


def test_a_cluster_rarely_detected_while_in_view_is_not_published():
    assoc = Associator(AssociationConfig(full_pass_every=5))
    a, b = np.array([-0.6, 0.0, 0.45]), np.array([0.6, 0.0, 0.45])
    for k, T in enumerate(_views((a + b) / 2, n=20, radius=3.5, sweep=np.pi / 2)):
        labels, boxes = [CHAIR * 256 + 1], [_box_of(a, (0.5, 0.5, 0.9), 0.0, T)]
        if k < 4:                                  # b is in view throughout but detected in 4 frames only
            labels.append(CHAIR * 256 + 2)
            boxes.append(_box_of(b, (0.5, 0.5, 0.9), 0.0, T))
        assoc.add_frame(k, K, T, SIZE, labels, boxes)
    assert len(assoc.tracks) == 2
    published = assoc.confirmed_tracks()
    assert len(published) == 1 and np.linalg.norm(published[0].center - a) < 0.1
    ratio, n_view = assoc.hit_ratio(next(i for i in assoc.tracks if i != published[0].object_id))
    assert ratio == pytest.approx(4 / 20) and n_view == 20


def test_box_size_thresholds_scale_with_the_resolution():
    # min_box_width/height are given at 640x480: 24 px there, 12 px at 320x240, 48 px at 1280x960.
    cfg = AssociationConfig(min_box_width=24, min_box_height=24)
    det = np.array([[100.0, 50.0, 116.0, 66.0]])                 # 16 x 16 px
    kept = [prune_detections(det, np.array([-1]), np.zeros((1, 0, 4)), np.zeros((1, 0), bool),
                             np.array([size], float), cfg)[0] for size in ((320, 240), (640, 480), (1280, 960))]
    assert kept == [True, False, False]
    # The same scaling decides which detections may open clusters (reliable).
    T = look_at([0.0, -6.0, 1.4], [0.0, 0.0, 0.4])
    box = _box_of([0, 0, 0.2], (0.3, 0.3, 0.4), 0.0, T)             # a far stool, under 24 x 24 px at f = 300
    assert 12 < box[2] - box[0] < 24 and 12 < box[3] - box[1] < 24
    for size, reliable in ((SIZE, True), ((640, 480), False)):
        assoc = Associator(cfg)
        assoc.add_frame(1, K, T, size, [CHAIR * 256 + 1], [box])
        assert assoc.rows.reliable.tolist() == [reliable] and len(assoc.tracks) == int(reliable)


def _yaw_turn(v, angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]])


def _arc_views(target, n, radius, a0, a1, turn=0.0):
    """Cameras on an arc around `target` looking at it, turned about z by `turn` (the target moves towards the
    left image border for a negative turn, the right one for a positive)."""
    out = []
    for a in np.linspace(a0, a1, n):
        p = np.array([target[0] + radius * np.cos(a), target[1] + radius * np.sin(a), 1.4])
        out.append(look_at(p, p + _yaw_turn(np.asarray(target) - p, turn)))
    return out


def _run_views(objects, views, cfg):
    assoc = Associator(cfg)
    for k, T in enumerate(views):
        instances, _, _ = render_instances(objects, K, T, SIZE)
        labels, boxes = detections_from_instances(instances)
        assoc.add_frame(k, K, T, SIZE, labels, boxes)
        assoc.refine_boxes()
    return assoc


def _split_off(assoc, object_id, from_frame):
    """Move a cluster's detections of frames >= from_frame into a new unpublished cluster, as a leader opening
    beyond lambda does; returns (the new id, its rows)."""
    rows = assoc.members(object_id)
    late = rows[assoc.rows.frame[rows] >= from_frame]
    split = assoc._new_track(int(late[0]))
    assoc.rows.assign[late] = split
    assoc._update_centers([object_id, split])
    return split, late


def test_a_split_cluster_merges_back_and_two_objects_never_do():
    # Narrow baseline (inside-out): the camera slides 0.3 m sideways, 2.5 m from two chairs 0.8 m apart.
    chairs = [BoxObject(CHAIR, np.array([x, 2.5, 0.45]), np.array([0.5, 0.5, 0.9]), 0.0) for x in (-0.4, 0.4)]
    views = [look_at(np.array([x, 0.0, 1.4]), np.array([x, 2.5, 0.45])) for x in np.linspace(-0.15, 0.15, 12)]
    assoc = _run_views(chairs, views, AssociationConfig())
    first, second = (t.object_id for t in assoc.confirmed_tracks())
    # The first chair's frames 6-11 split off: one centre still fits all its segments, so the DP-means objective
    # falls by merging them back.
    split, late = _split_off(assoc, first, 6)
    assoc.cfg = AssociationConfig(consistent_merges=False)
    assert assoc.merge_consistent() == ({}, set()) and split in assoc.tracks
    assoc.cfg = AssociationConfig()
    # A fragment of cut views alone (no reliable detection) is left to the truncated rules.
    reliable = assoc.rows.reliable[late].copy()
    assoc.rows.reliable[late] = False
    assert assoc.merge_consistent() == ({}, set()) and split in assoc.tracks
    assoc.rows.reliable[late] = reliable
    removed, dirty = assoc.merge_consistent()
    assert removed == {split: first} and dirty == set(range(12))
    assert split not in assoc.tracks and np.count_nonzero(assoc.rows.assign == first) == 12
    # The second chair's detections, split off the same way, share their frames with the first chair's and lie
    # 0.8 m from them: they go back into their own cluster, never into the first chair.
    split, _ = _split_off(assoc, second, 6)
    assert assoc.merge_consistent()[0] == {split: second}
    assert len(assoc.tracks) == 2


def test_an_always_truncated_object_is_recovered_as_one_track():
    chair = BoxObject(CHAIR, np.array([0.0, 0.0, 0.45]), np.array([0.5, 0.5, 0.9]), 0.3)
    views = _arc_views(chair.center, 30, 3.0, 0.0, np.pi / 2, turn=-np.arctan(190 / 300))
    for T in views:                                   # cut by the left border in every view
        _, boxes = detections_from_instances(render_instances([chair], K, T, SIZE)[0])
        assert len(boxes) == 1 and boxes[0, 0] < 0 and boxes[0, 2] - boxes[0, 0] < 40
    assoc = _run_views([chair], views, AssociationConfig())
    published = assoc.confirmed_tracks()
    assert len(assoc.tracks) == 1 and len(published) == 1
    assert np.linalg.norm(published[0].center[:2] - chair.center[:2]) < 0.3
    assert np.count_nonzero(assoc.rows.assign == published[0].object_id) >= 20
    # Without the deferred rule truncated detections open no cluster: the chair is lost.
    assert _run_views([chair], views, AssociationConfig(truncated_min_views=0)).tracks == {}


def test_an_object_first_seen_truncated_then_whole_gives_one_track():
    # A long table: the first 20 views see only its left end (cut by the right border), whose box-centre rays
    # meet ~0.65 m from the table centre, so the deferred rule opens a cluster there; whole views then open a
    # second one at the centre, farther than truncated_merge_distance. The truncated cluster's detections are
    # explained by the whole table's projected box, so the full pass merges them: one track, the older id.
    table = BoxObject(67, np.array([0.0, 0.0, 0.375]), np.array([2.0, 0.8, 0.75]), 0.0)
    arc = (3.0, -np.pi / 2 - 0.4, -np.pi / 2 + 0.4)
    views = _arc_views(table.center, 20, *arc, turn=0.6) + _arc_views(table.center, 40, *arc)
    assoc = _run_views([table], views, AssociationConfig())
    assert [t.object_id for t in assoc.confirmed_tracks()] == [0] and list(assoc.tracks) == [0]
    assert np.linalg.norm(assoc.tracks[0].center[:2] - table.center[:2]) < 0.1
    whole = assoc.rows.frame >= 20
    assert np.all(assoc.rows.assign[whole] == 0)
    # With the box test, the footprint-overlap merge and the frustum merge off (thresholds above 1 never hold) the
    # two clusters stay apart: a duplicate while published. Each test alone merges them.
    off = AssociationConfig(truncated_explained_iou=2.0, box_overlap_merge=2.0, frustum_merges=False)
    assert len(_run_views([table], views[:40], off).confirmed_tracks()) == 2
    for alone in ({'truncated_explained_iou': 0.5}, {'box_overlap_merge': 0.3}, {'frustum_merges': True}):
        assert len(_run_views([table], views[:40], replace(off, **alone)).confirmed_tracks()) == 1, alone


def _clipped_views(gt: Box3D, views):
    """Detection boxes of gt clipped to the image, with edge_valid False on the edges the border cut."""
    boxes, valid = [], []
    for T in views:
        uv, _ = project_points(K, invert_transform(T), gt.corners())
        raw = np.array([*uv.min(0), *uv.max(0)])
        box = np.clip(raw, -0.5, [SIZE[0] - 0.5, SIZE[1] - 0.5] * 2)
        boxes.append(box)
        valid.append(box == raw)
    return np.array(boxes), np.array(valid)


@pytest.mark.parametrize('hinge', [False, True])
def test_box_fit_of_an_object_never_seen_whole_reaches_the_border_where_its_detections_are_cut(hinge):
    # A 2 m table seen from 1.2-2 m around one of its ends, cut by the image border in every view. A cut edge
    # says the table reaches at least to the border: with the hinge the fitted box's projection does so in every
    # view; without it the fit (free to shrink towards the visible parts) falls short of the border in one.
    gt = Box3D(np.array([0.0, 0.0, 0.375]), np.array([2.0, 0.9, 0.75]), 0.0)
    views = [look_at([x, -1.2, 1.4], [x + 0.5, 0.0, 0.4]) for x in (-1.4, -1.2, -1.0, -0.8)]
    views += [look_at([-2.0, y, 1.4], [-0.6, y, 0.4]) for y in (-0.3, 0.3)]
    boxes, valid = _clipped_views(gt, views)
    assert (~valid).any(axis=1).all()                                   # truncated in every view
    Ks = np.repeat(K[None], len(views), 0)
    T_cw = np.stack([invert_transform(T) for T in views])
    fit = fit_box(Ks, T_cw, boxes, valid, (0.6, 3.0), np.array([-0.5, 0.0, 0.375]), floor_height=0.0,
                  anchor_weight=0.1, truncation_hinge=hinge)
    proj, _ = project_boxes(Ks, T_cw, fit.corners()[None])
    inside = ((proj[:, 0] - boxes) * [1, 1, -1, -1])[~valid]           # > 0: projected edge short of the border
    assert np.abs(proj[:, 0] - boxes)[valid].max() < 3.0               # the uncut edges are matched either way
    if hinge:
        assert inside.max() < 2.0
    else:
        assert inside.max() > 8.0


def test_box_fit_of_an_object_with_a_hidden_lower_part_stays_at_its_visible_surface():
    # A chair whose lower 0.36 m is hidden (behind a nearer table, unflagged) in 5 views from one side: its boxes
    # show only the upper part, and the fit, matching them with the class height, moves the box down and away
    # along the view. The detections' visible-surface depths (here 0.3 m behind the true nearest corner, as
    # landmarks on the back of a chair lie) bound the box's nearest corner and keep it near its place.
    gt = Box3D(np.array([0.0, 0.0, 0.45]), np.array([0.5, 0.5, 0.9]), 0.2)
    visible = Box3D(np.array([0.0, 0.0, 0.63]), np.array([0.5, 0.5, 0.54]), 0.2)
    views = [look_at([x, -2.6 + 0.1 * abs(x), 1.3], [0.0, 0.0, 0.45]) for x in (-0.4, -0.25, -0.1, 0.05, 0.2)]
    T_cw = np.stack([invert_transform(T) for T in views])
    boxes = np.stack([_box_of(visible.center, visible.size, visible.yaw, T) for T in views])
    near = np.array([(gt.corners() @ T[:3, :3].T + T[:3, 3])[:, 2].min() for T in T_cw])

    def centre_error(weight):
        fit = fit_box(np.repeat(K[None], len(views), 0), T_cw, boxes, np.ones((len(views), 4), bool), (0.35, 1.3),
                      gt.center + [0.1, 0.2, 0.0], floor_height=0.0, anchor_weight=0.1, shape=(0.5, 0.5, 0.9),
                      height_prior_weight=0.2, surface_depth=near + 0.3, surface_weight=weight)
        return np.linalg.norm(fit.center - gt.center)

    without, with_surface = centre_error(0.0), centre_error(1.0)
    assert without > 0.5
    assert with_surface < 0.35 and with_surface < 0.5 * without


def test_the_surface_bound_of_a_tall_box_seen_from_above_is_horizontal():
    # A 1.2 m chair behind a table, seen from 1.6 m looking down at it from 2 m in 5 views from one side: only its
    # top 0.5 m shows (the table hides the rest, unflagged), and the visible surface lies on its front face. A
    # bound on the optical depth of the nearest corner holds while the box sits far behind that surface (its top
    # corners are optically nearer than its footprint); the same bound on the horizontal distance does not.
    gt = Box3D(np.array([0.0, 0.0, 0.6]), np.array([0.5, 0.5, 1.2]), 0.0)
    visible = Box3D(np.array([0.0, 0.0, 0.95]), np.array([0.5, 0.5, 0.5]), 0.0)
    views = [look_at([x, -2.0, 1.6], [0.0, 0.0, 0.5]) for x in (-0.4, -0.2, 0.0, 0.2, 0.4)]
    T_cw = np.stack([invert_transform(T) for T in views])
    boxes = np.stack([_box_of(visible.center, visible.size, visible.yaw, T) for T in views])
    # the front face (y = -0.25) where the ray through the detection box's centre meets it
    rays = np.stack([T[:3, :3] @ np.linalg.solve(K, [(b[0] + b[2]) / 2, (b[1] + b[3]) / 2, 1.0])
                     for T, b in zip(views, boxes)])
    eyes = np.stack([T[:3, 3] for T in views])
    surface = (-0.25 - eyes[:, 1]) / rays[:, 1]                        # optical depth (ray: camera z = 1)
    fit = fit_box(np.repeat(K[None], len(views), 0), T_cw, boxes, np.ones((len(views), 4), bool), (0.35, 1.3),
                  gt.center + [0.0, 0.4, 0.0], floor_height=0.0, anchor_weight=0.1, shape=(0.5, 0.5, 1.2),
                  height_prior_weight=0.2, surface_depth=surface, surface_weight=1.0, bottom_below_weight=0.3)
    assert np.linalg.norm(fit.center[:2] - gt.center[:2]) < 0.1      # the optical-depth bound: 0.135 m


@pytest.mark.parametrize('hidden', [0.0, 0.36])
def test_box_fit_on_the_floor_weighs_a_bottom_edge_above_the_box_less(hidden):
    # The same chair seen from one side, its lowest `hidden` metres not in its detections (legs its mask misses)
    # and no edge flagged, no surface depth. Matching the bottom edges exactly stands the box on the floor where
    # they end, behind the chair; weighing a box that reaches below them less keeps it near, and costs nothing
    # when the bottom is seen.
    gt = Box3D(np.array([0.0, 0.0, 0.45]), np.array([0.5, 0.5, 0.9]), 0.2)
    visible = Box3D(np.array([0.0, 0.0, 0.45 + hidden / 2]), np.array([0.5, 0.5, 0.9 - hidden]), 0.2)
    views = [look_at([x, -2.6 + 0.1 * abs(x), 1.3], [0.0, 0.0, 0.45]) for x in (-0.4, -0.25, -0.1, 0.05, 0.2)]
    T_cw = np.stack([invert_transform(T) for T in views])
    boxes = np.stack([_box_of(visible.center, visible.size, visible.yaw, T) for T in views])

    def centre_error(weight):
        fit = fit_box(np.repeat(K[None], len(views), 0), T_cw, boxes, np.ones((len(views), 4), bool), (0.35, 1.3),
                      gt.center + [0.1, 0.2, 0.0], floor_height=0.0, anchor_weight=0.1, shape=(0.5, 0.5, 0.9),
                      height_prior_weight=0.2, bottom_below_weight=weight)
        return np.linalg.norm(fit.center - gt.center)

    two_sided, weighted = centre_error(1.0), centre_error(0.3)
    if hidden == 0.0:
        assert two_sided < 0.03 and weighted < 0.03
    else:
        assert two_sided > 0.6 and weighted < 0.7 * two_sided


@pytest.mark.parametrize('floor_height', [None, 0.0])
def test_the_outside_residuals_of_surface_points_have_their_analytic_jacobian(floor_height):
    from frodo_association.boxes import _outside_residuals
    rng = np.random.default_rng(3)
    points = rng.uniform(-1.0, 1.0, (40, 3)) + [0.0, 0.0, 0.6]
    n_c = 2 if floor_height is not None else 3
    p = np.concatenate([[0.1, -0.2, 0.5][:n_c], np.log([0.8, 0.6, 0.9]), [0.3]])[None]
    r, jac = _outside_residuals(p, points, floor_height)
    assert (r > 0).sum() > 20 and (r == 0).sum() > 20                   # points inside and outside
    numeric = np.stack([(_outside_residuals(p + h, points, floor_height)[0]
                         - _outside_residuals(p - h, points, floor_height)[0]) / 2e-6
                        for h in np.eye(p.shape[1])[:, None] * 1e-6], axis=-1)
    np.testing.assert_allclose(jac, numeric, atol=1e-5)


def test_surface_points_from_depth_place_a_table_whose_legs_are_hidden():
    # A table seen from one side in 5 views with only its top 0.12 m in its detections (the chairs in front hide
    # its legs, unflagged): matched with the class height, the boxes stand it on the floor behind. Points of
    # its top surface from a depth image (a few of them on the wall 1 m behind, a mask's bleed) hold the box
    # where the top was seen.
    gt = Box3D(np.array([0.0, 0.0, 0.375]), np.array([1.6, 0.9, 0.75]), 0.0)
    visible = Box3D(np.array([0.0, 0.0, 0.69]), np.array([1.6, 0.9, 0.12]), 0.0)
    views = [look_at([x, -3.0, 1.5], [0.0, 0.0, 0.4]) for x in (-0.6, -0.3, 0.0, 0.3, 0.6)]
    T_cw = np.stack([invert_transform(T) for T in views])
    boxes = np.stack([_box_of(visible.center, visible.size, visible.yaw, T) for T in views])
    rng = np.random.default_rng(0)
    top = np.column_stack([rng.uniform(-0.8, 0.8, 150), rng.uniform(-0.45, 0.45, 150), np.full(150, 0.75)])
    bleed = np.column_stack([rng.uniform(-0.8, 0.8, 10), np.full(10, 1.5), rng.uniform(0.6, 0.75, 10)])

    def centre_error(points):
        fit = fit_box(np.repeat(K[None], len(views), 0), T_cw, boxes, np.ones((len(views), 4), bool), (0.6, 3.0),
                      gt.center + [0.1, 0.3, 0.0], floor_height=0.0, anchor_weight=0.1, shape=(1.5, 0.9, 0.75),
                      height_prior_weight=0.2, bottom_below_weight=0.3, points=points, points_weight=1.0)
        return np.linalg.norm(fit.center - gt.center)

    without, with_points = centre_error(None), centre_error(np.concatenate([top, bleed]))
    assert without > 0.2
    assert with_points < 0.1
