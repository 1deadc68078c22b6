"""The detection node in a real rclpy graph: every image frame with its instance image yields one
/frodo/detections image with the same stamp; bad frames are reported on /diagnostics and skipped."""

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image

from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.testing import latest_status
from frodo_common.testing import spin_until as spin
from frodo_detection.detection_node import DetectionNode

CHAIR, PERSON = 62, 1


@pytest.fixture
def graph():
    rclpy.init()
    executor = SingleThreadedExecutor()
    probe = rclpy.create_node('detection_probe')
    executor.add_node(probe)
    got = {'det': [], 'diag': []}
    probe.create_subscription(Image, topics.DETECTIONS, got['det'].append, topics.FRAME_QOS)
    probe.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, got['diag'].append, 10)
    pubs = {'image': probe.create_publisher(Image, topics.IMAGE, topics.FRAME_QOS),
            'instances': probe.create_publisher(Image, topics.INSTANCES, topics.FRAME_QOS)}

    def spin_until(cond, timeout=8.0):
        return spin(executor, cond, timeout)

    def add(node):
        executor.add_node(node)
        spin_until(lambda: pubs['image'].get_subscription_count() > 0, 5.0)
        return node

    try:
        yield add, pubs, got, spin_until
    finally:
        executor.shutdown()
        rclpy.shutdown()


def _status(got, name='detection_node'):
    return latest_status(got['diag'], name)


def test_external_instances_are_filtered_and_bad_frames_survived(graph):
    add, pubs, got, spin_until = graph
    add(DetectionNode(parameter_overrides=[Parameter('min_area', value=50), Parameter('diagnostics_period', value=0.2)]))
    inst = np.zeros((40, 60), np.uint16)
    inst[5:25, 5:25] = CHAIR * 256 + 1
    inst[5:25, 30:50] = PERSON * 256 + 2
    rgb = np.zeros((40, 60, 3), np.uint8)
    # Instances first, image second: matched by stamp whatever the order.
    pubs['instances'].publish(conv.numpy_to_image(inst, '16UC1', 1000, 'cam'))
    pubs['image'].publish(conv.numpy_to_image(rgb, 'rgb8', 1000, 'cam'))
    assert spin_until(lambda: len(got['det']) == 1)
    out = got['det'][0]
    assert conv.stamp_to_ns(out.header.stamp) == 1000 and out.header.frame_id == 'cam' and out.encoding == '16UC1'
    labels = conv.image_to_numpy(out)
    assert set(np.unique(labels)) == {0, CHAIR * 256 + 1}
    # Wrong encoding and size mismatch: reported, skipped.
    pubs['image'].publish(conv.numpy_to_image(rgb, 'rgb8', 2000, 'cam'))
    pubs['instances'].publish(conv.numpy_to_image(inst.astype(np.uint8), 'mono8', 2000, 'cam'))
    pubs['image'].publish(conv.numpy_to_image(rgb, 'rgb8', 3000, 'cam'))
    pubs['instances'].publish(conv.numpy_to_image(inst[:20], '16UC1', 3000, 'cam'))
    # An empty frame still gives an (all zero) output.
    pubs['image'].publish(conv.numpy_to_image(rgb, 'rgb8', 4000, 'cam'))
    pubs['instances'].publish(conv.numpy_to_image(np.zeros_like(inst), '16UC1', 4000, 'cam'))
    assert spin_until(lambda: len(got['det']) == 2)
    assert conv.stamp_to_ns(got['det'][1].header.stamp) == 4000 and not conv.image_to_numpy(got['det'][1]).any()
    # A status report sent between the drops and the last frame can arrive after that frame's
    # output (different topics keep no order), so wait for the counters to reach their final values.
    assert spin_until(lambda: _status(got).get('frames_dropped') == '2' and _status(got).get('frames_published') == '2')
    status = _status(got)
    assert status['errors'] == '2' and 'is 60x20 but colour image is 60x40' in status['last_error']


