"""Object map save/load (frodo_optim.object_map): a round trip keeps everything the optimiser needs to go on;
a truncated or corrupt map gives a clear message instead of a crash; workers' maps are split by owner."""
import json

import numpy as np
import pytest
import trimesh

from frodo_common.geometry import Box3D
from frodo_optim.core import ObjectEstimate
from frodo_optim.object_map import (MAP_FILE, MapObject, MapWriter, ObjectMapError, load_map, load_maps,
                                    worker_map_dir)
from frodo_optim.states import STAGE_REASONS


def _object(oid: int, stage: str = 'dense', views: int = 12) -> MapObject:
    rng = np.random.default_rng(oid)
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    mesh.apply_translation([oid, 0.5, 0.3])
    pose = np.eye(4)
    pose[:3, :3] *= 0.45
    pose[:3, 3] = [oid, 0.5, 0.3]
    est = ObjectEstimate(oid, 'dining table' if oid % 2 else 'chair', 67 if oid % 2 else 62,
                         rng.normal(size=64).astype(np.float32), pose, 0.45,
                         (np.array([oid, 0.5, 0.3]), np.array([0.6, 0.6, 0.6]), 0.25), views, stage, mesh,
                         {'fused_s': 0.5, 'sparse_s': 2.0}, STAGE_REASONS.index('all stages done'))
    track = ('chair', Box3D(np.array([oid, 0.5, 0.31]), np.array([0.61, 0.6, 0.58]), 0.2))
    return MapObject(est, rng.normal(size=64).astype(np.float32), views, track)


def test_round_trip_keeps_estimates_inputs_and_meshes(tmp_path):
    saved = [_object(3), _object(4, stage='sparse')]
    path = MapWriter(tmp_path).save(saved, frame_id='map')
    assert path == tmp_path / MAP_FILE
    document = json.loads(path.read_text())
    assert document['frame_id'] == 'map' and [r['mesh'] for r in document['objects']] == [
        'meshes/3_dining_table.ply', 'meshes/4_chair.ply']   # the `frodo run` layout
    loaded, problems = load_map(tmp_path)
    assert problems == []
    for before, after in zip(saved, loaded):
        a, b = before.estimate, after.estimate
        assert (b.object_id, b.class_name, b.category, b.stage, b.num_views, b.stage_reason) == \
            (a.object_id, a.class_name, a.category, a.stage, a.num_views, a.stage_reason)
        assert np.allclose(b.code, a.code) and np.allclose(b.T_world_object, a.T_world_object)
        assert b.scale == a.scale and b.timings == a.timings
        assert all(np.allclose(x, y) for x, y in zip(b.box, a.box))
        assert np.allclose(b.mesh_world.vertices, a.mesh_world.vertices, atol=1e-6)
        assert np.array_equal(b.mesh_world.faces, a.mesh_world.faces)
        assert np.allclose(after.fused_code, before.fused_code) and after.fused_views == before.fused_views
        assert after.track[0] == before.track[0] and np.allclose(after.track[1].center, before.track[1].center)


def test_writer_rewrites_only_changed_meshes_and_removes_gone_ones(tmp_path):
    writer = MapWriter(tmp_path)
    a, b = _object(3), _object(4)
    writer.save([a, b])
    mesh_b = tmp_path / 'meshes' / '4_chair.ply'
    mesh_b.write_bytes(b'marker: not rewritten')     # unchanged estimate: the file is left alone
    writer.save([a, b])
    assert mesh_b.read_bytes() == b'marker: not rewritten'
    writer.save([a])
    assert not mesh_b.exists() and (tmp_path / 'meshes' / '3_dining_table.ply').exists()
    assert [o.estimate.object_id for o in load_map(tmp_path)[0]] == [3]


