"""Pieces of the public-source development data (frodo_datasets.real_data): recorded trajectory reading and
placement, world-file poses, intrinsics, and synthesize() rendering a given scene along given poses."""
import json

import numpy as np
import pytest
import trimesh

from frodo_common.geometry import invert_transform, look_at, make_transform, yaw_matrix
from frodo_datasets import real_data as rd
from frodo_datasets.render import Material, RenderObject
from frodo_datasets.scene import Scene, SceneObject
from frodo_datasets.synth import SynthConfig, sidecar_path, synthesize


def _trajectory(n=40, seed=0):
    """A hand-held-like path in a z-up world: eye at 1.3-1.7 m looking down at a desk ~1 m ahead."""
    rng = np.random.default_rng(seed)
    eyes = np.array([1.2, 0.6, 1.5]) + rng.normal(0, 0.1, (n, 3))
    return [look_at(e, np.array([0.4, 0.7, 0.7]) + rng.normal(0, 0.05, 3)) for e in eyes]


def test_recorded_trajectory_reads_tum_lines_and_a_bare_header(tmp_path):
    lines = ['timestamp tx ty tz qx qy qz qw',
             '1305031102.1758 1.3405 0.6266 1.6575 0.6574 0.6126 -0.2949 -0.3248',
             '1305031102.2159 1.3303 0.6256 1.6464 0.6579 0.6161 -0.2932 -0.3189']
    path = tmp_path / 'groundtruth.txt'
    path.write_text('\n'.join(lines) + '\n')
    stamps, poses = rd.read_recorded_trajectory(path)
    assert np.allclose(stamps, [1305031102.1758, 1305031102.2159])
    assert np.allclose(poses[0][:3, 3], [1.3405, 0.6266, 1.6575])
    R = poses[1][:3, :3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(R), 1.0)
    path.write_text('# ' + '\n'.join(lines) + '\n')  # the original TUM form reads the same
    assert np.allclose(rd.read_recorded_trajectory(path)[1][1], poses[1])


def test_sample_evenly_spreads_over_the_duration():
    stamps = np.linspace(0.0, 30.0, 3001)
    poses = [make_transform(None, [t, 0, 0]) for t in stamps]
    s, p = rd.sample_evenly(stamps, poses, 35)
    assert len(s) == len(p) == 35 and s[0] == 0.0 and s[-1] == 30.0
    assert np.allclose(np.diff(s), 30.0 / 34, atol=0.011)
    assert all(np.isclose(q[0, 3], t) for q, t in zip(p, s))


def test_place_trajectory_is_rigid_keeps_heights_and_frames_the_group():
    poses = _trajectory()
    centre = np.array([6.5, 1.0, 0.4])
    moved = rd.place_trajectory(poses, centre, distance=2.5, yaw_deg=-60.0)
    for i, j in ((0, 1), (3, 17), (10, 39)):  # relative motion unchanged
        assert np.allclose(invert_transform(poses[i]) @ poses[j], invert_transform(moved[i]) @ moved[j], atol=1e-9)
    P, Q = np.asarray(poses), np.asarray(moved)
    assert np.allclose(P[:, 2, 3], Q[:, 2, 3])  # recorded heights kept
    view = Q[:, :3, 2].mean(axis=0)
    assert np.isclose(np.degrees(np.arctan2(view[1], view[0])), -60.0, atol=1e-6)
    offset = centre[:2] - Q[:, :2, 3].mean(axis=0)
    assert np.isclose(np.linalg.norm(offset), 2.5) and np.allclose(offset / 2.5, [0.5, -np.sqrt(3) / 2])


def test_place_trajectory_refuses_a_world_that_is_not_z_up():
    y_up = make_transform(np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]))  # z-up world seen as y-up
    with pytest.raises(ValueError, match='not z-up'):
        rd.place_trajectory([y_up @ T for T in _trajectory()], np.zeros(3), 2.0, 0.0)


