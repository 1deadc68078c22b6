"""The `frodo` command: one entry point, one subcommand per module.

Subcommands live in modules exposing `add_arguments(parser)` and `run(args) -> int`, listed in
`SUBCOMMANDS`. Only the chosen subcommand's module is imported, so `frodo --help` stays fast; a
subcommand whose module is not installed is left out and named in the help's epilog.
"""
from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys
from typing import Sequence

# name: (module, one-line summary), in the order `frodo --help` lists them.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    'run': ('frodo_bringup.cli_run', 'Reconstruct a bag: launch the graph, play, wait until done, write outputs.'),
    'reconstruct': ('frodo_bringup.cli_reconstruct', 'Reconstruct a bag offline, deterministic, without ROS processes.'),
    'launch': ('frodo_bringup.cli_launch', 'Start the node graph (one process per node) until Ctrl-C.'),
    'play': ('frodo_bringup.cli_play', 'Publish a contract bag (ROS 2 MCAP) on the live graph.'),
    'record': ('frodo_bringup.cli_record', 'Record live topics into a rosbag2-compatible MCAP file.'),
    'params': ('frodo_bringup.cli_params', 'Print (or --write) the parameter YAML generated from the nodes.'),
    'synth': ('frodo_datasets.cli_synth', 'Render a synthetic scene into a contract bag with ground truth.'),
    'convert': ('frodo_datasets.cli_convert', 'Convert a ScanNet, Redwood, TUM RGB-D sequence or your own folder into a contract bag.'),
    'eval': ('frodo_bringup.cli_eval', 'Score objects.json against ground truth (CONTRACT.md protocol).'),
    'train': ('frodo_shape.cli_train', 'Train a shape prior (joint SDF + point decoder).'),
    'bench': ('frodo_bringup.cli_bench', 'Benchmarks: decoder, optimiser, association, demo run; JSON + plots.'),
    'report': ('frodo_bringup.cli_report', 'Run the evaluation sets offline and write the results page (docs/results.md).'),
    'demo': ('frodo_bringup.cli_demo', 'Reconstruct the demo bag (or a fresh synthetic scene) and score it against its ground truth.'),
}


def module_available(module: str) -> bool:
    """True when `module` can be imported (checked without importing it)."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    """The `frodo` parser; only the `selected` subcommand's module is imported to add its arguments."""
    available = {name: spec for name, spec in SUBCOMMANDS.items() if module_available(spec[0])}
    missing = [f'{name} ({spec[0]})' for name, spec in SUBCOMMANDS.items() if name not in available]
    epilog = 'Run `frodo COMMAND --help` for the options of a command.'
    if missing:
        epilog += ' Not installed in this environment: ' + ', '.join(missing) + '.'
    parser = argparse.ArgumentParser(prog='frodo', description='FroDO: From Detections to 3D Objects (ROS 2).',
                                     epilog=epilog)
    commands = parser.add_subparsers(dest='command', metavar='COMMAND')
    for name, (module_name, summary) in available.items():
        sub = commands.add_parser(name, help=summary, description=summary)
        if name == selected:
            module = importlib.import_module(module_name)
            module.add_arguments(sub)
            sub.set_defaults(run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse the command line and run the chosen subcommand; returns its exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    selected = argv[0] if argv and argv[0] in SUBCOMMANDS else None
    if selected is not None and not module_available(SUBCOMMANDS[selected][0]):
        print(f'frodo: error: command {selected!r} is not available here '
              f'(module {SUBCOMMANDS[selected][0]} is not installed)', file=sys.stderr)
        return 2
    parser = build_parser(selected)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    return int(args.run(args) or 0)


if __name__ == '__main__':
    sys.exit(main())
