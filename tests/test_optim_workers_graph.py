"""More than one optimiser and the saved object map, from the command line's side (issue 12): worker nodes get
unique names and their parameters (the `optim_node` section of the params files, then worker index/count), the
run collector keeps the latest complete map, `frodo run --optim-workers 2` waits for every worker, and in the
real graph on the demo bag two workers each reconstruct their share, the latest /frodo/objects message (worker 0
merges the shares) has every object once, a worker killed with SIGKILL comes back with its saved objects at
once while the map stays complete, and a killed merger (worker 0) publishes the complete map again."""
from __future__ import annotations

import ast
import io
import json
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from frodo_bringup.graph import (AUTO_OPTIM_WORKERS, NODES, GraphError, is_optimiser, optim_worker_count,
                                 optimiser_workers, ros_parameter_arguments, share_file, with_optimiser_parameters)
from frodo_bringup.launcher import Launcher
from frodo_bringup.player import Player
from frodo_bringup.readiness import GraphMonitor
from frodo_bringup.run import EXIT_OK, OutputCollector, run_bag
from frodo_bringup.session import RosSession
from frodo_bringup.testing import stub, wait_until, write_contract_bag
from frodo_common import conversions as conv
from frodo_common import topics
from frodo_optim.states import OBJECT_STATES, STATES_DTYPE

BAG = Path(__file__).resolve().parents[1] / 'bags' / 'demo_walk.mcap'


