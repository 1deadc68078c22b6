"""bench/bench_stages.py: each stage of each matched object scored against the ground truth of a real bag."""
from __future__ import annotations

import importlib.util
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _bench():
    spec = importlib.util.spec_from_file_location('bench_stages', REPO / 'bench' / 'bench_stages.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_stage_of_the_orbit_bags_object_is_scored(capsys):
    bench = _bench()
    rows, line = bench.score_bag(str(REPO / 'bags' / 'demo_orbit.mcap'), None)
    assert line.startswith('demo_orbit.mcap: 1/1 found, 0 FP')
    (row,) = rows
    assert set(bench.STAGES) <= set(row)
    assert row['assoc_cm'] < 10 and row['dense']['centre_cm'] < 5
    # the orbit sees its object whole: each stage keeps the placement good, and dense is no worse than fused
    assert all(row[s]['f1'] > 90 and row[s]['centre_cm'] < 5 for s in bench.STAGES)
    assert row['dense']['f1'] >= row['fused']['f1']
    text = bench.object_line(row)
    assert 'fused c' in text and 'dense c' in text
    (pooled,) = [p for p in bench.pooled_lines(rows) if ' dense ' in p]
    assert pooled.split()[0] == row['class'].split()[0] and 'n   1' in pooled
