"""`frodo reconstruct`: the whole method on a bag, offline and deterministic, without ROS processes.

    frodo reconstruct bags/demo_walk.mcap --out out/offline
    frodo reconstruct BAG --out DIR --params my.yaml

Writes what `frodo run --out DIR --viewer rrd` writes (`objects.json`, `meshes/<id>_<class>.ply`, the Rerun
recording `frodo.rrd`) from the same layers the nodes use (`frodo_bringup.pipeline`), as fast as the machine
allows, and prints each object's stages as they end. A bag with `/ground_truth/objects` is also scored
(`eval.json`, `result.png`). The same bag and parameters give the same objects.json (timings aside).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from frodo_bringup.outputs import summary_table

EXIT_FAILED = 1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `frodo reconstruct`."""
    parser.add_argument('bag', metavar='BAG', type=Path, help='ROS 2 MCAP bag (CONTRACT.md format)')
    parser.add_argument('--out', required=True, type=Path, metavar='DIR', help='output directory')
    parser.add_argument('--params', action='append', default=[], metavar='FILE',
                        help='ROS 2 parameter YAML (node sections, as for `frodo run`) or a shipped preset name '
                             '(repeatable; later files win)')
    parser.add_argument('--threads', type=int, default=0, metavar='N',
                        help='torch CPU threads (default: torch\'s own choice)')
    parser.add_argument('--workers', default='auto', metavar='N',
                        help='processes that refine objects at the same time, each with threads / N torch threads '
                             '(default: %(default)s, as `frodo run --optim-workers`: 2 on two or more CPUs, '
                             'where two one-thread workers end sooner than one two-thread process; results depend '
                             'on N through the thread count only)')
    parser.add_argument('--quiet', action='store_true', help='no per-object progress lines')
    parser.add_argument('--no-recording', action='store_true', help='do not write the Rerun recording DIR/frodo.rrd')
    parser.epilog = 'Exit code: 0 done, 1 the bag cannot give objects or a layer failed, 2 bad arguments.'


def run(args: argparse.Namespace) -> int:
    """Reconstruct, write, score when the bag has ground truth; returns the exit code."""
    from frodo_common.host import reproducible_math
    reproducible_math()                       # before torch is imported: the same bag gives the same bits
    from frodo_bringup.cli_demo import score_outputs
    from frodo_bringup.pipeline import PipelineConfig, PipelineError, reconstruct
    from frodo_bringup.preflight import BagRefused
    from frodo_common.bag import BagError
    from frodo_bringup.graph import GraphError, optim_worker_count
    try:
        workers = optim_worker_count(args.workers, option='--workers')
    except GraphError as err:
        print(f'frodo reconstruct: error: {err}', file=sys.stderr)
        return 2
    if args.threads > 0:
        import torch
        torch.set_num_threads(args.threads)
    started = time.perf_counter()
    try:
        config = PipelineConfig.from_params_files(args.params)
        result = reconstruct(args.bag, config, progress=None if args.quiet else lambda line: print(line, flush=True),
                             workers=workers)
    except (BagRefused, PipelineError, BagError, GraphError, FileNotFoundError) as err:
        print(f'frodo reconstruct: error: {err}', file=sys.stderr)
        return EXIT_FAILED
    args.out.mkdir(parents=True, exist_ok=True)
    records = result.write(args.out)
    if not args.no_recording:
        from frodo_bringup.recording import write_recording
        from frodo_bringup.run import RECORDING_FILE
        write_recording(args.bag, result, args.out / RECORDING_FILE, tracks=result.tracks,
                        associations=result.associations)
    print(summary_table(records))
    for problem in result.problems:
        print(f'warning: {problem}')
    phases = ', '.join(f'{name} {secs:.1f} s' for name, secs in result.seconds.items())
    print(f'done: {result.frames} frames, {len(records)} objects, {time.perf_counter() - started:.1f} s ({phases}); '
          f'outputs in {args.out}')
    if result.has_ground_truth:
        score_outputs(args.out, args.bag, 'frodo reconstruct')
    return 0