def test_workers_get_unique_names_and_the_optimiser_parameters(tmp_path):
    params = tmp_path / 'params.yaml'
    params.write_text("'/**':\n  ros__parameters:\n    diagnostics_period: 0.5\n"
                      "optim_node:\n  ros__parameters:\n    dense_enabled: false\n    prior: my prior\n")
    later = tmp_path / 'later.yaml'
    later.write_text('/optim_node:\n  ros__parameters:\n    prior: furniture\n')
    nodes = with_optimiser_parameters(optimiser_workers(NODES, 3), map_dir='/maps/a', resume=None)
    names = [n.name for n in nodes]
    assert names == ['detection_node', 'association_node', 'shape_node', 'optim_node', 'optim_node_1',
                     'optim_node_2']
    assert [is_optimiser(n) for n in names] == [False] * 3 + [True] * 3 and not is_optimiser('optim_node_x')
    assert optimiser_workers(NODES, 1) == optimiser_workers(NODES, '1') == NODES
    # auto: two workers where this process may use two CPUs or more
    assert optim_worker_count('auto') == optim_worker_count(None) == min(2, len(os.sched_getaffinity(0)))
    with pytest.raises(GraphError, match="positive integer or 'auto'"):
        optimiser_workers(NODES, 'two')
    # each of the 3 workers gets a third of the CPUs as torch threads (at least 1); the other nodes keep theirs
    threads = str(max(1, len(os.sched_getaffinity(0)) // 3))
    assert [dict(n.env).get('OMP_NUM_THREADS') for n in nodes] == [None] * 3 + [threads] * 3
    with pytest.raises(GraphError, match='at least 1'):
        optimiser_workers(NODES, 0)
    # A worker runs under another name: the optimiser's section of every file (later files win), then its own.
    assert ros_parameter_arguments(nodes[4], [params, later]) == [
        '-p', 'dense_enabled:=false', '-p', 'prior:=furniture', '-p', 'worker_index:=1', '-p', 'worker_count:=3',
        '-p', 'map_dir:=/maps/a']
    assert ros_parameter_arguments(nodes[0], [params]) == []
    # worker 0 keeps the optimiser's name (and so its section of the files), plus its index and count
    assert ros_parameter_arguments(nodes[3], [params, later]) == [
        '-p', 'worker_index:=0', '-p', 'worker_count:=3', '-p', 'map_dir:=/maps/a']
    command = Launcher(nodes, [params])._command(nodes[5])
    assert command[command.index('-r') + 1] == '__node:=optim_node_2' and 'worker_index:=2' in command
    assert command.index('--params-file') < command.index('worker_index:=2')   # the worker's own values win
    with pytest.raises(GraphError, match='unique'):
        Launcher(NODES + NODES[:1], [])
    bad = tmp_path / 'bad.yaml'
    bad.write_text('optim_node: [unclosed\n')
    with pytest.raises(GraphError, match='bad.yaml'):
        Launcher(nodes, [bad])


def test_launch_file_takes_optim_workers():
    """ROS 2 launch is not installed here, so only its structure is checked: the argument is declared and the
    optimiser nodes come from one function that names the workers like `optimiser_workers`."""
    tree = ast.parse(share_file('launch/frodo.launch.py').read_text())
    declared = [node.args[0].value for node in ast.walk(tree) if isinstance(node, ast.Call)
                and getattr(node.func, 'id', '') == 'DeclareLaunchArgument']
    assert declared == ['params_file', 'viewer', 'optim_workers']
    function = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == 'optimiser_nodes')
    assert "f'{executable}_{k}'" in ast.unparse(function) and "'worker_index': k" in ast.unparse(function)
    assert "executable if k == 0" in ast.unparse(function)
    assert [n.name for n in optimiser_workers(NODES, 2)][-2:] == ['optim_node', 'optim_node_1']
    default = next(node for node in ast.walk(tree) if isinstance(node, ast.Call)
                   and getattr(node.func, 'id', '') == 'DeclareLaunchArgument' and node.args[0].value == 'optim_workers')
    assert next(k.value.value for k in default.keywords if k.arg == 'default_value') == 'auto'
    auto = next(n.value.value for n in tree.body if isinstance(n, ast.Assign)
                and getattr(n.targets[0], 'id', '') == 'AUTO_OPTIM_WORKERS')
    assert auto == AUTO_OPTIM_WORKERS


def test_the_run_collector_keeps_the_latest_complete_map():
    """Each /frodo/objects message is the complete map (CONTRACT.md; several workers are merged by worker 0), so
    the collector keeps the latest one as it is: an object missing from it is gone, with or without a DELETE."""
    def complete(ids, deleted=()):
        markers = [conv.delete_marker('chair', oid, 1, 'world') for oid in deleted]
        markers += [conv.box_to_marker(np.array([oid, 0.0, 0.0]), np.ones(3), 0.0, 'chair', oid, 1, 'world')
                    for oid in ids]
        table = np.zeros(len(ids), dtype=STATES_DTYPE)
        table['object_id'], table['category'], table['scale'] = ids, 62, 1.0
        return MarkerArray(markers=markers), conv.table_to_cloud(table, 1, 'world')

    with RosSession('frodo_test_workers_collector') as session:
        collector = OutputCollector(session.node, ['optim_node', 'optim_node_1'])
        objects = session.node.create_publisher(MarkerArray, topics.OBJECTS, topics.LATCHED_QOS)
        states = session.node.create_publisher(PointCloud2, OBJECT_STATES, topics.LATCHED_QOS)

        def publish(ids, deleted=()):
            markers, table = complete(ids, deleted)
            objects.publish(markers)
            states.publish(table)

        publish([0, 1, 2, 3])
        assert wait_until(lambda: collector.snapshot()[0] is not None
                          and len(collector.snapshot()[0].markers) == 4 and len(collector.snapshot()[2]) == 4, 10)
        publish([0, 1, 2], deleted=[3])
        assert wait_until(lambda: [m.id for m in collector.snapshot()[0].markers] == [0, 1, 2], 10)
        assert sorted(collector.snapshot()[2]) == [0, 1, 2]      # the deleted object's state is left out
        publish([1, 2])           # e.g. a restarted merger that has not heard of object 0 yet: no DELETE
        assert wait_until(lambda: [m.id for m in collector.snapshot()[0].markers] == [1, 2]
                          and sorted(collector.snapshot()[2]) == [1, 2], 10)


def test_the_run_collector_knows_which_nodes_are_behind():
    """Each node's image counter (`IMAGE_COUNTERS`; workers count as the optimiser; a node that has not counted
    one yet took 0) against what it was sent: the images played, or for the association node the detections the
    detection node published. The slowest count paces rate 0; a node behind holds "done" back."""
    def report(name, **counters):
        return DiagnosticStatus(name=name, values=[KeyValue(key=k, value=str(v)) for k, v in counters.items()])

    names = ['detection_node', 'association_node', 'shape_node', 'optim_node', 'optim_node_1']
    with RosSession('frodo_test_collector_behind') as session:
        collector = OutputCollector(session.node, ['optim_node', 'optim_node_1'])
        assert collector.frames_taken(names) is None and collector.behind(names, 40) == []
        diagnostics = session.node.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 50)
        assert wait_until(lambda: diagnostics.get_subscription_count() > 0, 10)
        diagnostics.publish(DiagnosticArray(status=[
            report('detection_node', frames_received=40, frames_published=38),
            report('association_node', frames_received=37), report('shape_node', image_received=39),
            report('optim_node', image_received=40), report('optim_node_1'), report('other_node')]))
        assert wait_until(lambda: collector.frames_taken(names) == 0, 10)
        assert collector.behind(names, 40) == [('association_node', 37, 38, 'frames_published of detection_node'),
                                               ('shape_node', 39, 40, 'images played'),
                                               ('optim_node_1', 0, 40, 'images played')]
        diagnostics.publish(DiagnosticArray(status=[
            report('association_node', frames_received=38), report('shape_node', image_received=40),
            report('optim_node_1', image_received=40)]))
        assert wait_until(lambda: collector.frames_taken(names) == 38, 10)
        assert collector.behind(names, 40) == []


