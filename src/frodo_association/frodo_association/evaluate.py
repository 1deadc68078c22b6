"""Evaluation of the association stage (paper Sec. 5.1, supplement "DP-mean based Line Segment Clustering" and
"Detection Pruning") on scenes with ground truth: association purity and completeness, 3D box errors and the
detection pruning ablation.

Metrics (per scene, then pooled over scenes):
- purity: of the detections the associator published with an object id, the fraction whose object is the
  track matched to their ground-truth object (tracks and ground-truth objects matched one-to-one by Hungarian
  on shared detections);
- assigned: the same count over all detections (unassociated detections count as misses);
- completeness: fraction of observable ground-truth objects (>= min_track_views detections) recovered by
  exactly one track; duplicates: tracks beyond one per object; false tracks: tracks matching no object;
- box errors of matched tracks: centre (m), size (mean absolute error over dx, dy, dz after the quarter-turn
  canonicalisation), yaw (degrees, modulo 90);
- pruning: kept fraction, mean ground-truth visibility of kept and of pruned detections, fraction of kept
  detections less than 70 % visible ("bad kept").

Usage: python -m frodo_association.evaluate [--seeds 100-119] [--objects 2-5] [--frames 60]
       [--layout walk|dense|furniture] [--conditions NAME,...] [--no-ablation] [--json OUT]
       python -m frodo_association.evaluate --layout handheld [--seeds 100-105] [--conditions real-like,...]
           [--variants base,...] [--evidence depth,landmarks|depth|landmarks|none]
           (keyframes of a handheld kitchen capture, `handheld.py`; one row per condition and variant with
           recall, false tracks per scene (duplicates included) and the median centre error)
       python -m frodo_association.evaluate --bags A.mcap [B.mcap ...] [--pool] [--conditions NAME,...]
           [--set NAME=VALUE,...] [--evidence ...] [--trace]
           (contract bags with ground truth, their depth images and /slam/points maps giving surface depths; by default clean,
           one row per bag; --pool: one row per condition; --set:
           AssociationConfig values; --trace: per ground-truth object, why it is or is not published)
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from dataclasses import asdict, dataclass, replace

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from frodo_association.boxes import box_iou, box_inside_fraction, canonical_yaw, clip_boxes
from frodo_association.config import AssociationConfig, EvidenceConfig
from frodo_association.evidence import contact_edges, depth_points, surface_depths
from frodo_common.frames import depth_to_metres
from frodo_association.tracker import Associator
from frodo_association.synthetic import (BoxObject, SynthFrame, SynthScene, add_noise, make_furniture_scene,
                                        make_scene)
from frodo_common.geometry import bearing_span, invert_transform
from frodo_detection.core import FilterConfig, filter_instances, instance_boxes

LAYOUTS: dict[str, dict] = {
    'walk': {},                                                   # 320x240, ~3.6 m arc of 240 deg, 3.2 m square
    'dense': {'size': (640, 480), 'extent': 2.0, 'radius': 7.5, 'sweep_deg': 90.0},   # many objects, far
    'furniture': {},                                              # rendered procedural chairs/tables, 640x480
    'handheld': {},                                               # kitchen keyframes, close range (handheld.py)
}
CONDITIONS: dict[str, dict] = {
    'clean': {},
    'mask noise 2px': {'mask_noise': 2},
    'pose noise 0.5deg/2cm': {'rot_noise_deg': 0.5, 'trans_noise': 0.02},
    'all noise + 10% misses': {'mask_noise': 2, 'rot_noise_deg': 0.5, 'trans_noise': 0.02, 'miss_rate': 0.1},
}
_REAL_MASKS = {'boundary_px': 4, 'hole_prob': 0.3, 'bleed_prob': 0.3, 'miss_rate': 0.1}
_DRIFT = {'drift_m': 0.05, 'drift_deg': 2.0}
HANDHELD_CONDITIONS: dict[str, dict] = {
    'clean': {},
    'real masks': _REAL_MASKS,
    'pose drift': _DRIFT,
    'real-like': {**_REAL_MASKS, **_DRIFT},
}
"""Handheld keyframe conditions (`handheld.make_handheld_scene` arguments): real masks = edges +-4 px, holes,
bleeding, 10 % misses; pose drift = about 5 cm and 2 deg at the end of the 1000-frame sequence."""
HANDHELD_VARIANTS: dict[str, dict] = {
    'base': {},
    'far range 1.5-3 m (less truncation)': {'near': 1.5, 'far': 3.0},
    'chairs out (less occlusion)': {'push': (-0.15, 0.0)},
    'chairs pushed under': {'push': (0.3, 0.5)},
    '15 keyframes': {'n_keyframes': 15},
    '120 keyframes': {'n_keyframes': 120},
}
"""Layout variants of the handheld kitchen, one factor changed from 'base' (35 keyframes, 0.5-1.6 m beyond the
table, chairs pushed in by -0.1..0.35 m, 4 clutter boxes on the table)."""


@dataclass
class SceneResult:
    """Counts and errors of one scene (pooled by `summarise`)."""

    detections: int = 0
    associated: int = 0
    correct: int = 0
    objects: int = 0
    recovered: int = 0
    duplicates: int = 0
    false_tracks: int = 0
    center_err: list = None
    size_err: list = None
    yaw_err: list = None
    kept: int = 0
    kept_vis: list = None
    pruned_vis: list = None
    assoc_ms: list = None
    refine_ms: list = None
    boxes: list = None
    trace: list = None


def run_scene(scene: SynthScene, cfg: AssociationConfig, filt: FilterConfig,
              evidence: tuple[str, ...] = ('depth', 'landmarks'), trace: bool = False,
              evidence_cfg: EvidenceConfig | None = None) -> SceneResult:
    """Associate every frame of a scene and score the final state against its ground truth. `evidence`: which of
    the scene's depth images and landmarks (where it has them) give the detections' surface depths, as the node
    takes them (`evidence_cfg`, default EvidenceConfig()); `trace`: also say per ground-truth object why it is or
    is not published (`trace_objects`, in `res.trace`)."""
    assoc = Associator(cfg)
    e = evidence_cfg or EvidenceConfig()
    gt_rows: list[int] = []
    vis_rows: list[float] = []
    res = SceneResult(center_err=[], size_err=[], yaw_err=[], kept_vis=[], pruned_vis=[], assoc_ms=[], refine_ms=[])
    for frame in scene.frames:
        _, dets = filter_instances(frame.instances, filt)
        labels = np.array([d.label for d in dets], dtype=np.int64)
        boxes = np.array([d.bbox for d in dets], dtype=np.float64).reshape(-1, 4)
        surface, points = None, None
        landmarks = frame.landmarks if frame.landmarks is not None else scene.landmarks
        if (frame.depth is not None and 'depth' in evidence) or (landmarks is not None and 'landmarks' in evidence):
            surface = surface_depths(frame.instances, labels, frame.K, invert_transform(frame.T_world_camera_observed),
                                     depth_to_metres(frame.depth) if 'depth' in evidence and frame.depth
                                     is not None else None, landmarks if 'landmarks' in evidence else None,
                                     **e.surface_arguments())
        if frame.depth is not None and 'depth' in evidence and len(labels):
            points = depth_points(frame.instances, labels, depth_to_metres(frame.depth), frame.K,
                                  frame.T_world_camera_observed, cfg, e)
        contact = contact_edges(frame.instances, labels, boxes, surface) if cfg.box_contact_edges else None
        t0 = time.perf_counter()
        assoc.add_frame(frame.stamp, frame.K, frame.T_world_camera_observed, frame.size, labels, boxes, surface,
                        contact, points)
        t1 = time.perf_counter()
        assoc.refine_boxes()
        res.assoc_ms.append(1e3 * (t1 - t0))
        res.refine_ms.append(1e3 * (time.perf_counter() - t1))
        gt_rows += [frame.gt.get(int(lab), -1) for lab in labels]
        vis_rows += [frame.visibility.get(int(lab), np.nan) for lab in labels]
    assoc.settle()     # end of the sequence: final pass, confirmation and boxes
    gt = np.array(gt_rows, dtype=np.int64)
    vis = np.array(vis_rows)
    tables = np.concatenate([assoc.frame_table(int(s)) for s in assoc.frames.stamp])
    ids = tables['object_id'].astype(np.int64)
    kept = tables['kept'].astype(bool)
    tracks = assoc.confirmed_tracks()
    n_obj = len(scene.objects)
    counts = np.zeros((len(tracks), n_obj), dtype=np.int64)
    for k, t in enumerate(tracks):
        member_gt = gt[(ids == t.object_id) & (gt >= 0)]
        counts[k] = np.bincount(member_gt, minlength=n_obj)
    rows, cols = linear_sum_assignment(-counts) if len(tracks) else (np.zeros(0, int), np.zeros(0, int))
    match = {int(r): int(c) for r, c in zip(rows, cols) if counts[r, c] > 0}
    res.detections = int(np.count_nonzero(gt >= 0))
    res.associated = int(np.count_nonzero(ids >= 0))
    res.correct = int(sum(counts[r, c] for r, c in match.items()))
    observable = np.bincount(gt[gt >= 0], minlength=n_obj) >= cfg.min_track_views
    majority = counts.argmax(axis=1) if len(tracks) else np.zeros(0, int)
    per_object = np.bincount(majority, minlength=n_obj) if len(tracks) else np.zeros(n_obj, int)
    res.objects = int(observable.sum())
    res.recovered = int(np.count_nonzero(observable & (per_object == 1)))
    res.duplicates = int(np.clip(per_object - 1, 0, None).sum())
    res.false_tracks = len(tracks) - len(match)
    for k, t in enumerate(tracks):
        if k not in match or t.box is None:
            continue
        obj = scene.objects[match[k]]
        gt_size, gt_yaw = canonical_yaw(obj.size, obj.yaw)
        res.center_err.append(float(np.linalg.norm(t.box.center - obj.center)))
        res.size_err.append(float(np.mean(np.abs(t.box.size - gt_size))))
        d = (t.box.yaw - gt_yaw + np.pi / 4) % (np.pi / 2) - np.pi / 4
        res.yaw_err.append(float(np.degrees(abs(d))))
    res.boxes = [(t.coco_id, t.box.center, t.box.size, t.box.yaw, match.get(k, -1)) for k, t in enumerate(tracks)
                 if t.box is not None]
    if trace:
        res.trace = trace_objects(assoc, scene, gt, tracks, match)
    sel = ids >= 0
    res.kept = int(np.count_nonzero(kept & sel))
    res.kept_vis = vis[kept & sel].tolist()
    res.pruned_vis = vis[~kept & sel].tolist()
    return res


def placement_evidence(assoc: Associator, rows: np.ndarray, obj: BoxObject) -> tuple[float, float | None]:
    """What fixes an object's depth along the view, from its detections (`rows`) and its ground truth: the
    horizontal angle (degrees) over which its detections' cameras see its centre (a few degrees: the rays nearly
    parallel), and the median, over its detections with an uncut bottom edge, of the height between its box's
    projected bottom and the detection's bottom as a fraction of its projected height (None without such a
    detection; about 0 when the detections reach its floor contact, 0.3-0.7 when the masks miss a chair's legs or
    an unlabelled occluder hides its lower part: then the box fit puts it too far)."""
    frames = assoc.rows.frame[rows]
    T = assoc.frames.T_camera_world[frames]
    cams = np.einsum('fij,fj->fi', -np.transpose(T[:, :3, :3], (0, 2, 1)), T[:, :3, 3])     # camera centres
    spread = bearing_span(cams, obj.center)
    uncut = assoc.rows.fit_edges[rows, 3]
    if not uncut.any():
        return spread, None
    corners = obj.corners()
    pc = np.einsum('fij,cj->fci', T[uncut, :3, :3], corners) + T[uncut, None, :3, 3]       # (F, 8, 3)
    K = assoc.frames.K[frames[uncut]]
    v = K[:, 1, 1, None] * pc[..., 1] / np.maximum(pc[..., 2], 1e-6) + K[:, 1, 2, None]
    height = np.maximum(v.max(1) - v.min(1), 1.0)
    return spread, float(np.median((v.max(1) - assoc.rows.box[rows[uncut], 3]) / height))


def along_view_error(assoc: Associator, rows: np.ndarray, obj: BoxObject, center: np.ndarray) -> float:
    """Signed horizontal offset (m) of an estimated centre from the object's true one along the mean direction
    from its detections' cameras to it: positive when the estimate lies farther away than the truth."""
    T = assoc.frames.T_camera_world[assoc.rows.frame[rows]]
    cams = np.einsum('fij,fj->fi', -np.transpose(T[:, :3, :3], (0, 2, 1)), T[:, :3, 3])
    look = obj.center[:2] - cams[:, :2]
    look /= np.maximum(np.linalg.norm(look, axis=1, keepdims=True), 1e-9)
    view = look.mean(0)
    view /= max(float(np.linalg.norm(view)), 1e-9)
    return float((center[:2] - obj.center[:2]) @ view)


