"""Helpers for node tests in a real rclpy graph: spin until a condition holds, read a node's last report."""
from __future__ import annotations

import time
from typing import Callable, Iterable

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import Executor


def spin_until(executor: Executor, condition: Callable[[], bool], timeout: float = 10.0) -> bool:
    """Spin `executor` until `condition()` is true or `timeout` seconds passed; returns `condition()`."""
    deadline = time.time() + timeout
    while time.time() < deadline and not condition():
        executor.spin_once(timeout_sec=0.05)
    return condition()


def latest_status(reports: Iterable[DiagnosticArray], name: str) -> dict[str, str]:
    """Key/values of the last `/diagnostics` status of node `name` among `reports` ({} when none)."""
    statuses = [s for m in reports for s in m.status if s.name == name]
    return {kv.key: kv.value for kv in statuses[-1].values} if statuses else {}
