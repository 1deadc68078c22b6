"""Inside-out walks (issue 27): the scene and trajectory statistics, the capture statistics tool on a case with a
known answer, the `realwalk` preset end to end, and eval_sets' runner option. Deterministic, seconds."""
import json
import sys

import numpy as np
import pytest
import trimesh

from frodo_common.geometry import look_at
from frodo_datasets import eval_sets
from frodo_datasets.capture_stats import (azimuth_range, bag_statistics, capture_statistics, pool_statistics,
                                          turns_and_baselines)
from frodo_datasets.realcapture import preset_kwargs
from frodo_datasets.render import intrinsics
from frodo_datasets.scene import InsideOutPath, compose_scene, footprints_overlap

SEED = 9205   # realwalk room 5 (5 objects)


@pytest.fixture(scope='module')
def walk():
    kw = preset_kwargs('realwalk')
    scene = compose_scene(5, eval_sets.WALK_CLASSES, seed=SEED, layout='perimeter', family_set='heldout',
                          tuck_chairs=kw['tuck_chairs'], clutter=0)
    path = InsideOutPath(scene, seed=SEED + 1)
    return scene, path, path.keyframes(35, seed=SEED + 1)


def test_furniture_along_the_walls_and_the_camera_in_the_middle(walk):
    scene, path, poses = walk
    half = np.asarray(scene.room_size) / 2
    for o in scene.objects:   # every object within 1.6 m of a wall, none across the middle
        assert np.min(half - np.abs(o.footprint).max(axis=0)) < 1.6
        assert np.all(np.abs(o.footprint) <= half + 1e-6)
    eyes = np.array([T[:3, 3] for T in poses])
    assert np.all(np.abs(eyes[:, :2]) < half - 0.3) and np.all((eyes[:, 2] > 1.2) & (eyes[:, 2] < 1.7))
    assert np.linalg.norm(eyes[:, :2], axis=1).max() < 2.2
    assert not any(path._inside_furniture(e, margin=0.0) for e in eyes)
    # looking outwards: the optical axis points away from the room centre
    assert np.mean([T[:2, 2] @ T[:2, 3] > -0.2 for T in poses]) > 0.8
    tables = [o for o in scene.objects if o.class_name == 'dining table']
    tucked = [c for c in scene.objects if c.class_name == 'chair'
              and any(footprints_overlap(c.footprint, t.footprint, 0.0) for t in tables)]
    assert len(tucked) >= 2
    assert np.allclose(InsideOutPath(scene, seed=SEED + 1).pose(7.3), path.pose(7.3))   # deterministic


def test_rotation_dominated_narrow_baseline_keyframes(walk):
    _, path, poses = walk
    turns, baselines = turns_and_baselines(poses)
    assert 5.0 <= np.median(turns) <= 9.0 and 14.0 <= np.percentile(turns, 90) <= 22.0
    assert 0.05 <= np.median(baselines) <= 0.20
    assert turns.sum() > 250 and baselines.sum() < 5.0          # ~one turn round the room, a few metres walked
    times = path.keyframe_times(35, seed=SEED + 1)
    assert path.duration >= 30 and times[0] < 0.05 * path.duration and times[-1] > 0.95 * path.duration


def test_every_object_seen_from_one_side_in_a_few_keyframes(walk):
    scene, _, poses = walk
    W, H = 80, 60   # a quarter of the bags' resolution: 40 px there are ~3 here
    stats = capture_statistics(intrinsics(W, H), W, H, poses, [(o.id, o.class_name, o.mesh_world) for o in scene.objects],
                               min_pixels=3)
    views = [o.in_view for o in stats.objects]
    assert all(3 <= v <= 14 for v in views) and np.median(views) <= 10
    assert all(o.spread_deg < 45 for o in stats.objects)
    chairs = [o for o in stats.objects if o.class_name == 'chair']
    assert sum(o.cut > o.in_view / 2 for o in chairs) >= 2        # chairs behind tables: most views cut


def test_azimuth_range_wraps():
    assert azimuth_range([170.0, -170.0]) == pytest.approx(20.0)
    assert azimuth_range([10.0]) == 0.0 and azimuth_range([]) is None
    assert azimuth_range([0.0, 120.0, 240.0]) == pytest.approx(240.0)


def test_capture_statistics_known_case():
    """Three boxes and four views with known answers: a small box 3 m ahead in front of a big one 5 m ahead
    (hiding ~41 % of it: (0.4 / 2.8)^2 / (1 / 4.5)^2), a third one behind the camera; the camera steps 10 cm
    sideways and turns 5 degrees between views."""
    W, H = 128, 96
    K = intrinsics(W, H, 60.0)
    poses = []
    for k in range(4):
        eye = np.array([0.0, 0.1 * k, 1.0])
        yaw = np.radians(5.0 * k)
        poses.append(look_at(eye, eye + [np.cos(yaw), np.sin(yaw), 0.0]))

    def box(size, centre):
        return trimesh.creation.box((size,) * 3).apply_translation(centre)

    objects = [(1, 'chair', box(0.4, (3.0, 0.0, 1.0))), (2, 'dining table', box(1.0, (5.0, 0.0, 1.0))),
               (3, 'chair', box(0.5, (-3.0, 0.0, 1.0)))]
    stats = capture_statistics(K, W, H, poses, objects, min_pixels=20)
    near, far, behind = stats.objects
    assert (near.in_view, far.in_view, behind.in_view) == (4, 4, 0)
    assert (near.cut, far.cut, behind.cut) == (0, 4, 0)
    assert near.truncated == far.truncated == 0 and near.hidden == 0.0
    assert 0.35 < far.hidden < 0.47
    assert near.spread_deg == pytest.approx(np.degrees(np.arctan2(0.3, 3.0)), abs=1e-6)
    assert far.spread_deg == pytest.approx(np.degrees(np.arctan2(0.3, 5.0)), abs=1e-6)
    assert behind.spread_deg is None and behind.hidden is None
    assert np.allclose(stats.turns_deg, 5.0, atol=1e-6) and np.allclose(stats.baselines_m, 0.1)
    pooled = pool_statistics([stats])
    assert pooled['objects'] == 3 and pooled['in_view_median'] == 4 and pooled['never_in_view'] == pytest.approx(1 / 3)
    assert pooled['cut_fraction'] == 0.5 and pooled['turn_median_deg'] == pytest.approx(5.0)
    assert pooled['baseline_median_cm'] == pytest.approx(10.0)
    # a nearer object that hides less than the threshold does not cut
    assert capture_statistics(K, W, H, poses, objects, min_pixels=20, cut_threshold=0.6).objects[1].cut == 0


