"""Publishing from geometry (issue 27): implausible landmark depths are dropped, cut detections count as evidence,
an object still in view waits for confirm_window frames unless the input ended (`settle`), a detection in one
keyframe is never published, and a partial view's cluster lying inside another object's box is merged into it."""
from dataclasses import replace

import numpy as np

from frodo_association.config import AssociationConfig
from frodo_association.pruning import REFERENCE_SIZE
from frodo_association.segments import point_segment_distance
from frodo_association.synthetic import BoxObject, render_instances
from frodo_association.tracker import Associator, detections_from_instances
from frodo_common.geometry import look_at

CHAIR = 62
K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
SIZE = (320, 240)


def test_a_surface_depth_too_far_for_the_box_is_ignored():
    obj = BoxObject(CHAIR, np.array([0.3, 2.0, 0.45]), np.array([0.5, 0.5, 0.9]), 0.3)
    T = look_at(np.array([0.0, 0.0, 1.2]), obj.center)
    labels, boxes = detections_from_instances(render_instances([obj], K, T, SIZE)[0])
    near_face = np.linalg.norm(obj.center - T[:3, 3]) - 0.25
    segments = {}
    for name, depth in (('none', None), ('right', near_face), ('background', 2.0 * near_face)):
        a = Associator()
        a.add_frame(1, K, T, SIZE, labels, boxes, None if depth is None else np.array([depth]))
        segments[name] = a.rows.segment[0]
    # The background behind an untextured chair: the box is too wide for a chair that far, so the segment is the
    # size-derived one (through the object), not a short one behind it; the right depth still gives a short one.
    assert np.allclose(segments['background'], segments['none'])
    assert point_segment_distance(obj.center[None], segments['background'][None])[0, 0] < 0.2
    assert np.linalg.norm(np.diff(segments['right'], axis=0)) < np.linalg.norm(np.diff(segments['none'], axis=0))


def _run(objects, poses, cfg, keep=lambda k, i, box: True):
    a = Associator(cfg)
    for k, T in enumerate(poses):
        inst, gt, _ = render_instances(objects, K, T, SIZE)
        labels, boxes = detections_from_instances(inst)
        mask = np.array([keep(k, gt[int(lab)], box) for lab, box in zip(labels, boxes)], dtype=bool)
        a.add_frame(k + 1, K, T, SIZE, labels[mask], boxes[mask])
        a.refine_boxes()
    return a


def test_an_object_cut_by_the_border_in_all_but_one_view_is_published():
    # A chair cut by the left image border in every view but the first.
    obj = BoxObject(CHAIR, np.array([0.0, 2.5, 0.45]), np.array([0.5, 0.5, 0.9]), 0.0)
    poses = [look_at(np.array([x, 0.0, 1.2]), np.array([x + (0.9 if k == 0 else 1.6), 2.5, 0.45]))
             for k, x in enumerate(np.linspace(-0.6, 0.0, 12))]
    # Only the first view (whole) is reliable: it opens the cluster, the 9 truncated ones join it.
    a = _run([obj], poses, AssociationConfig(), keep=lambda k, i, box: k == 0 or box[0] <= 1)
    reliable = a.rows.reliable[a.rows.assign >= 0]
    assert reliable.sum() < AssociationConfig().min_track_views <= len(reliable)
    assert len(a.confirmed_tracks()) == 1 and len(a.members(a.confirmed_tracks()[0].object_id)) == 10


def test_an_object_in_view_at_the_end_of_the_keyframes_is_published_but_a_one_keyframe_detection_is_not():
    chair = BoxObject(CHAIR, np.array([2.4, 2.5, 0.45]), np.array([0.5, 0.5, 0.9]), 0.2)
    # 8 keyframes 0.35 m apart, the chair in view (whole) in the last 6 only: it never leaves the view.
    poses = [look_at(np.array([0.35 * k, 0.0, 1.2]), np.array([0.35 * k + 0.6, 2.5, 0.5])) for k in range(8)]
    whole = lambda k, i, box: k >= 2 and box[0] > 2 and box[2] < SIZE[0] - 3       # noqa: E731
    a = _run([chair], poses, AssociationConfig(confirm_window=5), keep=whole)     # in view in 6 frames
    assert len(a.confirmed_tracks()) == 1
    assert a._view_stats(a.confirmed_tracks()[0].object_id)[2]          # still in view in the last keyframe
    # The same chair in the last keyframe only is not published, not even at the end of the input.
    b = _run([chair], poses, AssociationConfig(), keep=lambda k, i, box: k == 7)
    b.settle()
    assert b.confirmed_tracks() == [] and 'consistent detections in 1 frames' in b.publish_blocker(0)
    # The default window (10 frames) holds it back while it is in view; the end of the input publishes it.
    c = _run([chair], poses, AssociationConfig(), keep=whole)
    assert c.confirmed_tracks() == [] and 'still in view' in c.publish_blocker(0)
    update = c.settle()
    assert len(c.confirmed_tracks()) == 1 and update.republish and c.confirmed_tracks()[0].box is not None


