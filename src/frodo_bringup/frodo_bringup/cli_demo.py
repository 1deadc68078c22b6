"""`frodo demo`: reconstruct the bundled demo bag and score the result against its ground truth.

    frodo demo                                   # bags/demo_walk.mcap -> out/demo
    frodo demo --bag bags/demo_orbit.mcap --out out/orbit

One `frodo run` (graph + Rerun recording `DIR/frodo.rrd`), then `frodo eval` of `DIR` against the
bag's `/ground_truth/objects` with the CONTRACT.md protocol; the report goes to `DIR/eval.json`, a
top/front view of prediction vs ground truth to `DIR/result.png`.
`--synth SEED` renders a fresh walk scene first (`frodo synth`), so the demo also runs on a scene
nobody tuned on.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from frodo_bringup.graph import GraphError
from frodo_bringup.outputs import OBJECTS_FILE
from frodo_bringup.player import PlayerError
from frodo_bringup.result_figure import draw_result
from frodo_bringup.run import EXIT_OK, RECORDING_FILE, run_bag
from frodo_bringup.session import stop_on_signals
from frodo_common.evaluation import EvaluationError, evaluate, load_ground_truth, load_predictions

DEFAULT_BAG = Path('bags/demo_walk.mcap')
DEFAULT_OUT = Path('out/demo')
EVAL_FILE = 'eval.json'
FIGURE_FILE = 'result.png'


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `frodo demo`."""
    parser.add_argument('--bag', type=Path, default=DEFAULT_BAG,
                        help='contract bag with /ground_truth/objects (default: %(default)s)')
    parser.add_argument('--out', type=Path, default=DEFAULT_OUT, help='output directory (default: %(default)s)')
    parser.add_argument('--synth', type=int, default=None, metavar='SEED',
                        help='first render a new walk scene with this seed into OUT/scene.mcap and use it')
    parser.add_argument('--params', action='append', default=[], metavar='FILE',
                        help='ROS 2 parameter YAML overriding the defaults, or a shipped preset by name (keyframes: input of few views far apart) (repeatable)')
    parser.add_argument('--timeout', type=float, default=300.0, metavar='S',
                        help='wait at most S s after the bag for the optimiser (default: %(default)s)')
    parser.add_argument('--no-viewer', action='store_true', help=f'do not record OUT/{RECORDING_FILE}')
    parser.add_argument('--no-progress', action='store_true', help='no progress bars')


def _synthesise(seed: int, out: Path, progress: bool) -> Path:
    """Render a walk scene like the demo bag's (4 chairs/tables, 50 frames) into out/scene.mcap."""
    from frodo_datasets import cli_synth
    bag = out / 'scene.mcap'
    argv = [str(bag), '--scene', 'walk', '--objects', '4', '--frames', '50', '--seed', str(seed)]
    if not progress:
        argv.append('--quiet')
    code = cli_synth.main(argv)
    if code != 0:
        raise RuntimeError(f'frodo synth exited with {code}')
    return bag


def run(args: argparse.Namespace) -> int:
    """Run, evaluate, print both tables. Exit code: the run's, or 1 when evaluation failed."""
    args.out.mkdir(parents=True, exist_ok=True)
    bag = args.bag
    if args.synth is not None:
        bag = _synthesise(args.synth, args.out, progress=not args.no_progress)
    if not bag.exists():
        print(f'frodo demo: error: {bag} not found (run from the repository root, or pass --bag)', file=sys.stderr)
        return 2
    with stop_on_signals() as stop:
        try:
            result = run_bag(bag, args.out, args.params, timeout=args.timeout, rate=1.0,
                             viewer='none' if args.no_viewer else 'rrd', stop=stop, progress=not args.no_progress)
        except (PlayerError, GraphError) as err:
            print(f'frodo demo: error: {err}', file=sys.stderr)
            return 2
    if not score_outputs(args.out, bag, 'frodo demo'):
        return result.exit_code or 1
    if not args.no_viewer and result.exit_code == EXIT_OK:
        print(f'view it: rerun {args.out / RECORDING_FILE}')
    return result.exit_code


def score_outputs(out: Path, bag: Path, command: str) -> bool:
    """Score out/objects.json against the bag's ground truth: print the tables, write eval.json and result.png.
    False (with the reason printed) when there is nothing to score."""
    try:
        pred, gt = load_predictions(out), load_ground_truth(bag)
    except EvaluationError as err:
        print(f'{command}: evaluation failed: {err}', file=sys.stderr)
        return False
    report = evaluate(pred, gt)
    print(f'\nevaluation against the ground truth of {bag} (CONTRACT.md protocol):')
    print(report.table())
    print('\n' + stage_table(out, report))
    payload = report.to_dict()
    payload['inputs'] = {'pred': str(out), 'gt': str(bag)}
    (out / EVAL_FILE).write_text(json.dumps(payload, indent=2) + '\n')
    figure = draw_result(pred, gt, report, out / FIGURE_FILE, title=Path(bag).name)
    print(f'report: {out / EVAL_FILE}, picture: {figure}')
    return True


def stage_table(out: Path, report) -> str:
    """Optimiser stage each object ended at (fused -> sparse -> dense, paper Sec. 5.3), why, and its F1."""
    try:
        records = json.loads((out / OBJECTS_FILE).read_text()).get('objects', [])
    except (OSError, ValueError):
        return f'(no {OBJECTS_FILE}: no stage table)'
    f1 = {p.pred_id: p.f1 for p in report.pairs}
    header = f'{"id":>4}  {"class":<14} {"stage":<7} {"why":<30} {"optimiser s":>11} {"F1%":>6}'
    lines = ['optimiser stages per object:', header, '-' * len(header)]
    for r in records:
        secs = (r.get('timings') or {}).get('optimiser_s')
        secs_text = '-' if secs is None else f'{secs:.1f}'
        f1_text = f'{f1[r["id"]]:.1f}' if r['id'] in f1 else '-'
        why = (r.get('stage_reason') or '-')[:30]
        lines.append(f'{r["id"]:>4}  {r["class"][:14]:<14} {r.get("stage") or "-":<7} {why:<30} {secs_text:>11} {f1_text:>6}')
    counts = {st: sum(r.get('stage') == st for r in records) for st in ('fused', 'sparse', 'dense')}
    lines.append('stages: ' + ', '.join(f'{n} {st}' for st, n in counts.items()))
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    """`python -m frodo_bringup.cli_demo ...`"""
    parser = argparse.ArgumentParser(prog='frodo demo', description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == '__main__':
    sys.exit(main())
