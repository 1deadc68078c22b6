"""FrodoNode in a real rclpy graph: parameters from specs, diagnostics on /diagnostics, guarded callbacks."""
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray

from frodo_common.node import FrodoNode
from frodo_common.params import ParamSpec


class _Boom(FrodoNode):
    def __init__(self):
        super().__init__('boom_node', (ParamSpec('threshold', 0.5, 'A test threshold.'),))
        self.explode = self.guarded(self._explode, 'explode')

    def _explode(self):
        raise ValueError('bad input')


def test_diagnostics_and_guarded_errors():
    rclpy.init()
    try:
        node = _Boom()
        listener = rclpy.create_node('listener')
        got = []
        listener.create_subscription(DiagnosticArray, '/diagnostics', got.append, 10)
        assert node.params['threshold'] == 0.5 and node.params['world_frame'] == 'world'
        assert node.explode() is None  # survived
        deadline = time.time() + 10
        while time.time() < deadline and not any(s.name == 'boom_node' for m in got for s in m.status):
            rclpy.spin_once(node, timeout_sec=0.1)
            rclpy.spin_once(listener, timeout_sec=0.1)
        status = next(s for m in got for s in m.status if s.name == 'boom_node')
        values = {kv.key: kv.value for kv in status.values}
        assert values['errors'] == '1' and 'bad input' in values['last_error']
        assert status.level == bytes([1])
    finally:
        rclpy.shutdown()