def test_truncated_or_corrupt_maps_are_named_and_give_nothing(tmp_path):
    MapWriter(tmp_path).save([_object(3)])
    text = (tmp_path / MAP_FILE).read_text()
    (tmp_path / MAP_FILE).write_text(text[:len(text) // 2])           # killed mid-write without the rename
    with pytest.raises(ObjectMapError, match='truncated or corrupt'):
        load_map(tmp_path)
    (tmp_path / MAP_FILE).write_bytes(b'\xff\xfe\x00garbage')
    with pytest.raises(ObjectMapError, match='truncated or corrupt'):
        load_map(tmp_path)
    (tmp_path / MAP_FILE).write_text(json.dumps({'frame_id': 'world', 'objects': {}}))
    with pytest.raises(ObjectMapError, match='not an object map'):
        load_map(tmp_path)
    (tmp_path / MAP_FILE).write_text(json.dumps({'format': 'other', 'objects': []}))
    with pytest.raises(ObjectMapError, match="format 'other'"):
        load_map(tmp_path)
    with pytest.raises(ObjectMapError, match='no object map there'):
        load_map(tmp_path / 'missing')
    objects, problems = load_maps(tmp_path)          # what the node calls: no exception, a message, empty
    assert objects == {} and 'not an object map' in problems[0]
    assert load_maps(tmp_path / 'missing') == ({}, [])


def test_a_frodo_run_output_folder_loads_too(tmp_path):
    MapWriter(tmp_path).save([_object(3), _object(4)])
    document = json.loads((tmp_path / MAP_FILE).read_text())
    run_fields = ('id', 'class', 'pose', 'scale', 'box', 'code', 'num_views', 'stage', 'stage_reason', 'timings',
                  'mesh', 'mesh_faces')        # what `frodo run --out` writes (frodo_bringup.outputs)
    run_document = {'frame_id': 'world', 'objects': [{k: r[k] for k in run_fields} for r in document['objects']]}
    (tmp_path / MAP_FILE).write_text(json.dumps(run_document))
    objects, problems = load_map(tmp_path)
    assert problems == [] and [(o.estimate.object_id, o.estimate.category) for o in objects] == [(3, 67), (4, 62)]
    assert objects[0].fused_code is None and objects[0].track is None


def test_a_bad_record_or_mesh_skips_only_that_object(tmp_path):
    MapWriter(tmp_path).save([_object(3), _object(4), _object(5)])
    document = json.loads((tmp_path / MAP_FILE).read_text())
    document['objects'][0]['pose'] = [[float('nan')] * 4] * 4
    (tmp_path / MAP_FILE).write_text(json.dumps(document))
    ply = tmp_path / 'meshes' / '5_dining_table.ply'
    ply.write_bytes(ply.read_bytes()[:200])          # truncated mesh
    objects, problems = load_map(tmp_path)
    assert [o.estimate.object_id for o in objects] == [4]
    assert len(problems) == 2 and 'object 3 skipped' in problems[0] and 'pose' in problems[0]
    assert 'object 5 skipped' in problems[1] and '5_dining_table.ply' in problems[1]


def test_worker_maps_are_split_by_owner_and_resumable_with_another_worker_count(tmp_path):
    for index in range(2):
        MapWriter(worker_map_dir(tmp_path, index, 2), (index, 2)).save(
            [_object(oid) for oid in range(1, 7) if oid % 2 == index])
    assert worker_map_dir(tmp_path, 0, 1) == tmp_path and worker_map_dir(tmp_path, 1, 2) == tmp_path / 'worker_1'
    everything, problems = load_maps(tmp_path)
    assert sorted(everything) == [1, 2, 3, 4, 5, 6] and problems == []
    thirds, _ = load_maps(tmp_path, owns=lambda oid: oid % 3 == 1)
    assert sorted(thirds) == [1, 4]
    # The same id in two maps (saved under another worker count): the later stage wins.
    MapWriter(tmp_path).save([_object(2, stage='fused', views=30)])
    assert load_maps(tmp_path)[0][2].estimate.stage == 'dense'
