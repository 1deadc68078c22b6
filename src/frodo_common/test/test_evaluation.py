"""Evaluation protocol (CONTRACT.md) on analytic cases: identity, concentric spheres, shifted cube,
matching gate and class, recall and false positives, loaders."""
import json

import numpy as np
import pytest
import trimesh

from frodo_common.evaluation import (EvalObject, EvaluationError, evaluate, load_ground_truth, load_mesh_folder,
                                     load_predictions, match)


def _box(shift=(0.0, 0.0, 0.0), size=1.0) -> trimesh.Trimesh:
    mesh = trimesh.creation.box((size, size, size))
    mesh.apply_translation(shift)
    return mesh


def _sphere(radius: float, centre=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    mesh.apply_translation(centre)
    return mesh


def test_identical_meshes_score_perfectly():
    mesh = _box()
    r = evaluate([EvalObject(7, 'chair', mesh)], [EvalObject(1, 'chair', mesh.copy())])
    p = r.pairs[0]
    assert (p.pred_id, p.gt_id) == (7, 1)
    assert p.cd_cm == pytest.approx(0.0, abs=1e-9)
    assert p.f1 == p.acc == p.comp == 100.0
    assert r.overall.recall == 100.0 and r.overall.false_positives == 0


def test_concentric_spheres_cd_equals_radius_gap():
    # Every point of one sphere is 10 cm from the other surface; sampling adds < 1 mm here.
    r = evaluate([EvalObject(1, 'chair', _sphere(0.6))], [EvalObject(1, 'chair', _sphere(0.5))])
    p = r.pairs[0]
    assert p.accuracy_m == pytest.approx(0.1, abs=0.002)
    assert p.completion_m == pytest.approx(0.1, abs=0.002)
    assert p.cd_cm == pytest.approx(10.0, abs=0.2)
    assert p.acc == p.comp == p.f1 == 0.0
    close = evaluate([EvalObject(1, 'chair', _sphere(0.53))], [EvalObject(1, 'chair', _sphere(0.5))]).pairs[0]
    assert close.cd_cm == pytest.approx(3.0, abs=0.2)
    assert close.f1 > 99.0


def test_shifted_cube_matches_analytic_surface_distance():
    # Unit cube shifted by d along x. Point-to-surface distances of the shifted cube's points:
    # +x face: d; -x face (inside): min(d, distance to a side face) -> mean (1 - (1 - 2d)^3) / 6;
    # side faces: 0 where they overlap, (x - 0.5) on the protruding strip of width d -> 4 * d * d / 2.
    d = 0.3
    expected = (d + (1 - (1 - 2 * d) ** 3) / 6 + 2 * d * d) / 6
    within = (4 * (1 - d + 0.05) + 1 - (1 - 0.1) ** 2) / 6  # area fraction within 5 cm
    p = evaluate([EvalObject(1, 'chair', _box((d, 0, 0)))], [EvalObject(2, 'chair', _box())]).pairs[0]
    # Sample-to-sample distances exceed point-to-surface ones by the sample spacing (< 1 cm for 10k points).
    assert expected < p.accuracy_m < expected + 0.01
    assert expected < p.completion_m < expected + 0.01  # symmetric configuration
    assert p.acc == pytest.approx(100 * within, abs=2.0)
    assert p.f1 == pytest.approx(100 * within, abs=2.0)


def test_gate_class_and_counts():
    gt = [EvalObject(1, 'chair', _box((0, 0, 0))), EvalObject(2, 'chair', _box((3, 0, 0))),
          EvalObject(3, 'dining table', _box((0, 3, 0)))]
    pred = [EvalObject(10, 'chair', _box((0.1, 0, 0))),           # matches GT 1
            EvalObject(11, 'chair', _box((3.6, 0, 0))),           # 0.6 m from GT 2: beyond the gate
            EvalObject(12, 'dining table', _box((0, 0, 0.05))),   # near GT 1 but wrong class
            EvalObject(13, 'dining table', _box((0, 3.2, 0)))]    # matches GT 3
    r = evaluate(pred, gt, n_samples=2000)
    assert sorted((p.pred_id, p.gt_id) for p in r.pairs) == [(10, 1), (13, 3)]
    assert r.unmatched_gt == [2] and r.unmatched_pred == [11, 12]
    assert r.overall.n_matched == 2 and r.overall.false_positives == 2
    assert r.overall.recall == pytest.approx(100 * 2 / 3)
    assert r.per_class['chair'].recall == 50.0 and r.per_class['chair'].false_positives == 1
    assert r.per_class['dining table'].recall == 100.0 and r.per_class['dining table'].false_positives == 1
    table = r.table()
    assert 'overall' in table and 'missed ground truth ids: [2]' in table


def test_hungarian_maximises_matches_then_distance():
    # Greedy nearest would pair pred 1 with GT 1 (0.1 m) and leave GT 2 unmatched (pred 2 is 0.6 m from it).
    gt = [EvalObject(1, 'chair', _sphere(0.2, (0, 0, 0))), EvalObject(2, 'chair', _sphere(0.2, (0.45, 0, 0)))]
    pred = [EvalObject(1, 'chair', _sphere(0.2, (0.1, 0, 0))), EvalObject(2, 'chair', _sphere(0.2, (-0.15, 0, 0)))]
    pairs = match(pred, gt)
    assert sorted(pairs) == [(0, 1), (1, 0)]


def test_empty_inputs_and_duplicate_ids():
    r = evaluate([], [EvalObject(1, 'chair', _box())])
    assert r.overall.recall == 0.0 and r.overall.cd_cm is None and r.unmatched_gt == [1]
    with pytest.raises(EvaluationError):
        evaluate([EvalObject(1, 'chair', _box()), EvalObject(1, 'chair', _box())], [])


def test_loaders(tmp_path):
    out = tmp_path / 'out'
    (out / 'meshes').mkdir(parents=True)
    _box((0.02, 0, 0)).export(out / 'meshes' / '4_dining_table.ply')
    _box().export(out / 'meshes' / '5_chair.ply')
    (out / 'objects.json').write_text(json.dumps({'frame_id': 'world', 'objects': [
        {'id': 4, 'class': 'dining table', 'mesh': 'meshes/4_dining_table.ply'},
        {'id': 5, 'class': 'chair'},                    # mesh path by convention
        {'id': 6, 'class': 'chair', 'mesh': None}]}))   # no mesh: not scorable, skipped
    pred = load_predictions(out)
    assert [(o.id, o.class_name) for o in pred] == [(4, 'dining table'), (5, 'chair')]
    gt = load_ground_truth(out / 'meshes')
    assert [(o.id, o.class_name) for o in gt] == [(4, 'dining table'), (5, 'chair')]
    assert load_mesh_folder(out / 'meshes')[0].mesh.faces.shape[1] == 3
    with pytest.raises(EvaluationError, match='objects.json'):
        load_predictions(tmp_path / 'missing')
    with pytest.raises(EvaluationError):
        load_ground_truth(tmp_path / 'missing.mcap')


def test_ground_truth_from_bag(tmp_path):
    from visualization_msgs.msg import MarkerArray

    from frodo_common.bag import BagWriter, qos_yaml
    from frodo_common.conversions import delete_marker, mesh_to_marker

    box = _box((1.0, 2.0, 0.5))
    sphere = _sphere(0.3)
    path = tmp_path / 'gt.mcap'
    with BagWriter(path) as bag:
        bag.add_topic('/ground_truth/objects', 'visualization_msgs/msg/MarkerArray',
                      qos_yaml(transient_local=True, depth=1))
        bag.write('/ground_truth/objects', MarkerArray(markers=[
            mesh_to_marker(box.vertices, box.faces, 'chair', 3, 10, 'world'),
            mesh_to_marker(sphere.vertices, sphere.faces, 'dining table', 8, 10, 'world'),
            delete_marker('dining table', 8, 10, 'world')]), 10)
    gt = load_ground_truth(path)
    assert [(o.id, o.class_name) for o in gt] == [(3, 'chair')]
    assert np.allclose(gt[0].mesh.bounds, box.bounds)
    r = evaluate([EvalObject(1, 'chair', box)], gt)
    assert r.pairs[0].cd_cm == pytest.approx(0.0, abs=1e-6)


def test_eval_command(tmp_path, capsys):
    cli_eval = pytest.importorskip('frodo_bringup.cli_eval')
    pred, gt = tmp_path / 'pred', tmp_path / 'gt'
    (pred / 'meshes').mkdir(parents=True)
    gt.mkdir()
    _box((0.01, 0, 0)).export(pred / 'meshes' / '1_chair.ply')
    _box().export(gt / '7_chair.ply')
    _box((3, 0, 0)).export(gt / '8_dining_table.ply')
    (pred / 'objects.json').write_text(json.dumps({'objects': [{'id': 1, 'class': 'chair',
                                                                 'mesh': 'meshes/1_chair.ply'}]}))
    assert cli_eval.main(['--pred', str(pred), '--gt', str(gt), '--samples', '2000']) == 0
    out = capsys.readouterr().out
    assert 'overall' in out and 'missed ground truth ids: [8]' in out
    report = json.loads((pred / 'eval.json').read_text())
    assert report['overall']['recall'] == 50.0 and report['pairs'][0]['gt_id'] == 7
    assert cli_eval.main(['--pred', str(pred), '--gt', str(gt), '--classes', 'chair',
                          '--json', str(tmp_path / 'chair.json')]) == 0
    assert json.loads((tmp_path / 'chair.json').read_text())['overall']['recall'] == 100.0
    assert cli_eval.main(['--pred', str(tmp_path / 'nothing'), '--gt', str(gt)]) == 1
