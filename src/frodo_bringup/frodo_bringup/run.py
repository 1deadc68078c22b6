"""`run_bag`: one complete reconstruction of a bag (what `frodo run` does).

Launch the graph, wait until its nodes are up and subscribed, play the bag, wait until the optimiser
reports `state` = idle and `pending_objects` = 0 after the bag has finished (CONTRACT.md "Done"),
write the output files from the latched `/frodo/objects`, `/frodo/boxes` and `/frodo/object_states`,
shut the graph down. With `viewer='rrd'` the Rerun viewer node records the run to `DIR/frodo.rrd`.
"""
from __future__ import annotations

import os
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence, TextIO

import yaml
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from frodo_bringup.graph import NODES, OPTIMISER, VIEWER, GraphNode
from frodo_bringup.launcher import Launcher, NodeExit
from frodo_bringup.outputs import summary_table, write_outputs
from frodo_bringup.player import PlayStats, Player, PlayerError
from frodo_bringup.session import RosSession
from frodo_common import topics
from frodo_common.conversions import cloud_to_table
from frodo_optim.states import OBJECT_STATES, states_to_records

# Exit codes of `frodo run`.
EXIT_OK, EXIT_GRAPH_FAILED, EXIT_NOT_DONE, EXIT_INTERRUPTED = 0, 1, 3, 130
RECORDING_FILE = 'frodo.rrd'
# Seconds to wait, once every node has reported, for the player's topics to match the nodes' subscriptions.
SUBSCRIPTION_MATCH_TIMEOUT = 10.0
# Consecutive optimiser reports of idle / 0 pending (after the bag ended) that mean "done".
DONE_REPORTS = 2


@dataclass
class RunResult:
    """Outcome of `run_bag`: exit code, written object records, playback stats, node failures."""

    exit_code: int
    records: list[dict[str, Any]] = field(default_factory=list)
    play: PlayStats | None = None
    done: bool = False
    failures: list[NodeExit] = field(default_factory=list)
    seconds: float = 0.0


class OutputCollector:
    """Keeps the latest `/frodo/objects`, `/frodo/boxes`, `/frodo/object_states` and node diagnostics."""

    def __init__(self, node: Node, optimiser: str = OPTIMISER):
        self.optimiser = optimiser
        self.objects: MarkerArray | None = None
        self.boxes: MarkerArray | None = None
        self.states: PointCloud2 | None = None
        self.statuses: dict[str, dict[str, str]] = {}
        self._optimiser_reports: list[tuple[float, bool]] = []  # (receive time, idle with nothing pending)
        self._lock = threading.Lock()
        node.create_subscription(MarkerArray, topics.OBJECTS, self._on_objects, topics.LATCHED_QOS)
        node.create_subscription(MarkerArray, topics.BOXES, self._on_boxes, topics.LATCHED_QOS)
        node.create_subscription(PointCloud2, OBJECT_STATES, self._on_states, topics.LATCHED_QOS)
        node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diagnostics, 50)

    def _on_objects(self, msg: MarkerArray) -> None:
        with self._lock:
            self.objects = msg

    def _on_boxes(self, msg: MarkerArray) -> None:
        with self._lock:
            self.boxes = msg

    def _on_states(self, msg: PointCloud2) -> None:
        with self._lock:
            self.states = msg

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        now = time.monotonic()
        with self._lock:
            for status in msg.status:
                values = {kv.key: kv.value for kv in status.values}
                self.statuses[status.name] = values
                if status.name == self.optimiser:
                    idle = values.get('state') == 'idle' and values.get('pending_objects') == '0'
                    self._optimiser_reports.append((now, idle))

    def missing_reports(self, names: Sequence[str]) -> list[str]:
        """Nodes in `names` that have not reported on /diagnostics yet (so may still be constructing)."""
        with self._lock:
            return sorted(set(names) - set(self.statuses))

    def optimiser_done(self, since: float) -> bool:
        """True when the last DONE_REPORTS optimiser reports, all received after `since`, say idle / 0 pending."""
        with self._lock:
            recent = [idle for received, idle in self._optimiser_reports if received > since]
        return len(recent) >= DONE_REPORTS and all(recent[-DONE_REPORTS:])

    def snapshot(self) -> tuple[MarkerArray | None, MarkerArray | None, dict[int, dict[str, Any]]]:
        """(objects, boxes, per-object info from the optimiser's states) as last received."""
        with self._lock:
            objects, boxes, states = self.objects, self.boxes, self.states
        info = states_to_records(cloud_to_table(states)) if states is not None else {}
        return objects, boxes, info


