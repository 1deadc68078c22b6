"""Where each object's error comes from: the offline pipeline's association box and every optimiser stage
(fused, sparse, dense) scored against the bag's ground truth, per object.

    .venv/bin/python bench/bench_stages.py BAG.mcap [BAG.mcap ...] [--params FILE] [--json OUT]
        [--oracle] [--figures DIR] [--dense-seeds 0,1,2] [--threads N]

Each bag is reconstructed as `frodo reconstruct` does (`frodo_bringup.pipeline.reconstruct`, deterministic),
with the estimate of every stage kept as it ends. The final map is matched to the ground truth with the
contract's protocol (`frodo_common.evaluation`); for each matched object the table gives the horizontal
distance (cm) between the centre of the ground-truth mesh's bounding box and the association box's centre
("assoc", with its vertical offset "dz") and each stage mesh's bounding-box centre ("c"), and each stage's
F1@5cm and COMP@5cm against that ground-truth object alone (`--json` also keeps each stage's own words, e.g. the
sparse start that won, and each stage code's `code_er`: the code regulariser Er of the sparse and dense stages, the
mean squared distance from the prior's training codes in their standard deviations, about 1 for a training shape).
The bag line counts the ground-truth objects
found, false positives and the classes missed. The last lines pool every bag: per class and stage the mean
F1, mean COMP and the median centre error. Used for issue 27 (docs/experiments/frodo_association_history.md,
"Starved views, and where realwalk-tune loses its objects").

With `--oracle`, each matched object's final mesh is also scored after corrections that only the ground truth
can give, to show what each kind of error costs: moved horizontally so that its bounding-box centre is the
truth's ("centred"), then the best of four quarter turns about the vertical through that centre ("turned"), or
instead the best uniform scale in 0.75-1.33 about its bottom centre ("scaled"). What is left after them is
the shape.

With `--figures DIR`, every ground-truth object gets a picture, DIR/BAG_gtID.png (`result_figure.draw_object_stages`):
its surface and its stage meshes from above, as its cameras see it and from the side along their mean viewing
direction, with the association's box centre and the rays from the cameras that saw it; a missed object is drawn
with the nearest estimate of its class within 1.5 m, if any.

The last line sums the set up: objects found of all ground-truth objects, the mean final F1@5cm per class, and
the F1 with every missed object counted as 0. Single objects' figures move with the dense stage's pixel draws
(`DenseConfig.seed`) and with torch's thread count (floating-point order) by up to tens of points, so a change is
judged over several draws: `--dense-seeds 0,1,2` runs the whole set once per seed and ends with each seed's
summary and their mean; `--threads N` fixes torch's threads (results repeat for a given count; two one-thread
runs side by side use 2 cores without the slowdown of two multi-threaded ones).
"""
from __future__ import annotations

from frodo_common.host import reproducible_math

reproducible_math()      # before torch: the same bag gives the same figures

import argparse                                               # noqa: E402
import json                                                   # noqa: E402
import time                                                   # noqa: E402
from dataclasses import replace                               # noqa: E402
from pathlib import Path                                      # noqa: E402

import numpy as np                                            # noqa: E402

from frodo_bringup.pipeline import PipelineConfig, reconstruct   # noqa: E402
from frodo_bringup.result_figure import draw_object_stages       # noqa: E402
from frodo_common import conversions as conv, topics              # noqa: E402
from frodo_common.bag import BagReader                            # noqa: E402
from frodo_common.evaluation import (EvalObject, evaluate, load_ground_truth, point_metrics,   # noqa: E402
                                     sample_surface)
from frodo_datasets.synth import sidecar_path                     # noqa: E402
from frodo_optim.sparse import code_statistics                    # noqa: E402
from frodo_shape.prior import ShapePrior                          # noqa: E402

STAGES = ('fused', 'sparse', 'dense')
ORACLES = ('as_is', 'centred', 'turned', 'scaled')
ORACLE_SCALES = np.exp(np.linspace(np.log(0.75), np.log(4 / 3), 11))


