"""`frodo run` (`run_bag`) on a stand-in graph: plays the bag, waits for the optimiser to be done, writes
objects.json and PLY meshes, and exits non-zero naming the node when the graph fails."""
from __future__ import annotations

import io
import json

import numpy as np
import pytest
import trimesh
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from visualization_msgs.msg import MarkerArray

from frodo_bringup.outputs import object_records, write_outputs
from frodo_bringup.player import PlayerError
from frodo_bringup.run import EXIT_GRAPH_FAILED, EXIT_OK, run_bag
from frodo_bringup.session import RosSession
from frodo_bringup.stub_node import TETRAHEDRON_FACES
from frodo_bringup.testing import stub, write_contract_bag
from frodo_common import conversions as conv
from frodo_common import topics

# The stand-in optimiser is one node (it knows no worker split): optim_workers=1 in every run below.
STUB_GRAPH = (stub('detection_node'), stub('optim_node'))


def _params(tmp_path, **optimiser) -> str:
    lines = ["'/**':", '  ros__parameters:', '    diagnostics_period: 0.2', 'optim_node:', '  ros__parameters:',
             '    act_as_optimiser: true']
    lines += [f'    {k}: {v}' for k, v in optimiser.items()]
    path = tmp_path / 'params.yaml'
    path.write_text('\n'.join(lines) + '\n')
    return str(path)


def test_run_writes_objects_meshes_and_recording(tmp_path):
    write_contract_bag(tmp_path / 'in.mcap', frames=10, period=0.05, instances=True)
    output = io.StringIO()
    result = run_bag(tmp_path / 'in.mcap', tmp_path / 'out', [_params(tmp_path)], timeout=15, rate=0,
                     viewer='rrd', nodes=STUB_GRAPH, startup_timeout=30, output=output, progress=False, optim_workers=1)
    assert result.exit_code == EXIT_OK, output.getvalue()
    assert result.done and result.play.total == 41  # 4 topics x 10 frames + ground truth for the viewer
    document = json.loads((tmp_path / 'out' / 'objects.json').read_text())
    (obj,) = document['objects']
    assert (obj['id'], obj['class'], obj['mesh']) == (7, 'chair', 'meshes/7_chair.ply')
    assert np.allclose(obj['box']['size'], 0.4) and len(obj['pose']) == 4
    mesh = trimesh.load(tmp_path / 'out' / obj['mesh'])
    assert len(mesh.faces) == len(TETRAHEDRON_FACES) and len(mesh.vertices) == 4
    assert (tmp_path / 'out' / 'logs' / 'optim_node.log').is_file()
    assert (tmp_path / 'out' / 'frodo.rrd').stat().st_size > 0
    assert 'done: 41 messages played, 1 objects' in output.getvalue()
    assert 0 <= result.done_after_bag_s < result.seconds
    assert f'(done {result.done_after_bag_s:.1f} s after the bag ended)' in output.getvalue()


def test_run_reports_a_crashed_node(tmp_path):
    write_contract_bag(tmp_path / 'in.mcap', frames=200, period=0.05, instances=True)  # 10 s of bag at rate 1
    output = io.StringIO()
    result = run_bag(tmp_path / 'in.mcap', tmp_path / 'out', [_params(tmp_path, crash_after=1.0)], timeout=5,
                     nodes=STUB_GRAPH, startup_timeout=20, output=output, progress=False, optim_workers=1)
    assert result.exit_code == EXIT_GRAPH_FAILED, output.getvalue()
    assert [f.name for f in result.failures] == ['optim_node'] and result.failures[0].returncode == 3
    assert 'node failure: optim_node exited with code 3' in output.getvalue()
    assert (result.play is None or result.play.interrupted) and result.seconds < 15


