"""`GraphMonitor`: says when a launched graph is ready (every node up and subscribed) and who joined late.

A FroDO node reports on `/diagnostics` on its first executor spin, i.e. once it is constructed and its
subscriptions exist (`frodo_common.node`). The monitor counts a node as up when a report carries the pid
of the process the launcher started last (so a restarted node counts only once its new process is up)
and the last one came less than `silent_after` seconds ago (a dead or hung node drops out),
and the graph as ready when every node is up and the subscriptions the ROS graph shows for each node have
not changed for `settle` seconds (discovery reports them one by one). It says so once per transition,
and publishes its own status on `/diagnostics` (name `frodo_launch`: `ready`, `waiting`, late joiners) so
that a player can wait for it (`frodo play --wait-ready`).

A node that comes up after frames have entered the graph (the largest `frames_received` any other node
reports) missed those frames: a bag started too early, or a restart after a crash. The monitor names it
and how many frames it missed, instead of the run ending with fewer (or no) objects and no warning.
"""
from __future__ import annotations

import threading
import time
from typing import Callable, Sequence

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node

from frodo_common import topics
from frodo_common.node import OK, WARN

# Name of the launcher's own status on /diagnostics.
LAUNCH_STATUS = 'frodo_launch'


class GraphMonitor:
    """Readiness and late joiners of the nodes `names`, watched through `node` (spun elsewhere).

    pids: returns {node name: pid of its current process} (the launcher's), or None to accept any pid.
    log: where transitions are written (the launcher's `[frodo]` log).
    """

    def __init__(self, node: Node, names: Sequence[str], log: Callable[[str], None],
                 pids: Callable[[], dict[str, int]] | None = None, settle: float = 1.0, period: float = 1.0,
                 publish: bool = True, silent_after: float = 5.0):
        self.node = node
        self.names = list(names)
        self.log = log
        self.pids = pids
        self.settle = settle
        self.silent_after = silent_after
        self.ready = False
        self.late: dict[str, int] = {}               # node -> frames that had entered the graph before it came up
        self._latest: dict[str, dict[str, str]] = {}  # node -> key/values of its last report
        self._heard: dict[str, float] = {}             # node -> when its last report came (monotonic)
        self._up_pid: dict[str, str] = {}              # node -> pid of the process seen up
        # node -> (pid, frames other nodes had received) at that process's first report: taken on arrival, not
        # at the next tick, so a loaded executor that runs the tick late does not call an early node late.
        self._joined: dict[str, tuple[str, int]] = {}
        self._subs: dict[str, tuple[str, ...]] = {}
        self._subs_since = time.monotonic()
        self._lock = threading.Lock()
        self._ready_event = threading.Event()
        node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diagnostics, 50)
        self._pub = node.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 10) if publish else None
        node.create_timer(period, self.tick)

    # ------------------------------------------------------------------ inputs
    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        with self._lock:
            for status in msg.status:
                if status.name in self.names:
                    values = {kv.key: kv.value for kv in status.values}
                    pid = values.get('pid', '')
                    if self._joined.get(status.name, ('',))[0] != pid:
                        self._joined[status.name] = (pid, self._frames_received_by_others(status.name))
                    self._latest[status.name] = values
                    self._heard[status.name] = time.monotonic()

    def _current_pid(self, name: str) -> str | None:
        if self.pids is None:
            return None
        pid = self.pids().get(name)
        return str(pid) if pid is not None else ''

    def frames_entered(self, excluding: str | None = None) -> int:
        """Largest `frames_received` reported by any watched node other than `excluding`."""
        with self._lock:
            return self._frames_received_by_others(excluding)

    def _frames_received_by_others(self, excluding: str | None) -> int:
        counts = [int(v.get('frames_received', '0') or 0) for n, v in self._latest.items() if n != excluding]
        return max(counts, default=0)

    def up(self) -> list[str]:
        """Nodes whose current process has reported, the last time less than `silent_after` seconds ago."""
        with self._lock:
            latest, heard = dict(self._latest), dict(self._heard)
        now = time.monotonic()
        out = []
        for name in self.names:
            values = latest.get(name)
            expected = self._current_pid(name)
            if (values is not None and (expected is None or values.get('pid') == expected)
                    and now - heard[name] < self.silent_after):
                out.append(name)
        return out

    def _subscriptions(self, name: str) -> tuple[str, ...]:
        try:
            found = self.node.get_subscriber_names_and_types_by_node(name, '/')
        except Exception:  # noqa: BLE001 - the node is not (or no longer) in the graph
            return ()
        return tuple(sorted(topic for topic, _ in found))

    # ------------------------------------------------------------------ state
    def tick(self) -> None:
        """Update readiness and late joiners; log transitions; publish the launcher's status."""
        up = self.up()
        for name in up:
            with self._lock:
                pid = self._latest.get(name, {}).get('pid', '')
                joined_pid, missed = self._joined.get(name, ('', 0))
            if self._up_pid.get(name) != pid:
                self._up_pid[name] = pid
                if joined_pid != pid:
                    missed = self.frames_entered(excluding=name)
                if missed:
                    self.late[name] = missed
                    self.log(f'WARNING: {name} came up after {missed} frame(s) had entered the graph and missed '
                             'them (start playing once the graph is ready: frodo play --wait-ready)')
        subs = {name: self._subscriptions(name) for name in up}
        now = time.monotonic()
        if subs != self._subs:
            self._subs, self._subs_since = subs, now
        waiting = [n for n in self.names if n not in up]
        ready = not waiting and now - self._subs_since >= self.settle
        if ready and not self.ready:
            count = sum(len(s) for s in subs.values())
            self.log(f'graph ready: {len(self.names)} node(s) up and subscribed ({count} subscriptions)')
            self._ready_event.set()
        elif self.ready and not ready:
            self.log(f'graph not ready: waiting for {", ".join(waiting) or "subscriptions to settle"}')
            self._ready_event.clear()
        self.ready = ready
        self._publish(waiting, subs)

    def wait_ready(self, timeout: float, stop: threading.Event | None = None) -> bool:
        """Block until the graph is ready (True) or timeout / stop (False)."""
        deadline = time.monotonic() + timeout
        while not self._ready_event.wait(0.1):
            if time.monotonic() >= deadline or (stop is not None and stop.is_set()):
                return False
        return True

    def _publish(self, waiting: list[str], subs: dict[str, tuple[str, ...]]) -> None:
        if self._pub is None:
            return
        values = {'ready': str(self.ready).lower(), 'nodes': ','.join(self.names), 'waiting': ','.join(waiting)}
        values.update({f'subscriptions.{name}': ','.join(topics_) for name, topics_ in subs.items()})
        values.update({f'late.{name}': str(n) for name, n in self.late.items()})
        message = 'ready' if self.ready else f'waiting for {", ".join(waiting) or "subscriptions to settle"}'
        level = OK if self.ready and not self.late else WARN
        status = DiagnosticStatus(level=bytes([level]), name=LAUNCH_STATUS, message=message,
                                  hardware_id=self.node.get_fully_qualified_name(),
                                  values=[KeyValue(key=k, value=v) for k, v in values.items()])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self._pub.publish(msg)


def launch_ready(msg: DiagnosticArray) -> bool | None:
    """True / False when `msg` carries the launcher's status (ready or not), None otherwise."""
    for status in msg.status:
        if status.name == LAUNCH_STATUS:
            return any(kv.key == 'ready' and kv.value == 'true' for kv in status.values)
    return None