def oracle_f1(mesh, truth) -> dict[str, float]:
    """F1@5cm of `mesh` against `truth` (trimesh meshes) as it is and after the ground-truth corrections of
    `--oracle` (the module docstring)."""
    truth_pts, pts = sample_surface(truth), sample_surface(mesh)
    f1 = lambda p: point_metrics(p, truth_pts)[5]          # noqa: E731
    centre = truth.bounds.mean(0)
    shift = centre - mesh.bounds.mean(0)
    shift[2] = 0.0
    centred = pts + shift
    turns = []
    for k in range(4):
        c, s = np.cos(k * np.pi / 2), np.sin(k * np.pi / 2)
        turns.append(f1((centred - centre) @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T + centre))
    base = np.array([centre[0], centre[1], mesh.bounds[0, 2]])
    return {'as_is': f1(pts), 'centred': f1(centred), 'turned': max(turns),
            'scaled': max(f1((centred - base) * k + base) for k in ORACLE_SCALES)}


def gt_families(bag: str) -> dict[int, str]:
    """Ground-truth object id -> shape family, from the bag's `<stem>.gt.json` sidecar (`frodo synth`), if any."""
    sidecar = sidecar_path(bag)
    if not sidecar.is_file():
        return {}
    objects = json.loads(sidecar.read_text()).get('scene', {}).get('objects', [])
    return {int(o['id']): o.get('family') for o in objects if 'id' in o}


def camera_centres(bag: str) -> dict[int, np.ndarray]:
    """Stamp -> camera centre (3,) of every pose message of the bag."""
    poses = (m.decode() for m in BagReader(bag).messages([topics.POSE]))
    return {conv.stamp_to_ns(p.header.stamp): conv.pose_to_matrix(p.pose)[:3, 3] for p in poses}


def draw_objects(bag: str, gt: list, report, result, meshes: dict, out_dir: Path, search: float = 1.5) -> None:
    """One figure per ground-truth object (`result_figure.draw_object_stages`): its matched estimate's stages, or
    for a missed object those of the nearest estimate of its class within `search` m (none: the truth alone)."""
    cams = camera_centres(bag)
    pred_of = {p.gt_id: p.pred_id for p in report.pairs}
    for g in gt:
        pred = pred_of.get(g.id)
        note = ''
        if pred is None:
            near = [(float(np.linalg.norm(e.mesh_world.bounds.mean(0) - g.mesh.bounds.mean(0))), oid)
                    for oid, e in result.estimates.items() if e.class_name == g.class_name]
            near = [n for n in near if n[0] < search]
            pred = min(near)[1] if near else None
            note = 'missed' + (f', nearest estimate {pred}' if pred is not None else '')
        seen = [cams[stamp] for stamp, rows in result.associations.items()
                if pred is not None and stamp in cams and np.any(rows['object_id'] == pred)]
        box = result.tracks[pred][1].center if pred is not None and pred in result.tracks else None
        f1 = next((f'F1@5cm {p.f1:.1f}' for p in report.pairs if p.gt_id == g.id), note)
        draw_object_stages(g, meshes.get(pred, {}) if pred is not None else {}, np.array(seen).reshape(-1, 3),
                           out_dir / f'{Path(bag).stem}_gt{g.id}.png', box_centre=box,
                           title=f'{Path(bag).stem}, ground truth {g.id} ({g.class_name}): {f1}, '
                                 f'{len(seen)} frames associated')