def test_world_file_poses(tmp_path):
    world = tmp_path / 'w.world'
    world.write_text('''<?xml version="1.0" ?><sdf version="1.6"><world name="default">
      <!-- <model name='Hidden'><include><uri>model://X</uri></include><pose>0 0 0 0 0 0</pose></model> -->
      <model name='ChairA_01_001'><static>true</static>
        <include><uri>model://aws_robomaker_residential_ChairA_01</uri></include>
        <pose frame=''>7.1 0.2 0.02 0 -0 1.5</pose></model>
      <model name='Ground'><link name='l'/></model>
    </world></sdf>''')
    poses = rd.read_world_poses(world)
    assert list(poses) == ['ChairA_01_001']
    model, T = poses['ChairA_01_001']
    assert model == 'aws_robomaker_residential_ChairA_01'
    assert np.allclose(T[:3, 3], [7.1, 0.2, 0.02]) and np.allclose(T[:3, :3], yaw_matrix(1.5))
    assert rd.class_of(model) == 'chair' and rd.class_of('aws_robomaker_residential_KitchenTable_01') == 'dining table'
    with pytest.raises(KeyError):
        rd.class_of('aws_robomaker_residential_SofaC_01')


def test_real_cad_split_keeps_chairs_and_tables_of_both_worlds():
    kept = [m.model for m in rd.REAL_CAD_MODELS]
    assert len(set(kept)) == len(kept) and not set(kept) & set(rd.REAL_CAD_DROPPED)
    for m in rd.REAL_CAD_MODELS:
        assert m.class_name == rd.class_of(m.model)  # one class fact for bags and split
        assert m.repo == (rd.AWS_BOOKSTORE_REPO if '_retail_' in m.model else rd.AWS_HOUSE_REPO)
    assert rd.class_of('aws_robomaker_retail_ChairB_01') == 'chair'
    for model in rd.REAL_CAD_DROPPED:  # the counters have no class
        with pytest.raises(KeyError):
            rd.class_of(model)
    chairs, tables = rd.real_cad_models(['chair']), rd.real_cad_models(('dining table',))
    assert {m.class_name for m in chairs} == {'chair'} and {m.class_name for m in tables} == {'dining table'}
    assert len(chairs) + len(tables) == len(kept) and rd.real_cad_models() == list(rd.REAL_CAD_MODELS)
    assert rd.real_cad_models(['couch']) == []


def _dae_chair(back_x: float) -> trimesh.Trimesh:
    """A box chair as the DAEs are (z up, on the floor, off-centre): seat, and a backrest at x = back_x."""
    seat = trimesh.creation.box((0.45, 0.45, 0.45))
    seat.apply_translation((0.0, 0.0, 0.225))
    back = trimesh.creation.box((0.05, 0.45, 0.45))
    back.apply_translation((back_x, 0.0, 0.675))
    chair = trimesh.util.concatenate([seat, back])
    chair.apply_translation((0.3, -0.2, 0.0))
    return chair


def test_real_cad_models_come_into_the_canonical_frame():
    # Where the DAEs have them (seen on renders): ChairA's backrest at +x, ChairD's at -x; the coffee table's long
    # side along x, the other tables' along y. Canonical: chairs face +x (backrest at -x), long sides along y.
    spec = {m.model.split('_', 3)[-1]: m for m in rd.REAL_CAD_MODELS}
    for name, back_x in [('ChairA_01', 0.2), ('ChairD_01', -0.2)]:
        chair = rd.real_cad_canonical(_dae_chair(back_x), spec[name])
        backrest = chair.vertices[chair.vertices[:, 2] > 0.1]
        assert np.allclose(chair.bounds.mean(axis=0), 0.0) and np.allclose(chair.extents, [0.45, 0.45, 0.9])
        assert backrest[:, 0].mean() < -0.15
    for name, dims in [('CoffeeTable_01', (1.315, 0.655, 0.322)), ('KitchenTable_01', (0.7, 1.8, 0.8)),
                       ('BalconyTable_01', (0.557, 0.557, 0.4)), ('ReadingDesk_01', (0.524, 1.144, 0.743))]:
        table = trimesh.creation.box(dims)
        table.apply_translation((0.3, -0.2, dims[2] / 2))
        table = rd.real_cad_canonical(table, spec[name])
        assert np.allclose(table.bounds.mean(axis=0), 0.0) and np.isclose(table.extents[2], dims[2])
        assert table.extents[1] >= table.extents[0] - 1e-9 and np.isclose(table.extents[1], max(dims[:2]))