def test_a_partial_view_inside_another_objects_box_is_merged_into_it():
    # Box-world walk (seed 119, 5 chairs, 2 px mask noise): one chair's detections in 6 frames, its lower part
    # hidden, open a cluster of their own 0.6 m from it; they lie inside its projected box.
    from frodo_association.evaluate import CONDITIONS, LAYOUTS, run_scene
    from frodo_association.synthetic import make_scene
    from frodo_detection.core import FilterConfig
    scene = make_scene(5, 119, n_frames=60, **LAYOUTS['walk'], **CONDITIONS['mask noise 2px'])
    merged = run_scene(scene, AssociationConfig(), FilterConfig())
    apart = run_scene(scene, AssociationConfig(explained_inside=2.0, frustum_merges=False), FilterConfig())
    assert (merged.recovered, merged.duplicates, merged.false_tracks) == (5, 0, 0)
    assert apart.duplicates == 1
    # Its detections never share a frame with the chair's and hold the chair's centre: the frustum merge alone
    # joins them too.
    frustum = run_scene(scene, AssociationConfig(explained_inside=2.0), FilterConfig())
    assert (frustum.recovered, frustum.duplicates, frustum.false_tracks) == (5, 0, 0)


def test_a_published_object_whose_box_no_detection_overlaps_keeps_its_largest_views():
    # realwalk-tune 8404: a table's box placed 0.8 m off, the camera inside it, kept none of its detections and
    # was never reconstructed.
    chair = BoxObject(CHAIR, np.array([0.0, 2.5, 0.45]), np.array([0.5, 0.5, 0.9]), 0.0)
    poses = [look_at(np.array([x, 0.0, 1.2]), np.array([0.0, 2.5, 0.45])) for x in np.linspace(-0.8, 0.8, 6)]
    a = _run([chair], poses, AssociationConfig())
    a.settle()
    (track,) = a.confirmed_tracks()
    rows = a.members(track.object_id)
    area = np.prod(a.rows.box[rows, 2:] - a.rows.box[rows, :2], axis=1)
    every = set(range(len(a.frames)))
    for center in ([0.0, 0.1, 1.0], [3.0, 2.5, 0.45]):       # around the first camera; far to one side
        track.box = type(track.box)(np.array(center), track.box.size, track.box.yaw)
        a.rows.kept[rows] = False
        a._prune_frames(sorted(every))
        assert not a.rows.kept[rows].any()
        assert a._keep_best_views(every)
        kept = a.rows.kept[rows]
        assert kept.sum() == AssociationConfig().min_track_views
        assert area[kept].min() >= area[~kept].max()
    # Where no detection passes the size and overlap tests (every view of a table overlaps the chairs in front of
    # it: realwalk-tune 8401), the ones that best match the box are kept all the same.
    a.cfg = replace(a.cfg, min_box_width=10_000)
    a.rows.kept[rows] = False
    a._prune_frames(sorted(every))
    assert not a.rows.kept[rows].any()
    assert a._keep_best_views(every)
    assert a.rows.kept[rows].sum() == AssociationConfig().min_track_views
    # Where some pass, only those are kept: the views failing the tests are not added to make up the number (they
    # had a chair placed 0.54 m off reconstructed, a false positive: realwalk-tune 8401).
    scale = np.sqrt(np.prod(a.frames.size[a.rows.frame[rows]], axis=1) / np.prod(REFERENCE_SIZE))
    widths = np.sort((a.rows.box[rows, 2] - a.rows.box[rows, 0]) / scale)
    threshold = float(widths[-3] + widths[-2]) / 2            # the two widest views pass (fewer than needed)
    a.cfg = replace(a.cfg, min_box_width=threshold)
    a.rows.kept[rows] = False
    assert a._keep_best_views(every)
    assert a.rows.kept[rows].sum() == 2
    assert (((a.rows.box[rows, 2] - a.rows.box[rows, 0]) / scale)[a.rows.kept[rows]] >= threshold).all()


def test_the_merges_run_again_after_the_final_box_fits():
    # Box-world walk, seed 19: a chair's last 3 detections form a cluster of their own; they lie inside the box the
    # chair gets only from the final fits at the end of the input, so only a merge after those fits joins them.
    # (realwalk 9200: a table's far end, confirmed at the end, stayed a duplicate, and the two boxes' mutual
    # overlap pruned every detection of both.)
    from frodo_association.evaluate import CONDITIONS, LAYOUTS
    from frodo_association.synthetic import make_scene
    from frodo_detection.core import FilterConfig, filter_instances
    scene = make_scene(5, 19, n_frames=60, **LAYOUTS['walk'], **CONDITIONS['clean'])
    a = Associator(AssociationConfig())
    for frame in scene.frames:
        _, dets = filter_instances(frame.instances, FilterConfig())
        a.add_frame(frame.stamp, frame.K, frame.T_world_camera_observed, frame.size,
                    np.array([d.label for d in dets], dtype=np.int64), np.array([d.bbox for d in dets]).reshape(-1, 4))
        a.refine_boxes()
    a.settle()
    published = a.confirmed_tracks()
    assert len(published) == 5
    assert sorted(len(a.members(t.object_id)) for t in published)[-2:] == [60, 60]
    unpublished = [oid for oid in a.tracks if not a.tracks[oid].confirmed]
    assert all(len(a.members(oid)) < AssociationConfig().min_track_views for oid in unpublished)