def score_bag(bag: str, config: PipelineConfig | None, oracle: bool = False,
              figures: Path | None = None) -> tuple[list[dict], str, int]:
    """(one row per matched object, the bag's summary line, its number of ground-truth objects); figures: also
    draw every ground-truth object into this folder (`draw_objects`)."""
    gt = load_ground_truth(bag)
    meshes: dict[int, dict[str, object]] = {}
    details: dict[int, dict[str, str]] = {}
    code_er: dict[int, dict[str, float]] = {}
    optim = (config or PipelineConfig()).optim
    prior = ShapePrior.load(optim.prior, device=optim.device)
    mean, std = (x.numpy() for x in code_statistics(prior.training_codes))

    def keep(stage) -> None:
        if stage.estimate is not None:
            meshes.setdefault(stage.object_id, {})[stage.stage] = stage.estimate.mesh_world.copy()
            code_er.setdefault(stage.object_id, {})[stage.stage] = float(
                np.mean(((np.asarray(stage.estimate.code) - mean) / std) ** 2))
        details.setdefault(stage.object_id, {})[stage.stage] = stage.detail

    t0 = time.perf_counter()
    result = reconstruct(bag, config, on_stage=keep, prior=prior)
    seconds = time.perf_counter() - t0
    final = [EvalObject(oid, e.class_name, e.mesh_world) for oid, e in result.estimates.items()]
    report = evaluate(final, gt)
    truth = {g.id: g for g in gt}
    families = gt_families(bag)
    rows = []
    for pair in report.pairs:
        g = truth[pair.gt_id]
        centre = g.mesh.bounds.mean(0)
        box = result.tracks[pair.pred_id][1]
        row = {'bag': Path(bag).stem, 'object': pair.pred_id, 'gt': pair.gt_id, 'family': families.get(pair.gt_id),
               'class': pair.class_name,
               'assoc_cm': 100 * float(np.linalg.norm(box.center[:2] - centre[:2])),
               'assoc_dz_cm': 100 * float(box.center[2] - centre[2])}
        for stage, mesh in meshes.get(pair.pred_id, {}).items():
            scored = evaluate([EvalObject(pair.pred_id, pair.class_name, mesh)], [g]).pairs
            row[stage] = {'centre_cm': 100 * float(np.linalg.norm(mesh.bounds.mean(0)[:2] - centre[:2])),
                          'f1': scored[0].f1 if scored else 0.0, 'comp': scored[0].comp if scored else 0.0,
                          'top_cm': 100 * float(mesh.bounds[1, 2] - g.mesh.bounds[1, 2]),
                          'bottom_cm': 100 * float(mesh.bounds[0, 2] - g.mesh.bounds[0, 2]),
                          'detail': details.get(pair.pred_id, {}).get(stage, ''),
                          'code_er': code_er[pair.pred_id][stage]}
        if oracle:
            row['oracle'] = oracle_f1(result.estimates[pair.pred_id].mesh_world, g.mesh)
        rows.append(row)
    if figures is not None:
        draw_objects(bag, gt, report, result, meshes, figures)
    missed = [truth[i].class_name for i in report.unmatched_gt]
    line = (f'{Path(bag).name}: {len(report.pairs)}/{len(gt)} found, {len(report.unmatched_pred)} FP, '
            f'F1 {"-" if report.overall.f1 is None else f"{report.overall.f1:.1f}"}, missed {missed}, {seconds:.0f} s')
    return rows, line, len(gt)


def final_f1(row: dict) -> float:
    """F1@5cm of the object's final mesh (its last stage's)."""
    return next(row[name]['f1'] for name in reversed(STAGES) if name in row)


def summary(rows: list[dict], n_truth: int) -> dict:
    """Objects found, mean final F1 per class and the F1 with every missed object as 0."""
    out = {'found': len(rows), 'objects': n_truth,
           'misses_as_0': sum(final_f1(r) for r in rows) / max(n_truth, 1)}
    for cls in sorted({r['class'] for r in rows}):
        out[cls] = float(np.mean([final_f1(r) for r in rows if r['class'] == cls]))
    return out


def summary_line(s: dict) -> str:
    classes = ', '.join(f'{k} {v:.1f}' for k, v in s.items() if k not in ('found', 'objects', 'misses_as_0'))
    return f"found {s['found']:.3g}/{s['objects']:.3g}, final F1 {classes}, F1 with misses as 0 {s['misses_as_0']:.1f}"


def with_dense_seed(config: PipelineConfig | None, seed: int) -> PipelineConfig:
    """`config` (default: the defaults) with the dense stage's pixel draws seeded by `seed`."""
    config = config or PipelineConfig()
    return replace(config, optim=replace(config.optim, dense=replace(config.optim.dense, seed=seed)))


