"""The `frodo` command line: every subcommand has a working --help, missing ones are named, not crashed on."""
from __future__ import annotations

import subprocess
import sys
import time

import pytest

from frodo_bringup import cli

AVAILABLE = [name for name, (module, _) in cli.SUBCOMMANDS.items() if cli.module_available(module)]


def test_top_level_help_is_fast_and_lists_commands():
    started = time.monotonic()
    proc = subprocess.run([sys.executable, '-m', 'frodo_bringup.cli', '--help'], capture_output=True, text=True,
                          timeout=30)
    assert proc.returncode == 0
    assert time.monotonic() - started < 5  # no subcommand module (torch, rclpy) is imported
    for name in ('run', 'launch', 'play', 'record', 'params'):
        assert name in proc.stdout


@pytest.mark.parametrize('name', AVAILABLE)
def test_every_subcommand_has_help(name, capsys):
    with pytest.raises(SystemExit) as exit_:
        cli.main([name, '--help'])
    assert exit_.value.code == 0
    assert f'usage: frodo {name}' in capsys.readouterr().out


def test_no_command_prints_help(capsys):
    assert cli.main([]) == 2
    assert 'COMMAND' in capsys.readouterr().out


def test_missing_subcommand_module_is_reported(monkeypatch, capsys):
    monkeypatch.setitem(cli.SUBCOMMANDS, 'ghost', ('frodo_bringup.no_such_module', 'Not there.'))
    assert cli.main(['ghost']) == 2
    assert 'frodo_bringup.no_such_module is not installed' in capsys.readouterr().err
    assert 'ghost (frodo_bringup.no_such_module)' in cli.build_parser().epilog
