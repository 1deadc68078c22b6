"""optim_node workers and the saved object map in a real rclpy graph (issue 12): two workers split the objects by
id, worker 0 merges their shares, and a plain depth-1 listener of /frodo/objects with the contract QoS finds the
complete map in the latest message (CONTRACT.md), also when it joins late and after the merger restarts;
a worker saving its map and a new one resuming from it republish the objects at once, keep them until enough
new views arrive and then refine them again, and a map that cannot be read is reported while the worker
starts empty."""
import json

import numpy as np
import rclpy
import torch
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from frodo_association.core import ASSOCIATION_DTYPE
from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.testing import latest_status, spin_until
from frodo_optim.object_map import MAP_FILE
from frodo_optim.optim_node import OptimNode
from frodo_optim.states import OBJECT_STATES, STAGES
from frodo_shape.prior import ShapePrior
from frodo_common.schemas import OBJECT_CODES_DTYPE

CHAIR = 62
STAMP = 1_000_000_000
# prior: the one whose training codes the probe publishes (a code means a shape only to its own decoder)
FAST = [Parameter('diagnostics_period', value=0.1), Parameter('mesh_resolution', value=24),
        Parameter('sparse_enabled', value=False), Parameter('prior', value='furniture')]


WORKER_NAMES = ('optim_node', 'optim_node_1')   # as frodo_bringup.graph.optimiser_workers names them


def _optimiser(name: str, *params: Parameter) -> OptimNode:
    return OptimNode(parameter_overrides=FAST + list(params), cli_args=['--ros-args', '-r', f'__node:={name}'])


class _Probe:
    """Publishes tracks and fused codes as the association and shape nodes do; listens to the outputs as an
    outside contract listener does (reliable, transient local, depth 1; the latest message is the map)."""

    def __init__(self, executor: SingleThreadedExecutor):
        self.executor = executor
        self.node = rclpy.create_node('optim_workers_probe')
        executor.add_node(self.node)
        self.messages: list[MarkerArray] = []
        self.latest: dict[int, Marker] = {}          # the objects (ADDs) of the latest /frodo/objects message
        self.boxes: list[MarkerArray] = []
        self.states: list[PointCloud2] = []
        self.diags: list[DiagnosticArray] = []
        self.node.create_subscription(MarkerArray, topics.OBJECTS, self._on_objects, topics.LATCHED_QOS)
        self.node.create_subscription(MarkerArray, topics.BOXES, self.boxes.append, topics.LATCHED_QOS)
        self.node.create_subscription(PointCloud2, OBJECT_STATES, self.states.append, topics.LATCHED_QOS)
        self.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self.diags.append, 50)
        self.tracks = self.node.create_publisher(MarkerArray, topics.TRACKS, topics.LATCHED_QOS)
        self.codes = self.node.create_publisher(PointCloud2, topics.OBJECT_CODES, topics.LATCHED_QOS)
        prior = ShapePrior.load('furniture', device='cpu')
        chairs = [i for i, c in enumerate(prior.training_classes) if c == 'chair']
        self.prior_codes = [prior.training_codes[i].numpy() for i in chairs]

    def _on_objects(self, msg: MarkerArray) -> None:
        self.messages.append(msg)
        assert all(m.action != Marker.DELETEALL for m in msg.markers)
        self.latest = {m.id: m for m in msg.markers if m.action == Marker.ADD}

    def publish(self, ids, views: int = 3, deleted=(), tracks: bool = True) -> None:
        table = np.zeros(len(ids), dtype=OBJECT_CODES_DTYPE)
        markers = MarkerArray(markers=[conv.delete_marker('chair', oid, STAMP, 'world') for oid in deleted])
        for i, oid in enumerate(ids):
            table[i] = (oid, CHAIR, views, self.prior_codes[oid % len(self.prior_codes)])
            markers.markers.append(conv.box_to_marker(np.array([1.5 * oid, 0.0, 0.4]), np.array([0.5, 0.5, 0.8]),
                                                      0.1 * oid, 'chair', oid, STAMP, 'world'))
        self.codes.publish(conv.table_to_cloud(table, STAMP, 'world'))
        if tracks:
            self.tracks.publish(markers)

    def status(self, name: str) -> dict[str, str]:
        return latest_status(self.diags, name)

    def spin(self, condition, timeout: float = 60.0) -> bool:
        return spin_until(self.executor, condition, timeout)


