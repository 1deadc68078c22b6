"""Benchmark: per-frame association latency with 10 objects in view (DESIGN.md target: <= 5 ms per frame).

Times `Associator.add_frame` (segments, DP-means step with same-frame exclusivity, periodic full EM pass,
merges, confirmation, pruning with the current boxes: everything before a frame's associations are published)
and, separately, `Associator.refine_boxes` (at most one 3D box fit per frame, run after publishing) on a
box-world walk where all 10 objects stay in view. Prints the machine it ran on.

Usage: python bench/bench_association.py [--frames 300] [--objects 10] [--seed 0]
"""
from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from frodo_association.tracker import Associator, detections_from_instances
from frodo_association.synthetic import make_scene


def _cpu_name() -> str:
    try:
        with open('/proc/cpuinfo') as fh:
            for line in fh:
                if line.startswith('model name'):
                    return line.split(':', 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--frames', type=int, default=300)
    ap.add_argument('--objects', type=int, default=10)
    ap.add_argument('--seed', type=int, default=0)
    args = ap.parse_args()
    scene = make_scene(args.objects, args.seed, n_frames=args.frames, size=(640, 480), extent=2.0, radius=7.5,
                       sweep_deg=90.0, mask_noise=1, rot_noise_deg=0.3, trans_noise=0.01)
    dets = [detections_from_instances(f.instances) for f in scene.frames]
    in_view = np.array([len(labels) for labels, _ in dets])
    assoc = Associator()
    t_assoc, t_refine = [], []
    for f, (labels, boxes) in zip(scene.frames, dets):
        t0 = time.perf_counter()
        assoc.add_frame(f.stamp, f.K, f.T_world_camera_observed, f.size, labels, boxes)
        t1 = time.perf_counter()
        assoc.refine_boxes()
        t_assoc.append(1e3 * (t1 - t0))
        t_refine.append(1e3 * (time.perf_counter() - t1))
    a, r = np.array(t_assoc), np.array(t_refine)
    print(f'machine: {platform.node()} | {_cpu_name()} | {os.cpu_count()} logical CPUs | '
          f'python {platform.python_version()} | numpy {np.__version__} | load avg {os.getloadavg()[0]:.1f}')
    print(f'scene: {args.objects} objects, {args.frames} frames 640x480, detections per frame: mean {in_view.mean():.1f}'
          f' (min {in_view.min()}), tracks at the end: {len(assoc.confirmed_tracks())}')
    for name, t in (('association (add_frame)', a), ('box refinement (refine_boxes)', r), ('total', a + r)):
        print(f'{name:30s} mean {t.mean():6.2f} ms  median {np.median(t):6.2f}  p95 {np.percentile(t, 95):6.2f}  '
              f'max {t.max():6.2f}')
    print(f'target: association <= 5 ms per frame: {"met" if a.mean() <= 5.0 else "NOT met"} (mean)')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
