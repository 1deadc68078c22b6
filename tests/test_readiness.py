"""GraphMonitor on hand-made reports: a node is up only with its current pid and while it keeps reporting;
the graph is ready when all are up; a node coming up after frames entered the graph is named as late."""
from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from frodo_bringup.readiness import GraphMonitor
from frodo_bringup.session import RosSession


def _report(name: str, **values) -> DiagnosticArray:
    return DiagnosticArray(status=[DiagnosticStatus(name=name, values=[KeyValue(key=k, value=str(v))
                                                                       for k, v in values.items()])])


def test_up_ready_late_and_silent():
    lines: list[str] = []
    with RosSession('frodo_test_readiness') as session:
        monitor = GraphMonitor(session.node, ['a', 'b'], lines.append, pids=lambda: {'a': 1, 'b': 2}, settle=0.0,
                               period=3600, publish=False, silent_after=0.5)
        monitor._on_diagnostics(_report('a', pid=1, frames_received=0))
        monitor._on_diagnostics(_report('b', pid=7))            # a report of b's previous process
        monitor.tick()
        assert monitor.up() == ['a'] and not monitor.ready
        monitor._on_diagnostics(_report('a', pid=1, frames_received=12))
        monitor._on_diagnostics(_report('b', pid=2))
        monitor.tick()
        assert monitor.ready and monitor.wait_ready(0.1)
        assert monitor.late == {'b': 12}
        assert lines[0].startswith('WARNING: b came up after 12 frame(s)')
        assert lines[1] == 'graph ready: 2 node(s) up and subscribed (0 subscriptions)'
        time.sleep(0.6)                                         # both stop reporting
        monitor.tick()
        assert monitor.up() == [] and not monitor.ready
        assert lines[-1] == 'graph not ready: waiting for a, b'


def test_a_node_up_before_frames_is_not_late_when_the_tick_runs_after_them():
    """The late count is taken when a process first reports, not when the (possibly delayed) tick runs."""
    lines: list[str] = []
    with RosSession('frodo_test_readiness_delay') as session:
        monitor = GraphMonitor(session.node, ['a', 'b'], lines.append, pids=lambda: {'a': 1, 'b': 2}, settle=0.0,
                               period=3600, publish=False)
        monitor._on_diagnostics(_report('a', pid=1, frames_received=0))
        monitor._on_diagnostics(_report('b', pid=2, frames_received=0))
        monitor._on_diagnostics(_report('a', pid=1, frames_received=12))   # frames flow before any tick
        monitor._on_diagnostics(_report('b', pid=2, frames_received=12))
        monitor.tick()
        assert monitor.ready and monitor.late == {}
        assert not any(line.startswith('WARNING') for line in lines), lines
