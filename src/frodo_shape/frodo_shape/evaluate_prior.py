"""Measurements of a shape prior (paper Sec. 4 embedding quality, Sec. 5.2 single-view encoder, supp. speed).

    python -m frodo_shape.evaluate_prior --prior furniture [--heldout 10] [--views 3] [--out metrics.json]
        [--real-cad data/real/build/src [--real-cad-figure real_cad.png]]

- Auto-decoder fit: codes of held-out procedural shapes (seeds never trained on) are optimised against
  their SDF samples (`ShapePrior.fit_sdf`), meshed, scaled to metres, and compared with the ground truth.
- Held-out designs (`--heldout-designs N`): the same fit for N shapes of each evaluation-only family
  (`frodo_datasets.shapes.eval_families`: cantilever and tub chairs, desks, round four-leg tables).
- Real-CAD split (`--real-cad SRC`): the same fit for artist-made models of real furniture products
  (`frodo_datasets.real_data.REAL_CAD_MODELS`, fetched by `scripts/fetch_real_cad.sh SRC`; data/real/README.md),
  per model and per class, with a check of each model's inside test (several are open shells).
- Training reconstruction: the same for training shapes with their learnt codes.
- Single-view encoder: held-out shapes rendered like the encoder's training data (random view, material,
  light, floor/wall/backdrop), cropped at the true box (`crops.square_crop`), encoded, meshed, compared.
  `--handheld-views N`: the same with near cameras and capture conditions (truncation, occlusion, mask
  errors, blur, exposure; `augment.py`) on every crop.
- Speed: SDF decoder points/s (forward, forward+backward), point decoder time, encoder images/s.

Metrics at metric object scale: CD = ½(mean NN distance pred→gt + gt→pred) in cm on 10k surface samples
each; F1@τ (%) = harmonic mean of precision (pred points within τ of gt) and recall (gt within τ of pred);
voxel IoU at 32³ over [-1, 1]³ in the normalised frame (inside test of gt vs decoded SDF < 0).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from frodo_common.host import cpu_model
from frodo_shape.meshing import grid_points
from frodo_shape.prior import ShapePrior
from frodo_shape.sdf_data import SamplingConfig, cached_samples, inside, inside_check
from frodo_shape.augment import CropAugmentation, augment_crop
from frodo_shape.train import (TrainingShape, design_shapes, library_shapes, load_config, render_scene, render_view,
                               to_training_shapes)

HELDOUT_SEED = 7919  # library seed of the held-out shapes (training priors use library_seed 0)
HANDHELD_CONFIG = 'furniture_encoder_handheld'  # its renders' distance and `augment:`: the --handheld-views crops


def surface_metrics(pred: trimesh.Trimesh, gt: trimesh.Trimesh, n: int = 10000, taus=(0.01, 0.05),
                    seed: int = 0) -> dict:
    """CD (cm) and F1@τ (%) between two metric meshes; an empty prediction scores CD=inf, F1=0."""
    if len(pred.faces) == 0:
        return {'cd_cm': float('inf'), **{f'f1@{int(t * 100)}cm': 0.0 for t in taus}}
    p, _ = trimesh.sample.sample_surface(pred, n, seed=seed)
    g, _ = trimesh.sample.sample_surface(gt, n, seed=seed + 1)
    d_pg, _ = cKDTree(g).query(p)
    d_gp, _ = cKDTree(p).query(g)
    out = {'cd_cm': float(50 * (d_pg.mean() + d_gp.mean()))}
    for t in taus:
        prec, rec = (d_pg < t).mean(), (d_gp < t).mean()
        out[f'f1@{int(round(t * 100))}cm'] = float(0 if prec + rec == 0 else 200 * prec * rec / (prec + rec))
    return out


def voxel_iou(prior: ShapePrior, code: np.ndarray, gt_normalised: trimesh.Trimesh, resolution: int = 32) -> float:
    """IoU of occupancy grids (resolution³ cell centres in [-1, 1]³): gt inside test vs decoded SDF < 0."""
    h = 1.0 / resolution
    pts = grid_points(resolution, 1.0 - h).reshape(-1, 3)
    occ_gt = inside(gt_normalised, pts)
    occ_pred = prior.sdf_numpy(pts, code) < 0
    union = np.logical_or(occ_gt, occ_pred).sum()
    return float(np.logical_and(occ_gt, occ_pred).sum() / union) if union else 1.0


def _metric(mesh: trimesh.Trimesh, scale: float) -> trimesh.Trimesh:
    m = mesh.copy()
    m.apply_scale(scale)
    return m


def _summary(rows: list[dict]) -> dict:
    keys = [k for k in rows[0] if isinstance(rows[0][k], float)] if rows else []
    return {k: {'median': float(np.median([r[k] for r in rows])), 'mean': float(np.mean([r[k] for r in rows]))}
            for k in keys}


def evaluate_fit(prior: ShapePrior, shapes: list[TrainingShape], steps: int = 400, resolution: int = 64,
                 cache_dir: Path | None = None, meshes: list | None = None) -> list[dict]:
    """Auto-decoder fit of `shapes` (codes optimised on their SDF samples): per-shape metrics. The fitted
    normalised-frame meshes are appended to `meshes` when a list is given."""
    rows = []
    for i, s in enumerate(shapes):
        smp = cached_samples(s.mesh, SamplingConfig(), cache_dir, seed=10_000 + i)
        code = prior.fit_sdf(smp.points, smp.sdf, steps=steps, seed=i)
        mesh = prior.mesh(code, resolution)
        if meshes is not None:
            meshes.append(mesh)
        rows.append({'name': s.name, 'class': s.class_name, **surface_metrics(_metric(mesh, s.scale), _metric(s.mesh, s.scale))})
    return rows


def evaluate_real_cad(prior: ShapePrior, src: str | Path, steps: int = 400, resolution: int = 64,
                      cache_dir: Path | None = None) -> tuple[dict, list[TrainingShape], list[trimesh.Trimesh]]:
    """Auto-decoder fit of the real-CAD split under `src` (models of the prior's classes), as `evaluate_fit`.

    Returns (results: per-model rows, summary, per-class summaries and a per-model description: extents in
    metres, closed or not, `inside_check`; the shapes; the fitted normalised-frame meshes).
    """
    from frodo_datasets.real_data import load_real_cad
    records = load_real_cad(src, prior.class_names)
    shapes = to_training_shapes(records)
    models = []
    for record, shape in zip(records, shapes):
        check = inside_check(shape.mesh)
        models.append({'name': shape.name, 'class': shape.class_name, 'source': str(record.source),
                       'extents_m': [round(float(v), 3) for v in record.mesh.extents],
                       'closed': bool(record.watertight), **check})
        if not record.watertight or not check['consistent']:
            print(f'real-CAD {shape.name}: {"closed" if record.watertight else "not closed (open shell parts)"}, '
                  f'inside test {check["inside_fraction"]:.3f} of the box vs {check["reference_fraction"]:.3f} '
                  f'{"(consistent)" if check["consistent"] else "(INCONSISTENT: SDF signs unreliable)"}',
                  file=sys.stderr)
    meshes: list[trimesh.Trimesh] = []
    rows = evaluate_fit(prior, shapes, steps, resolution, cache_dir, meshes)
    classes = [c for c in prior.class_names if any(r['class'] == c for r in rows)]
    return ({'summary': _summary(rows), 'per_class': {c: _summary([r for r in rows if r['class'] == c]) for c in classes},
             'rows': rows, 'models': models}, shapes, meshes)


def fit_figure(shapes: list[TrainingShape], meshes: list[trimesh.Trimesh], rows: list[dict], path: str | Path,
               title: str = '') -> None:
    """Ground truth (top) and fitted mesh (bottom) per shape, thumbnails of the normalised frame, with F1@5cm/CD."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, len(shapes), figsize=(1.7 * len(shapes), 3.6), squeeze=False)
    for j, (s, mesh, row) in enumerate(zip(shapes, meshes, rows)):
        for i, (m, label) in enumerate([(s.mesh, f'{s.name}\n{s.class_name}'),
                                        (mesh, f'fit: F1@5cm {row["f1@5cm"]:.0f}\nCD {row["cd_cm"]:.1f} cm')]):
            axes[i, j].imshow(thumbnail(m))
            axes[i, j].set_title(label, fontsize=7)
            axes[i, j].axis('off')
    if title:
        fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def evaluate_training(prior: ShapePrior, count: int, resolution: int = 64) -> list[dict]:
    """Reconstruction of the first `count` procedural training shapes per class from their learnt codes."""
    from frodo_datasets.shapes import generate, normalise
    rows = []
    for c in prior.class_names:
        picked = [i for i, s in enumerate(prior.training_shapes) if s['class'] == c and s.get('seed') is not None]
        for i in picked[:count]:
            s = prior.training_shapes[i]
            gt, scale = normalise(generate(c, int(s['seed']), s['family']))
            mesh = prior.mesh(prior.training_codes[i].cpu().numpy(), resolution)
            rows.append({'name': s['name'], 'class': c, **surface_metrics(_metric(mesh, scale), _metric(gt, scale))})
    return rows


def heldout_views(shapes: list[TrainingShape], views: int, seed: int = 1234, size: int = 128,
                  handheld: CropAugmentation | None = None, distance: tuple[float, float] = (0.7, 4.5)):
    """Rendered test crops: list of (shape index, crop (size, size, 3) uint8, mask (size, size) bool).

    handheld: instead of clean crops at the true box, crops of cameras `distance` m away with these capture
    conditions applied (`augment.augment_crop`; a seed stream the encoder's training never draws).
    """
    from frodo_shape.crops import square_crop
    out = []
    for i, s in enumerate(shapes):
        rng = np.random.default_rng([seed, i])
        n = 0
        while n < views:
            if handheld is None:
                v = render_scene(s, rng)
                if v is None:
                    continue
                crop, cmask = square_crop(*v, size, 0.1)
            else:
                v = render_view(s, rng, distance=distance)
                if v is None:
                    continue
                crop, cmask = augment_crop(*v, rng, size, aug=handheld)
            out.append((i, crop, cmask))
            n += 1
    return out


def evaluate_encoder(prior: ShapePrior, shapes: list[TrainingShape], views: int, resolution: int = 64,
                     handheld: CropAugmentation | None = None,
                     distance: tuple[float, float] = (0.7, 4.5)) -> list[dict]:
    """Single-view reconstruction of held-out shapes from rendered crops (clean, or with `handheld`
    capture conditions): per-view metrics."""
    data = heldout_views(shapes, views, handheld=handheld, distance=distance)
    codes = prior.encode(np.stack([d[1] for d in data]), np.stack([d[2] for d in data]))
    rows = []
    for (i, _, _), code in zip(data, codes):
        s = shapes[i]
        mesh = prior.mesh(code, resolution)
        rows.append({'name': s.name, 'class': s.class_name,
                     **surface_metrics(_metric(mesh, s.scale), _metric(s.mesh, s.scale)),
                     'voxel_iou': voxel_iou(prior, code, s.mesh)})
    return rows


def measure_speed(prior: ShapePrior, repeats: int = 5) -> dict:
    """Decoder and encoder throughput on the prior's device."""
    dev = prior.device
    dec = prior.decoder
    z = prior.training_codes[:1].clone()
    x = torch.rand(1, 65536, 3, device=dev) * 2 - 1

    def timed(fn) -> float:
        fn()
        t = time.perf_counter()
        for _ in range(repeats):
            fn()
        if dev.type == 'cuda':
            torch.cuda.synchronize()
        return (time.perf_counter() - t) / repeats

    with torch.no_grad():
        fwd = timed(lambda: dec.sdf(z, x))
        pts = timed(lambda: dec.points(z))
    zg = z.clone().requires_grad_(True)
    fb = timed(lambda: dec.sdf(zg, x).sum().backward())
    pfb = timed(lambda: dec.points(zg).sum().backward())
    out = {'sdf_points_per_s_fwd': 65536 / fwd, 'sdf_points_per_s_fwd_bwd': 65536 / fb,
           'point_decoder_ms_fwd': 1000 * pts, 'point_decoder_ms_fwd_bwd': 1000 * pfb}
    if prior.encoder is not None:
        s = prior.encoder.config.input_size
        crops = np.zeros((32, s, s, 3), np.uint8)
        out['encoder_images_per_s'] = 32 / timed(lambda: prior.encode(crops, np.ones((32, s, s), bool)))
    t = time.perf_counter()
    prior.mesh(z[0].cpu().numpy(), 64)
    out['mesh_64_s'] = time.perf_counter() - t
    return out


def thumbnail(mesh: trimesh.Trimesh, size: int = 128, color=(0.75, 0.72, 0.65)) -> np.ndarray:
    """Grey-shaded render (size, size, 3) uint8 of a normalised-frame mesh from the front-left, slightly above."""
    from frodo_common.geometry import look_at
    from frodo_datasets.render import Light, Material, RenderObject, Renderer
    if len(mesh.faces) == 0:
        return np.full((size, size, 3), 255, np.uint8)
    eye = np.array([2.6, 1.6, 1.4])
    f = 0.5 * size / 0.3
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1.0]])
    res = Renderer([RenderObject(mesh, Material(color=color), label=1)]).render(
        K, look_at(eye, np.zeros(3)), size, size, light=Light(direction=(-0.5, -0.8, -1.0)), ambient=0.4,
        shadows=False, background=(1.0, 1.0, 1.0))
    return res.rgb