def run_bag(bag: str | os.PathLike, out_dir: str | os.PathLike, params_files: Sequence[str | os.PathLike] = (),
            timeout: float = 300.0, rate: float = 1.0, viewer: str = 'none',
            nodes: Sequence[GraphNode] = NODES, startup_timeout: float = 60.0,
            stop: threading.Event | None = None, output: TextIO | None = None, progress: bool = True,
            env: dict[str, str] | None = None) -> RunResult:
    """Reconstruct one bag end to end; `timeout` bounds the wait for the graph after the bag has played."""
    output = output or sys.stdout
    stop = stop or threading.Event()
    started = time.monotonic()
    if not Path(bag).is_file():
        raise PlayerError(f'bag not found: {bag}')
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if viewer == 'rrd':
        nodes, params_files = tuple(nodes) + (VIEWER,), [*params_files, _viewer_params(out)]
    launcher = Launcher(nodes, params_files, on_failure='stop', log_dir=out / 'logs', output=output, env=env,
                        on_exit=lambda exit_: stop.set() if not exit_.expected else None)
    session = RosSession('frodo_run')
    collector = OutputCollector(session.node)
    result = RunResult(EXIT_OK)
    try:
        launcher.start()
        result.play, result.done = _play_and_wait(session.node, collector, launcher, bag, rate, timeout,
                                                  startup_timeout, stop, progress, ground_truth=viewer == 'rrd')
        result.records = write_outputs(out, *collector.snapshot())
    finally:
        launcher.shutdown()
        session.close()
    result.failures = launcher.failures
    result.seconds = time.monotonic() - started
    crashed = any(not e.expected for e in launcher.exits)
    result.exit_code = _exit_code(result, interrupted=stop.is_set() and not crashed)
    _report(launcher, result, out, output)
    return result


def _viewer_params(out: Path) -> Path:
    """Params file making the viewer node save its recording to out/frodo.rrd."""
    path = out / 'logs' / 'viewer_params.yaml'
    path.parent.mkdir(parents=True, exist_ok=True)
    params = {'mode': 'save', 'rrd_path': str((out / RECORDING_FILE).resolve())}
    path.write_text(yaml.safe_dump({VIEWER.name: {'ros__parameters': params}}))
    return path


def _play_and_wait(node: Node, collector: OutputCollector, launcher: Launcher, bag, rate: float, timeout: float,
                   startup_timeout: float, stop: threading.Event, progress: bool,
                   ground_truth: bool) -> tuple[PlayStats | None, bool]:
    deadline = time.monotonic() + startup_timeout
    while collector.missing_reports(launcher.node_names) and time.monotonic() < deadline and not stop.is_set():
        stop.wait(0.1)
    if stop.is_set():
        return None, False
    missing = collector.missing_reports(launcher.node_names)
    if missing:
        launcher.log(f'no diagnostics from {", ".join(missing)} after {startup_timeout:.0f} s; playing anyway')
    player = Player(node, bag, rate=rate, progress=progress, ground_truth=ground_truth)
    for problem in player.problems:
        launcher.log(f'bag: {problem}')
    unmatched = player.wait_for_subscribers(SUBSCRIPTION_MATCH_TIMEOUT, wanted=[topics.IMAGE], stop=stop)
    if unmatched:
        launcher.log(f'subscribers of {", ".join(unmatched)} not matched after {SUBSCRIPTION_MATCH_TIMEOUT:.0f} s '
                     '(QoS mismatch?); playing anyway')
    launcher.log(f'playing {player.message_count} messages ({player.duration:.1f} s of bag time)')
    stats = player.play(stop)
    finished = time.monotonic()
    deadline = finished + timeout
    while not stop.is_set() and time.monotonic() < deadline:
        if collector.optimiser_done(since=finished):
            return stats, True
        stop.wait(0.1)
    if not stop.is_set():
        launcher.log(f'{OPTIMISER} did not report idle with 0 pending objects within {timeout:.0f} s')
    return stats, False


def _exit_code(result: RunResult, interrupted: bool) -> int:
    if result.failures:
        return EXIT_GRAPH_FAILED
    if interrupted:
        return EXIT_INTERRUPTED
    return EXIT_OK if result.done else EXIT_NOT_DONE


def _report(launcher: Launcher, result: RunResult, out: Path, output: TextIO) -> None:
    print(summary_table(result.records), file=output)
    played = f'{result.play.total} messages played' if result.play is not None else 'bag not played'
    state = {EXIT_OK: 'done', EXIT_GRAPH_FAILED: 'FAILED', EXIT_NOT_DONE: 'NOT DONE (timeout)',
             EXIT_INTERRUPTED: 'interrupted'}[result.exit_code]
    print(f'{state}: {played}, {len(result.records)} objects, {result.seconds:.1f} s; outputs in {out}',
          file=output)
    for failure in result.failures:
        print(f'node failure: {failure.describe()}', file=output)
