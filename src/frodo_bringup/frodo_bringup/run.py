"""`run_bag`: one complete reconstruction of a bag (what `frodo run` does).

Launch the graph, wait until its nodes are up and subscribed, play the bag, wait until the optimiser
(every optimiser worker) reports `state` = idle and `pending_objects` = 0 after the bag has finished
(CONTRACT.md "Done") and no node's diagnostics counters move any more (see `OutputCollector.done`),
write the output files from the latest `/frodo/objects`, `/frodo/boxes` and `/frodo/object_states` (complete
in every message, with several optimiser workers too: worker 0 merges their shares), shut the graph down.
With `viewer='rrd'` the Rerun viewer node records the run to `DIR/frodo.rrd`.
"""
from __future__ import annotations

import collections
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence, TextIO

import yaml
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import PointCloud2
import numpy as np
from visualization_msgs.msg import Marker, MarkerArray

from frodo_bringup.graph import (NODES, OPTIMISER, VIEWER, GraphNode, is_optimiser, optimiser_workers,
                                 resolve_params_file, section_parameters, with_optimiser_parameters)
from frodo_bringup.launcher import Launcher, NodeExit
from frodo_bringup.outputs import current_markers, summary_table, write_outputs
from frodo_bringup.player import Backpressure, PlayStats, Player, PlayerError
from frodo_bringup.preflight import BagRefused, check_bag
from frodo_bringup.session import RosSession
from frodo_common import topics
from frodo_common.conversions import cloud_to_table
from frodo_optim.states import OBJECT_STATES, states_to_records

# Exit codes of `frodo run`.
EXIT_OK, EXIT_GRAPH_FAILED, EXIT_NOT_DONE, EXIT_INTERRUPTED = 0, 1, 3, 130
RECORDING_FILE = 'frodo.rrd'
# Seconds to wait, once every node has reported, for the player's topics to match the nodes' subscriptions.
SUBSCRIPTION_MATCH_TIMEOUT = 10.0
# Seconds the player's subscription matches must stay unchanged before playing (see Player.wait_for_subscribers).
SUBSCRIPTION_SETTLE = 1.0
# Seconds the nodes get to stop on SIGINT before SIGTERM: the outputs are written by then, and on a loaded
# 2-core machine (load average 20) an idle shape_node took 6-7 s to exit, beyond the launcher's default 5 s.
STOP_GRACE = 20.0
# Consecutive reports (after the bag ended) of an idle optimiser and unchanged node counters that mean "done".
DONE_REPORTS = 2
# Seconds after the bag's end that "done" waits for nodes that have not taken every image played (they may be
# busy in a long callback with images queued; after this the images are taken as lost, and the run says so).
LOST_IMAGES_GRACE = 10.0
# Nodes whose image counter counts another node's outputs: (that node, its counter of them).
UPSTREAM = {'association_node': ('detection_node', 'frames_published')}
# Per node, the /diagnostics counter of colour images (or of the detections made from them) it has taken:
# the slowest one paces playback at rate 0 (player.Backpressure).
IMAGE_COUNTERS = {'detection_node': 'frames_received', 'association_node': 'frames_received',
                  'shape_node': 'image_received', 'optim_node': 'image_received'}


@dataclass
class RunResult:
    """Outcome of `run_bag`: exit code, written object records, playback stats, node failures."""

    exit_code: int
    records: list[dict[str, Any]] = field(default_factory=list)
    play: PlayStats | None = None
    done: bool = False
    failures: list[NodeExit] = field(default_factory=list)
    seconds: float = 0.0
    done_after_bag_s: float | None = None  # from the bag's last message to done (None: not done)
    behind: list[tuple[str, int, int, str]] = field(default_factory=list)  # OutputCollector.behind when done
    foreign: list[tuple[str, str]] = field(default_factory=list)  # (node, pid) of another graph in this ROS domain


def image_counter(name: str) -> str | None:
    """The node's image counter in IMAGE_COUNTERS (optimiser workers count as the optimiser), or None."""
    return IMAGE_COUNTERS.get(OPTIMISER if is_optimiser(name) else name)


