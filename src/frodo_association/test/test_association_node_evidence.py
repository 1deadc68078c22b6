"""The association node's optional inputs in a real rclpy graph (issue 9, contract v1.1): registered depth
(32FC1 m and 16UC1 mm) and SLAM landmarks give detections a visible-surface depth; handheld keyframes of a
kitchen come in with depth for the first half and landmarks only for the rest; a depth image with the wrong
encoding or size is reported and survived, and the frame is still associated."""

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from visualization_msgs.msg import Marker, MarkerArray

from frodo_association.association_node import AssociationNode
from frodo_association.handheld import make_handheld_scene
from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.testing import latest_status
from frodo_common.testing import spin_until as spin


def test_association_node_with_depth_and_landmarks():
    scene = make_handheld_scene(3, n_chairs=2, n_keyframes=16, clutter=0)
    rclpy.init()
    executor = SingleThreadedExecutor()
    try:
        node = AssociationNode(parameter_overrides=[Parameter('diagnostics_period', value=0.2)])
        probe = rclpy.create_node('association_evidence_probe')
        executor.add_node(node)
        executor.add_node(probe)
        assoc, tracks, diags = {}, [], []
        probe.create_subscription(PointCloud2, topics.ASSOCIATIONS,
                                  lambda m: assoc.__setitem__(conv.stamp_to_ns(m.header.stamp), m), topics.FRAME_QOS)
        probe.create_subscription(MarkerArray, topics.TRACKS, tracks.append, topics.LATCHED_QOS)
        probe.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, diags.append, 10)
        det_pub = probe.create_publisher(Image, topics.DETECTIONS, topics.FRAME_QOS)
        depth_pub = probe.create_publisher(Image, '/camera/depth/image_raw', topics.FRAME_QOS)
        slam_pub = probe.create_publisher(PointCloud2, topics.SLAM_POINTS, topics.FRAME_QOS)
        pose_pub = probe.create_publisher(PoseStamped, topics.POSE, topics.FRAME_QOS)
        info_pub = probe.create_publisher(CameraInfo, topics.CAMERA_INFO, topics.FRAME_QOS)

        def spin_until(cond, timeout=20.0):
            return spin(executor, cond, timeout)

        def status():
            return latest_status(diags, 'association_node')

        spin_until(lambda: det_pub.get_subscription_count() > 0 and depth_pub.get_subscription_count() > 0
                   and slam_pub.get_subscription_count() > 0)
        f0 = scene.frames[0]
        info_pub.publish(conv.make_camera_info(f0.K, *f0.size, f0.stamp, 'cam'))
        half = len(scene.frames) // 2
        for k, f in enumerate(scene.frames):
            if k == half:       # from here on no depth: the landmarks take over
                slam_pub.publish(conv.xyz_to_cloud(scene.landmarks.astype(np.float32), f.stamp, 'world'))
            if k == 1:          # wrong encoding: reported, the frame is associated without depth
                depth_pub.publish(conv.numpy_to_image(np.clip(f.depth * 50, 0, 255).astype(np.uint8), 'mono8', f.stamp,
                                                      'cam'))
            elif k == 2:        # not registered (wrong size): reported, not used
                depth_pub.publish(conv.numpy_to_image(f.depth[::2, ::2].copy(), '32FC1', f.stamp, 'cam'))
            elif k % 2 and k < half:
                depth_pub.publish(conv.numpy_to_image(np.round(f.depth * 1000).astype(np.uint16), '16UC1',
                                                      f.stamp, 'cam'))
            elif k < half:
                depth_pub.publish(conv.numpy_to_image(f.depth, '32FC1', f.stamp, 'cam'))
            spin_until(lambda: False, timeout=0.05)    # depth first, as from a bag beside the detection node
            pose_pub.publish(conv.make_pose_stamped(f.T_world_camera, f.stamp, 'world'))
            det_pub.publish(conv.numpy_to_image(f.instances, '16UC1', f.stamp, 'cam'))
        assert spin_until(lambda: all(f.stamp in assoc for f in scene.frames)
                          and status().get('frames_published') == str(len(scene.frames)))
        st = status()
        assert int(st['frames_with_depth']) == half - 2
        assert int(st['frames_with_landmarks']) == len(scene.frames) - half
        assert int(st['errors']) >= 1 and int(st['warnings']) >= 1
        assert st['evidence_ms_mean'] != 'n/a'
        # the depth images' visible surfaces reach the box fit as points, the landmark-only frames give none
        assoc_rows = node.frame_associator.associator
        with_points = np.isfinite(assoc_rows.rows.points[:, 0, 0])
        depth_frames = set(assoc_rows.rows.frame[with_points])
        assert depth_frames and max(depth_frames) < half and 1 not in depth_frames and 2 not in depth_frames
        cubes = [m for m in tracks[-1].markers if m.action == Marker.ADD]
        assert len(cubes) == len(scene.objects)
        for m in cubes:
            centre, _, _ = conv.marker_to_box(m)
            err = min(np.linalg.norm(centre - o.center) for o in scene.objects)
            assert err < 0.2, (m.ns, centre)
    finally:
        executor.shutdown()
        rclpy.shutdown()