def _idle(probe: _Probe, name: str) -> bool:
    status = probe.status(name)
    return status.get('state') == 'idle' and status.get('pending_objects') == '0'


def _ids(array: MarkerArray) -> list[int]:
    return sorted(m.id for m in array.markers if m.action == Marker.ADD)


def _state_ids(probe: _Probe) -> list[int]:
    return sorted(conv.cloud_to_table(probe.states[-1])['object_id'].tolist()) if probe.states else []


def test_two_workers_split_the_objects_and_a_depth_1_listener_gets_the_complete_map():
    rclpy.init()
    executor = SingleThreadedExecutor()
    try:
        workers = [_optimiser(WORKER_NAMES[k], Parameter('worker_index', value=k),
                              Parameter('worker_count', value=2)) for k in range(2)]
        for w in workers:
            executor.add_node(w)
        probe = _Probe(executor)
        assert probe.spin(lambda: probe.tracks.get_subscription_count() == 2 and probe.codes.get_subscription_count() == 2)
        probe.publish([1, 2, 3, 4, 5])
        assert probe.spin(lambda: sorted(probe.latest) == [1, 2, 3, 4, 5] and _idle(probe, 'optim_node')
                          and _idle(probe, 'optim_node_1')), (sorted(probe.latest), probe.status('optim_node'))
        for k, w in enumerate(workers):
            assert sorted(w.estimates) == [i for i in (1, 2, 3, 4, 5) if i % 2 == k]   # its share, nothing else
            assert sorted(w.tracks) == sorted(w.estimates) and probe.status(WORKER_NAMES[k])['worker'] == f'{k}/2'
        assert probe.status('optim_node')['shares_merged'] == '2/2'
        assert probe.status('optim_node')['pending_by_worker'] == '0 0'
        # Each mesh of the merged map is its worker's estimate (worker 1's came through its serialised share).
        for oid in (2, 3):
            est = workers[oid % 2].estimates[oid]
            corners = est.mesh_world.vertices[est.mesh_world.faces].reshape(-1, 3)
            assert np.array_equal(conv.marker_to_mesh(probe.latest[oid])[0], corners)
        # One writer of the contract topics (the merger, worker 0); worker 1 publishes its share internally.
        for topic in (topics.OBJECTS, topics.BOXES, OBJECT_STATES):
            assert [i.node_name for i in probe.node.get_publishers_info_by_topic(topic)] == ['optim_node'], topic
        assert [i.node_name for i in probe.node.get_publishers_info_by_topic(
            topics.object_share_topic('objects', 1))] == ['optim_node_1']
        assert probe.spin(lambda: _ids(probe.boxes[-1]) == [1, 2, 3, 4, 5] and _state_ids(probe) == [1, 2, 3, 4, 5], 10)

        # A listener joining now (depth 1, contract QoS) gets the complete map in its one latched message.
        late_node = rclpy.create_node('late_listener')
        executor.add_node(late_node)
        late: list[MarkerArray] = []
        late_node.create_subscription(MarkerArray, topics.OBJECTS, late.append, topics.LATCHED_QOS)
        assert probe.spin(lambda: len(late) == 1 and _ids(late[0]) == [1, 2, 3, 4, 5], 20)

        # The association drops object 3 (worker 1's): the map keeps the other four and DELETEs 3; never DELETEALL.
        probe.publish([1, 2, 4, 5], deleted=[3])
        assert probe.spin(lambda: sorted(probe.latest) == [1, 2, 4, 5] and _idle(probe, 'optim_node_1')
                          and _ids(probe.boxes[-1]) == [1, 2, 4, 5] and _state_ids(probe) == [1, 2, 4, 5])
        assert [(m.id, m.action) for m in probe.messages[-1].markers if m.action == Marker.DELETE] == [(3, Marker.DELETE)]
        # The merged map keeps the inputs' data time (STAMP, far from now), worker 1's share and the DELETEs too.
        assert {conv.stamp_to_ns(m.header.stamp) for m in probe.messages[-1].markers + probe.boxes[-1].markers} \
            == {STAMP}
        assert conv.stamp_to_ns(probe.states[-1].header.stamp) == STAMP

        # The merger restarts (same name, nothing resumed): it takes worker 1's latched share at once and
        # publishes the complete map again once its own objects are back from the latched inputs.
        executor.remove_node(workers[0])
        workers[0].on_shutdown()
        workers[0].destroy_node()
        count = len(probe.messages)
        workers[0] = _optimiser('optim_node', Parameter('worker_index', value=0), Parameter('worker_count', value=2))
        executor.add_node(workers[0])
        assert probe.spin(lambda: len(probe.messages) > count and sorted(probe.latest) == [1, 2, 4, 5]
                          and _idle(probe, 'optim_node')), sorted(probe.latest)

        # The optimiser node speaks for every worker: busy, with their pending objects, while worker 1 says it
        # is busy (here a stand-in for worker 1, which no longer reports); another graph's worker 1 of 3 is not
        # one of its workers.
        executor.remove_node(workers[1])
        workers[1].on_shutdown()
        workers[1].destroy_node()
        diagnostics = probe.node.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 10)

        def worker_1_says(state: str, pending: int, worker: str = '1/2') -> None:
            diagnostics.publish(DiagnosticArray(status=[DiagnosticStatus(name='optim_node_1', values=[
                KeyValue(key='state', value=state), KeyValue(key='pending_objects', value=str(pending)),
                KeyValue(key='worker', value=worker)])]))

        worker_1_says('busy', 2)
        assert probe.spin(lambda: probe.status('optim_node').get('pending_by_worker') == '0 2', 10)
        assert probe.status('optim_node')['state'] == 'busy' and probe.status('optim_node')['pending_objects'] == '2'
        worker_1_says('idle', 0)
        worker_1_says('busy', 5, worker='1/3')
        assert probe.spin(lambda: _idle(probe, 'optim_node'), 10), probe.status('optim_node')
        assert probe.status('optim_node')['pending_by_worker'] == '0 0'
    finally:
        executor.shutdown()
        rclpy.shutdown()