def test_realwalk_preset_bag_and_its_statistics(tmp_path):
    from frodo_datasets.cli_synth import main
    out = tmp_path / 'walk.mcap'
    assert main([str(out), '--preset', 'realwalk', '--frames', '4', '--width', '64', '--height', '48',
                 '--objects', '4', '--classes', 'dining table,chair', '--seed', '3', '--quiet']) == 0
    doc = json.loads(out.with_name('walk.gt.json').read_text())
    assert doc['config']['scene'] == 'insideout' and doc['scene']['layout'] == 'perimeter'
    assert doc['config']['capture']['motion_blur_s'] > 0 and doc['config']['pose_noise']['drift_per_second']
    assert np.all(np.diff([f['capture_time_s'] for f in doc['frames']]) > 3.0)   # 4 keyframes over ~35 s
    stats = bag_statistics(out)
    assert stats.frames == 4 and len(stats.objects) == 4 and len(stats.turns_deg) == 3
    with pytest.raises(FileNotFoundError):
        bag_statistics(tmp_path / 'missing.mcap')


def test_realwalk_sets():
    held, tune = eval_sets.SETS['realwalk'], eval_sets.SETS['realwalk-tune']
    assert len(held.seeds) >= 12 and sum(held.objects) >= 40 and held.family_set == 'heldout'
    assert tune.family_set == 'train' and held.preset == tune.preset == 'realwalk'
    tune2 = eval_sets.SETS['realwalk-tune2']
    assert tune2.family_set == 'train' and tune2.preset == 'realwalk' and sum(tune.objects) + sum(tune2.objects) >= 100
    tune3 = eval_sets.SETS['realwalk-tune3']
    assert tune3.family_set == 'train' and tune3.preset == 'realwalk' and len(tune3.seeds) == 40
    assert not set(tune3.seeds) & (set(held.seeds) | set(tune.seeds) | set(tune2.seeds))
    config = eval_sets.scene_config(held, held.seeds[0], held.objects[0], 'full')
    assert config.scene == 'insideout' and config.frames == 35 and config.classes == eval_sets.WALK_CLASSES
    assert eval_sets.scene_config(held, held.seeds[0], held.objects[0], 'full100').frames == 100


def test_runner_option(tmp_path, monkeypatch):
    bag, pred = tmp_path / 'a.mcap', tmp_path / 'pred'
    offline = eval_sets.runner_command('reconstruct', bag, pred, ['my.yaml'])
    assert offline[1:] == ['reconstruct', str(bag), '--out', str(pred), '--quiet', '--params', 'my.yaml']
    live = eval_sets.runner_command('run', bag, pred, rate=0.5, timeout=60)
    assert live[1:] == ['run', str(bag), '--out', str(pred), '--rate', '0.5', '--no-progress', '--timeout', '60']
    with pytest.raises(ValueError):
        eval_sets.runner_command('graph', bag, pred)
    calls = []
    monkeypatch.setattr(eval_sets, 'run', lambda *a: calls.append(a))
    eval_sets.main(['run', 'realwalk', str(tmp_path)])
    eval_sets.main(['run', 'realwalk', str(tmp_path), '--runner', 'run'])
    assert [c[-1] for c in calls] == ['reconstruct', 'run']


def test_run_reconstructs_with_the_offline_pipeline_by_default(tmp_path, monkeypatch):
    """`run` calls the runner's command on every built bag and records the runner with the scores."""
    fake = tmp_path / 'fake_frodo.py'
    fake.write_text('import json, pathlib, sys\n'
                    'out = pathlib.Path(sys.argv[sys.argv.index("--out") + 1]); out.mkdir(parents=True)\n'
                    '(out / "objects.json").write_text(json.dumps({"argv": sys.argv[1:]}))\n')
    monkeypatch.setattr(eval_sets, '_frodo', lambda: [sys.executable, str(fake)])
    monkeypatch.setattr(eval_sets, 'score', lambda pred_dir, bag: {
        'argv': json.loads((pred_dir / 'objects.json').read_text())['argv'], 'pairs': [],
        'overall': {'n_matched': 0, 'n_gt': 4, 'false_positives': 0, 'f1': None}})
    held = eval_sets.SETS['realwalk']
    scene = held.scenes()[0][0]
    bag = eval_sets.bag_path(tmp_path, 'full', scene)
    bag.parent.mkdir(parents=True)
    bag.write_bytes(b'')
    eval_sets.run(held, tmp_path, ['full'], scenes='0-1')
    result = json.loads((tmp_path / 'results' / 'full' / f'{scene}.json').read_text())
    assert result['argv'][0] == 'reconstruct' and result['run']['runner'] == 'reconstruct'
    assert not (tmp_path / 'results' / 'full' / f'{held.scenes()[1][0]}.json').exists()   # not built: skipped
    assert eval_sets.pool([result])['timed_out'] == 0
