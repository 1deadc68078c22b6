"""`frodo run`: reconstruct a bag end to end and write `objects.json` and meshes (see `frodo_bringup.run`)."""
from __future__ import annotations

import argparse
import sys

from frodo_bringup.cli_launch import add_optimiser_arguments
from frodo_bringup.graph import GraphError
from frodo_bringup.player import PlayerError
from frodo_bringup.run import EXIT_GRAPH_FAILED, EXIT_INTERRUPTED, EXIT_NOT_DONE, run_bag
from frodo_bringup.session import stop_on_signals


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `frodo run`."""
    parser.add_argument('bag', metavar='BAG', help='ROS 2 MCAP bag (CONTRACT.md format)')
    parser.add_argument('--out', required=True, metavar='DIR',
                        help='output directory: objects.json, meshes/<id>_<class>.ply, logs/')
    parser.add_argument('--params', action='append', default=[], metavar='FILE',
                        help='ROS 2 parameter YAML overriding the defaults, or a shipped preset by name (keyframes: input of few views far apart) (repeatable)')
    parser.add_argument('--timeout', type=float, default=300.0, metavar='S',
                        help='after the bag has played, wait at most S s for the optimiser to finish '
                             '(default: %(default)s)')
    parser.add_argument('--rate', type=float, default=1.0,
                        help='playback speed factor; 0 = as fast as possible (default: %(default)s)')
    parser.add_argument('--viewer', choices=('none', 'rrd'), default='none',
                        help='rrd: also run the Rerun viewer node, saving DIR/frodo.rrd (ground truth included) '
                             '(default: %(default)s)')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')
    add_optimiser_arguments(parser)
    parser.epilog = (f'Exit code: 0 done, {EXIT_GRAPH_FAILED} a node failed, 2 bad arguments, {EXIT_NOT_DONE} '
                     f'timeout (outputs still written), {EXIT_INTERRUPTED} interrupted.')


def run(args: argparse.Namespace) -> int:
    """Run the reconstruction; returns the `frodo run` exit code."""
    with stop_on_signals() as stop:
        try:
            result = run_bag(args.bag, args.out, args.params, timeout=args.timeout, rate=args.rate,
                             viewer=args.viewer, stop=stop, progress=not args.no_progress,
                             optim_workers=args.optim_workers, map_dir=args.map_dir or args.resume,
                             resume=args.resume)
        except (PlayerError, GraphError) as err:
            print(f'frodo run: error: {err}', file=sys.stderr)
            return 2
    return result.exit_code
