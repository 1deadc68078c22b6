"""`frodo report`: run the evaluation sets through the offline pipeline and write the results page.

    frodo report                                   # every set -> docs/results.md, pictures in docs/results/
    frodo report --sets demo,heldout-walks --limit 1
    frodo report --page /tmp/results.md --work /tmp/report --params my.yaml

Run it from a checkout (the demo bags are read from bags/, the public real bags from data/real/build/). See
`frodo_bringup.report` for the sets and how results are stored and reused.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from frodo_bringup.report import DEFAULT_PAGE, DEFAULT_WORK, REPORT_SETS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `frodo report`."""
    parser.add_argument('--sets', default=','.join(REPORT_SETS), metavar='NAMES',
                        help=f'comma-separated, from: {", ".join(REPORT_SETS)} (default: all)')
    parser.add_argument('--page', type=Path, default=DEFAULT_PAGE, help='results page to write (default: %(default)s)')
    parser.add_argument('--work', type=Path, default=DEFAULT_WORK,
                        help='bags, runs and stored results, per commit (default: %(default)s)')
    parser.add_argument('--params', action='append', default=[], metavar='FILE',
                        help='parameter YAML or shipped preset for every bag (repeatable; later files win)')
    parser.add_argument('--limit', type=int, default=None, metavar='N', help='at most N bags per set')
    parser.add_argument('--commit', default=None, metavar='KEY',
                        help='use (and resume) the results stored under KEY (a directory of --work) instead of the '
                             "checkout's commit, e.g. to re-render after a commit that changed only documents")
    parser.epilog = 'Exit code: 0 page written, 1 a bag failed (the page says which), 2 bad arguments.'


def run(args: argparse.Namespace) -> int:
    """Write the page; returns the exit code."""
    from frodo_common.host import reproducible_math
    reproducible_math()                       # before torch is imported (see frodo_common.host)
    from frodo_bringup.report import report
    names = [n.strip() for n in args.sets.split(',') if n.strip()]
    command = ' '.join(['frodo report', *sys.argv[2:]]) if sys.argv[1:2] == ['report'] else 'frodo report'
    try:
        failed = report(names, page=args.page, work=args.work, params=args.params, limit=args.limit,
                        command=command, log=lambda line: print(line, flush=True), commit=args.commit)
    except ValueError as err:
        print(f'frodo report: error: {err}', file=sys.stderr)
        return 2
    for line in failed:
        print(f'frodo report: failed: {line}', file=sys.stderr)
    return 1 if failed else 0
