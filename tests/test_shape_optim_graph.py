"""Shape node and optimiser node together in a real rclpy graph, with the shipped furniture prior.

Frames of the demo bag (image, instance labels, camera pose and intrinsics) and one object's association rows
and box go in; per-frame codes, fused object codes, a placed mesh on /frodo/objects, /frodo/boxes and
/frodo/object_states come out (first the fused placement, then the sparse and the dense stages' refinements,
paper Sec. 4.3),
and the mesh scores well against the bag's ground truth (CONTRACT.md protocol). Bad input (detections of
another size than the image, a box with NaN) is reported on /diagnostics and survived.
"""
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from visualization_msgs.msg import Marker, MarkerArray

from frodo_association.core import ASSOCIATION_DTYPE
from frodo_association.evaluate import scene_from_bag
from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.testing import latest_status
from frodo_common.testing import spin_until as spin
from frodo_common.bag import BagReader
from frodo_common.evaluation import EvalObject, evaluate, load_ground_truth_bag
from frodo_optim.optim_node import OptimNode
from frodo_optim.states import OBJECT_STATES, STAGE_REASONS, STAGES
from frodo_shape.shape_node import ShapeNode

BAG = Path(__file__).resolve().parents[1] / 'bags' / 'demo_walk.mcap'
TABLE_CLASS = 67
OBJECT_ID = 7


