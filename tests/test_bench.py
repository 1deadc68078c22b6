"""`frodo bench` sections on tiny inputs: structure of the figures, optional scripts skipped with a note,
plots written; the figures themselves are measured by running `frodo bench`, not asserted here."""
from __future__ import annotations

import json

from frodo_bringup import bench, cli


def test_sections_return_figures_and_plots_are_written(tmp_path):
    read = bench.bag_read_throughput(bench.DEMO_BAG)
    assert read['messages'] == 211 and read['messages_per_s'] > 0
    assoc = bench.association_latency([2], frames=12)
    (row,) = assoc['rows']
    assert row['objects'] == 2 and row['frames'] == 12
    assert row['total_ms']['mean'] >= row['association_ms']['mean'] > 0 and row['total_cpu_ms']['mean'] > 0
    assert bench.optimiser_sweep('bench_does_not_exist', [5], 1, 1, 'cpu') == {
        'skipped': 'bench/bench_does_not_exist.py not found'}
    doc = {'machine': bench.machine_info('cpu'), 'association': assoc,
           'sparse': {'rows': [{'views': 5, 'ms_per_iteration': 20.0}, {'views': 35, 'ms_per_iteration': 60.0}]}}
    assert bench.write_plots(doc, tmp_path) == ['optimiser.png', 'association.png']
    assert (tmp_path / 'association.png').stat().st_size > 0
    assert 'association,  2 objects' in bench.summary(doc)


def test_frodo_bench_writes_json(tmp_path, capsys):
    assert cli.main(['bench', '--quick', '--only', 'bag_read', '--out', str(tmp_path), '--device', 'cpu']) == 0
    doc = json.loads((tmp_path / 'bench.json').read_text())
    assert doc['quick'] and doc['bag_read']['bag'] == 'demo_walk.mcap' and doc['machine']['device'] == 'cpu'
    assert 'bag read+decode' in capsys.readouterr().out
