"""`frodo bench` sections on tiny inputs: structure of the figures, optional scripts skipped with a note,
plots written; the figures themselves are measured by running `frodo bench`, not asserted here."""
from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

from frodo_bringup import bench, cli


def _bench_dense():
    spec = importlib.util.spec_from_file_location('bench_dense', Path(__file__).parents[1] / 'bench' / 'bench_dense.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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
    page = bench.markdown_page(doc | {'plots': ['optimiser.png']}, 'figures')
    assert page.startswith('# Performance') and doc['machine']['cpu'] in page
    assert '| 35 | 60.0 | 1.2x |' in page                 # the paper's 70 ms per sparse iteration against 60 ms
    assert f"| 2 | {row['detections_per_frame']} |" in page and '![optimiser.png](figures/optimiser.png)' in page
    assert 'with depth images' not in page
    dense = {'rows': [{'views': 35, 'ms_per_iteration': 80.0, 'ms_per_iteration_depth': 95.0}]}
    page = bench.markdown_page(doc | {'dense': dense}, 'figures')     # an RGB-D bag's cost in a column of its own
    assert '| views | ms per iteration | paper (GPU) / this | with depth images: ms |' in page
    assert '| 35 | 80.0 | 62.0x | 95.0 |' in page
    assert '35 views 80.0 ms (95.0 with depth)' in bench.summary(doc | {'dense': dense})


def test_frodo_bench_writes_json(tmp_path, capsys):
    assert cli.main(['bench', '--quick', '--only', 'bag_read', '--out', str(tmp_path), '--device', 'cpu']) == 0
    doc = json.loads((tmp_path / 'bench.json').read_text())
    assert doc['quick'] and doc['bag_read']['bag'] == 'demo_walk.mcap' and doc['machine']['device'] == 'cpu'
    assert 'bag read+decode' in capsys.readouterr().out
    page = tmp_path / 'docs' / 'performance.md'
    assert cli.main(['bench', '--quick', '--only', 'association', '--out', str(tmp_path / 'b'), '--device', 'cpu',
                     '--page', str(page)]) == 0
    assert '## Association per frame' in page.read_text() and (tmp_path / 'docs' / 'performance' / 'association.png').exists()


def test_dense_bench_oracle_code_is_the_true_shape_in_its_object_frame(tmp_path):
    """`bench_dense.py stages --code oracle`: the ground-truth mesh is brought to its object frame with the
    sidecar's true pose before the auto-decoder fit, so the prior fits it as it fits its own shapes (a wrong
    frame, e.g. a yaw left in, fits far worse)."""
    import pytest
    from frodo_common.evaluation import load_ground_truth_bag
    from frodo_datasets.synth import SynthConfig, sidecar_path, synthesize
    from frodo_shape.prior import ShapePrior

    bench_dense = _bench_dense()
    bag = tmp_path / 'room.mcap'
    synthesize(SynthConfig(scene='orbit', objects=1, classes=('chair',), frames=2, width=64, height=48, seed=3), bag)
    (gt,) = load_ground_truth_bag(bag)
    prior = ShapePrior.load('furniture')
    _, fit = bench_dense.oracle_code(prior, bag, gt.id, gt.mesh, steps=150)
    assert fit['f1'] > 88          # 92 here; the same fit without the rotation of the true pose: 82
    sidecar_path(bag).unlink()
    with pytest.raises(SystemExit, match='gt.json'):
        bench_dense.oracle_code(prior, bag, gt.id, gt.mesh)


def test_dense_bench_opacity_reads_one_row_per_family_and_every_resolution(capsys):
    """`bench_dense.py opacity`: with one shape per class, one row per class, H per resolution within [0, 1]."""
    bench_dense = _bench_dense()
    bench_dense.main(['opacity', '--prior', 'furniture', '--shapes', '1', '--rays', '40', '--resolutions', '24,48'])
    rows = capsys.readouterr().out.splitlines()[2:]
    assert sorted(row[:14].strip() for row in rows) == ['chair', 'dining table']
    for row in rows:
        cells = re.findall(r'(\d\.\d\d) \(\s*(\d+)%\)', row)
        assert len(cells) == 2
        assert all(0.0 <= float(h) <= 1.0 and 0 <= int(share) <= 100 for h, share in cells)


def test_stage_counts_add_up_and_are_stated_against_the_roofline(tmp_path):
    """`stages` on the demo bag with few iterations: every optimiser stage that ran has its counts, the SDF
    queries per iteration follow from the totals and the rate is a fraction of the measured roofline."""
    from frodo_bringup.testing import FAST_OPTIM_PARAMS
    params = tmp_path / 'fast.yaml'
    params.write_text(FAST_OPTIM_PARAMS)
    limits = bench.roofline('cpu', quick=True)
    assert limits['matmul_gflops'] > 0 and limits['sdf_forward_gflops'] > 0
    doc = bench.pipeline_stages(bench.DEMO_BAG, 'cpu', limits, params=[params])
    rows = {r['stage']: r for r in doc['rows']}
    assert set(rows) == {'fused', 'sparse', 'dense'} and rows['fused']['objects'] == 4
    for name in ('sparse', 'dense'):
        row = rows[name]
        assert row['iterations'] > 0 and row['sdf_queries'] > 0 and row['gflop'] > 0
        assert row['sdf_queries_per_iteration'] == round(row['sdf_queries'] / row['iterations'])
        assert 0 < row['fraction_of_matmul_peak'] < 1.5
    assert rows['sparse']['point_shapes'] > 0          # the sparse stage decodes points, the dense one SDFs
    assert rows['dense']['sdf_queries_with_grad'] > 0
    assert 'of the matmul peak' in bench.summary({'machine': bench.machine_info('cpu'), 'roofline': limits,
                                                  'stages': doc})


def test_stage_latencies_count_from_each_objects_confirmation():
    confirmed = {1: 10.0, 2: 12.0, 3: 20.0}
    reached = {1: {'code': 10.25, 'code_ready': 10.25, 'fused': 10.5, 'sparse': 14.0, 'dense': 30.0},
               2: {'code': 12.0, 'code_ready': 13.0, 'fused': 13.25, 'sparse': 18.0}}
    assert bench.stage_latencies(confirmed, reached) == {'code': [0.0, 0.25], 'code_ready': [0.25, 1.0],
                                                         'fused': [0.5, 1.25], 'sparse': [4.0, 6.0], 'dense': [20.0]}
    # a code that reached the probe before the object's track: confirmation is the code's arrival, never negative
    early = bench.stage_latencies({1: 10.0}, {1: {'code': 9.75, 'code_ready': 10.0, 'fused': 10.5}})
    assert early['code'] == [0.0] and early['code_ready'] == [0.25] and early['fused'] == [0.75]


def test_synthetic_room_section_times_frodo_reconstruct_and_reads_its_scores(tmp_path):
    room = bench.synthetic_room(tmp_path, objects=1, frames=12, seed=5)
    assert room['objects'] == room['ground_truth'] == 1 and room['frames'] == 12 and room['wall_s'] > 0
    assert 0 <= room['found'] <= 1 and (tmp_path / 'reconstruct' / 'eval.json').exists()
    doc = {'machine': bench.machine_info('cpu'), 'room': room}
    assert f"frodo reconstruct {room['wall_s']} s wall" in bench.summary(doc)
    assert '## Synthetic room of 1 objects' in bench.markdown_page(doc, 'figures')


def test_before_section_runs_a_commits_code_and_this_checkouts_on_one_bag(tmp_path):
    bag = tmp_path / 'room.mcap'
    cli.main(['synth', str(bag), '--objects', '1', '--frames', '12', '--seed', '5', '--quiet'])
    # HEAD: a commit every clone holds (BEFORE_SPEED_WORK is not in a shallow one)
    result = bench.before_and_now(bag, tmp_path / 'before', revision='HEAD')
    code = tmp_path / 'before' / 'code'
    assert result['code'] == str(code) and (code / 'src' / 'frodo_optim' / 'frodo_optim' / 'sparse.py').is_file()
    for run in (result['before'], result['now']):
        assert run['wall_s'] > 0 and run['ground_truth'] == 1
        assert sum(run['final_stages'].values()) == run['found'] + run['false_positives']
    assert result['speed_up'] == round(result['before']['wall_s'] / result['now']['wall_s'], 2)
    doc = {'machine': bench.machine_info('cpu'), 'before': result}
    assert f"({result['speed_up']}x)" in bench.summary(doc)
    assert '## Before the speed work (issue 28)' in bench.markdown_page(doc, 'figures')
    assert bench.before_and_now(bag, tmp_path / 'none', revision='0' * 40) == {
        'skipped': 'commit 0000000000 is not in a git checkout here (run from a full clone of the repository)'}


def test_dense_bench_timing_measures_colour_alone_and_with_depth(capsys):
    """`bench_dense.py timing`: one row per configuration from colour and masks, and one with depth images."""
    bench_dense = _bench_dense()
    bench_dense.main(['timing', '--views', '2', '--iterations', '1'])
    out = capsys.readouterr().out
    result = json.loads(out[out.index('{'):])
    assert [len(result[k]) for k in ('dense', 'dense_depth')] == [1, 1]
    assert all(result[k][0]['iterations'] == 1 and result[k][0]['seconds_per_iteration'] > 0
               for k in ('dense', 'dense_depth'))