def object_line(row: dict) -> str:
    def stage(name: str) -> str:
        s = row.get(name)
        return f'{name} -' if s is None else f"{name} c {s['centre_cm']:5.1f} F1 {s['f1']:5.1f} COMP {s['comp']:5.1f}"
    line = (f"  {row['object']:3d} {row['class'][:12]:12s} assoc {row['assoc_cm']:5.1f} dz {row['assoc_dz_cm']:5.1f} | "
            + ' | '.join(stage(s) for s in STAGES))
    if 'oracle' in row:
        line += ' | final F1 ' + ' '.join(f"{k} {row['oracle'][k]:5.1f}" for k in ORACLES)
    return line


def pooled_lines(rows: list[dict]) -> list[str]:
    lines = []
    for cls in sorted({r['class'] for r in rows}):
        of_class = [r for r in rows if r['class'] == cls]
        for name in STAGES:
            got = [r[name] for r in of_class if name in r]
            if got:
                lines.append(f'{cls:12s} {name:6s} n {len(got):3d}  F1 {np.mean([g["f1"] for g in got]):5.1f}  '
                             f'COMP {np.mean([g["comp"] for g in got]):5.1f}  '
                             f'median centre {np.median([g["centre_cm"] for g in got]):5.1f} cm')
        oracles = [r['oracle'] for r in of_class if 'oracle' in r]
        if oracles:
            lines.append(f'{cls:12s} final  n {len(oracles):3d}  mean F1 ' + ', '.join(
                f'{k} {np.mean([o[k] for o in oracles]):5.1f}' for k in ORACLES))
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('bags', nargs='+')
    parser.add_argument('--params', action='append', default=[], help='parameter YAML (repeatable)')
    parser.add_argument('--json', help='write the per-object rows here (keyed by bag and ground-truth id `gt`, '
                        'with the ground truth\'s shape `family` where the bag has a `.gt.json` sidecar, and per '
                        'stage the mesh top\'s and bottom\'s height above the truth\'s: `top_cm`, `bottom_cm`)')
    parser.add_argument('--oracle', action='store_true',
                        help='also score each final mesh after ground-truth corrections (centred, turned, scaled)')
    parser.add_argument('--dense-seeds', default='',
                        help='comma-separated dense-stage seeds: the whole set once per seed (default: the config\'s)')
    parser.add_argument('--figures', type=Path, default=None,
                        help='draw every ground-truth object with its stages into this folder: from above, as seen '
                             'and from the side along the view (BAG_gtID.png)')
    parser.add_argument('--threads', type=int, default=0, help='torch threads (default: torch\'s own)')
    args = parser.parse_args(argv)
    if args.threads > 0:
        import torch
        torch.set_num_threads(args.threads)
    config = PipelineConfig.from_params_files(args.params) if args.params else None
    seeds = [int(s) for s in args.dense_seeds.split(',') if s.strip()] or [None]
    rows: list[dict] = []
    summaries = []
    for seed in seeds:
        run_config = config if seed is None else with_dense_seed(config, seed)
        prefix = '' if seed is None else f'[dense seed {seed}] '
        seed_rows: list[dict] = []
        n_truth = 0
        for bag in args.bags:
            bag_rows, line, n_gt = score_bag(bag, run_config, args.oracle, args.figures)
            print(prefix + line, flush=True)
            for row in bag_rows:
                print(object_line(row), flush=True)
                if seed is not None:
                    row['dense_seed'] = seed
            seed_rows += bag_rows
            n_truth += n_gt
        print('\n'.join(pooled_lines(seed_rows)))
        summaries.append(summary(seed_rows, n_truth))
        print(prefix + summary_line(summaries[-1]), flush=True)
        rows += seed_rows
    if len(seeds) > 1:
        keys = dict.fromkeys(k for s in summaries for k in s)          # first-seen order
        mean = {k: float(np.mean([s[k] for s in summaries if k in s])) for k in keys}
        print(f'mean over dense seeds {",".join(map(str, seeds))}: ' + summary_line(mean))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + '\n')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