def test_load_real_cad_names_the_fetch_script_without_sources(tmp_path):
    with pytest.raises(FileNotFoundError, match='fetch_real_cad.sh'):
        rd.load_real_cad(tmp_path)
    assert rd.load_real_cad(tmp_path, ['couch']) == []


def test_tum_intrinsics_scale_keeps_pixel_centres():
    K = rd.tum_intrinsics(320, 240)
    assert np.allclose([K[0, 0], K[1, 1]], [517.3 / 2, 516.5 / 2])
    assert np.allclose([K[0, 2], K[1, 2]], [(318.6 + 0.5) / 2 - 0.5, (255.3 + 0.5) / 2 - 0.5])
    assert np.allclose(rd.tum_intrinsics(640, 480)[:2, 2], [318.6, 255.3])


def test_synthesize_renders_the_given_scene_along_the_given_poses(tmp_path):
    box = trimesh.creation.box((0.5, 0.5, 0.9))
    chair = SceneObject(1, 'chair', 62, box, make_transform(None, [2.0, 0.0, 0.45]), Material(color=(0.8, 0.2, 0.2)))
    floor = trimesh.creation.box((8, 8, 0.05))
    floor.apply_translation((0, 0, -0.025))
    scene = Scene([chair], [RenderObject(floor, Material(), 0)], (8.0, 8.0), 'walk', 0)
    poses = [look_at([0.0, y, 1.4], [2.0, 0.0, 0.45]) for y in (-0.3, 0.0, 0.3)]
    K = rd.tum_intrinsics(64, 48)
    config = SynthConfig(frames=3, width=64, height=48, slam=False, shadows=False)
    result = synthesize(config, tmp_path / 'b.mcap', scene=scene, poses=poses, K=K)
    assert result.scene is scene and np.allclose(result.K, K)
    assert all(np.allclose(a, b) for a, b in zip(result.true_poses, poses))
    doc = json.loads(sidecar_path(tmp_path / 'b.mcap').read_text())
    assert np.allclose(doc['camera']['K'], K) and doc['scene']['objects'][0]['class'] == 'chair'
    with pytest.raises(ValueError, match='2 poses given for 3 frames'):
        synthesize(config, tmp_path / 'c.mcap', scene=scene, poses=poses[:2], K=K)


def test_visible_fraction_counts_surface_inside_the_image():
    box = trimesh.creation.box((0.5, 0.5, 0.9))
    chair = SceneObject(1, 'chair', 62, box, make_transform(None, [2.0, 0.0, 0.45]), Material())
    scene = Scene([chair], [], (8.0, 8.0), 'walk', 0)
    K = rd.tum_intrinsics(320, 240)
    facing = look_at([0.0, 0.0, 1.0], [2.0, 0.0, 0.45])
    away = look_at([0.0, 0.0, 1.0], [-2.0, 0.0, 0.45])
    aside = look_at([0.0, 0.0, 1.0], [2.0, 1.0, 0.45])  # the box at the left image border: partly inside
    f = rd.visible_fraction(scene, [facing, away, aside], K, 320, 240)
    assert f[0] == 1.0 and f[1] == 0.0 and 0.05 < f[2] < 0.95
