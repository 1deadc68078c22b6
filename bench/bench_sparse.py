"""Time the sparse stage (paper Sec. 5.3) of one object: yaw search and per-iteration cost over N views.

    .venv/bin/python bench/bench_sparse.py [--views 35] [--iterations 30] [--threads 1] [--no-placement]

Views are synthetic (a training chair's decoded points splatted into 640x480 masks from cameras on a
circle), which is enough for timing: the cost depends on the numbers of views, mask samples and points.
"""
from __future__ import annotations

import argparse
import json
import math
import platform

import numpy as np
import torch
from scipy.ndimage import binary_dilation

from frodo_common.geometry import look_at, project_points, invert_transform
from frodo_optim.sparse import SparseConfig, pose_matrix, refine, view_from_mask
from frodo_shape.prior import ShapePrior


def make_views(prior, n_views: int, mask_samples: int, width=640, height=480):
    code = prior.training_codes[0].numpy()
    pts = prior.decode_points(code)[0].detach().numpy().astype(np.float64)
    T = pose_matrix(0.4, [0.0, 0.0, 0.45], 0.5)
    world = pts @ T[:3, :3].T + T[:3, 3]
    f = 0.5 * width / math.tan(math.radians(30))
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
    views = []
    for k in range(n_views):
        a = 2 * math.pi * k / n_views
        Twc = look_at([2.5 * math.cos(a), 2.5 * math.sin(a), 1.2], [0, 0, 0.45])
        uv, _ = project_points(K, invert_transform(Twc), world)
        mask = np.zeros((height, width), bool)
        uv = np.clip(np.round(uv).astype(int), 0, [width - 1, height - 1])
        mask[uv[:, 1], uv[:, 0]] = True
        views.append(view_from_mask(K, Twc, binary_dilation(mask, iterations=2), mask_samples))
    box = (np.array([0, 0, 0.45]), np.array([0.5, 0.5, 0.9]), 0.0)
    return code, box, views


def measure(prior, views: int, iterations: int = 30, repeats: int = 3, placement: bool = True) -> dict:
    """Median initialisation seconds (yaw search, and the placement search unless `placement` is False) and
    milliseconds per Adam iteration of the sparse stage over `views` views."""
    cfg = SparseConfig(max_views=views, iterations=iterations, placement_search=placement)
    code, box, view_list = make_views(prior, views, cfg.mask_samples)
    no_iterations = SparseConfig(**{**cfg.__dict__, 'iterations': 0})
    rows = []
    for _ in range(repeats):
        search = refine(prior, code, box, view_list, config=no_iterations)
        # Warm-started (no yaw search) with and without the iterations: the difference is the iterations' cost.
        setup = refine(prior, code, box, view_list, config=no_iterations, init_yaw=search.init_yaw)
        full = refine(prior, code, box, view_list, config=cfg, init_yaw=search.init_yaw)
        per_it = (full.seconds - setup.seconds) / max(full.iterations, 1)
        rows.append((search.seconds, per_it))
    search_s, per_it = np.median(np.array(rows), axis=0)
    return {'views': views, 'iterations': iterations, 'repeats': repeats, 'mask_samples': cfg.mask_samples,
            'point_samples': cfg.point_samples, 'yaw_candidates': cfg.yaw_candidates,
            'placement_search': placement, 'init_yaw_search_s': round(float(search_s), 4), 'ms_per_iteration': round(1e3 * float(per_it), 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--views', type=int, default=35)
    ap.add_argument('--iterations', type=int, default=30)
    ap.add_argument('--threads', type=int, default=1)
    ap.add_argument('--repeats', type=int, default=3)
    ap.add_argument('--no-placement', action='store_true', help='box-only initialisation (no placement search)')
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    prior = ShapePrior.load('furniture', device='cpu')
    out = measure(prior, args.views, args.iterations, args.repeats, placement=not args.no_placement)
    out.update(threads=args.threads, machine=platform.processor() or platform.machine())
    print(json.dumps(out))


if __name__ == '__main__':
    main()
