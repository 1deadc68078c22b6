"""optim_node builds an object's TRIANGLE_LIST marker once per estimate: republishing the map after another
object's stage re-stamps the cached marker instead of rebuilding it, its points stay an array, and the map it
publishes (serialised from those arrays) is the message a rebuilt marker would give."""
import numpy as np
import rclpy
from rclpy.serialization import deserialize_message, serialize_message
from visualization_msgs.msg import MarkerArray

from frodo_common import conversions as conv
from frodo_optim.core import fused_estimate
from frodo_optim.optim_node import OptimNode


def test_mesh_marker_is_built_once_per_estimate_and_restamped():
    rclpy.init()
    try:
        node = OptimNode()
        try:
            prior = node.reconstructor.prior
            code = prior.training_codes[2].numpy()
            mesh = prior.mesh(code, resolution=24)
            box = (np.array([1.0, 2.0, 0.4]), np.array([0.5, 0.5, 0.8]), 0.3)
            est = fused_estimate(5, 'chair', 62, code, 3, mesh, box)
            rgba = (0.95, 0.55, 0.15, 1.0)
            first = node._mesh_marker(est, 1_000, 'world', rgba)
            again = node._mesh_marker(est, 2_000_000_123, 'world', rgba)
            fresh = conv.mesh_to_marker(est.mesh_world.vertices, est.mesh_world.faces, 'chair', 5, 2_000_000_123,
                                        'world', rgba)
            assert again is first and conv.with_points(*again.parts()) == fresh   # as rebuilt, new stamp included
            assert node.map_wire                                   # Fast DDS reads the serialised map back
            delete = conv.delete_marker('table', 9, 5, 'world')
            as_message = serialize_message(MarkerArray(markers=[delete, fresh]))   # colours: float32 on the wire
            assert deserialize_message(node._map_message([delete, again]), MarkerArray) == \
                deserialize_message(as_message, MarkerArray)
            replaced = fused_estimate(5, 'chair', 62, code, 4, mesh, (box[0] + 1.0, box[1], box[2]))
            moved = node._mesh_marker(replaced, 3_000, 'world', rgba)
            assert moved is not first and moved.points[0, 0] == first.points[0, 0] + 1.0
            node.estimates = {5: replaced}
            node._publish()
            assert set(node.mesh_markers) == {5}
            node.estimates = {}
            node._publish()                                # the object is gone: its cached marker too
            assert node.mesh_markers == {}
        finally:
            node.on_shutdown()
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
