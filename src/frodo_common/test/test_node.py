"""FrodoNode in a real rclpy graph: parameters from specs, diagnostics on /diagnostics, guarded callbacks."""
import threading
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from frodo_common.frame_cache import FrameCache
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


class _Busy(FrodoNode):
    """A node whose only callback holds its executor thread (and, in pure Python, the GIL) for `seconds`."""

    def __init__(self, seconds: float):
        super().__init__('busy_node', (), parameter_overrides=[Parameter('diagnostics_period', value=0.25)])
        self.seconds = seconds
        self.done = False
        self.timer = self.create_timer(0.05, self._work)

    def _work(self):
        self.timer.cancel()
        end = time.monotonic() + self.seconds
        total = 0
        while time.monotonic() < end:
            total += sum(range(1000))   # GIL-bound Python work
        self.done = True


def test_diagnostics_keep_their_period_while_every_callback_is_busy():
    """Reports come from their own thread: a callback busy for 3 s (the only executor thread) does not
    hold them back, as it did when they came from an executor timer."""
    rclpy.init()
    try:
        node = _Busy(3.0)
        listener = rclpy.create_node('listener')
        got = []
        listener.create_subscription(DiagnosticArray, '/diagnostics',
                                     lambda m: got.extend(time.monotonic() for s in m.status if s.name == 'busy_node'),
                                     10)
        node_executor, listener_executor = SingleThreadedExecutor(), SingleThreadedExecutor()
        node_executor.add_node(node)
        listener_executor.add_node(listener)
        def spin_node():
            end = time.monotonic() + 15
            while not node.done and time.monotonic() < end:
                node_executor.spin_once(timeout_sec=0.05)
        spinner = threading.Thread(target=spin_node)
        spinner.start()
        deadline = time.time() + 20
        while time.time() < deadline and not node.done:
            listener_executor.spin_once(timeout_sec=0.05)
        spinner.join()
        assert node.done
        assert len(got) >= 6, f'{len(got)} reports during 3 s of busy callback (period 0.25 s)'
        node.destroy_node()
        assert not node._diag_thread.is_alive()
    finally:
        rclpy.shutdown()


class _Cached(FrodoNode):
    def __init__(self):
        super().__init__('cached_node', ())
        self.cache = FrameCache(('image', 'detections'), stale_after_ns=10, stale_after_s=0)


def test_frames_a_node_got_only_in_part_are_reported_with_their_missing_parts():
    rclpy.init()
    try:
        node = _Cached()
        node.cache.add(0, 'detections', 'd')         # its image never came (the node started late)
        node.cache.add(100, 'image', 'i')
        node.cache.add(100, 'detections', 'd')
        level, _, values = node._collect()
        assert values['frames_missed'] == 1 and values['missing_parts'] == 'image (1)'
        assert values['warnings'] == 1 and 'never complete, missing image (1)' in values['last_error']
        assert level == 1
        assert node._collect()[2]['warnings'] == 1   # warned once per increase, not per report
        node.destroy_node()
    finally:
        rclpy.shutdown()