def retrieval_figure(prior: ShapePrior, shapes: list[TrainingShape], path: str | Path, rows: int = 6, k: int = 4,
                     seed: int = 99) -> None:
    """CAD retrieval (supplement Fig. "nearest CAD models"): input crop, then the k nearest training shapes."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from frodo_datasets.shapes import generate, normalise
    picked = [shapes[i] for i in np.random.default_rng(seed).choice(len(shapes), min(rows, len(shapes)), replace=False)]
    data = heldout_views(picked, 1, seed=seed)
    codes = prior.encode(np.stack([d[1] for d in data]), np.stack([d[2] for d in data]))
    fig, axes = plt.subplots(len(data), k + 2, figsize=(1.6 * (k + 2), 1.7 * len(data)), squeeze=False)
    for r, ((i, crop, _), code) in enumerate(zip(data, codes)):
        panels = [(crop, 'input crop'), (thumbnail(picked[i].mesh), 'true shape')]
        for j, name, dist in prior.nearest_training(code, k):
            s = prior.training_shapes[j]
            mesh = normalise(generate(s['class'], int(s['seed']), s['family']))[0] if s.get('seed') is not None \
                else prior.mesh(prior.training_codes[j], 48)
            panels.append((thumbnail(mesh), f'{s["family"]} d={dist:.2f}'))
        for ax, (img, title) in zip(axes[r], panels):
            ax.imshow(img)
            ax.set_title(title, fontsize=7)
            ax.axis('off')
    fig.suptitle(f'CAD retrieval with prior {prior.path.name}: held-out crop, true shape, {k} nearest training shapes '
                 'in code space', fontsize=8)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def compare_point_decoders(prior: ShapePrior, variants=('small', 'paper'), steps: int = 400, batch: int = 16,
                           lr: float = 1e-3, seed: int = 0) -> dict:
    """Capacity of point-decoder variants: each is fitted from scratch to the training shapes' surfaces
    with the prior's (frozen) training codes, same steps and batch; returns per variant the parameter count,
    ms per training step, and the final chamfer (CD as in `surface_metrics`, cm at metric scale)."""
    from frodo_datasets.shapes import generate, normalise
    from frodo_shape.models import POINT_DECODER_VARIANTS, PointDecoder, count_parameters
    from frodo_shape.train import chamfer
    idx = [i for i, s in enumerate(prior.training_shapes) if s.get('seed') is not None]
    surf = torch.stack([torch.from_numpy(trimesh.sample.sample_surface(
        normalise(generate(prior.training_shapes[i]['class'], int(prior.training_shapes[i]['seed']),
                           prior.training_shapes[i]['family']))[0], 2048, seed=i)[0]).float() for i in idx])
    codes = prior.training_codes[idx].cpu()
    scales = torch.tensor(prior.training_scales[idx], dtype=torch.float32)
    out = {}
    for v in variants:
        torch.manual_seed(seed)
        net = PointDecoder(prior.code_dim, POINT_DECODER_VARIANTS[v], prior.decoder.point_net.num_points)
        opt = torch.optim.Adam(net.parameters(), lr=lr)
        gen = torch.Generator().manual_seed(seed)
        t = time.perf_counter()
        for _ in range(steps):
            b = torch.randint(0, len(idx), (batch,), generator=gen)
            loss = chamfer(net(codes[b]), surf[b]).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        ms = 1000 * (time.perf_counter() - t) / steps
        with torch.no_grad():
            pred = net(codes)
            cds = []
            for p, g, s in zip(pred, surf, scales):
                d_pg, _ = cKDTree(g.numpy()).query(p.numpy())
                d_gp, _ = cKDTree(p.numpy()).query(g.numpy())
                cds.append(50 * float(s) * (d_pg.mean() + d_gp.mean()))
        out[v] = {'parameters': count_parameters(net), 'ms_per_step': ms,
                  'cd_cm_median': float(np.median(cds)), 'cd_cm_mean': float(np.mean(cds)), 'steps': steps,
                  'batch': batch}
    return out


def machine() -> str:
    """One line naming the machine the numbers were measured on."""
    return f'{cpu_model()}, {torch.get_num_threads()} torch threads, torch {torch.__version__}'


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--prior', default='furniture')
    ap.add_argument('--heldout', type=int, default=10, help='held-out procedural shapes per class')
    ap.add_argument('--train-count', type=int, default=5, help='training shapes per class to reconstruct (0: skip)')
    ap.add_argument('--views', type=int, default=3, help='rendered views per held-out shape (encoder)')
    ap.add_argument('--handheld-views', type=int, default=0,
                    help=f'views per held-out shape with the capture conditions of {HANDHELD_CONFIG}.yaml (encoder)')
    ap.add_argument('--fit-steps', type=int, default=400,
                    help='code optimisation steps per held-out (and real-CAD) shape (0: skip the held-out fit)')
    ap.add_argument('--heldout-designs', type=int, default=0,
                    help='shapes per held-out design (evaluation-only families) to fit (0: skip)')
    ap.add_argument('--real-cad', default=None, metavar='SRC',
                    help='also fit the real-CAD split found under SRC (scripts/fetch_real_cad.sh; pycollada on '
                         'PYTHONPATH, e.g. SRC/pydeps); --heldout 0 --train-count 0 --views 0 fit only it')
    ap.add_argument('--real-cad-figure', default=None, help='save ground truth vs fitted real-CAD meshes (PNG) here')
    ap.add_argument('--resolution', type=int, default=64)
    ap.add_argument('--threads', type=int, default=1)
    ap.add_argument('--cache', default=None, help='SDF sample cache folder')
    ap.add_argument('--out', default=None, help='write the results as JSON here')
    ap.add_argument('--figure', default=None, help='save a CAD-retrieval figure (PNG) here')
    ap.add_argument('--point-variants', nargs='*', default=None,
                    help="compare point-decoder variants fitted to the training codes (e.g. small paper)")
    ap.add_argument('--point-steps', type=int, default=400)
    args = ap.parse_args(argv)
    if args.real_cad and args.fit_steps <= 0:
        ap.error('--real-cad needs --fit-steps > 0')
    torch.set_num_threads(args.threads)
    prior = ShapePrior.load(args.prior)
    results: dict = {'prior': str(prior.path), 'machine': machine()}
    t = time.time()
    held = library_shapes(prior.class_names, args.heldout, seed=HELDOUT_SEED)
    assert not set(s.name for s in held) & set(prior.training_names), 'held-out shapes overlap the training set'
    results['speed'] = measure_speed(prior)
    print('speed', json.dumps(results['speed'], indent=1), flush=True)
    if args.fit_steps > 0 and held:
        rows = evaluate_fit(prior, held, args.fit_steps, args.resolution, Path(args.cache) if args.cache else None)
        results['heldout_fit'] = {'summary': _summary(rows), 'per_class': {
            c: _summary([r for r in rows if r['class'] == c]) for c in prior.class_names}, 'rows': rows}
        print('held-out auto-decoder fit', json.dumps(results['heldout_fit']['summary']), flush=True)
    if args.fit_steps > 0 and args.heldout_designs > 0:
        designs = design_shapes(prior.class_names, args.heldout_designs, seed=HELDOUT_SEED)
        rows = evaluate_fit(prior, designs, args.fit_steps, args.resolution, Path(args.cache) if args.cache else None)
        for r, s in zip(rows, designs):
            r['family'] = s.family
        families = sorted({(s.class_name, s.family) for s in designs})
        results['heldout_designs_fit'] = {'summary': _summary(rows), 'per_family': {
            f'{c}/{f}': _summary([r for r in rows if r['class'] == c and r['family'] == f]) for c, f in families},
            'rows': rows}
        print('held-out designs auto-decoder fit', json.dumps(results['heldout_designs_fit']['per_family']), flush=True)
    if args.real_cad:
        real, shapes, meshes = evaluate_real_cad(prior, args.real_cad, args.fit_steps, args.resolution,
                                                 Path(args.cache) if args.cache else None)
        results['real_cad'] = {'src': str(args.real_cad), 'fit_steps': args.fit_steps, **real}
        for r in real['rows']:
            print(f'real-CAD {r["name"]:16s} {r["class"]:12s} CD {r["cd_cm"]:5.2f} cm  F1@1cm {r["f1@1cm"]:5.1f}  '
                  f'F1@5cm {r["f1@5cm"]:5.1f}', flush=True)
        print('real-CAD auto-decoder fit', json.dumps(real['per_class']), flush=True)
        if args.real_cad_figure:
            fit_figure(shapes, meshes, real['rows'], args.real_cad_figure,
                       f'real-CAD split, auto-decoder fit ({args.fit_steps} steps) with prior {prior.path.name}')
    rows = evaluate_training(prior, args.train_count, args.resolution)
    if rows:
        results['training_recon'] = {'summary': _summary(rows), 'rows': rows}
        print('training reconstruction', json.dumps(results['training_recon']['summary']), flush=True)
    if prior.encoder is not None and args.views > 0:
        rows = evaluate_encoder(prior, held, args.views, args.resolution)
        results['heldout_single_view'] = {'summary': _summary(rows), 'per_class': {
            c: _summary([r for r in rows if r['class'] == c]) for c in prior.class_names}, 'rows': rows}
        print('held-out single view', json.dumps(results['heldout_single_view']['summary']), flush=True)
    if prior.encoder is not None and args.handheld_views > 0:
        config = load_config(HANDHELD_CONFIG)
        distance = tuple(float(d) for d in config['renders']['distance'])
        rows = evaluate_encoder(prior, held, args.handheld_views, args.resolution,
                                CropAugmentation.from_dict(config['augment']), distance)
        results['heldout_single_view_handheld'] = {'summary': _summary(rows), 'per_class': {
            c: _summary([r for r in rows if r['class'] == c]) for c in prior.class_names}, 'rows': rows}
        print('held-out single view, handheld crops', json.dumps(results['heldout_single_view_handheld']['summary']),
              flush=True)
    if args.point_variants:
        results['point_decoder_variants'] = compare_point_decoders(prior, args.point_variants, args.point_steps)
        print('point decoder variants', json.dumps(results['point_decoder_variants']), flush=True)
    if args.figure and prior.encoder is not None and held:
        retrieval_figure(prior, held, args.figure)
    results['seconds'] = time.time() - t
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