def _entry_depth(box, T, obj):
    """Optical depth where the ray through the centre of a detection box enters an upright box with yaw 0 (the
    visible surface a depth image or the map's landmarks give)."""
    d = T[:3, :3] @ np.array([((box[0] + box[2]) / 2 - K[0, 2]) / K[0, 0], ((box[1] + box[3]) / 2 - K[1, 2]) / K[1, 1],
                              1.0])
    with np.errstate(divide='ignore'):
        t1, t2 = (obj.center - obj.size / 2 - T[:3, 3]) / d, (obj.center + obj.size / 2 - T[:3, 3]) / d
    near, far = np.minimum(t1, t2).max(), np.maximum(t1, t2).min()
    return near if near <= far else np.nan


def _publish_split(a, object_id, from_frame):
    """Move a cluster's detections of frames >= from_frame into a new published cluster (a split object, both
    halves published); returns the new id."""
    rows = a.members(object_id)
    late = rows[a.rows.frame[rows] >= from_frame]
    half = a._new_track(int(late[0]))
    a.rows.assign[late] = half
    a._update_centers([object_id, half])
    a.tracks[half].confirmed = True
    return half


def test_a_long_table_split_into_two_published_halves_merges_when_one_lies_in_the_others_views():
    # Inside-out walk (fresh room 8600): a 2.6 m table 1.1-1.4 m away, too long for the view; the camera turns from
    # its right end to its left end. Its two halves published apart, with boxes whose footprints barely overlap.
    table = BoxObject(67, np.array([-0.45, -1.5, 0.36]), np.array([2.6, 0.9, 0.72]), 0.0)
    a = Associator(AssociationConfig())
    for k, s in enumerate(np.linspace(0, 1, 22)):
        eye = np.array([-0.6 * np.cos(np.pi * (0.15 + 0.7 * s)), -0.6 * np.sin(np.pi * (0.15 + 0.7 * s)), 1.45])
        T = look_at(eye, eye + np.array([0.8 - 1.6 * s, -1.0, -0.7]))
        labels, boxes = detections_from_instances(render_instances([table], K, T, SIZE)[0])
        a.add_frame(k, K, T, SIZE, labels, boxes, np.array([_entry_depth(b, T, table) for b in boxes]))
    half = _publish_split(a, 0, 11)
    for oid in (0, half):
        a.fit_object_box(oid)
    # The first half's box centre lies in the frustum of the second half's detections (inside the box, within
    # the depths of its segment) in most frames that see it, and no frame holds both: one table.
    a.cfg = replace(a.cfg, box_overlap_merge=2.0, truncated_explained_iou=2.0)      # the frustum test alone
    assert a._frustum_duplicates(a.confirmed_tracks()) == [(half, 0)]
    a.cfg = replace(a.cfg, frustum_merges=False)
    assert a.merge_explained() == ({}, set())
    # The first half's box 2 m farther along the second half's views, beyond their depths, is another object.
    near_box = a.tracks[0].box
    a.tracks[0].box = replace(near_box, center=near_box.center + [0.0, -2.0, 0.0])
    assert a._frustum_duplicates(a.confirmed_tracks()) == []
    a.tracks[0].box = near_box
    a.cfg = replace(a.cfg, frustum_merges=True)
    removed, dirty = a.merge_explained()
    assert removed == {half: 0} and list(a.tracks) == [0] and dirty == set(range(22))


def test_a_frustum_holds_the_part_of_a_box_in_view_when_its_centre_is_not():
    # A 3 m table seen from 2 m at its left end, then at its right end (cut by the image border each time), split
    # into two published halves: from the right end the left half's box centre is out of view, but the part of
    # its box in view lies inside the detections there.
    from frodo_common.geometry import Box3D
    table = BoxObject(67, np.array([0.0, 2.0, 0.36]), np.array([3.0, 0.9, 0.72]), 0.0)
    views = [look_at(np.array([x, 0.0, 1.4]), np.array([x, 2.0, 0.3]))
             for x in [*np.linspace(-1.3, -1.0, 6), *np.linspace(1.0, 1.3, 6)]]
    a = Associator(AssociationConfig())
    for k, T in enumerate(views):
        a.add_frame(k, K, T, SIZE, *detections_from_instances(render_instances([table], K, T, SIZE)[0]))
    a.settle()
    right = _publish_split(a, 0, 6)
    a.fit_object_box(0)
    a.tracks[right].box = Box3D(table.center, table.size, 0.0)
    assert (right, 0) in a._frustum_duplicates(a.confirmed_tracks())
    a.cfg = replace(a.cfg, explained_inside=2.0)                # the projected-box test off: the centre alone
    assert (right, 0) not in a._frustum_duplicates(a.confirmed_tracks())
