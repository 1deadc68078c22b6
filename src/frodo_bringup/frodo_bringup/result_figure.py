"""A picture of a reconstruction against its ground truth: top and front views of surface samples, ground
truth in grey, predictions coloured by class, each matched pair labelled with its F1 at 5 cm.

    python -m frodo_bringup.result_figure out/demo bags/demo_walk.mcap out/demo/result.png

`frodo demo` writes it as DIR/result.png.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence


from frodo_common.evaluation import EvalObject, EvaluationResult, sample_surface

CLASS_COLOURS = {'chair': '#f28c26', 'dining table': '#3399f2'}
SAMPLES = 1500


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
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


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