def trace_objects(assoc: Associator, scene: SynthScene, gt: np.ndarray, tracks: list, match: dict[int, int],
                  far: float = 0.5) -> list[str]:
    """One line per ground-truth object: its detections (reliable / truncated / other; how many with a surface
    depth), the clusters holding them, and its fate: published (box centre error; 'placement' when farther than
    `far` m, with `placement_evidence`), or why not: never detected, never clustered, taken by another object's
    track, or the first publishing condition its main cluster fails (`Associator.publish_blocker`). gt: (rows,)
    object index of every detection row (-1: none); tracks / match: the published tracks and {track index: object
    index} of `run_scene`."""
    from frodo_common.categories import category_by_id

    lines = []
    by_object = {o: k for k, o in match.items()}
    owner = {t.object_id: match.get(k, -1) for k, t in enumerate(tracks)}
    for obj_index, obj in enumerate(scene.objects):
        rows = np.nonzero(gt == obj_index)[0]
        name = category_by_id(obj.coco_id).name
        rel, trunc = assoc.rows.reliable[rows], assoc.rows.truncated[rows]
        clusters = np.unique(assoc.rows.assign[rows], return_counts=True)
        held = ', '.join(f'{"none" if c < 0 else c}: {n}' for c, n in zip(*clusters))
        head = (f'object {obj_index} ({name}, {np.linalg.norm(obj.size[:2]):.2f} m across): {len(rows)} detections '
                f'in {len(np.unique(assoc.rows.frame[rows]))} frames, {int(rel.sum())} reliable, '
                f'{int(trunc.sum())} truncated, {int((~rel & ~trunc).sum())} other, '
                f'{int(np.isfinite(assoc.rows.surface[rows]).sum())} with surface depth; clusters {{{held or "-"}}}: ')
        if obj_index in by_object:
            t = tracks[by_object[obj_index]]
            err = np.linalg.norm(t.box.center - obj.center) if t.box is not None else float('nan')
            kept = int(np.count_nonzero(assoc.rows.kept[assoc.members(t.object_id)]))
            fate = f'published as {t.object_id} with {kept} kept detections, box centre {err:.2f} m off'
            if t.box is not None and len(rows):
                fate += f' ({along_view_error(assoc, rows, obj, t.box.center):+.2f} m along the view)'
            if err > far:
                spread, gap = placement_evidence(assoc, rows, obj)
                fate += (f' (placement: seen over {spread:.0f} deg, ' + ('no uncut bottom edge)' if gap is None else
                         f'detection bottoms {gap:.2f} of its height above its bottom)'))
        elif len(rows) == 0:
            fate = 'never detected (or no detection matched it)'
        else:
            assigned = clusters[0] >= 0
            if not assigned.any():
                fate = 'never clustered (its detections opened no cluster and joined none)'
            else:
                main = int(clusters[0][assigned][np.argmax(clusters[1][assigned])])
                t = assoc.tracks[main]
                if t.confirmed:
                    fate = f'its main cluster {main} is published for object {owner.get(main, -1)}'
                else:
                    fate = f'main cluster {main} not published: {assoc.publish_blocker(main)}'
        lines.append(head + fate)
    for k, t in enumerate(tracks):
        if k not in match:
            member_gt = gt[assoc.members(t.object_id)]
            of = np.bincount(member_gt[member_gt >= 0]).argmax() if (member_gt >= 0).any() else -1
            lines.append(f'false track {t.object_id} ({category_by_id(t.coco_id).name}) at '
                         f'{np.round(t.center, 2).tolist()}: {len(member_gt)} detections'
                         + (f', duplicate of object {of}' if of >= 0 else ''))
    return lines


