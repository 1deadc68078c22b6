"""Benchmark: per-frame association latency (DESIGN.md targets: association <= 5 ms per frame with 10 objects in
view; association and box refinement together <= 5 ms).

Times `Associator.add_frame` (segments, DP-means step with same-frame exclusivity, periodic full EM pass,
merges, confirmation, pruning with the current boxes: everything before a frame's associations are published)
and, separately, `Associator.refine_boxes` (at most one 3D box fit per frame, run after publishing), and their
sum per frame. `--scene walk` (default): a box-world walk where all 10 objects stay in view; `--scene handheld`:
35 keyframes of the handheld kitchen (`frodo_association.handheld`, real-like masks and drift) with depth, also
timing the surface depths from depth (`evidence.surface_depths`). The contact edges of the masks
(`evidence.contact_edges`, computed by the node before `add_frame`) are timed as a row of their own; `total` is
association + box refinement, as the node's latency. Prints the machine it ran on.

Usage: python bench/bench_association.py [--scene walk|handheld] [--frames 300] [--objects 10] [--seed 0] [--profile]
(--profile: also where the CPU time goes, cProfile on the process CPU clock, functions of frodo_association by
cumulative time; the timings then include the profiler's overhead.)
"""
from __future__ import annotations

import argparse
import cProfile
import os
import platform
import pstats
import time

import numpy as np

from frodo_association.config import AssociationConfig
from frodo_association.evidence import contact_edges, surface_depths
from frodo_common.host import cpu_model
from frodo_common.frames import depth_to_metres
from frodo_association.synthetic import make_scene
from frodo_association.tracker import Associator, detections_from_instances
from frodo_common.geometry import invert_transform


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--frames', type=int, default=300)
    ap.add_argument('--objects', type=int, default=10)
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--scene', default='walk', choices=('walk', 'handheld'))
    ap.add_argument('--profile', action='store_true', help='print the cumulative CPU time per function (cProfile)')
    args = ap.parse_args()
    if args.scene == 'walk':
        scene = make_scene(args.objects, args.seed, n_frames=args.frames, size=(640, 480), extent=2.0, radius=7.5,
                           sweep_deg=90.0, mask_noise=1, rot_noise_deg=0.3, trans_noise=0.01)
    else:
        from frodo_association.evaluate import HANDHELD_CONDITIONS
        from frodo_association.handheld import make_handheld_scene
        scene = make_handheld_scene(args.seed, **HANDHELD_CONDITIONS['real-like'])
    dets = [detections_from_instances(f.instances) for f in scene.frames]
    in_view = np.array([len(labels) for labels, _ in dets])
    assoc = Associator(AssociationConfig())
    t_evidence, t_contact, t_assoc, t_refine = [], [], [], []
    profiler = cProfile.Profile(time.process_time) if args.profile else None
    if profiler:
        profiler.enable()
    for f, (labels, boxes) in zip(scene.frames, dets):
        surface = None
        t0 = time.perf_counter()
        if f.depth is not None:
            surface = surface_depths(f.instances, labels, f.K, invert_transform(f.T_world_camera_observed),
                                     depth_to_metres(f.depth))
            t_evidence.append(1e3 * (time.perf_counter() - t0))
        t0 = time.perf_counter()
        contact = contact_edges(f.instances, labels, boxes, surface)
        t_contact.append(1e3 * (time.perf_counter() - t0))
        t0 = time.perf_counter()
        assoc.add_frame(f.stamp, f.K, f.T_world_camera_observed, f.size, labels, boxes, surface, contact)
        t1 = time.perf_counter()
        assoc.refine_boxes()
        t_assoc.append(1e3 * (t1 - t0))
        t_refine.append(1e3 * (time.perf_counter() - t1))
    if profiler:
        profiler.disable()
        stats = pstats.Stats(profiler)
        stats.sort_stats('cumulative').print_stats(r'frodo_association|robust_lsq', 25)
    a, r = np.array(t_assoc), np.array(t_refine)
    print(f'machine: {platform.node()} | {cpu_model()} | {os.cpu_count()} logical CPUs | '
          f'python {platform.python_version()} | numpy {np.__version__} | load avg {os.getloadavg()[0]:.1f}')
    print(f'scene: {args.scene}, {len(scene.objects)} objects, {len(scene.frames)} frames 640x480, detections per frame:'
          f' mean {in_view.mean():.1f} (min {in_view.min()}), tracks at the end: {len(assoc.confirmed_tracks())}')
    rows = [('contact edges (masks)', np.array(t_contact)), ('association (add_frame)', a),
            ('box refinement (refine_boxes)', r), ('total', a + r)]
    if t_evidence:
        rows.insert(0, ('surface depth (depth image)', np.array(t_evidence)))
    for name, t in rows:
        print(f'{name:30s} mean {t.mean():6.2f} ms  median {np.median(t):6.2f}  p95 {np.percentile(t, 95):6.2f}  '
              f'max {t.max():6.2f}')
    print(f'target: association <= 5 ms per frame: {"met" if a.mean() <= 5.0 else "NOT met"} (mean); '
          f'association + box refinement <= 5 ms: {"met" if (a + r).mean() <= 5.0 else "NOT met"} (mean), '
          f'{"met" if np.percentile(a + r, 95) <= 5.0 else "NOT met"} (p95)')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