def test_run_ignores_and_names_another_graphs_diagnostics(tmp_path):
    """Reports of an optim_node this run did not start (another graph in the ROS domain: busy, no image taken)
    must neither pace playback nor hold off "done"; the run names it. Without the pid check this run never
    ends (timeout, exit 3)."""
    write_contract_bag(tmp_path / 'in.mcap', frames=10, period=0.05, instances=True)
    busy = DiagnosticArray(status=[DiagnosticStatus(name='optim_node', values=[
        KeyValue(key=k, value=v) for k, v in {'pid': '999999', 'state': 'optimising', 'pending_objects': '3',
                                               'image_received': '0'}.items()])])
    output = io.StringIO()
    with RosSession('frodo_test_other_graph') as other:
        publisher = other.node.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 10)
        other.node.create_timer(0.1, lambda: publisher.publish(busy))
        result = run_bag(tmp_path / 'in.mcap', tmp_path / 'out', [_params(tmp_path)], timeout=15, rate=0,
                         nodes=STUB_GRAPH, startup_timeout=30, output=output, progress=False, optim_workers=1)
    assert result.exit_code == EXIT_OK and result.done, output.getvalue()
    assert result.foreign == [('optim_node', '999999')]
    text = output.getvalue()
    assert text.count('ignoring /diagnostics of a optim_node with pid 999999') == 1
    assert 'WARNING: another graph ran in this ROS domain (optim_node (pid 999999))' in text
    assert 'done: 40 messages played, 1 objects' in text  # 4 topics x 10 frames


def test_run_rejects_a_missing_bag_before_starting_nodes(tmp_path):
    with pytest.raises(PlayerError, match='bag not found'):
        run_bag(tmp_path / 'missing.mcap', tmp_path / 'out', nodes=STUB_GRAPH)


def test_outputs_follow_marker_actions_and_prefer_optimiser_info(tmp_path):
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    faces = np.array([[0, 1, 2], [0, 1, 3]])
    objects = MarkerArray(markers=[conv.mesh_to_marker(vertices, faces, 'dining table', 2, 0, 'world'),
                                   conv.mesh_to_marker(vertices, faces, 'chair', 3, 0, 'world'),
                                   conv.delete_marker('chair', 3, 0, 'world')])
    boxes = MarkerArray(markers=[conv.box_to_marker((1, 2, 0.5), (1.8, 0.9, 1.0), 0.3, 'dining table', 2, 0,
                                                    'world')])
    info = {2: {'stage': 'dense', 'num_views': 12, 'scale': 0.7}}
    records = write_outputs(tmp_path, objects, boxes, info)
    assert [r['id'] for r in records] == [2]  # object 3 was deleted
    (table,) = records
    assert (table['stage'], table['num_views'], table['scale']) == ('dense', 12, 0.7)
    assert np.allclose(np.array(table['pose'])[:3, 3], [1, 2, 0.5])
    assert abs(table['box']['yaw'] - 0.3) < 1e-9
    mesh = trimesh.load(tmp_path / 'meshes' / '2_dining_table.ply')
    assert np.allclose(sorted(mesh.vertices.tolist()), sorted(vertices.tolist()))
    assert object_records(None, None) == []


def test_run_rejects_bad_bags_at_once_with_exit_2(tmp_path, capsys):
    from frodo_bringup import cli
    from frodo_common.bag import BagWriter
    (tmp_path / 'garbage.mcap').write_text('not a bag\n' * 100)
    assert cli.main(['run', str(tmp_path / 'garbage.mcap'), '--out', str(tmp_path / 'out')]) == 2
    assert 'is not an MCAP file' in capsys.readouterr().err
    with BagWriter(tmp_path / 'poses.mcap') as bag:
        bag.write(topics.POSE, conv.make_pose_stamped(np.eye(4), 10, 'world'), 10)
    assert cli.main(['run', str(tmp_path / 'poses.mcap'), '--out', str(tmp_path / 'out')]) == 2
    err = capsys.readouterr().err
    assert f'no message on the required input(s) {topics.IMAGE}, {topics.CAMERA_INFO}' in err
    assert not (tmp_path / 'out' / 'logs').exists()  # no node was started


def test_run_refuses_a_bag_without_masks_under_the_external_backend(tmp_path, capsys):
    from frodo_bringup import cli
    write_contract_bag(tmp_path / 'no_masks.mcap', frames=3)
    assert cli.main(['run', str(tmp_path / 'no_masks.mcap'), '--out', str(tmp_path / 'out')]) == 2
    err = capsys.readouterr().err
    assert 'no instance masks' in err and 'backend: maskrcnn' in err
    assert not (tmp_path / 'out' / 'logs').exists()  # no node was started