def summarise(results: list[SceneResult]) -> dict:
    """Pooled metrics of several scenes."""
    s = lambda name: sum(getattr(r, name) for r in results)           # noqa: E731
    cat = lambda name: np.concatenate([np.asarray(getattr(r, name), float) for r in results])  # noqa: E731
    kept_vis, pruned_vis = cat('kept_vis'), cat('pruned_vis')
    kept_vis, pruned_vis = kept_vis[np.isfinite(kept_vis)], pruned_vis[np.isfinite(pruned_vis)]
    ms = lambda a: float(np.mean(a)) if len(a) else float('nan')       # noqa: E731
    return {
        'scenes': len(results), 'objects': s('objects'), 'detections': s('detections'),
        'purity': s('correct') / max(s('associated'), 1), 'assigned': s('correct') / max(s('detections'), 1),
        'completeness': s('recovered') / max(s('objects'), 1), 'duplicates': s('duplicates'),
        'false_tracks': s('false_tracks'),
        'center_err_m': ms(cat('center_err')),
        'center_err_median_m': float(np.median(cat('center_err'))) if len(cat('center_err')) else float('nan'),
        'false_per_scene': (s('false_tracks') + s('duplicates')) / max(len(results), 1), 'size_err_m': ms(cat('size_err')), 'yaw_err_deg': ms(cat('yaw_err')),
        'kept_frac': s('kept') / max(s('associated'), 1), 'kept_vis': ms(kept_vis), 'pruned_vis': ms(pruned_vis),
        'bad_kept_frac': float(np.mean(kept_vis < 0.7)) if len(kept_vis) else float('nan'),
        'assoc_ms_mean': ms(cat('assoc_ms')), 'refine_ms_mean': ms(cat('refine_ms')),
    }


