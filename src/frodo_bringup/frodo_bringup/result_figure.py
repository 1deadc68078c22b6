"""A picture of a reconstruction against its ground truth: top and front views of surface samples, ground
truth in grey, predictions coloured by class, each matched pair labelled with its F1 at 5 cm.

    python -m frodo_bringup.result_figure out/demo bags/demo_walk.mcap out/demo/result.png

`frodo demo` writes it as DIR/result.png. `draw_object_stages` draws one object's optimiser stages against its
ground truth in the frame of the cameras that saw it (`bench/bench_stages.py --figures`).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from frodo_common.evaluation import EvalObject, EvaluationResult, sample_surface

CLASS_COLOURS = {'chair': '#f28c26', 'dining table': '#3399f2'}
STAGE_COLOURS = {'fused': '#f2b600', 'sparse': '#3366cc', 'dense': '#d62728'}
SAMPLES = 1500


def _save(fig, path: str | Path, dpi: int) -> Path:
    """Write a matplotlib figure to `path` (PNG; parent folders made), close it and return the path."""
    import matplotlib.pyplot as plt
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def draw_result(pred: Sequence[EvalObject], gt: Sequence[EvalObject], result: EvaluationResult,
                path: str | Path, title: str = '') -> Path:
    """Write the figure to `path` (PNG) and return it."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    f1 = {p.pred_id: p.f1 for p in result.pairs}
    fig, (top, front) = plt.subplots(1, 2, figsize=(11, 5), gridspec_kw={'width_ratios': [1, 1]})
    for obj in gt:
        pts = sample_surface(obj.mesh, SAMPLES, seed=obj.id)
        top.scatter(pts[:, 0], pts[:, 1], s=1, c='0.65', linewidths=0)
        front.scatter(pts[:, 0], pts[:, 2], s=1, c='0.65', linewidths=0)
    for obj in pred:
        pts = sample_surface(obj.mesh, SAMPLES, seed=obj.id)
        colour = CLASS_COLOURS.get(obj.class_name, '#7f7f7f')
        top.scatter(pts[:, 0], pts[:, 1], s=1, c=colour, linewidths=0)
        front.scatter(pts[:, 0], pts[:, 2], s=1, c=colour, linewidths=0)
        score = f'F1 {f1[obj.id]:.0f}' if obj.id in f1 else 'unmatched'
        centre = pts.mean(axis=0)
        top.annotate(f'{obj.id} {obj.class_name}\n{score}', centre[:2], fontsize=8, ha='center',
                     bbox={'boxstyle': 'round', 'fc': 'white', 'alpha': 0.7, 'lw': 0})
    for missed in result.unmatched_gt:
        obj = next(o for o in gt if o.id == missed)
        top.annotate(f'missed GT {missed}', obj.centroid[:2], fontsize=8, ha='center', color='crimson')
    top.set(title='top view (x, y)', xlabel='x (m)', ylabel='y (m)', aspect='equal')
    front.set(title='front view (x, z)', xlabel='x (m)', ylabel='z (m)', aspect='equal')
    handles = [plt.Line2D([], [], ls='', marker='o', color='0.65', label='ground truth')]
    handles += [plt.Line2D([], [], ls='', marker='o', color=c, label=f'predicted {n}') for n, c in CLASS_COLOURS.items()]
    fig.legend(handles=handles, loc='lower center', ncol=len(handles), fontsize=9, markerscale=2)
    s = result.overall
    summary = (f'recall {s.recall:.0f} %, FP {s.false_positives}, CD {s.cd_cm:.2f} cm, F1@5cm {s.f1:.1f}'
               if s.f1 is not None else f'recall {s.recall:.0f} %, FP {s.false_positives}')
    fig.suptitle(f'{title}  {summary}'.strip())
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    return _save(fig, path, dpi=110)


