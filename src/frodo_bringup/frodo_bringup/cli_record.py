"""`frodo record`: record live topics into a rosbag2-compatible MCAP file until Ctrl-C / SIGTERM / --duration."""
from __future__ import annotations

import argparse
import sys
import time

from frodo_bringup.recorder import INFRASTRUCTURE_TOPICS, Recorder
from frodo_bringup.session import RosSession, stop_on_signals
from frodo_common.bag import BagError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `frodo record`."""
    parser.add_argument('out', metavar='OUT.mcap', help='output bag (overwritten)')
    parser.add_argument('topics', nargs='*', metavar='TOPIC', help='topics to record (subscribed as they appear)')
    parser.add_argument('--all', action='store_true',
                        help=f'record every topic except {", ".join(INFRASTRUCTURE_TOPICS)}')
    parser.add_argument('--duration', type=float, metavar='S', help='stop after S seconds')


def run(args: argparse.Namespace) -> int:
    """Record until stopped; 0 on success, 2 on bad options."""
    if not args.topics and not args.all:
        print('frodo record: error: name the topics to record or use --all', file=sys.stderr)
        return 2
    if not args.out.endswith('.mcap'):
        print(f'frodo record: error: output must be an .mcap file, got {args.out}', file=sys.stderr)
        return 2
    with RosSession('frodo_recorder') as session, stop_on_signals() as stop:
        try:
            recorder = Recorder(session.node, args.out, args.topics, all_topics=args.all)
        except (BagError, OSError) as err:
            print(f'frodo record: error: {err}', file=sys.stderr)
            return 2
        deadline = time.monotonic() + args.duration if args.duration is not None else None
        try:
            while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
                stop.wait(0.1 if deadline is None else max(0.0, min(0.1, deadline - time.monotonic())))
        finally:
            recorder.close()
    for problem in recorder.problems:
        print(f'frodo record: warning: {problem}', file=sys.stderr)
    counts = ', '.join(f'{topic} {n}' for topic, n in sorted(recorder.counts.items())) or 'no messages'
    print(f'frodo record: wrote {recorder.path} ({counts})', file=sys.stderr)
    return 0
