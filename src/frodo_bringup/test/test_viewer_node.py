"""The Rerun viewer node, run as its own process in a real rclpy graph, records frames, detections and object
meshes into an .rrd that `rerun rrd verify` accepts, all at their messages' stamps (bag time, one time range;
no wall-clock timeline); an object missing from a later /frodo/objects message (each one is the complete map,
CONTRACT.md) is cleared."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image
from visualization_msgs.msg import MarkerArray

from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.geometry import look_at
from frodo_common.testing import latest_status


def _wait_for_subscribers(node, publishers, timeout=20.0):
    deadline = time.time() + timeout
    while time.time() < deadline and any(p.get_subscription_count() == 0 for p in publishers):
        rclpy.spin_once(node, timeout_sec=0.1)


def _start_viewer(rrd: Path) -> subprocess.Popen:
    """The viewer node as its own process, saving to rrd."""
    return subprocess.Popen([sys.executable, '-m', 'frodo_bringup.viewer_node', '--ros-args',
                             '-p', f'rrd_path:={rrd}', '-p', 'mode:=save'],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)


def _stop_viewer(proc: subprocess.Popen) -> str:
    """SIGINT the viewer (as a launcher does); its output."""
    os.killpg(proc.pid, signal.SIGINT)
    return proc.communicate(timeout=20)[0]


def test_viewer_records_a_verifiable_rrd(tmp_path):
    rrd = tmp_path / 'view.rrd'
    proc = _start_viewer(rrd)
    rclpy.init()
    try:
        node = rclpy.create_node('viewer_feeder')
        pubs = {'image': node.create_publisher(Image, topics.IMAGE, topics.FRAME_QOS),
                'info': node.create_publisher(CameraInfo, topics.CAMERA_INFO, topics.FRAME_QOS),
                'pose': node.create_publisher(PoseStamped, topics.POSE, topics.FRAME_QOS),
                'det': node.create_publisher(Image, topics.DETECTIONS, topics.FRAME_QOS),
                'objects': node.create_publisher(MarkerArray, topics.OBJECTS, topics.LATCHED_QOS)}
        diags = []
        node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, diags.append, 50)
        _wait_for_subscribers(node, pubs.values())
        K = np.array([[100.0, 0, 32], [0, 100, 24], [0, 0, 1]])
        stamps = [1_700_000_000_000_000_000 + i * 10**8 for i in range(3)]
        labels = np.zeros((48, 64), np.uint16)
        labels[10:20, 10:20] = 62 * 256 + 1
        for stamp in stamps:
            i = stamps.index(stamp)
            pubs['info'].publish(conv.make_camera_info(K, 64, 48, stamp, 'cam'))
            pubs['image'].publish(conv.numpy_to_image(np.full((48, 64, 3), 40 * i, np.uint8), 'rgb8', stamp, 'cam'))
            pubs['pose'].publish(conv.make_pose_stamped(look_at([2, 0, 1], [0, 0, 0.5]), stamp, 'world'))
            pubs['det'].publish(conv.numpy_to_image(labels, '16UC1', stamp, 'cam'))
        verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=float)
        # the optimiser stamps an object with the newest frame it used (data time)
        pubs['objects'].publish(MarkerArray(markers=[conv.mesh_to_marker(verts, [[0, 1, 2]], 'chair', 1, stamps[1],
                                                                         'world')]))
        deadline = time.time() + 20
        while time.time() < deadline and latest_status(diags, 'viewer_node').get('maps_logged') != '1':
            rclpy.spin_once(node, timeout_sec=0.1)
        assert latest_status(diags, 'viewer_node').get('objects_shown') == '1'
        # The next map has object 2 only, and no DELETE of object 1 (e.g. from a restarted optimiser).
        pubs['objects'].publish(MarkerArray(markers=[conv.mesh_to_marker(verts, [[0, 1, 2]], 'chair', 2, stamps[2],
                                                                         'world')]))
        deadline = time.time() + 20
        while time.time() < deadline and latest_status(diags, 'viewer_node').get('maps_logged') != '2':
            rclpy.spin_once(node, timeout_sec=0.1)
        assert latest_status(diags, 'viewer_node').get('objects_shown') == '1'
        assert int(latest_status(diags, 'viewer_node').get('frames_logged', 0)) == 3
    finally:
        rclpy.shutdown()
        out = _stop_viewer(proc)
    assert proc.returncode == 0, out
    assert rrd.exists() and rrd.stat().st_size > 0
    rerun_cli = Path(sys.executable).with_name('rerun')
    verify = subprocess.run([str(rerun_cli), 'rrd', 'verify', str(rrd)], capture_output=True, text=True, timeout=60)
    assert verify.returncode == 0, verify.stdout + verify.stderr
    stats = subprocess.run([str(rerun_cli), 'rrd', 'print', str(rrd)], capture_output=True, text=True, timeout=60)
    assert 'world/objects' in stats.stdout + stats.stderr and 'world/camera' in stats.stdout + stats.stderr
    assert '/world/objects/chair_1 - data columns: [Clear:is_recursive]' in stats.stdout + stats.stderr
    assert '/world/objects/chair_2 - data columns: [Clear' not in stats.stdout + stats.stderr
    from rerun.chunk import RrdReader
    timed: dict[str, set] = {}
    for chunk in RrdReader(rrd).stream():
        batch = chunk.to_record_batch()
        assert set(chunk.timeline_names) <= {'stamp', 'frame'}          # no log_time / log_tick
        if 'stamp' in batch.schema.names:
            timed.setdefault(chunk.entity_path, set()).update(batch.column('stamp').cast(pa.int64()).to_pylist())
    assert timed['/world/camera/image/rgb'] == set(stamps)
    assert timed['/world/camera/image/detections'] == set(stamps)
    assert timed['/world/objects/chair_1'] == {stamps[1], stamps[2]}      # shown at frame 2, cleared at frame 3
    assert timed['/world/objects/chair_2'] == {stamps[2]}


def test_frames_completed_before_the_camera_info_are_logged_when_it_arrives(tmp_path):
    """Image and pose of a frame may arrive before the first camera_info (another topic): the frame is held and
    logged once the camera info comes, not dropped."""
    proc = _start_viewer(tmp_path / 'view.rrd')
    rclpy.init()
    try:
        node = rclpy.create_node('viewer_feeder')
        image = node.create_publisher(Image, topics.IMAGE, topics.FRAME_QOS)
        pose = node.create_publisher(PoseStamped, topics.POSE, topics.FRAME_QOS)
        info = node.create_publisher(CameraInfo, topics.CAMERA_INFO, topics.FRAME_QOS)
        diags = []
        node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, diags.append, 50)
        _wait_for_subscribers(node, [image, pose, info])
        stamps = [1_700_000_000_000_000_000 + i * 10**8 for i in range(2)]
        for stamp in stamps:
            image.publish(conv.numpy_to_image(np.zeros((48, 64, 3), np.uint8), 'rgb8', stamp, 'cam'))
            pose.publish(conv.make_pose_stamped(look_at([2, 0, 1], [0, 0, 0.5]), stamp, 'world'))
        deadline = time.time() + 3       # the viewer has them, without a camera info: nothing logged yet
        while time.time() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
        assert int(latest_status(diags, 'viewer_node').get('frames_logged', 0)) == 0
        K = np.array([[100.0, 0, 32], [0, 100, 24], [0, 0, 1]])
        info.publish(conv.make_camera_info(K, 64, 48, stamps[-1], 'cam'))
        deadline = time.time() + 20
        while time.time() < deadline and latest_status(diags, 'viewer_node').get('frames_logged') != '2':
            rclpy.spin_once(node, timeout_sec=0.1)
        assert latest_status(diags, 'viewer_node').get('frames_logged') == '2'
    finally:
        rclpy.shutdown()
        out = _stop_viewer(proc)
    assert proc.returncode == 0, out