def demo_frames(n_frames: int = 6):
    """(stamp, image msg, instances, the table's label, its box, the SynthFrame with K and pose) for n frames
    showing the bag's last ground-truth table, and that table's ground-truth box."""
    scene, _ = scene_from_bag(BAG)
    target = next(k for k, o in reversed(list(enumerate(scene.objects))) if o.coco_id == TABLE_CLASS)
    images = {conv.stamp_to_ns(m.decode().header.stamp): m.decode()
              for m in BagReader(BAG).messages([topics.IMAGE])}
    frames = []
    for f in scene.frames:
        labels = [lab for lab, g in f.gt.items() if g == target]
        if labels and f.stamp in images:
            ys, xs = np.nonzero(f.instances == labels[0])
            frames.append((f.stamp, images[f.stamp], f.instances, labels[0],
                           (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1), f))
    step = max(1, len(frames) // n_frames)
    return frames[::step][:n_frames], scene.objects[target]


def association_table(stamp, label, bbox, centre) -> PointCloud2:
    row = np.zeros(1, dtype=ASSOCIATION_DTYPE)
    row[0] = (*centre, label, OBJECT_ID, 1, bbox)
    return conv.table_to_cloud(row, stamp, 'world')


@pytest.mark.skipif(not BAG.exists(), reason='demo bag missing')
def test_shape_and_optimiser_nodes_reconstruct_an_object_from_the_demo_bag():
    frames, gt_box = demo_frames()
    assert len(frames) >= 4
    rclpy.init()
    executor = SingleThreadedExecutor()
    try:
        period = Parameter('diagnostics_period', value=0.2)
        shape = ShapeNode(parameter_overrides=[period])
        optim = OptimNode(parameter_overrides=[period, Parameter('mesh_resolution', value=48),
                                               Parameter('dense_iterations', value=8),
                                               Parameter('dense_grid_resolution', value=24)])
        probe = rclpy.create_node('shape_optim_probe')
        for node in (shape, optim, probe):
            executor.add_node(node)
        codes, object_codes, objects, boxes, states, diags = [], [], [], [], [], []
        probe.create_subscription(PointCloud2, topics.CODES, codes.append, topics.FRAME_QOS)
        probe.create_subscription(PointCloud2, topics.OBJECT_CODES, object_codes.append, topics.LATCHED_QOS)
        probe.create_subscription(MarkerArray, topics.OBJECTS, objects.append, topics.LATCHED_QOS)
        probe.create_subscription(MarkerArray, topics.BOXES, boxes.append, topics.LATCHED_QOS)
        probe.create_subscription(PointCloud2, OBJECT_STATES, states.append, topics.LATCHED_QOS)
        probe.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, diags.append, 10)
        image_pub = probe.create_publisher(Image, topics.IMAGE, topics.FRAME_QOS)
        det_pub = probe.create_publisher(Image, topics.DETECTIONS, topics.FRAME_QOS)
        assoc_pub = probe.create_publisher(PointCloud2, topics.ASSOCIATIONS, topics.FRAME_QOS)
        tracks_pub = probe.create_publisher(MarkerArray, topics.TRACKS, topics.LATCHED_QOS)
        info_pub = probe.create_publisher(CameraInfo, topics.CAMERA_INFO, topics.FRAME_QOS)
        pose_pub = probe.create_publisher(PoseStamped, topics.POSE, topics.FRAME_QOS)

        def spin_until(cond, timeout=30.0):
            return spin(executor, cond, timeout)

        def status(name):
            return latest_status(diags, name)

        assert spin_until(lambda: image_pub.get_subscription_count() > 0 and assoc_pub.get_subscription_count() > 0
                          and tracks_pub.get_subscription_count() > 0)
        # Bad input first: detections of another size than the image.
        stamp0, image0, instances0, label0, bbox0, frame0 = frames[0]
        bad_stamp = stamp0 - 1
        image_pub.publish(conv.numpy_to_image(np.zeros((4, 4, 3), np.uint8), 'rgb8', bad_stamp, 'camera'))
        det_pub.publish(conv.numpy_to_image(instances0, '16UC1', bad_stamp, 'camera'))
        assoc_pub.publish(association_table(bad_stamp, label0, bbox0, gt_box.center))
        assert spin_until(lambda: int(status('shape_node').get('errors', 0)) >= 1)
        assert spin_until(lambda: info_pub.get_subscription_count() > 0 and pose_pub.get_subscription_count() > 0)
        for stamp, image, instances, label, bbox, frame in frames:
            pose_pub.publish(conv.make_pose_stamped(frame.T_world_camera_observed, stamp, 'world'))
            image_pub.publish(image)
            det_pub.publish(conv.numpy_to_image(instances, '16UC1', stamp, 'camera'))
            assoc_pub.publish(association_table(stamp, label, bbox, gt_box.center))
            executor.spin_once(timeout_sec=0.01)
        # camera info only after the frames: the optimiser holds complete frames until it arrives
        info_pub.publish(conv.make_camera_info(frame0.K, *frame0.size, stamp0, 'camera'))
        assert spin_until(lambda: len(codes) >= len(frames) and object_codes
                          and conv.cloud_to_table(object_codes[-1])['num_views'].tolist() == [len(frames)])
        assert all(conv.cloud_to_table(m)['object_id'].tolist() == [OBJECT_ID] for m in codes)
        fused = conv.cloud_to_table(object_codes[-1])
        assert fused['object_id'].tolist() == [OBJECT_ID]
        assert fused['category'][0] == TABLE_CLASS and np.isfinite(fused['code']).all()

        nan_box = conv.box_to_marker(np.full(3, np.nan), gt_box.size, 0.0, 'dining table', OBJECT_ID + 1, stamp0,
                                     'world')
        good_box = conv.box_to_marker(gt_box.center, gt_box.size, gt_box.yaw, 'dining table', OBJECT_ID, stamp0,
                                      'world')
        tracks_pub.publish(MarkerArray(markers=[nan_box, good_box]))
        assert spin_until(lambda: objects and any(m.id == OBJECT_ID for m in objects[-1].markers)
                          and status('optim_node').get('state') == 'idle'
                          and status('optim_node').get('dense_objects') == '1'
                          and states and 'dense' in {STAGES[s] for s in conv.cloud_to_table(states[-1])['stage']},
                          timeout=180.0), status('optim_node')
        assert int(status('optim_node')['errors']) >= 1       # the NaN box
        mesh_marker = next(m for m in objects[-1].markers if m.id == OBJECT_ID)
        assert mesh_marker.type == Marker.TRIANGLE_LIST and mesh_marker.header.frame_id == 'world'
        vertices, faces = conv.marker_to_mesh(mesh_marker)
        assert len(faces) > 500 and np.isfinite(vertices).all()
        assert [m.id for m in boxes[-1].markers if m.action == Marker.ADD] == [OBJECT_ID]
        state = conv.cloud_to_table(states[-1])
        assert list(state['object_id']) == [OBJECT_ID] and STAGES[state['stage'][0]] == 'dense'
        assert STAGE_REASONS[state['stage_reason'][0]] == 'all stages done'
        stages = [STAGES[t['stage'][t['object_id'] == OBJECT_ID][0]] for t in map(conv.cloud_to_table, states)
                  if (t['object_id'] == OBJECT_ID).any()]
        # each stage is published as it completes: fused, then sparse, then dense
        assert stages.index('fused') < stages.index('sparse') < stages.index('dense')
        assert int(status('optim_node')['views_held']) >= 4

        import trimesh
        gt = [o for o in load_ground_truth_bag(BAG) if o.class_name == 'dining table']
        pred = EvalObject(OBJECT_ID, 'dining table', trimesh.Trimesh(vertices, faces, process=False))
        result = evaluate([pred], gt)
        assert result.overall.recall == 50.0 and len(result.pairs) == 1   # one of the two tables
        assert result.pairs[0].centroid_distance_m < 0.1 and result.pairs[0].f1 > 80.0, result.table()
        assert status('shape_node')['objects'] == '1'
        # Every output keeps the bag's time (2023), never the nodes' clocks: per-frame codes their frame's stamp,
        # the fused codes the newest frame encoded, the object's markers the newest frame its estimate used (the
        # track came with the first frame's stamp), the state table the newest frame the optimiser received.
        newest = max(f[0] for f in frames)
        assert sorted(conv.stamp_to_ns(m.header.stamp) for m in codes) == sorted(f[0] for f in frames)
        assert conv.stamp_to_ns(object_codes[-1].header.stamp) == newest
        assert {conv.stamp_to_ns(m.header.stamp) for m in objects[-1].markers + boxes[-1].markers
                if m.id == OBJECT_ID} == {newest}
        assert conv.stamp_to_ns(states[-1].header.stamp) == newest
        assert time.time_ns() - newest > 365 * 86400 * 10**9       # the bag is from 2023, not now()
    finally:
        executor.shutdown()
        rclpy.shutdown()