class OutputCollector:
    """Keeps the latest `/frodo/objects`, `/frodo/boxes` and `/frodo/object_states` (each message is the complete
    map, CONTRACT.md) and each node's last DONE_REPORTS `/diagnostics` reports (receive time, key/values).

    optimisers: the nodes that must all be idle for the graph to be done (the optimiser or its workers).
    pids: returns {node name: pid of the process started for it, None before it is started} (the launcher's),
    or None to accept any report. With it, a report whose `pid` is not that process's is dropped: it comes from
    another graph with the same node names in this ROS domain, and its counters would otherwise pace playback and
    decide "done" for this run. `log` says so once per such process.
    """

    def __init__(self, node: Node, optimisers: Sequence[str] = (OPTIMISER,),
                 pids: Callable[[], dict[str, int | None]] | None = None, log: Callable[[str], None] | None = None):
        self.optimisers = list(optimisers)
        self.pids = pids
        self.log = log
        self.foreign: set[tuple[str, str]] = set()   # (node name, pid) of reports from processes not started here
        self._objects_raw: bytes | None = None        # the latest map, serialised (see _on_objects)
        self.boxes: dict[int, Marker] | None = None
        self.states: dict[int, np.void] = {}
        self._told: dict[int, tuple[int, int]] = {}   # id -> (stage, stage reason) last said by stage_changes
        self._reports: dict[str, collections.deque[tuple[float, dict[str, str]]]] = {}
        self._lock = threading.Lock()
        node.create_subscription(MarkerArray, topics.OBJECTS, self._on_objects, topics.LATCHED_QOS, raw=True)
        node.create_subscription(MarkerArray, topics.BOXES, self._on_boxes, topics.LATCHED_QOS)
        node.create_subscription(PointCloud2, OBJECT_STATES, self._on_states, topics.LATCHED_QOS)
        node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diagnostics, 50)

    def _on_objects(self, raw: bytes) -> None:
        # Kept serialised: every map carries every object's mesh, and turning each one into Python objects took
        # CPU from the optimiser on a small machine (issue 28); only the latest is read, by `snapshot`.
        with self._lock:
            self._objects_raw = raw

    def _on_boxes(self, msg: MarkerArray) -> None:
        with self._lock:
            self.boxes = current_markers(msg)

    def _on_states(self, msg: PointCloud2) -> None:
        table = cloud_to_table(msg)
        with self._lock:
            self.states = {int(row['object_id']): row for row in table}

    def stage_changes(self) -> list[str]:
        """One line per object whose stage or stage reason changed since the last call (progress while the
        optimiser works), e.g. 'object 3 (chair): sparse, in progress, 12 views, 4.2 s'."""
        with self._lock:
            states = dict(self.states)
        lines = []
        for oid, row in sorted(states.items()):
            now = (int(row['stage']), int(row['stage_reason']))
            if self._told.get(oid) == now:
                continue
            self._told[oid] = now
            record = states_to_records(row.reshape(1))[oid]
            lines.append(f'object {oid} ({record["class"]}): {record["stage"]}, {record["stage_reason"]}, '
                         f'{record["num_views"]} views, {record["timings"]["optimiser_s"]:.1f} s')
        return lines

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        now = time.monotonic()
        started = self.pids() if self.pids is not None else None
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if started is not None and status.name in started and values.get('pid') != str(started[status.name]):
                self._note_foreign(status.name, values.get('pid', '?'))
                continue
            with self._lock:
                reports = self._reports.setdefault(status.name, collections.deque(maxlen=DONE_REPORTS))
                reports.append((now, values))

    def _note_foreign(self, name: str, pid: str) -> None:
        with self._lock:
            first = (name, pid) not in self.foreign
            self.foreign.add((name, pid))
        if first and self.log is not None:
            self.log(f'ignoring /diagnostics of a {name} with pid {pid}, not the one this run started: another '
                     f'FroDO graph runs in ROS domain {os.environ.get("ROS_DOMAIN_ID", "0")} and its topics mix '
                     'with this run\'s; give each graph a ROS_DOMAIN_ID of its own')

    def frames_taken(self, names: Sequence[str]) -> int | None:
        """Images taken by the slowest of `names`, from the counters of their latest reports
        (`IMAGE_COUNTERS`); None while none of them has reported one."""
        with self._lock:
            counts = [self._latest_count(name, image_counter(name)) for name in names
                      if image_counter(name) and name in self._reports]
        return min(counts) if counts else None

    def behind(self, names: Sequence[str], images: int) -> list[tuple[str, int, int, str]]:
        """(name, taken, expected, of what) for each node in `names` that has reported fewer inputs than it
        was sent: `images` played, or for a node fed by another (`UPSTREAM`) what that one published."""
        with self._lock:
            return self._behind(names, images)

    def _behind(self, names: Sequence[str], images: int) -> list[tuple[str, int, int, str]]:
        late = []
        for name in names:
            if not image_counter(name) or name not in self._reports:
                continue
            source = UPSTREAM.get(name)
            if source is None:
                expected, what = images, 'images played'
            elif source[0] in self._reports:
                expected, what = self._latest_count(*source), f'{source[1]} of {source[0]}'
            else:
                continue
            taken = self._latest_count(name, image_counter(name))
            if taken < expected:
                late.append((name, taken, expected, what))
        return late

    def _latest_count(self, name: str, key: str) -> int:
        return int(self._reports[name][-1][1].get(key, 0))

    def missing_reports(self, names: Sequence[str]) -> list[str]:
        """Nodes in `names` that have not reported on /diagnostics yet (so may still be constructing)."""
        with self._lock:
            return sorted(set(names) - set(self._reports))

    def _recent(self, name: str, since: float) -> list[dict[str, str]]:
        """The node's last DONE_REPORTS reports if all were received after `since`, else []."""
        reports = list(self._reports.get(name, ()))
        if len(reports) < DONE_REPORTS or reports[0][0] <= since:
            return []
        return [values for _, values in reports]

    def done(self, names: Sequence[str], since: float, images: int = 0, grace: float = 0.0) -> bool:
        """The graph has finished what it got before `since`.

        CONTRACT.md "Done": the optimiser (every worker) reports `state` idle with `pending_objects` 0, here
        in its last DONE_REPORTS reports after `since`; and, so that frames still queued upstream are not
        missed, every node in `names` reported the same key/values (counters) in its last DONE_REPORTS reports,
        and each has taken all `images` played -- or `grace` seconds have passed since `since` (images lost
        in transport never arrive). Why the count: reports come from a thread of their own, so a node busy in
        one long callback reports steady counters while images still wait in its queue.
        """
        with self._lock:
            if time.monotonic() - since < grace and self._behind(names, images):
                return False
            for name in self.optimisers:
                optimiser = self._recent(name, since)
                if not optimiser or not all(v.get('state') == 'idle' and v.get('pending_objects') == '0'
                                            for v in optimiser):
                    return False
            for name in names:
                recent = self._recent(name, since)
                if not recent or any(values != recent[0] for values in recent[1:]):
                    return False
        return True

    def snapshot(self) -> tuple[MarkerArray | None, MarkerArray | None, dict[int, dict[str, Any]]]:
        """(objects, boxes, per-object info from the optimiser's states) of the latest messages; the states of
        objects not on /frodo/objects or /frodo/boxes (deleted since) are left out."""
        with self._lock:
            raw, boxes, got_boxes = self._objects_raw, dict(self.boxes or {}), self.boxes is not None
            states = dict(self.states)
        got_objects = raw is not None
        objects = current_markers(deserialize_message(raw, MarkerArray)) if got_objects else {}
        rows = [row for oid, row in sorted(states.items()) if oid in objects or oid in boxes]
        info = states_to_records(np.array(rows, dtype=rows[0].dtype)) if rows else {}
        return (MarkerArray(markers=[objects[k] for k in sorted(objects)]) if got_objects else None,
                MarkerArray(markers=[boxes[k] for k in sorted(boxes)]) if got_boxes else None, info)


