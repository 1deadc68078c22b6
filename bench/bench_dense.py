"""Dense stage (paper Sec. 5.3) benchmarks: speed, and the per-stage / per-energy accuracy tables.

    .venv/bin/python bench/bench_dense.py timing [--views 35] [--iterations 10] [--threads 2]
    .venv/bin/python bench/bench_dense.py stages BAG.mcap [BAG ...] [--ablation] [--json OUT.json]
    .venv/bin/python bench/bench_dense.py opacity [--resolutions 32,48,64,128] [--shapes 6]

`timing`: one object (a prior chair rendered from N cameras on a circle, colour + masks), seconds per dense
iteration and for the whole stage, plus the sparse stage for reference; each configuration once from colour and
masks alone (`dense`) and once with the rendered depth image as well (`dense_depth`: the depth points of Eg and
the free space of the silhouette, what an RGB-D bag costs).

`opacity`: how opaque the dense silhouette (paper Eq. 8, `dense.foreground_probability`) renders the prior's
own training shapes from the SDF volume of each resolution: rays from 20-50 degrees above the horizontal (a
standing camera) through random points inside the shape (on its 128^3 grid), so every ray should read H ~ 1.
Per class and family, the mean H and the share of rays under 0.5: thin parts (table tops, slats) read as partly
transparent on a coarse volume, and a fit then thickens them.

`stages` (paper Table 3 analogue; with --ablation also Table 2; --fused-only stops after fusion, to compare
encoders: `--prior DIR`; `--code oracle` starts the optimiser from the true shape's code instead of the
encoders'): the back end alone, on contract bags with ground truth. Association is an oracle (each instance
mask of /camera/instances is matched to its ground-truth object, `frodo_association.evaluate.scene_from_bag`),
and each object's 3D box is the ground-truth box perturbed (centre N(0, 5 cm), size x U(0.9, 1.1), yaw
+ U(-10, 10) deg; seeded): what is measured is what the optimiser gets out of the same views, not the front
end. Per object, up to `--views` (35) views spread over the sequence; codes from the shipped encoder (or
`--prior`'s) on square crops; then
  vote fusion -> mean fusion (fused stage: box-fit placement) -> sparse (from the mean code) -> dense,
each scored against the ground-truth mesh with the contract metrics (CD cm, ACC/COMP/F1 at 5 cm).
--ablation adds, for sparse and sparse+dense: Es+Er, +Ep, +Eg (landmarks; and depth in the dense stage when
the bag has it), all.
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

from frodo_common import conversions as conv
from frodo_common.frames import depth_to_metres
from frodo_common import topics
from frodo_common.bag import BagReader
from frodo_common.evaluation import point_metrics, sample_surface
from frodo_common.geometry import look_at
from frodo_optim.core import place_from_box
from frodo_optim.dense import DenseConfig, Rays, foreground_probability, refine_dense
from frodo_optim.photometric import ViewBatch, dense_view_from_frame
from frodo_optim.sparse import SparseConfig, pose_matrix, refine, select_views, view_from_mask
from frodo_optim.support import class_height_range, floor_height
from frodo_shape.crops import square_crop
from frodo_shape.fusion import fuse_mean, fuse_vote
from frodo_shape.meshing import grid_points, sdf_grid
from frodo_shape.prior import DEFAULT_PRIOR, ShapePrior

DEPTH_TOPICS = (topics.DEPTH, '/camera/aligned_depth_to_color/image_raw')  # contract v1.1; synth default


def _machine(threads: int) -> str:
    import os
    return f'{platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch threads {threads}'


# ------------------------------------------------------------------ timing
def timing(args) -> None:
    from frodo_datasets.render import Material, Renderer, RenderObject, intrinsics
    prior = ShapePrior.load(DEFAULT_PRIOR, device=args.device)
    chairs = [i for i, c in enumerate(prior.training_classes) if c == 'chair']
    code = prior.training_codes[chairs[3]].cpu().numpy()
    mesh = prior.mesh(code, resolution=64)
    s = 0.5
    T = pose_matrix(0.7, [0.0, 0.0, -s * mesh.bounds[0, 2]], s)
    world = mesh.copy().apply_transform(T)
    renderer = Renderer([RenderObject(world, Material(color=(0.8, 0.3, 0.2), kind='checker', scale=6), label=1)])
    W, H = 320, 240
    K = intrinsics(W, H, 60.0)
    centre = world.bounds.mean(0)
    dense_views, depth_views, sparse_views = [], [], []
    for k in range(args.views):
        a = 2 * np.pi * k / args.views
        Twc = look_at(centre + np.array([2.2 * np.cos(a), 2.2 * np.sin(a), 0.9]), centre)
        out = renderer.render(K, Twc, W, H, shadows=False)
        dense_views.append(dense_view_from_frame(K, Twc, out.labels == 1, None, out.rgb))
        depth_views.append(dense_view_from_frame(K, Twc, out.labels == 1, None, out.rgb, out.depth))
        sparse_views.append(view_from_mask(K, Twc, out.labels == 1, 96))
    other = prior.training_codes[chairs[7]].cpu().numpy()
    code0 = (0.5 * code + 0.5 * other).astype(np.float32)
    T0 = pose_matrix(0.8, T[:3, 3] + [0.04, -0.03, 0.0], 0.52)
    rows: dict[str, list] = {'dense': [], 'dense_depth': []}
    for config in args.configs:
        cfg = DenseConfig(**{'max_views': args.views, 'iterations': args.iterations, 'max_seconds': 1e9,
                             **(json.loads(config) if config else {})})
        for key, views in (('dense', dense_views), ('dense_depth', depth_views)):
            res = refine_dense(prior, code0, T0, views, config=cfg)
            rows[key].append({'config': config or 'default',
                              'seconds_per_iteration': round(res.seconds_per_iteration, 3),
                              'stage_seconds': round(res.seconds, 2), 'iterations': res.iterations,
                              'improved': res.improved})
    lo, hi = world.bounds
    box = ((lo + hi) / 2, hi - lo, 0.7)
    sp = refine(prior, code0, box, sparse_views, config=SparseConfig(max_views=args.views))
    print(json.dumps({'views': args.views, 'machine': _machine(torch.get_num_threads()), 'device': str(prior.device),
                      **rows, 'sparse_seconds': round(sp.seconds, 2)}, indent=1))


# ------------------------------------------------------------------ per-stage accuracy
def _perturbed_box(box, rng):
    centre, size, yaw = box
    return (np.asarray(centre) + rng.normal(0, 0.05, 3) * np.array([1, 1, 0.3]),
            np.asarray(size) * rng.uniform(0.9, 1.1, 3), float(yaw + math.radians(rng.uniform(-10, 10))))


def _score(mesh_world, gt_points) -> dict:
    if mesh_world is None or len(mesh_world.faces) == 0:
        return {'cd': float('nan'), 'acc': 0.0, 'comp': 0.0, 'f1': 0.0}
    _, _, cd, acc, comp, f1 = point_metrics(sample_surface(mesh_world, 10000), gt_points)
    return {'cd': cd, 'acc': acc, 'comp': comp, 'f1': f1}


def _objects_of_bag(path: Path, prior, n_views: int, rng):
    """Per ground-truth object: (class, gt points, box, sparse views, dense views, codes (N, 64), slam points)."""
    from frodo_association.evaluate import scene_from_bag
    from frodo_common.categories import category_by_id
    from frodo_common.evaluation import load_ground_truth_bag
    scene, _ = scene_from_bag(str(path))
    gt = load_ground_truth_bag(path)
    images, depths, slam = {}, {}, None
    for m in BagReader(path).messages([topics.IMAGE, *DEPTH_TOPICS, topics.SLAM_POINTS]):
        msg = m.decode()
        if m.topic == topics.IMAGE:
            images[conv.stamp_to_ns(msg.header.stamp)] = conv.image_to_rgb(msg)
        elif m.topic in DEPTH_TOPICS:
            depths[conv.stamp_to_ns(msg.header.stamp)] = depth_to_metres(conv.image_to_numpy(msg))
        else:
            slam = conv.cloud_to_xyz(msg)
    out = []
    for k, obj in enumerate(scene.objects):
        frames = [(f, lab) for f in scene.frames for lab, g in f.gt.items() if g == k and f.stamp in images]
        frames = select_views(frames, n_views)
        if len(frames) < 3:
            continue
        sviews, dviews, crops, masks = [], [], [], []
        for f, lab in frames:
            mask = f.instances == lab
            unknown = (f.instances > 0) & ~mask
            sv = view_from_mask(f.K, f.T_world_camera_observed, mask, 96, unknown, rng, depths.get(f.stamp))
            dv = dense_view_from_frame(f.K, f.T_world_camera_observed, mask, unknown, images[f.stamp],
                                       depths.get(f.stamp), size=96, rng=rng)
            if sv is None or dv is None:
                continue
            sviews.append(sv), dviews.append(dv)
            ys, xs = np.nonzero(mask)
            c, m = square_crop(images[f.stamp], mask, (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1))
            crops.append(c), masks.append(m)
        name = category_by_id(obj.coco_id).name
        # ground truth mesh of this object: the one of its class nearest to the box centre
        cands = [g for g in gt if g.class_name == name]
        g = min(cands, key=lambda e: np.linalg.norm(e.mesh.bounds.mean(0) - obj.center))
        out.append({'class': name, 'gt_points': sample_surface(g.mesh, 10000), 'gt_id': g.id, 'gt_mesh': g.mesh,
                    'box': _perturbed_box((obj.center, obj.size, obj.yaw), rng), 'sparse_views': sviews,
                    'dense_views': dviews, 'codes': prior.encode(np.stack(crops), np.stack(masks)), 'slam': slam,
                    'has_depth': bool(depths)})
    return out


def oracle_code(prior, bag: Path, gt_id: int, gt_mesh, steps: int = 400):
    """The code of the object's true shape as far as the prior can express it: the ground-truth mesh brought
    to its canonical frame with the true pose of the bag's `.gt.json` sidecar (`frodo synth`,
    `eval_sets build`), then an auto-decoder fit to its SDF samples (`ShapePrior.fit_sdf`). Returns the code
    and the fit's score in the object frame (how well the prior expresses this shape at all)."""
    from frodo_datasets.shapes.canonical import normalise
    from frodo_datasets.synth import sidecar_path
    from frodo_shape.sdf_data import SamplingConfig, sample_sdf
    sidecar = sidecar_path(bag)
    if not sidecar.is_file():
        raise SystemExit(f'--code oracle needs the true poses of {sidecar} '
                         '(bags made by frodo synth / eval_sets build)')
    poses = {o['id']: np.asarray(o['T_world_object']) for o in json.loads(sidecar.read_text())['scene']['objects']}
    canonical = gt_mesh.copy().apply_transform(np.linalg.inv(poses[gt_id]))
    normalised, scale = normalise(canonical)
    samples = sample_sdf(normalised, SamplingConfig(), seed=gt_id)
    code = prior.fit_sdf(samples.points, samples.sdf, steps=steps, seed=gt_id)
    fitted = prior.mesh(code, resolution=64).apply_scale(scale)
    return code, _score(fitted, sample_surface(normalised.apply_scale(scale), 10000))