def test_done_waits_for_images_queued_behind_a_long_callback(tmp_path):
    """A node reports from a thread of its own, so one stuck in a long callback reports steady counters while
    images wait in its queue; "done" then also needs every image taken (or LOST_IMAGES_GRACE to pass)."""
    write_contract_bag(tmp_path / 'in.mcap', frames=4, period=0.05, instances=True)
    params = tmp_path / 'params.yaml'
    params.write_text("'/**':\n  ros__parameters:\n    diagnostics_period: 0.2\n"
                      'shape_node:\n  ros__parameters:\n    seconds_per_image: 1.0\n'
                      'optim_node:\n  ros__parameters:\n    act_as_optimiser: true\n    busy_for: 0.1\n')
    output = io.StringIO()
    result = run_bag(tmp_path / 'in.mcap', tmp_path / 'out', [params], timeout=30, rate=0,
                     nodes=(stub('detection_node'), stub('shape_node'), stub('optim_node')), startup_timeout=30,
                     output=output, progress=False)
    assert result.exit_code == EXIT_OK and result.done, output.getvalue()
    assert result.behind == [] and 'images played within' not in output.getvalue()


def test_frodo_run_with_two_workers_waits_for_both(tmp_path):
    write_contract_bag(tmp_path / 'in.mcap', frames=10, period=0.05, instances=True)
    params = tmp_path / 'params.yaml'
    params.write_text("'/**':\n  ros__parameters:\n    diagnostics_period: 0.2\n"
                      'optim_node:\n  ros__parameters:\n    act_as_optimiser: true\n')
    output = io.StringIO()
    result = run_bag(tmp_path / 'in.mcap', tmp_path / 'out', [params], timeout=15, rate=0,
                     nodes=(stub('detection_node'), stub('optim_node')), startup_timeout=30, output=output,
                     progress=False, optim_workers=2)
    assert result.exit_code == EXIT_OK and result.done, output.getvalue()
    for name in ('optim_node', 'optim_node_1'):   # each worker got the optimiser's section and logs on its own
        assert (tmp_path / 'out' / 'logs' / f'{name}.log').is_file()
    assert 'started optim_node' in output.getvalue() and 'started optim_node_1' in output.getvalue()
    assert [r['id'] for r in json.loads((tmp_path / 'out' / 'objects.json').read_text())['objects']] == [7]


