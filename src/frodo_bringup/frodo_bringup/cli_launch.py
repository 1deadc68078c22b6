"""`frodo launch`: start the node graph, one process per node, until Ctrl-C / SIGTERM or a failure.

It says when the graph is ready (every node up and subscribed; also on /diagnostics as `frodo_launch`)
and names nodes that came up after frames had entered the graph (see `readiness.GraphMonitor`)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from frodo_bringup.graph import (AUTO_OPTIM_WORKERS, NODES, GraphError, GraphNode, optimiser_workers, parse_node_spec,
                                 select_nodes, with_nodes, with_optimiser_parameters)
from frodo_bringup.launcher import FAILURE_POLICIES, Launcher, describe_returncode
from frodo_bringup.readiness import GraphMonitor
from frodo_bringup.session import RosSession, stop_on_signals


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `frodo launch`."""
    parser.add_argument('--params', action='append', default=[], metavar='FILE',
                        help='ROS 2 parameter YAML overriding the defaults, or a shipped preset by name (keyframes) (repeatable; later files win); '
                             'see `frodo params` for every parameter')
    parser.add_argument('--nodes', metavar='A,B', type=lambda s: s.split(','),
                        help=f'comma-separated subset of the graph ({",".join(n.name for n in NODES)}) '
                             'and of the --add-node names')
    parser.add_argument('--add-node', action='append', default=[], metavar='NAME=MODULE',
                        help='also start MODULE.main() as node NAME (repeatable); a graph node\'s name replaces '
                             'it, e.g. detection_node=my_pkg.my_detector')
    parser.add_argument('--on-failure', choices=FAILURE_POLICIES, default='stop',
                        help='when a node dies: stop the graph, restart the node (3 tries), or ignore it '
                             '(default: %(default)s)')
    parser.add_argument('--log-dir', metavar='DIR', help='also write each node\'s output to DIR/<node>.log')
    add_optimiser_arguments(parser)


def add_optimiser_arguments(parser: argparse.ArgumentParser) -> None:
    """--optim-workers, --map-dir, --resume (shared by `frodo launch` and `frodo run`)."""
    parser.add_argument('--optim-workers', default='auto', metavar='N',
                        help='run N optimiser processes (optim_node, optim_node_1 ... optim_node_<N-1>), worker k '
                             'taking the objects with id %% N == k, each with 1/N of the CPUs; optim_node merges '
                             'their shares into the complete /frodo/objects and reports for all of them; '
                             f'auto: {AUTO_OPTIM_WORKERS} where there are {AUTO_OPTIM_WORKERS} CPUs or more, else 1 '
                             '(default: %(default)s)')
    parser.add_argument('--map-dir', metavar='DIR',
                        help='the optimiser saves its object map (objects.json + meshes/) to DIR after each '
                             'published stage (DIR/worker_<k>/ with several workers)')
    parser.add_argument('--resume', metavar='DIR',
                        help='the optimiser starts from the object map in DIR (also each time it is restarted) '
                             'and saves to DIR unless --map-dir names another folder')


def optimiser_nodes(nodes: tuple[GraphNode, ...], args: argparse.Namespace) -> tuple[GraphNode, ...]:
    """`nodes` with the optimiser split into --optim-workers workers, saving to --map-dir, resuming --resume."""
    resume = str(Path(args.resume).resolve()) if args.resume else None
    map_dir = str(Path(args.map_dir).resolve()) if args.map_dir else resume
    return with_optimiser_parameters(optimiser_workers(nodes, args.optim_workers), map_dir=map_dir, resume=resume)


def run(args: argparse.Namespace) -> int:
    """Start the graph and return when it is down: 0 when no node failed, 1 otherwise, 2 on bad options."""
    try:
        graph = with_nodes(NODES, [parse_node_spec(spec) for spec in args.add_node])
        launcher = Launcher(optimiser_nodes(select_nodes(args.nodes, graph), args), args.params,
                            on_failure=args.on_failure,
                            log_dir=args.log_dir)
    except GraphError as err:
        print(f'frodo launch: error: {err}', file=sys.stderr)
        return 2
    with stop_on_signals(on_repeat=launcher.kill) as stop, RosSession('frodo_launch') as session:
        GraphMonitor(session.node, launcher.node_names, launcher.log, pids=lambda: launcher.pids)
        launcher.start()
        launcher.log(f'started: {", ".join(launcher.node_names)} (Ctrl-C to stop, twice to kill); '
                     "play a bag once the graph is ready (frodo play --wait-ready)")
        stopping = False
        while not launcher.wait(0.1):
            if stop.is_set() and not stopping:
                launcher.shutdown(timeout=0)
                stopping = True
    for name in dict.fromkeys(f.name for f in launcher.failures):
        failures = [f for f in launcher.failures if f.name == name]
        times = f' ({len(failures)} times)' if len(failures) > 1 else ''
        launcher.log(f'FAILED: {name} {describe_returncode(failures[-1].returncode)}{times}')
    launcher.log('graph down')
    return launcher.returncode
