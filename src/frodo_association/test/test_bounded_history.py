"""Bounded detection history for long runs (`max_detections_per_object`, issue 12 "Long runs"): a cluster holds at
most that many detections, the rows the per-frame work scans stop growing, retired rows' memory is freed, and a
republished frame still carries every detection (retired ones as last published)."""
import numpy as np

from frodo_association.config import AssociationConfig
from frodo_association.synthetic import make_scene
from frodo_association.tracker import Associator, detections_from_instances

CAP = 40


def _run(assoc: Associator, scene, dets, on_frame=None) -> None:
    for k, (f, (labels, boxes)) in enumerate(zip(scene.frames, dets)):
        update = assoc.add_frame(f.stamp, f.K, f.T_world_camera, f.size, labels, boxes)
        refined = assoc.refine_boxes()
        if on_frame is not None:
            on_frame(k, update, refined)


def test_history_is_bounded_and_outputs_stay_complete():
    scene = make_scene(3, 7, n_frames=200)
    dets = [detections_from_instances(f.instances) for f in scene.frames]
    n_dets = {f.stamp: len(labels) for f, (labels, _) in zip(scene.frames, dets)}
    unbounded = Associator(AssociationConfig(max_detections_per_object=0))
    _run(unbounded, scene, dets)
    bounded = Associator(AssociationConfig(max_detections_per_object=CAP))
    held: list[int] = []

    def check(k, update, refined):
        assign = bounded.rows.assign
        assert np.bincount(assign[assign >= 0], minlength=1).max() <= CAP
        # Unassigned detections are retired after CAP frames.
        assert np.all(bounded.rows.frame[assign < 0] >= len(bounded.frames) - CAP - 1)
        held.append(len(bounded.rows))
        for s in update.republish + refined.republish:
            table = bounded.frame_table(s)
            assert len(table) == n_dets[s]                       # retired rows included, as last published
            assert np.array_equal(table['label'], dets[bounded.frame_index[s]][0])

    _run(bounded, scene, dets, check)
    mixed = [fi for fi in bounded._retired if bounded.frames.start[fi] < bounded.frames.stop[fi]]
    assert mixed and len(mixed) == len(bounded._retired)      # frames without live rows hold nothing
    for fi in mixed:                                           # retired rows in place, as last published
        table = bounded.frame_table(int(bounded.frames.stamp[fi]))
        assert np.array_equal(table['label'], dets[fi][0]) and np.allclose(table['bbox'], dets[fi][1])
    assert bounded.retired > 0 and len(unbounded.rows) == bounded.retired + len(bounded.rows)
    # The rows the per-frame work scans stop growing: at most CAP per cluster plus CAP frames of unassigned ones.
    per_frame = max(n_dets.values())
    assert max(held[100:]) <= CAP * len(bounded.tracks) + CAP * per_frame
    assert max(held[150:]) <= max(held[50:100]) + per_frame
    assert len(unbounded.rows) > 2 * max(held[150:])
    # Retired rows are freed: the columns are reallocated to at most twice the live rows.
    assert len(bounded.rows._cols['assign']) <= max(16, 2 * max(held[-2:]) + per_frame)
    # The same objects are published (same ids), their boxes still close to the truth (unbounded: 0.005 m; the
    # thinned older views keep the viewpoints spread over the 240-degree walk).
    assert [t.object_id for t in unbounded.confirmed_tracks()] == [t.object_id for t in bounded.confirmed_tracks()]
    assert len(bounded.confirmed_tracks()) == 3
    for t in bounded.confirmed_tracks():
        truth = min(np.linalg.norm(np.asarray(o.center) - t.center) for o in scene.objects)
        assert truth < 0.15 and min(np.linalg.norm(np.asarray(o.center) - t.box.center) for o in scene.objects) < 0.05
