"""`frodo params`: the ROS 2 parameter YAML generated from the nodes' PARAMS (the shipped config/frodo.yaml)."""
from __future__ import annotations

import argparse
import sys

from frodo_bringup.graph import ALL_NODES, GraphError, params_yaml, select_nodes, source_config_path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `frodo params`."""
    action = parser.add_mutually_exclusive_group()
    action.add_argument('--write', action='store_true',
                        help=f'write it to the shipped file ({source_config_path()})')
    action.add_argument('--check', action='store_true',
                        help='exit 1 when the shipped file differs from the generated YAML')
    parser.add_argument('--nodes', metavar='A,B', type=lambda s: s.split(','),
                        help='only these nodes (printing only; --write and --check use the whole graph)')


def run(args: argparse.Namespace) -> int:
    """Print, write or check the parameter YAML; 0 on success."""
    try:
        text = params_yaml(select_nodes(None if args.write or args.check else args.nodes, ALL_NODES))
    except GraphError as err:
        print(f'frodo params: error: {err}', file=sys.stderr)
        return 2
    path = source_config_path()
    if args.write:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        print(f'frodo params: wrote {path}', file=sys.stderr)
    elif args.check:
        if not path.is_file() or path.read_text() != text:
            print(f'frodo params: {path} is out of date; run `frodo params --write`', file=sys.stderr)
            return 1
        print(f'frodo params: {path} is up to date', file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0