def _saved_ids(map_dir) -> list[int]:
    """Object ids of the saved map (empty while there is none yet)."""
    try:
        return [r['id'] for r in json.loads((map_dir / MAP_FILE).read_text())['objects']]
    except (FileNotFoundError, json.JSONDecodeError):
        return []


def test_a_saved_map_is_republished_at_once_by_a_resuming_worker_and_refined_on_new_input(tmp_path):
    rclpy.init()
    executor = SingleThreadedExecutor()
    try:
        first = _optimiser('optim_node', Parameter('map_dir', value=str(tmp_path / 'map')))
        executor.add_node(first)
        probe = _Probe(executor)
        assert probe.spin(lambda: probe.tracks.get_subscription_count() == 1)
        probe.publish([1, 2])
        assert probe.spin(lambda: sorted(probe.latest) == [1, 2] and _idle(probe, 'optim_node'))
        # written after each stage, just after the stage is published: wait for the second object's save
        assert probe.spin(lambda: _saved_ids(tmp_path / 'map') == [1, 2], 10)
        saved = json.loads((tmp_path / 'map' / MAP_FILE).read_text())
        assert saved['objects'][0]['fused_views'] == 3
        client = probe.node.create_client(Trigger, '/optim_node/save_map')
        assert client.wait_for_service(timeout_sec=10)
        future = client.call_async(Trigger.Request())
        assert probe.spin(future.done, 10) and future.result().success, future.result()
        assert str(tmp_path / 'map' / MAP_FILE) in future.result().message
        before = {m.id: conv.marker_to_mesh(m)[0] for m in probe.latest.values()}
        executor.remove_node(first)
        first.on_shutdown()
        first.destroy_node()

        # A restarted optimiser (same name, as after a crash) resumes before any input arrives.
        probe.latest.clear()
        count = len(probe.states)
        second = _optimiser('optim_node', Parameter('resume', value=str(tmp_path / 'map')),
                            Parameter('sparse_enabled', value=True))
        executor.add_node(second)
        assert probe.spin(lambda: sorted(probe.latest) == [1, 2] and len(probe.states) > count, 20)
        assert probe.spin(lambda: probe.status('optim_node').get('objects_resumed') == '2', 10)
        for oid, vertices in before.items():
            assert np.allclose(conv.marker_to_mesh(probe.latest[oid])[0], vertices, atol=1e-5)
        # The latched inputs arrive again, the fused codes first (no track yet: the objects stay), but no views
        # yet: the saved estimates stay (no sparse pass without views)
        probe.publish([1, 2], tracks=False)
        assert probe.spin(lambda: int(probe.status('optim_node').get('object_codes_received', 0)) >= 1
                          and _idle(probe, 'optim_node'))
        assert sorted(second.estimates) == [1, 2] and sorted(probe.latest) == [1, 2]
        probe.publish([1, 2])
        assert probe.spin(lambda: int(probe.status('optim_node').get('resumed_waiting_for_views', 0)) >= 2
                          and _idle(probe, 'optim_node'))
        assert probe.status('optim_node')['resumed_unrefined'] == '2'
        executor.remove_node(second)
        second.on_shutdown()
        second.destroy_node()

        # Without the sparse stage a resumed object goes on with new input at once: more views, a new fused pass.
        third = _optimiser('optim_node', Parameter('resume', value=str(tmp_path / 'map')))
        executor.add_node(third)
        assert probe.spin(lambda: sorted(third.estimates) == [1, 2])
        probe.publish([1, 2, 3], views=5)
        # the published state table reaches the probe after the node's own estimates are updated: wait for it too
        assert probe.spin(lambda: sorted(third.estimates) == [1, 2, 3] and _idle(probe, 'optim_node')
                          and all(e.num_views == 5 for e in third.estimates.values())
                          and _state_ids(probe) == [1, 2, 3])
        table = conv.cloud_to_table(probe.states[-1])
        assert sorted(table['object_id'].tolist()) == [1, 2, 3] and {STAGES[s] for s in table['stage']} == {'fused'}
        executor.remove_node(third)
        third.on_shutdown()
        third.destroy_node()

        # A damaged map: named on /diagnostics, and the worker starts empty instead of crashing.
        (tmp_path / 'map' / MAP_FILE).write_text('{"format": "frodo_object_map", "version": 1, "obj')
        fourth = _optimiser('optim_node', Parameter('resume', value=str(tmp_path / 'map')))
        executor.add_node(fourth)
        assert probe.spin(lambda: 'truncated or corrupt' in probe.status('optim_node').get('last_error', ''), 20)
        assert fourth.estimates == {} and probe.status('optim_node')['warnings'] == '1'
        executor.remove_node(fourth)
        fourth.on_shutdown()
        fourth.destroy_node()
    finally:
        executor.shutdown()
        rclpy.shutdown()


