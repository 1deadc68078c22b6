"""Benchmark: does the association's per-frame cost stay flat on a long run (issue 12 "Long runs")?

A box-world walk (`make_scene`, 640x480, every object in view) is replayed `--frames` frames long by looping it
with shifted stamps (as the soak loops the demo bag), through `Associator.add_frame` + `refine_boxes` with
`max_detections_per_object` = `--cap` (0: unbounded history). Per block of `--block` frames: process CPU ms per
frame (mean), detection rows held at the block's end (what clustering, pruning and centre updates scan), rows
retired so far, and the bytes the detection columns hold. Prints the machine it ran on.

Usage: python bench/bench_association_history.py [--frames 3000] [--loop 200] [--objects 4] [--cap 400] [--block 500]
"""
from __future__ import annotations

import argparse
import os
import time

from frodo_association.config import AssociationConfig
from frodo_association.synthetic import make_scene
from frodo_association.tracker import Associator, detections_from_instances


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--frames', type=int, default=3000)
    ap.add_argument('--loop', type=int, default=200, help='frames of the walk that is looped')
    ap.add_argument('--objects', type=int, default=4)
    ap.add_argument('--cap', type=int, default=400, help='max_detections_per_object (0: unbounded)')
    ap.add_argument('--block', type=int, default=500)
    ap.add_argument('--seed', type=int, default=0)
    args = ap.parse_args()
    scene = make_scene(args.objects, args.seed, n_frames=args.loop, size=(640, 480), extent=2.0, radius=7.5)
    dets = [detections_from_instances(f.instances) for f in scene.frames]
    assoc = Associator(AssociationConfig(max_detections_per_object=args.cap))
    period = scene.frames[-1].stamp - scene.frames[0].stamp + (scene.frames[1].stamp - scene.frames[0].stamp)
    print(f'load average {os.getloadavg()[0]:.1f}; {len(scene.objects)} objects, walk of {args.loop} frames looped '
          f'to {args.frames}, max_detections_per_object {args.cap}')
    print('| frames | CPU ms per frame (mean) | rows held | rows retired | detection columns (kB) | objects |')
    print('|---|---|---|---|---|---|')
    cpu = 0.0
    for k in range(args.frames):
        f = scene.frames[k % args.loop]
        labels, boxes = dets[k % args.loop]
        t0 = time.process_time()
        assoc.add_frame(f.stamp + (k // args.loop) * period, f.K, f.T_world_camera, f.size, labels, boxes)
        assoc.refine_boxes()
        cpu += time.process_time() - t0
        if (k + 1) % args.block == 0:
            held = sum(a.nbytes for a in assoc.rows._cols.values()) / 1024
            print(f'| {k + 1 - args.block + 1}-{k + 1} | {1000 * cpu / args.block:.2f} | {len(assoc.rows)} | '
                  f'{assoc.retired} | {held:.0f} | {len(assoc.confirmed_tracks())} |', flush=True)
            cpu = 0.0
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
