"""`frodo bench` finds what it reads (the demo bag, bench/ scripts) relative to the working directory, as `frodo
demo` does, never through its own file's location: installed (colcon's install/, site-packages) there is no
repository above the module, and `Path(__file__).parents[3]` pointed into the install tree."""
from __future__ import annotations

import ast
import importlib.util
import json
import shutil
from pathlib import Path

import pytest

from frodo_bringup import bench, cli, cli_demo

REPO = Path(__file__).resolve().parents[1]


def test_bench_module_does_not_locate_files_from_its_own_path():
    tree = ast.parse(Path(bench.__file__).read_text())
    names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    assert '__file__' not in names and not hasattr(bench, 'REPO')
    assert bench.DEMO_BAG == cli_demo.DEFAULT_BAG and not bench.DEMO_BAG.is_absolute()


def test_an_installed_copy_finds_the_bag_and_scripts_of_the_working_directory(tmp_path, monkeypatch):
    """bench.py copied where an install puts it: run from the repository root, it finds the same files."""
    site = tmp_path / 'install' / 'frodo_bringup' / 'lib' / 'python3.12' / 'site-packages' / 'frodo_bringup'
    site.mkdir(parents=True)
    shutil.copy(bench.__file__, site / 'bench.py')
    spec = importlib.util.spec_from_file_location('installed_frodo_bench', site / 'bench.py')
    installed = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(installed)
    monkeypatch.chdir(REPO)
    assert installed.demo_bag() == REPO / 'bags' / 'demo_walk.mcap'
    assert installed.load_bench_script('bench_sparse') is not None
    monkeypatch.chdir(tmp_path)
    assert installed.load_bench_script('bench_sparse') is None
    assert installed.optimiser_sweep('bench_sparse', [5], 1, 1, 'cpu') == {'skipped': 'bench/bench_sparse.py not found'}
    with pytest.raises(FileNotFoundError, match=r'bags/demo_walk\.mcap not found .*pass --bag'):
        installed.demo_bag()


def test_frodo_bench_elsewhere_takes_bag_and_out_relative_to_the_working_directory(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    shutil.copy(REPO / 'bags' / 'demo_walk.mcap', tmp_path / 'walk.mcap')
    assert cli.main(['bench', '--quick', '--only', 'bag_read', '--bag', 'walk.mcap', '--out', 'o',
                     '--device', 'cpu']) == 0
    doc = json.loads((tmp_path / 'o' / 'bench.json').read_text())
    assert doc['bag_read']['bag'] == 'walk.mcap' and doc['bag_read']['messages'] == 211
    # Without --bag and no bags/ here: the section says why, the run exits 1, the other sections still run.
    assert cli.main(['bench', '--quick', '--only', 'bag_read', 'sparse', '--out', 'p', '--device', 'cpu']) == 1
    doc = json.loads((tmp_path / 'p' / 'bench.json').read_text())
    assert doc['bag_read']['error'].startswith('FileNotFoundError: bags/demo_walk.mcap not found in ')
    assert doc['sparse']['skipped'] == 'bench/bench_sparse.py not found'
    capsys.readouterr()


def test_frodo_bench_help(capsys):
    with pytest.raises(SystemExit) as exit_:
        cli.main(['bench', '--help'])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert '--bag' in out and '--out' in out
