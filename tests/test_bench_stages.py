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


def test_every_stage_of_the_orbit_bags_object_is_scored(capsys, tmp_path):
    bench = _bench()
    rows, line, n_truth = bench.score_bag(str(REPO / 'bags' / 'demo_orbit.mcap'), None, figures=tmp_path)
    assert line.startswith('demo_orbit.mcap: 1/1 found, 0 FP') and n_truth == 1
    (row,) = rows
    assert row['gt'] == 1 and row['family'] == 'four_leg'      # from the bag's .gt.json sidecar
    assert [p.name for p in tmp_path.iterdir()] == ['demo_orbit_gt1.png']
    assert (tmp_path / 'demo_orbit_gt1.png').read_bytes()[:4] == b'\x89PNG'
    assert set(bench.STAGES) <= set(row)
    assert row['assoc_cm'] < 10 and row['dense']['centre_cm'] < 5
    # the orbit sees its object whole: each stage keeps the placement good, and dense is no worse than fused
    assert all(row[s]['f1'] > 90 and row[s]['centre_cm'] < 5 for s in bench.STAGES)
    assert row['dense']['f1'] >= row['fused']['f1']
    # a design the prior was trained on stays among its training codes (Er about 1 for those)
    assert all(0 < row[s]['code_er'] < 3 for s in bench.STAGES), {s: row[s]['code_er'] for s in bench.STAGES}
    text = bench.object_line(row)
    assert 'fused c' in text and 'dense c' in text
    (pooled,) = [p for p in bench.pooled_lines(rows) if ' dense ' in p]
    assert pooled.split()[0] == row['class'].split()[0] and 'n   1' in pooled


def test_the_object_figures_frame_points_along_the_view_from_its_cameras():
    import numpy as np
    from frodo_bringup.result_figure import view_frame
    centre = np.array([1.0, 2.0, 0.4])
    cameras = np.array([[1.0, -1.0, 1.5], [1.5, -0.8, 1.5]])          # south of the object, looking north
    R = view_frame(centre, cameras)
    assert np.allclose(R @ R.T, np.eye(3))
    along, across, up = R @ (np.array([1.0, 2.5, 0.4]) - centre)      # half a metre beyond it
    assert along > 0.49 and abs(across) < 0.1 and up == 0.0
    assert np.allclose(view_frame(centre, np.zeros((0, 3))), np.eye(3))   # no cameras: world axes


def test_the_oracle_scores_undo_a_shift_a_quarter_turn_and_a_scale():
    import numpy as np
    import trimesh
    bench = _bench()
    # an L of two boxes (no quarter-turn symmetry), standing on the floor
    truth = trimesh.util.concatenate([trimesh.creation.box((0.6, 0.2, 0.8)),
                                      trimesh.creation.box((0.2, 0.5, 0.8))])
    truth.apply_translation([1.0, 2.0, 0.4 - truth.bounds[0, 2]])
    assert bench.oracle_f1(truth, truth)['as_is'] == 100.0
    shifted = truth.copy().apply_translation([0.25, 0.0, 0.0])
    got = bench.oracle_f1(shifted, truth)
    assert got['as_is'] < 70 and got['centred'] == 100.0
    centre = truth.bounds.mean(0)
    turned = truth.copy().apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 0, 1], centre))
    got = bench.oracle_f1(turned, truth)
    assert got['centred'] < 90 and got['turned'] > 99.9
    bottom = [centre[0], centre[1], truth.bounds[0, 2]]
    grown = truth.copy().apply_transform(trimesh.transformations.scale_matrix(bench.ORACLE_SCALES[-1], bottom))
    got = bench.oracle_f1(grown, truth)
    assert got['centred'] < 90 and got['scaled'] > 99.9


def test_the_summary_counts_misses_as_zero_and_dense_seeds_each_run_the_set(tmp_path, capsys):
    import json
    bench = _bench()
    rows = [{'class': 'chair', 'fused': {'f1': 10.0}, 'sparse': {'f1': 50.0}, 'dense': {'f1': 80.0}},
            {'class': 'chair', 'fused': {'f1': 40.0}},
            {'class': 'dining table', 'fused': {'f1': 5.0}, 'sparse': {'f1': 70.0}}]
    got = bench.summary(rows, 4)
    assert got['found'] == 3 and got['chair'] == 60.0 and got['dining table'] == 70.0
    assert got['misses_as_0'] == (80 + 40 + 70) / 4
    out = tmp_path / 'rows.json'
    assert bench.main([str(REPO / 'bags' / 'demo_orbit.mcap'), '--dense-seeds', '0,1', '--json', str(out)]) == 0
    text = capsys.readouterr().out
    assert text.count('demo_orbit.mcap: 1/1 found') == 2
    assert '[dense seed 0] found 1/1' in text and '[dense seed 1] found 1/1' in text
    assert 'mean over dense seeds 0,1: found 1/1' in text
    assert sorted(r['dense_seed'] for r in json.loads(out.read_text())) == [0, 1]


def test_a_bag_where_nothing_is_found_is_reported_not_a_crash(tmp_path):
    from frodo_bringup.pipeline import PipelineConfig
    bench = _bench()
    params = tmp_path / 'none.yaml'
    params.write_text('optim_node:\n  ros__parameters:\n    min_views: 100000\n')   # no object is reconstructed
    rows, line, n_truth = bench.score_bag(str(REPO / 'bags' / 'demo_orbit.mcap'),
                                          PipelineConfig.from_params_files([params]), figures=tmp_path)
    assert rows == [] and n_truth == 1
    assert line.startswith('demo_orbit.mcap: 0/1 found, 0 FP, F1 -, missed [\'chair\']')
    assert (tmp_path / 'demo_orbit_gt1.png').is_file()         # the missed object is drawn alone