ABLATION = {  # name: (sparse overrides, dense overrides)
    'Es+Er': ({'w_geometry': 0.0, 'w_photometric': 0.0}, {'w_geometry': 0.0, 'w_photometric': 0.0, 'w_depth': 0.0}),
    'Es+Er+Ep': ({'w_geometry': 0.0}, {'w_geometry': 0.0, 'w_depth': 0.0}),
    'Es+Er+Eg': ({'w_photometric': 0.0}, {'w_photometric': 0.0}),
    'all': ({}, {}),
}


def stages(args) -> None:
    prior = ShapePrior.load(args.prior, device=args.device)
    sparse_base = json.loads(args.sparse) if args.sparse else {}
    dense_base = json.loads(args.dense) if args.dense else {}
    variants = ABLATION if args.ablation else {'all': ({}, {})}
    rows = []
    for bag in args.bags:
        rng = np.random.default_rng(args.seed)
        objects = _objects_of_bag(Path(bag), prior, args.views, rng)
        # support priors as in the node: floor from the (perturbed) boxes, the class height range
        floor = None if args.no_support else floor_height([o['box'] for o in objects], objects[0]['slam'] if objects else None)
        for i, o in enumerate(objects):
            row = {'bag': Path(bag).name, 'object': i, 'gt_id': o['gt_id'], 'class': o['class'],
                   'views': len(o['sparse_views'])}
            centre, size, yaw = o['box']
            for fusion, code in (('vote', fuse_vote(o['codes'], prior.training_codes.cpu())), ('mean', fuse_mean(o['codes']))):
                mesh = prior.mesh(code, resolution=64)
                T, _, _ = place_from_box(mesh, centre, size, yaw)
                row[f'fused_{fusion}'] = _score(mesh.copy().apply_transform(T), o['gt_points'])
            code = fuse_mean(o['codes'])
            if args.code == 'oracle':
                code, row['oracle_fit'] = oracle_code(prior, Path(bag), o['gt_id'], o['gt_mesh'])
                mesh = prior.mesh(code, resolution=64)
                T, _, _ = place_from_box(mesh, centre, size, yaw)
                row['fused_oracle'] = _score(mesh.copy().apply_transform(T), o['gt_points'])
            for name, (s_over, d_over) in ({} if args.fused_only else variants).items():
                scfg = SparseConfig(**{'max_views': args.views, **sparse_base, **s_over})
                t0 = time.perf_counter()
                colour = ViewBatch(select_views(o['dense_views'], scfg.max_views)) if scfg.w_photometric > 0 else None
                heights = None if args.no_support else class_height_range(o['class'])
                sp = refine(prior, code, o['box'], o['sparse_views'], o['slam'], scfg, photometric=colour,
                            floor_height=floor, height_range=heights, code_class=o['class'],
                            neighbour_boxes=[n['box'] for n in objects if n is not o])
                t_sparse = time.perf_counter() - t0
                mesh = prior.mesh(sp.code, resolution=64)
                row[f'sparse[{name}]'] = _score(mesh.copy().apply_transform(sp.T_world_object), o['gt_points'])
                dcfg = DenseConfig(**{'max_views': args.views, **dense_base, **d_over})
                landmarks, region = (o['slam'], o['box']) if sp.landmarks is None else (sp.landmarks, None)
                dn = refine_dense(prior, sp.code, sp.T_world_object, o['dense_views'], landmarks, region, dcfg,
                                  floor_height=floor, height_range=heights)
                dmesh = prior.mesh(dn.code, resolution=64) if dn.improved else mesh
                row[f'dense[{name}]'] = _score(dmesh.copy().apply_transform(dn.T_world_object), o['gt_points'])
                row[f'dense[{name}]'].update(improved=dn.improved, seconds=round(dn.seconds, 1),
                                             s_per_it=round(dn.seconds_per_iteration, 3), sparse_seconds=round(t_sparse, 1))
            rows.append(row)
            print(json.dumps({k: ({kk: (round(vv, 2) if isinstance(vv, float) else vv) for kk, vv in v.items()}
                                  if isinstance(v, dict) else v) for k, v in row.items()}), flush=True)
    summary = {}
    keys = [k for k in rows[0] if isinstance(rows[0][k], dict)] if rows else []
    for k in keys:
        for cls in ('chair', 'dining table', 'all'):
            sel = [r[k] for r in rows if cls == 'all' or r['class'] == cls]
            if sel:
                summary[f'{k} / {cls}'] = {m: round(float(np.nanmean([s[m] for s in sel])), 2) for m in ('cd', 'acc', 'comp', 'f1')} \
                    | {'n': len(sel)}
    for k, v in summary.items():
        print(f'{k:<36} CD {v["cd"]:6.2f}  ACC {v["acc"]:6.1f}  COMP {v["comp"]:6.1f}  F1 {v["f1"]:6.1f}  (n={v["n"]})')
    if args.json:
        Path(args.json).write_text(json.dumps({'machine': _machine(torch.get_num_threads()), 'args': vars(args),
                                               'rows': rows, 'summary': summary}, indent=1, default=str))


