"""Back end replayed on recorded front-end outputs: the optimiser's stages on the association's own boxes and codes.

    # 1. record the front end's outputs while the graph runs a bag (private ROS_DOMAIN_ID):
    frodo record REC.mcap /frodo/tracks /frodo/object_codes /frodo/detections /frodo/associations &
    frodo run BAG --out DIR --rate 1 --params nodense.yaml ; kill -INT %1
    # 2. replay the optimiser offline, any number of configurations, scored per object (contract metrics):
    .venv/bin/python bench/bench_replay.py BAG REC.mcap [BAG REC.mcap ...] [--sparse JSON] [--dense JSON|off]
        [--box oracle] [--dense-starts N] [--json OUT.json]

Unlike `bench_dense.py stages` (oracle association, ground-truth boxes perturbed), the inputs are exactly what
`optim_node` receives in the graph: the final `/frodo/tracks` box and `/frodo/object_codes` code of each
object, and its views rebuilt as the node builds them (`/frodo/detections` + `/frodo/associations` matched by
stamp with `/camera/pose`, re-sends moving views, `ViewStore` thinning), so configurations of the sparse and
dense stages can be compared on the same real-capture inputs without re-running the (non-deterministic,
slow) front end. Objects are scored as `frodo eval` scores them: matched to ground truth within 0.5 m,
CD (cm) and F1@5cm; unmatched predictions are counted.

`--box oracle` swaps each object's track box for the upright box around the nearest ground-truth mesh of its
class (`frodo_association.evaluate.upright_box`), views and codes unchanged: the gain is what a perfect front-end
box would be worth to the back end, the rest of the gap to `bench_dense.py stages` (oracle association) is views
and codes.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from frodo_association.evaluate import upright_box
from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.bag import BagReader
from frodo_common.categories import BY_NAME, category_by_id
from frodo_common.evaluation import EvalObject, evaluate, load_ground_truth_bag
from frodo_optim.core import fused_estimate
from frodo_optim.dense import DenseConfig, refine_dense_starts
from frodo_optim.optim_node import PARAMS as NODE_PARAMS
from frodo_optim.photometric import dense_view_from_frame
from frodo_optim.sparse import SparseConfig, ViewStore, refine, view_from_mask
from frodo_optim.support import FLOOR_CLASSES, floor_height
from frodo_shape.prior import DEFAULT_PRIOR, ShapePrior

DEPTH_TOPICS = ('/camera/depth/image_raw',)


def backend_inputs(bag: Path, recorded: Path, dense: bool, fill_views: int, dense_fill_views: int | None = None,
                   mask_samples: int = 96, crop: int = 96):
    """{object id: (class name, box, code, views, dense views)}, slam points (N, 3) of a recorded run.
    dense_fill_views: `fill_views` of the dense views (None: the same)."""
    camera_info, poses, images, depths, slam = None, {}, {}, {}, None
    for m in BagReader(bag).messages([topics.CAMERA_INFO, topics.POSE, topics.SLAM_POINTS, topics.IMAGE, *DEPTH_TOPICS]):
        msg = m.decode()
        if m.topic == topics.CAMERA_INFO and camera_info is None:
            camera_info = (conv.camera_info_to_K(msg), (int(msg.width), int(msg.height)))
        elif m.topic == topics.POSE:
            poses[conv.stamp_to_ns(msg.header.stamp)] = conv.pose_to_matrix(msg.pose)
        elif m.topic == topics.SLAM_POINTS:
            slam = conv.cloud_to_xyz(msg)
        elif m.topic == topics.IMAGE and dense:
            images[conv.stamp_to_ns(msg.header.stamp)] = m
        elif m.topic in DEPTH_TOPICS and dense:
            depths[conv.stamp_to_ns(msg.header.stamp)] = m
    K, (width, height) = camera_info
    store, dense_store = ViewStore(64), ViewStore(64, capacity=1000)
    tracks, codes, detections, done = {}, {}, {}, set()
    rng = np.random.default_rng(0)
    reader = BagReader(recorded, unique_stamp_topics=())
    for m in reader.messages([topics.DETECTIONS, topics.ASSOCIATIONS, topics.TRACKS, topics.OBJECT_CODES]):
        msg = m.decode()
        if m.topic == topics.TRACKS:
            for mk in msg.markers:
                if mk.action == 3:        # DELETEALL
                    tracks.clear()
                elif mk.action == 2:      # DELETE
                    tracks.pop(mk.id, None)
                elif mk.type == 1:        # CUBE
                    tracks[mk.id] = (mk.ns, conv.marker_to_box(mk))
        elif m.topic == topics.OBJECT_CODES:
            for row in conv.cloud_to_table(msg):
                codes[int(row['object_id'])] = (int(row['category']), int(row['num_views']),
                                                np.asarray(row['code'], dtype=np.float32))
        elif m.topic == topics.DETECTIONS:
            detections[conv.stamp_to_ns(msg.header.stamp)] = conv.image_to_numpy(msg)
        else:
            stamp = conv.stamp_to_ns(msg.header.stamp)
            rows = conv.cloud_to_table(msg)
            if stamp in done:     # a re-send after merges: move the stored views
                owners = {int(r['label']): (int(r['object_id']), bool(r['kept'])) for r in rows}
                store.assign(stamp, owners)
                dense_store.assign(stamp, owners)
                continue
            labels = detections.pop(stamp, None)
            if labels is None or stamp not in poses:
                continue
            done.add(stamp)
            T = poses[stamp]
            detected = labels > 0
            rgb = depth = None
            if dense and stamp in images:
                rgb = conv.image_to_rgb(images[stamp].decode())
                if stamp in depths:
                    dmsg = depths[stamp].decode()
                    depth = conv.image_to_numpy(dmsg).astype(np.float32) * (0.001 if dmsg.encoding == '16UC1' else 1.0)
            for r in rows:
                mask = labels == r['label']
                view = view_from_mask(K, T, mask, mask_samples, detected & ~mask, rng)
                if view is None:
                    continue
                key = (stamp, int(r['label']), int(r['object_id']), bool(r['kept']))
                store.add(*key, view)
                if rgb is not None:
                    dv = dense_view_from_frame(K, T, mask, detected & ~mask, rgb, depth, size=crop, rng=rng)
                    if dv is not None:
                        dense_store.add(*key, dv)
    out = {}
    for oid, (ns, box) in tracks.items():
        if oid not in codes or codes[oid][1] < 2:
            continue
        known = category_by_id(codes[oid][0])
        out[oid] = (known.name if known else ns, box, codes[oid][2], store.views_of(oid, fill_views),
                    dense_store.views_of(oid, fill_views if dense_fill_views is None else dense_fill_views))
    return out, (slam[np.isfinite(slam).all(1)] if slam is not None and len(slam) else slam)


def oracle_boxes(objects: dict, gt) -> dict:
    """`backend_inputs` objects with each box replaced by the upright box of the nearest ground-truth mesh of its
    class (any class when none has it)."""
    boxes = [(g.class_name, upright_box(np.asarray(g.mesh.vertices))) for g in gt]
    out = {}
    for oid, (name, box, *rest) in objects.items():
        same = [b for c, b in boxes if c == name] or [b for _, b in boxes]
        out[oid] = (name, min(same, key=lambda b: np.linalg.norm(b[0][:2] - np.asarray(box[0])[:2])), *rest)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('pairs', nargs='+', help='BAG REC [BAG REC ...]')
    ap.add_argument('--sparse', default='', help='JSON SparseConfig overrides')
    ap.add_argument('--dense', default='off', help="JSON DenseConfig overrides, or 'off' (default)")
    ap.add_argument('--json', default='')
    ap.add_argument('--threads', type=int, default=1)
    ap.add_argument('--no-floor', action='store_true', help='no floor estimate (E_floor off)')
    ap.add_argument('--no-height', action='store_true', help='no class height range (E_size off)')
    ap.add_argument('--prior', default=DEFAULT_PRIOR,
                    help=f"shipped prior name or prior folder (default {DEFAULT_PRIOR!r}, the nodes'); "
                    'the recording must come from a graph that ran the same prior (its codes)')
    node_fill = next(p.default for p in NODE_PARAMS if p.name == 'fill_views')
    ap.add_argument('--fill-views', type=int, default=node_fill, help=f"optim_node's fill_views (default {node_fill}, the node's)")
    ap.add_argument('--dense-fill-views', type=int, default=None, help='fill_views of the dense stage (default: --fill-views)')
    node_resolution = next(p.default for p in NODE_PARAMS if p.name == 'mesh_resolution')
    ap.add_argument('--mesh-resolution', type=int, default=node_resolution,
                    help=f"optim_node's mesh_resolution: marching-cubes grid of the evaluated meshes (default {node_resolution})")
    node_starts = next(p.default for p in NODE_PARAMS if p.name == 'dense_starts')
    ap.add_argument('--dense-starts', type=int, default=node_starts,
                    help=f"optim_node's dense_starts: dense stage from the sparse result and up to N - 1 of its other "
                    f"runs' end states (default {node_starts}, the node's)")
    ap.add_argument('--box', choices=('track', 'oracle'), default='track',
                    help="'oracle': ground-truth boxes instead of the recorded track boxes (see above)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    prior = ShapePrior.load(args.prior)
    scfg = SparseConfig(**(json.loads(args.sparse) if args.sparse else {}))
    dense = args.dense != 'off'
    dcfg = DenseConfig(**(json.loads(args.dense) if dense and args.dense else {}))
    rows, pooled = [], {'fused': [], 'sparse': [], 'dense': []}
    for bag, rec in zip(args.pairs[0::2], args.pairs[1::2]):
        objects, slam = backend_inputs(Path(bag), Path(rec), dense, fill_views=args.fill_views,
                                       dense_fill_views=args.dense_fill_views)
        gt = load_ground_truth_bag(bag)
        if args.box == 'oracle':
            objects = oracle_boxes(objects, gt)
        preds = {'fused': [], 'sparse': [], 'dense': []}
        floor = None if args.no_floor else floor_height([o[1] for o in objects.values() if o[0] in FLOOR_CLASSES], slam)
        for oid, (name, box, code, views, dviews) in sorted(objects.items()):
            mesh = prior.mesh(code, resolution=args.mesh_resolution)
            if mesh is None or len(mesh.faces) == 0:
                continue
            fused = fused_estimate(oid, name, 0, code, len(views), mesh, box)
            preds['fused'].append(EvalObject(oid, name, fused.mesh_world))
            t0 = time.perf_counter()
            heights = None if args.no_height or name not in BY_NAME else BY_NAME[name].height_range
            sp = refine(prior, code, box, views, slam, scfg, floor_height=floor, height_range=heights, code_class=name,
                        neighbour_boxes=[o[1] for other, o in objects.items() if other != oid])
            t_sparse = time.perf_counter() - t0
            smesh = prior.mesh(sp.code, resolution=args.mesh_resolution) if sp.ok else None
            if smesh is None or len(smesh.faces) == 0:
                preds['sparse'].append(preds['fused'][-1])
                preds['dense'].append(preds['fused'][-1])
                continue
            preds['sparse'].append(EvalObject(oid, name, smesh.copy().apply_transform(sp.T_world_object)))
            row = {'bag': Path(bag).stem, 'id': oid, 'floor': None if floor is None else round(floor, 3), 'class': name, 'views': len(views), 'placement': sp.placement,
                   'reason': sp.reason, 'sparse_s': round(t_sparse, 1), 'scale': round(sp.scale, 3),
                   'z_bottom': round(float(preds['sparse'][-1].mesh.bounds[0, 2]), 3),
                   'energies': {k: round(v, 4) for k, v in sp.energies.items()}, 'input_energy': round(sp.input_energy, 4)}
            if dense:
                landmarks, region = (slam, box) if sp.landmarks is None else (sp.landmarks, None)   # as optim_node
                dn, row['dense_start'] = refine_dense_starts(prior, sp.code, sp.T_world_object, dviews, landmarks,
                                                             region, dcfg, floor_height=floor, height_range=heights,
                                                             alternatives=sp.alternatives, max_starts=args.dense_starts)
                row['dense_s'], row['dense_best_iteration'] = round(dn.seconds, 1), dn.best_iteration
                row['dense_energies'] = {k: round(v, 4) for k, v in dn.energies.items()}
                dmesh = prior.mesh(dn.code, resolution=args.mesh_resolution) if dn.improved else None
                preds['dense'].append(EvalObject(oid, name, dmesh.copy().apply_transform(dn.T_world_object))
                                      if dmesh is not None and len(dmesh.faces) else preds['sparse'][-1])
                row['dense_improved'] = bool(dn.improved)
            rows.append(row)
        for stage in ('fused', 'sparse') + (('dense',) if dense else ()):
            res = evaluate(preds[stage], gt)
            for p in res.pairs:
                pooled[stage].append((Path(bag).stem, p.pred_id, p.class_name, p.cd_cm, p.f1,
                                      p.centroid_distance_m))
                for r in rows:
                    if r['bag'] == Path(bag).stem and r['id'] == p.pred_id:
                        r[f'{stage}_f1'], r[f'{stage}_cd'] = round(p.f1, 1), round(p.cd_cm, 2)
            pooled.setdefault(f'{stage}_fp', []).append(len(res.unmatched_pred))
            pooled.setdefault(f'{stage}_gt', []).append(len(gt))
        for r in rows:
            if r['bag'] == Path(bag).stem:
                print(json.dumps(r), flush=True)
    summary = {}
    for stage in ('fused', 'sparse') + (('dense',) if dense else ()):
        m = pooled[stage]
        if m:
            summary[stage] = {'matched': len(m), 'gt': int(sum(pooled[f'{stage}_gt'])),
                              'fp': int(sum(pooled[f'{stage}_fp'])),
                              'cd': round(float(np.mean([x[3] for x in m])), 2),
                              'f1': round(float(np.mean([x[4] for x in m])), 1),
                              'centre_cm_median': round(100 * float(np.median([x[5] for x in m])), 1)}
    print(json.dumps({'sparse': args.sparse, 'dense': args.dense, 'box': args.box, 'summary': summary}), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({'rows': rows, 'pooled': pooled, 'summary': summary}, indent=1))


if __name__ == '__main__':
    main()
