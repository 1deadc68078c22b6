"""Bad camera input reaching the association node (the first node that needs intrinsics and poses):
camera info with zero focal length or a size other than the images', non-unit quaternions. Each is
rejected with a diagnostic naming the problem and the node keeps working on the good frames."""
from __future__ import annotations

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from frodo_association.association_node import AssociationNode
from frodo_association.synthetic import make_scene
from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.testing import latest_status, spin_until


def info_size(node: AssociationNode):
    """(width, height) of the camera info the node holds, None before a valid one."""
    held = node.cache.camera_info
    return None if held is None else tuple(held[1])


def test_bad_camera_info_and_quaternions_are_rejected_and_survived():
    scene = make_scene(2, seed=3, n_frames=6)
    rclpy.init()
    executor = SingleThreadedExecutor()
    try:
        node = AssociationNode(parameter_overrides=[Parameter('diagnostics_period', value=0.2)])
        probe = rclpy.create_node('bad_camera_probe')
        executor.add_node(node)
        executor.add_node(probe)
        tables, diags = {}, []
        probe.create_subscription(PointCloud2, topics.ASSOCIATIONS,
                                  lambda m: tables.__setitem__(conv.stamp_to_ns(m.header.stamp), m), topics.FRAME_QOS)
        probe.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, diags.append, 10)
        det = probe.create_publisher(Image, topics.DETECTIONS, topics.FRAME_QOS)
        pose = probe.create_publisher(PoseStamped, topics.POSE, topics.FRAME_QOS)
        info = probe.create_publisher(CameraInfo, topics.CAMERA_INFO, topics.FRAME_QOS)
        assert spin_until(executor, lambda: min(p.get_subscription_count() for p in (det, pose, info)) > 0)

        def status():
            return latest_status(diags, 'association_node')

        def send(frame, pose_msg=None):
            pose.publish(pose_msg or conv.make_pose_stamped(frame.T_world_camera, frame.stamp, 'world'))
            det.publish(conv.numpy_to_image(frame.instances, '16UC1', frame.stamp, 'cam'))

        f = scene.frames
        zero_focal = conv.make_camera_info(np.diag([0.0, 0.0, 1.0]), *f[0].size, f[0].stamp, 'cam')
        info.publish(zero_focal)
        assert spin_until(executor, lambda: 'fx, fy must be finite and > 0' in status().get('last_error', ''))
        # A camera info whose size is not the images': the frame is dropped, naming both sizes.
        w, h = f[0].size
        info.publish(conv.make_camera_info(f[0].K, w * 2, h * 2, f[0].stamp, 'cam'))
        assert spin_until(executor, lambda: info_size(node) == (w * 2, h * 2))  # topics are not ordered
        send(f[0])
        assert spin_until(executor, lambda: 'do not match camera_info' in status().get('last_error', ''))
        assert f[0].stamp not in tables
        # The right camera info: good frames go through; a pose with a non-unit quaternion is dropped.
        info.publish(conv.make_camera_info(f[1].K, w, h, f[1].stamp, 'cam'))
        assert spin_until(executor, lambda: info_size(node) == (w, h))
        send(f[1])
        assert spin_until(executor, lambda: f[1].stamp in tables)
        bad_pose = conv.make_pose_stamped(f[2].T_world_camera, f[2].stamp, 'world')
        bad_pose.pose.orientation.w *= 3.0
        send(f[2], bad_pose)
        send(f[3])
        assert spin_until(executor, lambda: f[3].stamp in tables)
        assert spin_until(executor, lambda: 'not 1' in status().get('last_error', '') and
                          status().get('frames_dropped') == '2')
        assert f[2].stamp not in tables
    finally:
        executor.shutdown()
        rclpy.shutdown()
