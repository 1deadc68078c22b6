"""`frodo demo` end to end: the real node graph (detection, association, shape, optimiser, one process each)
reconstructs the bundled demo bag, and the result is scored against the bag's ground truth."""
from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from frodo_bringup import cli_demo
from frodo_bringup.run import EXIT_OK
from frodo_common.evaluation import load_ground_truth

BAG = Path(__file__).resolve().parents[1] / 'bags' / 'demo_walk.mcap'


@pytest.mark.skipif(not BAG.exists(), reason='demo bag missing')
def test_demo_reconstructs_and_scores_the_demo_bag(tmp_path, capsys):
    out = tmp_path / 'demo'
    # the command's own 300 s bound: three dense starts per object take the demo to ~100 s on an idle 2-core VM
    # and past 120 s on a loaded CI runner (a chair still in its dense stage), which is slow, not wrong
    code = cli_demo.main(['--bag', str(BAG), '--out', str(out), '--no-progress'])
    printed = capsys.readouterr().out
    assert code == EXIT_OK, printed
    objects = json.loads((out / 'objects.json').read_text())['objects']
    assert objects and all((out / o['mesh']).is_file() for o in objects)
    assert (out / 'frodo.rrd').stat().st_size > 0 and (out / 'result.png').stat().st_size > 0
    report = json.loads((out / 'eval.json').read_text())
    n_gt = len(load_ground_truth(BAG))
    overall = report['overall']
    assert overall['n_gt'] == n_gt and overall['false_positives'] == 0, printed
    assert overall['n_matched'] >= n_gt - 1, printed          # at most one object missed
    tables = report['per_class']['dining table']
    assert tables['n_matched'] == tables['n_gt'] and tables['f1'] > 85.0, printed
    assert 'evaluation against the ground truth' in printed
    assert 'optimiser stages per object' in printed and 'stages: ' in printed   # final stage and reason per object
    assert re.search(r'\[frodo\] object \d+ \((chair|dining table)\): (fused|sparse|dense), ', printed), printed  # progress
