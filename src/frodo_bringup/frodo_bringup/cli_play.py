"""`frodo play`: publish a contract bag on the live graph (like `ros2 bag play`, without ROS 2 installed)."""
from __future__ import annotations

import argparse
import sys
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray

from frodo_bringup.player import REQUIRED_INPUTS, Player, PlayerError, parse_remaps
from frodo_bringup.readiness import launch_ready
from frodo_bringup.session import RosSession, stop_on_signals
from frodo_common import topics


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `frodo play`."""
    parser.add_argument('bag', metavar='BAG', help='ROS 2 MCAP bag (CONTRACT.md format)')
    parser.add_argument('--rate', type=float, default=1.0,
                        help='playback speed factor; 0 = as fast as possible (default: %(default)s)')
    parser.add_argument('--start-offset', type=float, default=0.0, metavar='S',
                        help='skip the first S seconds of the bag')
    parser.add_argument('--loop', action='store_true', help='play the bag again and again until Ctrl-C')
    parser.add_argument('--remap', nargs='+', default=[], metavar='FROM:=TO',
                        help='publish bag topic FROM on topic TO')
    parser.add_argument('--topics', nargs='+', metavar='TOPIC', help='play only these bag topics')
    parser.add_argument('--clock', action='store_true', help='publish bag time on /clock (for use_sim_time)')
    parser.add_argument('--ground-truth', action='store_true',
                        help='also publish /ground_truth/objects (evaluation only; left out by default)')
    parser.add_argument('--wait-subscribers', type=float, default=0.0, metavar='S',
                        help='before playing, wait up to S s for a subscriber on each of '
                             f'{", ".join(REQUIRED_INPUTS)} (those in the bag)')
    parser.add_argument('--wait-ready', type=float, default=0.0, metavar='S',
                        help='before playing, wait up to S s until `frodo launch` reports the graph ready '
                             '(every node up and subscribed)')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')


def run(args: argparse.Namespace) -> int:
    """Play the bag; 0 when everything was published, 1 when interrupted, 2 on bad options or a missing bag."""
    try:
        remaps = parse_remaps(args.remap)
    except PlayerError as err:
        return _fail(err)
    with RosSession('frodo_player') as session, stop_on_signals() as stop:
        try:
            player = Player(session.node, args.bag, rate=args.rate, start_offset=args.start_offset,
                            loop=args.loop, remaps=remaps, topics=args.topics, clock=args.clock,
                            ground_truth=args.ground_truth, progress=not args.no_progress)
        except PlayerError as err:
            return _fail(err)
        for problem in player.problems:
            print(f'frodo play: warning: {problem}', file=sys.stderr)
        missing = player.missing_required()
        if missing and args.topics is None:
            print(f'frodo play: warning: the bag has no message on required input(s) {", ".join(missing)} '
                  '(CONTRACT.md); the graph will produce nothing from it', file=sys.stderr)
        if args.wait_ready > 0 and not _wait_ready(session, args.wait_ready, stop):
            print(f'frodo play: warning: no "graph ready" from frodo launch within {args.wait_ready:g} s; '
                  'playing anyway', file=sys.stderr)
        if args.wait_subscribers > 0:
            unmatched = player.wait_for_subscribers(args.wait_subscribers, stop=stop)
            if unmatched:
                print(f'frodo play: warning: no subscriber on {", ".join(unmatched)}; playing anyway',
                      file=sys.stderr)
        stats = player.play(stop)
        player.close()
    print(f'frodo play: published {stats.total} messages on {len(stats.published)} topics in '
          f'{stats.seconds:.1f} s' + (' (interrupted)' if stats.interrupted else ''), file=sys.stderr)
    return 1 if stats.interrupted else 0


def _wait_ready(session: RosSession, timeout: float, stop: threading.Event) -> bool:
    """Wait until a `frodo launch` reports its graph ready on /diagnostics; False on timeout or stop."""
    ready = threading.Event()
    subscription = session.node.create_subscription(
        DiagnosticArray, topics.DIAGNOSTICS, lambda msg: ready.set() if launch_ready(msg) else None, 50)
    deadline = time.monotonic() + timeout
    while not ready.wait(0.1) and not stop.is_set() and time.monotonic() < deadline:
        pass
    session.node.destroy_subscription(subscription)
    return ready.is_set()


def _fail(err: Exception) -> int:
    print(f'frodo play: error: {err}', file=sys.stderr)
    return 2