@pytest.mark.skipif(not BAG.exists(), reason='demo bag missing')
def test_two_workers_on_the_demo_bag_share_the_objects_and_a_killed_one_resumes_its_map(tmp_path):
    params = tmp_path / 'params.yaml'
    params.write_text("'/**':\n  ros__parameters:\n    diagnostics_period: 0.5\n"
                      'optim_node:\n  ros__parameters:\n    dense_enabled: false\n    sparse_iterations: 5\n'
                      '    sparse_yaw_candidates: 8\n    mesh_resolution: 32\n')
    map_dir = tmp_path / 'map'
    nodes = with_optimiser_parameters(optimiser_workers(NODES, 2), map_dir=str(map_dir), resume=str(map_dir))
    names = [n.name for n in nodes]
    workers = [n for n in names if is_optimiser(n)]
    session = RosSession('frodo_test_workers')
    lines: list[str] = []
    launcher = Launcher(nodes, [params], on_failure='restart', restart_delay=0.5, output=io.StringIO())
    try:
        monitor = GraphMonitor(session.node, names, lines.append, pids=lambda: launcher.pids, settle=0.5, period=0.25)
        collector = OutputCollector(session.node, workers)
        launcher.start()
        assert monitor.wait_ready(120), lines
        player = Player(session.node, BAG, rate=1.0, progress=False)
        assert not player.wait_for_subscribers(10, wanted=[topics.IMAGE, topics.POSE], settle=0.5)
        stats = player.play(threading.Event())
        finished = time.monotonic()
        assert stats.total > 0
        assert wait_until(lambda: collector.done(names, since=finished), 240), {
            w: collector._reports.get(w) for w in workers}
        objects, _, info = collector.snapshot()
        ids = [m.id for m in objects.markers]
        assert len(ids) == len(set(ids)) >= 3 and sorted(info) == sorted(ids), (ids, sorted(info))
        saved = {k: [r['id'] for r in json.loads((map_dir / f'worker_{k}' / 'objects.json').read_text())['objects']]
                 for k in range(2)}
        assert sorted(saved[0] + saved[1]) == sorted(ids)             # every object once, in its worker's map
        assert all(i % 2 == k for k in range(2) for i in saved[k]) and saved[0] and saved[1], saved

        old_pid = launcher.pids['optim_node_1']
        os.kill(old_pid, signal.SIGKILL)
        assert wait_until(lambda: launcher.pids['optim_node_1'] != old_pid and 'optim_node_1' in monitor.up(), 90), lines
        new_pid = str(launcher.pids['optim_node_1'])
        assert wait_until(lambda: collector._reports['optim_node_1'][-1][1].get('pid') == new_pid, 10)
        latest = collector._reports['optim_node_1'][-1][1]
        # the restarted worker has its objects back before any new frame (the bag has ended)
        assert latest['objects_resumed'] == str(len(saved[1])) and latest['objects'] == str(len(saved[1])), latest
        assert sorted(m.id for m in collector.snapshot()[0].markers) == sorted(ids)   # the map stayed complete
        late_listener = OutputCollector(session.node, workers)   # depth 1, contract QoS: the latched merged map
        assert wait_until(lambda: late_listener.snapshot()[0] is not None
                          and sorted(m.id for m in late_listener.snapshot()[0].markers) == sorted(ids), 20)

        # The merger (worker 0) killed: restarted, it has its own share from its saved map and worker 1's from
        # its latched share topics, and publishes the complete map again (frodo_optim.merge).
        old_pid = launcher.pids['optim_node']
        os.kill(old_pid, signal.SIGKILL)
        assert wait_until(lambda: launcher.pids['optim_node'] != old_pid and 'optim_node' in monitor.up(), 90), lines
        after_restart = OutputCollector(session.node, workers)
        assert wait_until(lambda: after_restart.snapshot()[0] is not None
                          and sorted(m.id for m in after_restart.snapshot()[0].markers) == sorted(ids), 30)
    finally:
        launcher.shutdown(timeout=30)
        session.close()
    assert [e.name for e in launcher.failures] == ['optim_node_1', 'optim_node']