# ------------------------------------------------------------------ opacity
def opacity(args) -> None:
    prior = ShapePrior.load(args.prior)
    cfg = DenseConfig()
    rng = np.random.default_rng(args.seed)
    resolutions = [int(r) for r in args.resolutions.split(',')]
    reference = max(resolutions)
    groups: dict[tuple[str, str], dict[int, list[np.ndarray]]] = {}
    for cls in sorted(set(prior.training_classes)):
        idx = [i for i, c in enumerate(prior.training_classes) if c == cls]
        for i in idx[::max(1, len(idx) // args.shapes)][:args.shapes]:
            code = prior.training_codes[i].cpu().numpy()
            grids = {r: sdf_grid(lambda p: prior.sdf_numpy(p, code), r,
                                 coarse=4 if r == reference else max(1, cfg.grid_coarse)) for r in resolutions}
            inside = np.argwhere(grids[reference] < 0)
            if not len(inside):
                continue
            points = grid_points(reference)[tuple(inside[rng.choice(len(inside), args.rays)].T)]
            azimuth = rng.uniform(0, 2 * np.pi, args.rays)
            elevation = np.radians(rng.uniform(20, 50, args.rays))
            d = np.stack([np.cos(azimuth) * np.cos(elevation), np.sin(azimuth) * np.cos(elevation),
                          -np.sin(elevation)], 1)
            ones = torch.ones(1, args.rays)
            rays = Rays(torch.as_tensor(points - 2.5 * d, dtype=torch.float32)[None],
                        torch.as_tensor(d, dtype=torch.float32)[None], ones, ones)
            family = prior.training_shapes[i].get('family', '-')
            for r, grid in grids.items():
                volume = torch.as_tensor(np.ascontiguousarray(grid.transpose(2, 1, 0)))[None, None]
                with torch.no_grad():
                    H = foreground_probability(volume, torch.eye(3), torch.zeros(3), torch.tensor(1.0), rays,
                                               cfg.ray_step, cfg.sharpness)
                groups.setdefault((cls, family), {}).setdefault(r, []).append(H.reshape(-1).numpy())
    print(f'prior {prior.path.name}: mean foreground probability H of rays through the inside of its training '
          f'shapes (ray step {cfg.ray_step}, sharpness {cfg.sharpness:g}); in brackets, the share of rays under 0.5')
    print(f'{"class":<14}{"family":<14}{"shapes":>7}' + ''.join(f'{f"{r}^3":>16}' for r in resolutions))
    for (cls, family), per_res in sorted(groups.items()):
        cells = ''.join(f'{np.concatenate(per_res[r]).mean():>8.2f} ({np.mean(np.concatenate(per_res[r]) < 0.5):4.0%})'
                        for r in resolutions)
        print(f'{cls:<14}{family:<14}{len(per_res[resolutions[0]]):>7}{cells}')


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest='cmd', required=True)
    t = sub.add_parser('timing', help='seconds per dense iteration at N views')
    t.add_argument('--views', type=int, default=35)
    t.add_argument('--iterations', type=int, default=10)
    t.add_argument('--configs', nargs='*', default=[''],
                   help="DenseConfig overrides as JSON, e.g. '{\"grid_resolution\": 48}' ('' = defaults)")
    s = sub.add_parser('stages', help='per-stage accuracy (Table 3 analogue), --ablation for Table 2')
    s.add_argument('bags', nargs='+')
    s.add_argument('--views', type=int, default=35)
    s.add_argument('--ablation', action='store_true')
    s.add_argument('--sparse', default='', help='SparseConfig overrides (JSON)')
    s.add_argument('--dense', default='', help='DenseConfig overrides (JSON)')
    s.add_argument('--seed', type=int, default=0)
    s.add_argument('--no-support', action='store_true', help='no floor / class height priors (support.py)')
    s.add_argument('--json', default='')
    s.add_argument('--prior', default=DEFAULT_PRIOR,
                   help=f"shipped prior name or prior folder (default {DEFAULT_PRIOR!r}, the nodes')")
    s.add_argument('--code', choices=('encoder', 'oracle'), default='encoder',
                   help="start the sparse stage from the encoders' mean code (default) or from the true shape's "
                        "code (auto-decoder fit to the ground-truth mesh; needs the bag's .gt.json sidecar): is it "
                        "the start or the energy that limits the result?")
    s.add_argument('--fused-only', action='store_true',
                   help='score the fused encoder codes only (no sparse / dense stage): an encoder comparison')
    o = sub.add_parser('opacity', help="how opaque the dense silhouette renders the prior's shapes per volume "
                                       'resolution')
    o.add_argument('--resolutions', default='32,48,64,128', help='SDF volume resolutions; the largest is the '
                   'reference that finds the points inside')
    o.add_argument('--shapes', type=int, default=30, help='training shapes per class (evenly spaced)')
    o.add_argument('--rays', type=int, default=300, help='rays per shape')
    o.add_argument('--seed', type=int, default=0)
    o.add_argument('--prior', default=DEFAULT_PRIOR)
    for p in (t, s, o):
        p.add_argument('--threads', type=int, default=1)
        p.add_argument('--device', default='cpu')
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    return {'timing': timing, 'stages': stages, 'opacity': opacity}[args.cmd](args)


if __name__ == '__main__':
    sys.exit(main() or 0)