def run_bag(bag: str | os.PathLike, out_dir: str | os.PathLike, params_files: Sequence[str | os.PathLike] = (),
            timeout: float = 300.0, rate: float = 1.0, viewer: str = 'none',
            nodes: Sequence[GraphNode] = NODES, startup_timeout: float = 60.0,
            stop: threading.Event | None = None, output: TextIO | None = None, progress: bool = True,
            env: dict[str, str] | None = None, player_factory: Callable[..., Player] = Player,
            optim_workers: int | str | None = 'auto', map_dir: str | os.PathLike | None = None,
            resume: str | os.PathLike | None = None) -> RunResult:
    """Reconstruct one bag end to end; `timeout` bounds the wait for the graph after the bag has played.
    `optim_workers` optimiser processes split the objects ('auto': `graph.optim_worker_count`); the optimiser
    saves its object map to `map_dir` and starts from the one in `resume` (`frodo launch --map-dir / --resume`).
    `player_factory(node, bag, rate=, progress=, ground_truth=)` makes the player (e.g. a
    `long_bag.RepeatingPlayer` for soak runs).

    Raises PlayerError (missing or unreadable bag, not an MCAP, required input topics absent, no instance masks
    with the `external` detection backend: `preflight.check_bag`) before any node is started.
    """
    output = output or sys.stdout
    stop = stop or threading.Event()
    started = time.monotonic()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    nodes = with_optimiser_parameters(optimiser_workers(nodes, optim_workers),
                                      map_dir=str(Path(map_dir).resolve()) if map_dir else None,
                                      resume=str(Path(resume).resolve()) if resume else None)
    if viewer == 'rrd':
        nodes, params_files = tuple(nodes) + (VIEWER,), [*params_files, _viewer_params(out)]
    launcher = Launcher(nodes, params_files, on_failure='stop', log_dir=out / 'logs', output=output, env=env,
                        on_exit=lambda exit_: stop.set() if not exit_.expected else None,
                        sigint_timeout=STOP_GRACE)
    session = RosSession('frodo_run')
    result = RunResult(EXIT_OK)
    try:
        player = player_factory(session.node, bag, rate=rate, progress=progress, ground_truth=viewer == 'rrd')
        try:
            check_bag(player.reader, section_parameters([resolve_params_file(f) for f in params_files],
                                                         'detection_node').get('backend', 'external'))
        except BagRefused as err:
            raise PlayerError(str(err)) from err
        collector = OutputCollector(session.node, [n for n in launcher.node_names if is_optimiser(n)] or [OPTIMISER],
                                    pids=lambda: {n: launcher.pids.get(n) for n in launcher.node_names},
                                    log=launcher.log)
        launcher.start()
        result.play, result.done, result.behind, result.done_after_bag_s = _play_and_wait(
            player, collector, launcher, timeout, startup_timeout, stop)
        result.records = write_outputs(out, *collector.snapshot())
        result.foreign = sorted(collector.foreign)
    finally:
        launcher.shutdown()
        session.close()
    result.failures = launcher.failures
    result.seconds = time.monotonic() - started
    crashed = any(not e.expected for e in launcher.exits)
    result.exit_code = _exit_code(result, interrupted=stop.is_set() and not crashed)
    _report(result, out, output)
    return result