def test_a_resumed_object_is_refined_again_once_enough_new_views_arrive(tmp_path, two_chairs):
    torch.manual_seed(0)
    K, frames, boxes, codes = two_chairs
    H, W = frames[0][2].shape
    rclpy.init()
    executor = SingleThreadedExecutor()
    try:
        probe = _Probe(executor)
        frame_pubs = {name: probe.node.create_publisher(t, topic, topics.FRAME_QOS) for name, t, topic in (
            ('det', Image, topics.DETECTIONS), ('assoc', PointCloud2, topics.ASSOCIATIONS),
            ('pose', PoseStamped, topics.POSE), ('info', CameraInfo, topics.CAMERA_INFO))}

        def publish_objects(views):
            table = np.zeros(2, dtype=OBJECT_CODES_DTYPE)
            for i, oid in enumerate((1, 2)):
                table[i] = (oid, CHAIR, views, codes[oid])
            probe.codes.publish(conv.table_to_cloud(table, STAMP, 'world'))
            probe.tracks.publish(MarkerArray(markers=[conv.box_to_marker(*boxes[oid], 'chair', oid, STAMP, 'world')
                                                      for oid in (1, 2)]))

        # The saved map: both chairs placed at the fused stage from 3 views.
        first = _optimiser('optim_node', Parameter('map_dir', value=str(tmp_path)))
        executor.add_node(first)
        assert probe.spin(lambda: probe.tracks.get_subscription_count() == 1)
        publish_objects(views=3)
        assert probe.spin(lambda: sorted(first.estimates) == [1, 2] and _idle(probe, 'optim_node'))
        executor.remove_node(first)
        first.on_shutdown()
        first.destroy_node()

        second = _optimiser('optim_node', Parameter('resume', value=str(tmp_path)), Parameter('sparse_enabled', value=True),
                            Parameter('dense_enabled', value=False), Parameter('sparse_iterations', value=5),
                            Parameter('sparse_yaw_candidates', value=8))
        executor.add_node(second)
        assert probe.spin(lambda: frame_pubs['assoc'].get_subscription_count() == 1 and sorted(second.estimates) == [1, 2])
        publish_objects(views=2)                      # no views yet: the saved estimates stay
        assert probe.spin(lambda: int(probe.status('optim_node').get('resumed_waiting_for_views', 0)) >= 2
                          and _idle(probe, 'optim_node'))
        frame_pubs['info'].publish(conv.make_camera_info(K, W, H, frames[0][0], 'camera'))
        for stamp, _, labels, Twc in frames:      # six new views of each chair
            rows = np.zeros(2, dtype=ASSOCIATION_DTYPE)
            for i, oid in enumerate((1, 2)):
                ys, xs = np.nonzero(labels == oid)
                rows[i] = (*boxes[oid][0], oid, oid, 1, (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1))
            frame_pubs['pose'].publish(conv.make_pose_stamped(Twc, stamp, 'world'))
            frame_pubs['det'].publish(conv.numpy_to_image(labels, '16UC1', stamp, 'camera'))
            frame_pubs['assoc'].publish(conv.table_to_cloud(rows, stamp, 'world'))
            executor.spin_once(timeout_sec=0.01)
        assert probe.spin(lambda: int(probe.status('optim_node').get('views_stored', 0)) >= 12)
        publish_objects(views=6)                      # the shape node's codes grow with the views: a new pass
        assert probe.spin(lambda: _idle(probe, 'optim_node') and all(e.stage == 'sparse' for e in second.estimates.values()),
                          120), {k: v for k, v in probe.status('optim_node').items() if 'sparse' in k or k == 'state'}
        assert probe.status('optim_node')['resumed_unrefined'] == '0'
        # the published state table follows the node's own estimates
        assert probe.spin(lambda: {STAGES[s] for s in conv.cloud_to_table(probe.states[-1])['stage']} == {'sparse'})
        executor.remove_node(second)
        second.on_shutdown()
        second.destroy_node()
    finally:
        executor.shutdown()
        rclpy.shutdown()