class _StubDetector:
    """Stands in for MaskRCNNDetector (whose wiring test_core checks with the real network)."""

    def __init__(self):
        self.calls = 0

    def detect(self, rgb):
        self.calls += 1
        out = np.zeros(rgb.shape[:2], np.uint16)
        out[4:30, 4:30] = CHAIR * 256 + 1
        out[30:40, 40:44] = CHAIR * 256 + 2          # tiny: filtered out
        return out


def test_maskrcnn_backend_runs_the_detector_on_every_image(graph):
    add, pubs, got, spin_until = graph
    detector = _StubDetector()
    # min_area is given at 640x480: 10000 there is 100 px in this 64x48 image.
    add(DetectionNode(detector=detector, parameter_overrides=[Parameter('backend', value='maskrcnn'),
                                                              Parameter('min_area', value=10000)]))
    rgb = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    pubs['image'].publish(conv.numpy_to_image(rgb, 'bgr8', 5000, 'cam'))
    pubs['image'].publish(conv.numpy_to_image(rgb, 'rgb8', 6000, 'cam'))
    assert spin_until(lambda: len(got['det']) == 2)
    out = conv.image_to_numpy(got['det'][0])
    assert out.shape == (48, 64) and conv.stamp_to_ns(got['det'][0].header.stamp) == 5000
    assert set(np.unique(out)) == {0, CHAIR * 256 + 1} and detector.calls == 2


def test_bad_colour_images_and_unknown_categories_are_converted_or_dropped_with_a_diagnostic(graph):
    add, pubs, got, spin_until = graph
    add(DetectionNode(parameter_overrides=[Parameter('min_area', value=50), Parameter('diagnostics_period', value=0.2)]))
    inst = np.zeros((40, 60), np.uint16)
    inst[5:25, 5:25] = CHAIR * 256 + 1
    inst[25:38, 30:50] = 200 * 256 + 1                         # category 200: no COCO class
    rgb = np.random.default_rng(3).integers(0, 255, (40, 60, 3), dtype=np.uint8)
    bgra = np.concatenate([rgb[..., ::-1], np.full((40, 60, 1), 255, np.uint8)], axis=2)
    short = conv.numpy_to_image(rgb, 'rgb8', 3000, 'cam')
    short.data = bytes(short.data)[:-7]                          # step x height != data size
    wide = conv.numpy_to_image(np.zeros((1, 10000, 3), np.uint8), 'rgb8', 5000, 'cam')
    frames = [(1000, conv.numpy_to_image(rgb[..., 0], 'mono8', 1000, 'cam'), inst),   # converted
              (2000, conv.numpy_to_image(bgra, 'bgra8', 2000, 'cam'), inst),            # converted
              (3000, short, inst),                                                      # dropped
              (4000, conv.numpy_to_image(inst, '16UC1', 4000, 'cam'), inst),            # dropped: not colour
              (5000, wide, np.zeros((1, 10000), np.uint16)),                           # dropped: too wide
              (6000, conv.numpy_to_image(rgb, 'rgb8', 6000, 'cam'), np.zeros_like(inst))]  # empty: published
    for stamp, image, instances in frames:
        pubs['instances'].publish(conv.numpy_to_image(instances, '16UC1', stamp, 'cam'))
        pubs['image'].publish(image)
    assert spin_until(lambda: len(got['det']) == 3)
    assert [conv.stamp_to_ns(m.header.stamp) for m in got['det']] == [1000, 2000, 6000]
    assert set(np.unique(conv.image_to_numpy(got['det'][0]))) == {0, CHAIR * 256 + 1}
    # counters are reported from their own thread, and the empty frame is counted after it is published: wait
    # for the report that holds the last frame too
    assert spin_until(lambda: _status(got).get('frames_dropped') == '3'
                      and _status(got).get('frames_without_detections') == '1')
    status = _status(got)
    assert status['images_converted'] == '2'
    assert status['instances_unknown_category'] == '2' and status['warnings'] == '3'
    assert status['errors'] == '3'