def upright_box(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(centre, size, yaw) of the smallest upright box around vertices (N, 3) (minimum-area rectangle in xy)."""
    (cx, cy), (w, h), angle = cv2.minAreaRect(vertices[:, :2].astype(np.float32))
    z0, z1 = vertices[:, 2].min(), vertices[:, 2].max()
    return np.array([cx, cy, (z0 + z1) / 2]), np.array([w, h, z1 - z0]), float(np.radians(angle))


def scene_from_bag(path: str, min_iou: float = 0.3, min_inside: float = 0.9) -> tuple[SynthScene, list[str]]:
    """A contract bag with /camera/instances and /ground_truth/objects as a scene to score.

    Ground-truth objects: upright boxes around the ground-truth meshes (class from the marker ns). Each
    instance is labelled with the ground-truth object of its class whose projected mesh (bounding box of
    the projected vertices, clipped to the image) has the highest IoU with the instance box, at least
    `min_iou`; an instance box with no such match that lies at least `min_inside` inside the projected box
    of objects of its class is the partial view of the one of them it overlaps most (a chair pushed under a
    table shows its backrest only). Without occlusion in the ground truth this is an approximation. Each
    frame carries its registered depth image, if the bag has one at its stamp, and the latest /slam/points map
    stamped no later than it (as the association node sees them).
    Returns (scene, notes).
    """
    from frodo_common import conversions as conv
    from frodo_common import topics
    from frodo_common.bag import BagReader
    from frodo_common.categories import BY_NAME
    from frodo_common.geometry import project_points

    reader = BagReader(path)
    notes = list(reader.problems)
    info, poses, instances, depths, objects, vertices, maps = None, {}, {}, {}, [], [], {}
    for m in reader.messages([topics.CAMERA_INFO, topics.POSE, topics.INSTANCES, topics.DEPTH, topics.GROUND_TRUTH,
                              topics.SLAM_POINTS]):
        msg = m.decode()
        if m.topic == topics.CAMERA_INFO and info is None:
            info = (conv.camera_info_to_K(msg), (int(msg.width), int(msg.height)))
        elif m.topic == topics.POSE:
            poses[conv.stamp_to_ns(msg.header.stamp)] = conv.pose_to_matrix(msg.pose)
        elif m.topic == topics.INSTANCES:
            instances[conv.stamp_to_ns(msg.header.stamp)] = conv.image_to_numpy(msg)
        elif m.topic == topics.DEPTH:
            depths[conv.stamp_to_ns(msg.header.stamp)] = conv.image_to_numpy(msg)
        elif m.topic == topics.SLAM_POINTS:
            points = conv.cloud_to_xyz(msg)
            maps[conv.stamp_to_ns(msg.header.stamp)] = points[np.isfinite(points).all(1)]
        elif m.topic == topics.GROUND_TRUTH and not objects:
            for marker in msg.markers:
                if marker.ns not in BY_NAME:
                    notes.append(f'ground-truth class {marker.ns!r} unknown, skipped')
                    continue
                verts, _ = conv.marker_to_mesh(marker)
                objects.append(BoxObject(BY_NAME[marker.ns].coco_id, *upright_box(verts)))
                vertices.append(verts[np.linspace(0, len(verts) - 1, min(len(verts), 2000)).astype(int)])
    if info is None or not objects:
        raise ValueError(f'{path}: needs {topics.CAMERA_INFO} and {topics.GROUND_TRUTH}')
    K, size = info
    owner = np.concatenate([np.full(len(v), k) for k, v in enumerate(vertices)])
    points = np.concatenate(vertices)
    classes = np.array([o.coco_id for o in objects])
    frames = []
    map_stamps = np.array(sorted(maps), dtype=np.int64)
    for stamp in sorted(set(poses) & set(instances)):
        uv, depth = project_points(K, invert_transform(poses[stamp]), points)
        front = depth > 0.05
        gt_boxes = np.zeros((len(objects), 4))
        seen = np.zeros(len(objects), dtype=bool)
        for k in range(len(objects)):
            sel = front & (owner == k)
            if sel.any():
                gt_boxes[k] = [*uv[sel].min(0), *uv[sel].max(0)]
                seen[k] = True
        gt_boxes = clip_boxes(gt_boxes[None], np.array([size], float))[0]
        labels, boxes, _ = instance_boxes(instances[stamp])
        iou = box_iou(boxes[:, None, :], gt_boxes[None, :, :])
        iou[:, ~seen] = 0.0
        iou[(labels[:, None] >> 8) != classes[None, :]] = 0.0
        # Partial views (no match at min_iou): the objects of the class holding the box, ranked by IoU above all.
        partial = (box_inside_fraction(boxes[:, None, :], gt_boxes[None, :, :]) >= min_inside) & (iou > 0)
        iou = np.where((iou.max(axis=1, initial=0.0) < min_iou)[:, None] & partial, iou + 1.0, iou)
        gt = {int(lab): int(row.argmax()) for lab, row in zip(labels, iou) if row.size and row.max() >= min_iou}
        latest = np.searchsorted(map_stamps, stamp, side='right') - 1
        frames.append(SynthFrame(stamp, K, poses[stamp], poses[stamp], size, instances[stamp], gt, {},
                                 depth=depths.get(stamp), landmarks=maps[int(map_stamps[latest])] if latest >= 0 else None))
    notes.append(f'{len(frames)} frames with pose and instances, {len(objects)} ground-truth objects'
                 + (f', {len(maps)} SLAM maps' if maps else ''))
    return SynthScene(objects, frames), notes


def _range(text: str) -> list[int]:
    lo, _, hi = text.partition('-')
    return list(range(int(lo), int(hi or lo) + 1))


HEADER = ('| scenes | pruning | purity | assigned | completeness | dup | false | centre err (m) | size err (m) | '
          'yaw err (deg) | kept | vis kept / pruned | bad kept | assoc ms | refine ms |')


def table_row(name: str, prune: bool, m: dict) -> str:
    """One Markdown row of HEADER."""
    return (f"| {name} | {'on' if prune else 'off'} | {m['purity']:.3f} | {m['assigned']:.3f} | "
            f"{m['completeness']:.3f} | {m['duplicates']} | {m['false_tracks']} | {m['center_err_m']:.3f} | "
            f"{m['size_err_m']:.3f} | {m['yaw_err_deg']:.1f} | {m['kept_frac']:.2f} | "
            f"{m['kept_vis']:.2f} / {m['pruned_vis']:.2f} | {m['bad_kept_frac']:.3f} | "
            f"{m['assoc_ms_mean']:.2f} | {m['refine_ms_mean']:.2f} |")


def draw_scene_result(scene: SynthScene, res: SceneResult, path: str, title: str = '') -> None:
    """Top view of a scene (ground-truth boxes black, camera path grey) and the published boxes (matched:
    green, line to their object; duplicate or false: red), beside one keyframe's instance image."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from frodo_common.geometry import box_corners

    fig, (ax_img, ax) = plt.subplots(1, 2, figsize=(11, 4.4), gridspec_kw={'width_ratios': [1.25, 1]})
    frame = max(scene.frames, key=lambda f: len(f.gt))
    ax_img.imshow(np.where(frame.instances > 0, frame.instances % 256 * 37 % 255 + 1, 0), cmap='nipy_spectral',
                  interpolation='nearest')
    ax_img.set_title(f'a keyframe ({len(scene.frames)} in all): instance masks as seen', fontsize=9)
    ax_img.axis('off')
    eyes = np.array([f.T_world_camera_observed[:3, 3] for f in scene.frames])
    ax.plot(eyes[:, 0], eyes[:, 1], '.', color='0.6', ms=3, label='keyframes (observed poses)')
    for o in scene.objects:
        c = box_corners(o.center, o.size, o.yaw)[[0, 2, 6, 4, 0], :2]
        ax.plot(c[:, 0], c[:, 1], 'k-', lw=1.5)
    for coco, center, size, yaw, gt in res.boxes:
        c = box_corners(center, size, yaw)[[0, 2, 6, 4, 0], :2]
        ax.plot(c[:, 0], c[:, 1], '-', color='tab:green' if gt >= 0 else 'tab:red', lw=1.2)
        if gt >= 0:
            g = scene.objects[gt].center
            ax.plot([center[0], g[0]], [center[1], g[1]], '-', color='tab:green', lw=0.8)
    ax.set_aspect('equal')
    ax.set_title(title or 'top view: ground truth (black), published (green), duplicate/false (red)', fontsize=9)
    ax.tick_params(labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


HANDHELD_HEADER = ('| condition | variant | evidence | scenes | objects | recall | false / scene | dup | false | '
                   'median centre err (m) | mean centre err (m) | size err (m) | yaw err (deg) | assoc ms | refine ms |')


def handheld_rows(seeds: list[int], conditions: list[str], variants: list[str], evidence: tuple[str, ...],
                  cfg: AssociationConfig, filt: FilterConfig, out: dict,
                  evidence_cfg: EvidenceConfig | None = None) -> None:
    """Evaluate handheld keyframe scenes (made one at a time), print one HANDHELD_HEADER row per condition and
    variant, and store the pooled metrics in out['results']."""
    from frodo_association.handheld import make_handheld_scene

    ev = ','.join(evidence) or 'none'
    for variant in variants:
        for name in conditions:
            res = [run_scene(make_handheld_scene(seed, **HANDHELD_CONDITIONS[name], **HANDHELD_VARIANTS[variant]),
                             cfg, filt, evidence, evidence_cfg=evidence_cfg) for seed in seeds]
            m = summarise(res)
            out['results'][f'{name} / {variant} / {ev}'] = m
            print(f"| {name} | {variant} | {ev} | {m['scenes']} | {m['objects']} | {m['completeness']:.3f} | "
                  f"{m['false_per_scene']:.2f} | {m['duplicates']} | {m['false_tracks']} | "
                  f"{m['center_err_median_m']:.3f} | {m['center_err_m']:.3f} | {m['size_err_m']:.3f} | "
                  f"{m['yaw_err_deg']:.1f} | {m['assoc_ms_mean']:.2f} | {m['refine_ms_mean']:.2f} |", flush=True)


def main(argv: list[str] | None = None) -> int:
    """Command line: evaluate box-world walks (or contract bags with ground truth), with and without pruning;
    print a Markdown table."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--bags', nargs='+', metavar='MCAP', help='score these contract bags (with /camera/instances '
                    'and /ground_truth/objects) instead of box-world scenes')
    ap.add_argument('--seeds', default='100-119', help='scene seeds, e.g. 100-119 (tuning used 0-19)')
    ap.add_argument('--objects', default='2-5', help='objects per scene, cycled over the seeds')
    ap.add_argument('--frames', type=int, default=60)
    ap.add_argument('--layout', default='walk', choices=sorted(LAYOUTS),
                    help="'walk': boxes, 240 deg arc at ~3.6 m; 'dense': boxes in a 4 m square seen from 7.5 m "
                         "over 90 deg; 'furniture': the walk with rendered procedural chairs and tables")
    ap.add_argument('--no-ablation', action='store_true', help='only run with pruning on')
    ap.add_argument('--conditions', help='comma-separated subset of: ' + ', '.join(CONDITIONS).replace('%', '%%')
                    + ' (default: all of them; with --bags: clean; noise is added to the bags\' instance images and '
                    'poses with the same models)')
    ap.add_argument('--pool', action='store_true', help='with --bags: one row per condition over all bags')
    ap.add_argument('--json', help='also write the results as JSON')
    ap.add_argument('--variants', default='base', help='handheld: comma-separated subset of: ' + ', '.join(HANDHELD_VARIANTS))
    ap.add_argument('--evidence', default='depth,landmarks',
                    help="handheld: surface depth from 'depth', 'landmarks', both (depth first) or 'none'")
    ap.add_argument('--set', default='', metavar='NAME=VALUE,...', help='override AssociationConfig and '
                    'EvidenceConfig fields (the association node\'s parameters)')
    ap.add_argument('--trace', action='store_true', help='with --bags: per ground-truth object, why it is or is '
                    'not published (`trace_objects`)')
    args = ap.parse_args(argv)
    filt = FilterConfig()
    base, evidence_cfg = AssociationConfig(), EvidenceConfig()
    overrides: dict[str, dict] = {'association': {}, 'evidence': {}}
    for item in filter(None, args.set.split(',')):
        key, _, value = (part.strip() for part in item.partition('='))
        owner = 'association' if hasattr(base, key) else 'evidence' if hasattr(evidence_cfg, key) else None
        if owner is None:
            ap.error(f'--set: {key!r} is no AssociationConfig or EvidenceConfig field')
        kind = type(getattr(base if owner == 'association' else evidence_cfg, key))
        overrides[owner][key] = value.lower() in ('1', 'true') if kind is bool else kind(value)
    base = replace(base, **overrides['association'])
    evidence_cfg = replace(evidence_cfg, **overrides['evidence'])
    out = {'machine': f'{platform.node()} ({platform.processor() or platform.machine()})', 'results': {}}
    if args.layout == 'handheld':
        evidence = () if args.evidence == 'none' else tuple(args.evidence.split(','))
        cfg = base
        seeds = _range(args.seeds)
        print(f'# association evaluation: handheld keyframes, seeds {args.seeds}, {out["machine"]}')
        print(HANDHELD_HEADER)
        print('|' + '---|' * (HANDHELD_HEADER.count('|') - 1))
        handheld_rows(seeds, [c.strip() for c in (args.conditions or ','.join(HANDHELD_CONDITIONS)).split(',')],
                      [v.strip() for v in args.variants.split(',')], evidence, cfg, filt, out, evidence_cfg)
        out['config'] = {**asdict(cfg), **asdict(evidence_cfg)}
        if args.json:
            with open(args.json, 'w') as fh:
                json.dump(out, fh, indent=1)
        return 0
    conditions = [c.strip() for c in (args.conditions or ('clean' if args.bags else ','.join(CONDITIONS))).split(',')]
    if args.bags:
        groups = {}
        for k, path in enumerate(args.bags):
            scene, notes = scene_from_bag(path)
            print(f'# {path}: ' + '; '.join(notes))
            for name in conditions:
                key = name if args.pool else (path if name == 'clean' else f'{path} / {name}')
                groups.setdefault(key, []).append(add_noise(scene, k, **CONDITIONS[name]))
        print(f'# association evaluation of {len(args.bags)} bag(s), {out["machine"]}')
    else:
        seeds, n_objects = _range(args.seeds), _range(args.objects)
        make = make_furniture_scene if args.layout == 'furniture' else make_scene
        groups = {name: [make(n_objects[i % len(n_objects)], seed, n_frames=args.frames,
                              **LAYOUTS[args.layout], **CONDITIONS[name]) for i, seed in enumerate(seeds)]
                  for name in conditions}
        print(f'# association evaluation: {args.layout} layout, seeds {args.seeds}, {args.objects} objects, '
              f'{args.frames} frames, {out["machine"]}')
    print(HEADER)
    print('|' + '---|' * (HEADER.count('|') - 1))
    for name, scenes in groups.items():
        for prune in (True,) if args.no_ablation else (True, False):
            evidence = () if args.evidence == 'none' else tuple(args.evidence.split(','))
            res = [run_scene(scene, replace(base, prune=prune), filt, evidence, args.trace and prune, evidence_cfg)
                   for scene in scenes]
            for scene_no, r in enumerate(res if args.trace and prune else ()):
                print(f'# trace: {name}, scene {scene_no}\n' + '\n'.join(f'#   {line}' for line in r.trace))
            m = summarise(res)
            out['results'][f'{name} / prune={prune}'] = m
            print(table_row(name, prune, m), flush=True)
    out['config'] = {**asdict(base), **asdict(evidence_cfg)}
    if args.json:
        with open(args.json, 'w') as fh:
            json.dump(out, fh, indent=1)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