def _viewer_params(out: Path) -> Path:
    """Params file making the viewer node save its recording to out/frodo.rrd."""
    path = out / 'logs' / 'viewer_params.yaml'
    path.parent.mkdir(parents=True, exist_ok=True)
    params = {'mode': 'save', 'rrd_path': str((out / RECORDING_FILE).resolve())}
    path.write_text(yaml.safe_dump({VIEWER.name: {'ros__parameters': params}}))
    return path


def _play_and_wait(player: Player, collector: OutputCollector, launcher: Launcher, timeout: float,
                   startup_timeout: float, stop: threading.Event
                   ) -> tuple[PlayStats | None, bool, list[tuple[str, int, int, str]], float | None]:
    """Wait for the nodes, play, wait until done; returns (playback stats or None, done, the nodes still
    behind when done: `OutputCollector.behind`, seconds from the bag's end to done or None)."""
    deadline = time.monotonic() + startup_timeout
    while collector.missing_reports(launcher.node_names) and time.monotonic() < deadline and not stop.is_set():
        stop.wait(0.1)
    if stop.is_set():
        return None, False, [], None
    missing = collector.missing_reports(launcher.node_names)
    if missing:
        launcher.log(f'no diagnostics from {", ".join(missing)} after {startup_timeout:.0f} s; playing anyway')
    for problem in player.problems:
        launcher.log(f'bag: {problem}')
    problems_before = list(player.problems)
    inputs = player.played_topics((topics.IMAGE, topics.CAMERA_INFO, topics.POSE, topics.INSTANCES,
                                     topics.SLAM_POINTS))
    unmatched = player.wait_for_subscribers(SUBSCRIPTION_MATCH_TIMEOUT, wanted=inputs, stop=stop,
                                            settle=SUBSCRIPTION_SETTLE)
    if unmatched:
        launcher.log(f'subscribers of {", ".join(unmatched)} not matched after {SUBSCRIPTION_MATCH_TIMEOUT:.0f} s '
                     '(QoS mismatch?); playing anyway')
    launcher.log(f'playing {player.message_count} messages ({player.duration:.1f} s of bag time)')
    stats = player.play(stop, Backpressure(lambda: collector.frames_taken(launcher.node_names)))
    if stats.paced_seconds > 1:
        launcher.log(f'playback waited {stats.paced_seconds:.1f} s for the graph to keep up')
    for problem in player.problems[len(problems_before):]:
        launcher.log(f'bag: {problem}')
    finished = time.monotonic()
    deadline = finished + timeout
    played = stats.published.get(player.output_topic(topics.IMAGE), 0)
    grace = min(LOST_IMAGES_GRACE, timeout / 2)
    while not stop.is_set() and time.monotonic() < deadline:
        for line in collector.stage_changes():
            launcher.log(line)
        if collector.done(launcher.node_names, since=finished, images=played, grace=grace):
            behind = collector.behind(launcher.node_names, played)
            for name, taken, expected, what in behind:
                launcher.log(f'{name} took {taken} of the {expected} {what} within {grace:.0f} s of the bag\'s end; '
                             'the map is built from what the graph got')
            return stats, True, behind, time.monotonic() - finished
        stop.wait(0.1)
    if not stop.is_set():
        launcher.log(f'graph not done within {timeout:.0f} s of the bag\'s end ({", ".join(collector.optimisers)} '
                     'idle with 0 pending objects and all node counters steady)')
    return stats, False, [], None


