"""`frodo eval`: score reconstructed objects against ground truth with the CONTRACT.md protocol.

    frodo eval --pred out/demo --gt bags/demo_walk.mcap [--json out/demo/eval.json]

`--pred` is a `frodo run --out` directory (objects.json + meshes/); `--gt` is a bag with
`/ground_truth/objects`, another output-style directory, or a folder of `<id>_<class>.ply` meshes.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from frodo_common.evaluation import (MATCH_GATE_M, N_SAMPLES, THRESHOLD_M, EvaluationError, evaluate,
                                     load_ground_truth, load_predictions)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `frodo eval`."""
    parser.add_argument('--pred', type=Path, required=True, help='output directory of `frodo run --out`')
    parser.add_argument('--gt', type=Path, required=True,
                        help='ground truth: bag (.mcap) with /ground_truth/objects, or a folder of meshes')
    parser.add_argument('--json', type=Path, default=None, help='write the full report here (default PRED/eval.json)')
    parser.add_argument('--classes', default=None,
                        help='comma-separated classes to score (default: every class in the ground truth)')
    parser.add_argument('--samples', type=int, default=N_SAMPLES, help=f'surface samples per mesh ({N_SAMPLES})')
    parser.add_argument('--threshold', type=float, default=THRESHOLD_M, help=f'F-score distance, m ({THRESHOLD_M})')
    parser.add_argument('--gate', type=float, default=MATCH_GATE_M, help=f'matching gate, m ({MATCH_GATE_M})')
    parser.add_argument('--seed', type=int, default=0, help='surface sampling seed (0)')


def run(args: argparse.Namespace) -> int:
    """Print the report table and write the JSON report. 0 on success, 1 when inputs cannot be read."""
    try:
        pred = load_predictions(args.pred)
        gt = load_ground_truth(args.gt)
    except EvaluationError as err:
        print(f'frodo eval: error: {err}', file=sys.stderr)
        return 1
    classes = ({c.strip() for c in args.classes.split(',') if c.strip()} if args.classes
               else {o.class_name for o in gt})
    pred = [o for o in pred if o.class_name in classes]
    gt = [o for o in gt if o.class_name in classes]
    result = evaluate(pred, gt, n_samples=args.samples, threshold=args.threshold, gate=args.gate, seed=args.seed)
    print(f'predictions: {args.pred}  ground truth: {args.gt}  classes: {", ".join(sorted(classes))}')
    print(result.table())
    out = args.json if args.json is not None else args.pred / 'eval.json'
    out.parent.mkdir(parents=True, exist_ok=True)
    report = result.to_dict()
    report['inputs'] = {'pred': str(args.pred), 'gt': str(args.gt), 'classes': sorted(classes)}
    out.write_text(json.dumps(report, indent=2) + '\n')
    print(f'report: {out}')
    return 0


def main(argv: list[str] | None = None) -> int:
    """`python -m frodo_bringup.cli_eval ...`"""
    parser = argparse.ArgumentParser(prog='frodo eval', description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == '__main__':
    sys.exit(main())