def view_frame(centre: np.ndarray, cameras: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) to (along the view, across it, up) coordinates: 'along' is the horizontal mean direction
    from the camera centres (C, 3) to `centre` (world x when there are none)."""
    look = (centre - cameras)[:, :2] if len(cameras) else np.array([[1.0, 0.0]])
    look = look / np.maximum(np.linalg.norm(look, axis=1, keepdims=True), 1e-9)
    d = look.mean(0)
    d = d / np.linalg.norm(d) if np.linalg.norm(d) > 1e-9 else np.array([1.0, 0.0])
    return np.array([[d[0], d[1], 0.0], [-d[1], d[0], 0.0], [0.0, 0.0, 1.0]])


def draw_object_stages(truth: EvalObject, stages: dict, cameras: np.ndarray, path: str | Path, title: str = '',
                       box_centre: np.ndarray | None = None) -> Path:
    """One object's stage meshes (`stages`: {'fused' | 'sparse' | 'dense': trimesh mesh, world frame}) against its
    ground truth, in three panels centred on the truth: from above, as the cameras see it (across the view, up)
    and from the side (along the view, up), where an error in depth along the view shows. cameras: (C, 3) world
    centres of the cameras whose detections were associated with the object, drawn as rays in the top panel;
    box_centre: the association's box centre (+). Writes `path` (PNG) and returns it."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    centre = truth.mesh.bounds.mean(0)
    span = max(1.0, 0.6 * float(np.max(truth.mesh.extents)) + 0.4)      # metres either side of the truth's centre
    R = view_frame(centre, cameras)
    local = lambda p: (np.asarray(p, float) - centre) @ R.T       # noqa: E731  (along, across, up)
    fig, axes = plt.subplots(1, 3, figsize=(15, 5))
    panels = ((0, 1, 'from above', 'along the view (m)', 'across (m)'), (1, 2, 'as seen', 'across (m)', 'up (m)'),
              (0, 2, 'from the side', 'along the view (m)', 'up (m)'))
    clouds = [('ground truth', '0.6', local(sample_surface(truth.mesh, SAMPLES, seed=0)))]
    clouds += [(name, STAGE_COLOURS.get(name, 'k'), local(sample_surface(mesh, SAMPLES, seed=1)))
               for name, mesh in stages.items()]
    for ax, (i, j, name, xlabel, ylabel) in zip(axes, panels):
        for label, colour, pts in clouds:
            ax.scatter(pts[:, i], pts[:, j], s=1, c=colour, linewidths=0, alpha=0.6)
        if box_centre is not None:
            b = local(box_centre[None])[0]
            ax.plot(b[i], b[j], '+', c='k', ms=14, mew=2)
        ax.set(title=name, xlabel=xlabel, ylabel=ylabel, aspect='equal')
        ax.set_xlim(-span, span)
    for cam in local(cameras):
        axes[0].plot([cam[0], 0.0], [cam[1], 0.0], '-', c='green', lw=0.6, alpha=0.5)
    axes[0].set_ylim(-span, span)
    handles = [plt.Line2D([], [], ls='', marker='o', color=colour, label=label) for label, colour, _ in clouds]
    handles += [plt.Line2D([], [], ls='', marker='+', color='k', mew=2, label='association box centre')] \
        if box_centre is not None else []
    handles += [plt.Line2D([], [], color='green', label='rays from its cameras')] if len(cameras) else []
    fig.legend(handles=handles, loc='lower center', ncol=len(handles), fontsize=9)
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    return _save(fig, path, dpi=80)


def main(argv: list[str] | None = None) -> int:
    """`python -m frodo_bringup.result_figure PRED_DIR GT OUT.png`"""
    from frodo_common.evaluation import EvaluationError, evaluate, load_ground_truth, load_predictions
    parser = argparse.ArgumentParser(prog='python -m frodo_bringup.result_figure', description=__doc__.splitlines()[0])
    parser.add_argument('pred', type=Path, help='output directory of `frodo run --out`')
    parser.add_argument('gt', type=Path, help='bag with /ground_truth/objects or a folder of meshes')
    parser.add_argument('out', type=Path, help='PNG to write')
    args = parser.parse_args(argv)
    try:
        pred, gt = load_predictions(args.pred), load_ground_truth(args.gt)
    except EvaluationError as err:
        print(f'error: {err}', file=sys.stderr)
        return 1
    print(draw_result(pred, gt, evaluate(pred, gt), args.out, title=args.gt.name))
    return 0


if __name__ == '__main__':
    sys.exit(main())