def _exit_code(result: RunResult, interrupted: bool) -> int:
    if result.failures:
        return EXIT_GRAPH_FAILED
    if interrupted:
        return EXIT_INTERRUPTED
    return EXIT_OK if result.done else EXIT_NOT_DONE


def _report(result: RunResult, out: Path, output: TextIO) -> None:
    print(summary_table(result.records), file=output)
    played = f'{result.play.total} messages played' if result.play is not None else 'bag not played'
    state = {EXIT_OK: 'done', EXIT_GRAPH_FAILED: 'FAILED', EXIT_NOT_DONE: 'NOT DONE (timeout)',
             EXIT_INTERRUPTED: 'interrupted'}[result.exit_code]
    after = f' (done {result.done_after_bag_s:.1f} s after the bag ended)' if result.done_after_bag_s is not None else ''
    print(f'{state}: {played}, {len(result.records)} objects, {result.seconds:.1f} s{after}; outputs in {out}',
          file=output)
    for failure in result.failures:
        print(f'node failure: {failure.describe()}', file=output)
    if result.foreign:
        others = ', '.join(f'{name} (pid {pid})' for name, pid in result.foreign)
        print(f'WARNING: another graph ran in this ROS domain ({others}); its messages may be mixed into these '
              'outputs: run again with a ROS_DOMAIN_ID of its own', file=output)
