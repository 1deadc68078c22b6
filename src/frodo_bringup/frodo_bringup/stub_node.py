"""A configurable stand-in node for launcher tests and dry runs of the command line.

It counts images on the contract image topic (optionally taking its time over each) and reports on
/diagnostics; optionally it crashes with a given exit code after a delay, ignores Ctrl-C or stalls in its ROS
teardown, and optionally it behaves like a minimal optimiser: `state` / `pending_objects` diagnostics and one
fixed object (a tetrahedron and its box) on the latched /frodo/objects and /frodo/boxes once images have
arrived. Launch it under any node name with
`-r __node:=NAME`.
"""
from __future__ import annotations

import ctypes
import math
import os
import signal
import sys
import time
from typing import Any

import numpy as np
from sensor_msgs.msg import Image
from visualization_msgs.msg import MarkerArray

from frodo_common import topics
from frodo_common.conversions import box_to_marker, mesh_to_marker, stamp_to_ns
from frodo_common.node import FrodoNode, run_node
from frodo_common.params import ParamSpec

PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec('crash_after', 0.0, 'Seconds after start-up to exit on purpose (0: never).'),
    ParamSpec('crash_code', 3, 'Exit code used by crash_after.'),
    ParamSpec('act_as_optimiser', False, 'Report state/pending_objects and publish one object after images.'),
    ParamSpec('busy_for', 0.5, 'As optimiser: seconds after the last image during which state is busy.'),
    ParamSpec('seconds_per_image', 0.0, 'Seconds each image callback takes (a node busy in one long callback; '
              'its images wait in the queue meanwhile).'),
    ParamSpec('startup_delay', 0.0, 'Seconds the constructor takes (a node loading a big model).'),
    ParamSpec('ignore_sigint', False, 'Ignore SIGINT (a node that hangs on Ctrl-C; SIGTERM still stops it).'),
    ParamSpec('stall_teardown', 0.0, 'Seconds destroy_node blocks in C with the GIL held, deaf to signals '
              '(a ROS teardown stalled in rcl / DDS).'),
)
TETRAHEDRON_VERTICES = np.array([[0.0, 0.0, 0.0], [0.4, 0.0, 0.0], [0.0, 0.4, 0.0], [0.0, 0.0, 0.4]]) + [1, 2, 0]
TETRAHEDRON_FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


class StubNode(FrodoNode):
    """Counts images; may crash on purpose or pretend to be the optimiser."""

    def __init__(self):
        super().__init__('stub_node', PARAMS)
        self.last_image = 0.0
        self.object_published = False
        self.create_subscription(Image, topics.IMAGE, self.guarded(self.on_image), topics.FRAME_QOS)
        self.objects_pub = self.create_publisher(MarkerArray, topics.OBJECTS, topics.LATCHED_QOS)
        self.boxes_pub = self.create_publisher(MarkerArray, topics.BOXES, topics.LATCHED_QOS)
        if self.params['crash_after'] > 0:
            self.create_timer(float(self.params['crash_after']), self.crash)
        time.sleep(float(self.params['startup_delay']))
        if self.params['ignore_sigint']:
            signal.signal(signal.SIGINT, signal.SIG_IGN)

    def on_image(self, msg: Image) -> None:
        """Count the frame; as optimiser publish the fixed object once."""
        self.count('frames_received')
        self.count('image_received')   # the shape and optimiser nodes' name for it (run.IMAGE_COUNTERS)
        time.sleep(float(self.params['seconds_per_image']))
        self.last_image = time.monotonic()
        if self.params['act_as_optimiser'] and not self.object_published:
            self.publish_object(stamp_to_ns(msg.header.stamp))

    def publish_object(self, stamp_ns: int) -> None:
        """Publish one chair: a tetrahedron mesh and its bounding box."""
        frame = self.params['world_frame']
        lo, hi = TETRAHEDRON_VERTICES.min(0), TETRAHEDRON_VERTICES.max(0)
        self.objects_pub.publish(MarkerArray(markers=[
            mesh_to_marker(TETRAHEDRON_VERTICES, TETRAHEDRON_FACES, 'chair', 7, stamp_ns, frame)]))
        self.boxes_pub.publish(MarkerArray(markers=[
            box_to_marker((lo + hi) / 2, hi - lo, 0.0, 'chair', 7, stamp_ns, frame)]))
        self.object_published = True

    def crash(self) -> None:
        """Exit the process at once with crash_code (what a segfaulting or failing node looks like)."""
        self.get_logger().error(f'stub crashing on purpose with code {self.params["crash_code"]}')
        sys.stderr.flush()
        os._exit(int(self.params['crash_code']))

    def destroy_node(self) -> None:
        """With stall_teardown, first block the way a deadlocked rcl / DDS teardown does: in C, GIL held, signals
        only cutting a sleep short (PyDLL keeps the GIL during the call)."""
        end = time.monotonic() + float(self.params['stall_teardown'])
        while (left := end - time.monotonic()) > 0:
            ctypes.PyDLL(None).sleep(math.ceil(left))
        super().destroy_node()

    def diagnostic_values(self) -> dict[str, Any]:
        """As optimiser: busy while images keep coming, else idle; never any pending object."""
        if not self.params['act_as_optimiser']:
            return {}
        busy = time.monotonic() - self.last_image < self.params['busy_for']
        return {'state': 'busy' if busy else 'idle', 'pending_objects': 0}


def main(args: list[str] | None = None) -> int:
    """Run the stub node until Ctrl-C / SIGTERM."""
    return run_node(StubNode, args)


if __name__ == '__main__':
    sys.exit(main())
