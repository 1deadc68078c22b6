"""Graph-level faults with the real nodes while a bag plays: nodes that start late are named with the frames
they missed (and still get the latched state), the launcher says when the graph is ready, and a node
killed with SIGKILL is reported by name and restarted while the others keep running with their state."""
from __future__ import annotations

import io
import os
import signal
import threading
from pathlib import Path

import pytest

from frodo_bringup.graph import NODES
from frodo_bringup.launcher import Launcher
from frodo_bringup.long_bag import repeat_bag
from frodo_bringup.player import Player
from frodo_bringup.readiness import GraphMonitor
from frodo_bringup.session import RosSession
from frodo_bringup.testing import wait_until

BAG = Path(__file__).resolve().parents[1] / 'bags' / 'demo_walk.mcap'
BY_NAME = {n.name: n for n in NODES}


@pytest.fixture
def params(tmp_path) -> Path:
    path = tmp_path / 'params.yaml'
    path.write_text("'/**':\n  ros__parameters:\n    diagnostics_period: 0.5\n")
    return path


class _Graph:
    """A probe session with a GraphMonitor over `names`; launchers started through it are shut down at the end."""

    def __init__(self, names):
        self.session = RosSession('frodo_test_faults')
        self.lines: list[str] = []
        self.launchers: list[Launcher] = []
        self.monitor = GraphMonitor(self.session.node, names, self.lines.append, pids=self.pids, settle=0.5,
                                    period=0.25)

    def pids(self) -> dict[str, int]:
        return {name: pid for launcher in self.launchers for name, pid in launcher.pids.items()}

    def launch(self, names, params, **kwargs) -> Launcher:
        launcher = Launcher([BY_NAME[n] for n in names], [params], output=io.StringIO(), **kwargs)
        self.launchers.append(launcher)
        launcher.start()
        return launcher

    def status(self, name: str) -> dict[str, str]:
        with self.monitor._lock:
            return dict(self.monitor._latest.get(name, {}))

    def close(self) -> None:
        for launcher in self.launchers:
            launcher.shutdown(timeout=20)
        self.session.close()


@pytest.fixture
def graph():
    graphs = []

    def make(names):
        graphs.append(_Graph(names))
        return graphs[-1]
    yield make
    for g in graphs:
        g.close()


def _play(graph: _Graph, stop: threading.Event, bag: Path = BAG) -> threading.Thread:
    player = Player(graph.session.node, bag, rate=1.0, progress=False)
    thread = threading.Thread(target=player.play, args=(stop,), daemon=True)
    thread.start()
    return thread


def test_nodes_started_late_while_a_bag_plays_are_named_with_what_they_missed(graph, params):
    g = graph(['detection_node', 'association_node', 'shape_node', 'optim_node'])
    g.launch(['detection_node', 'association_node'], params)
    assert wait_until(lambda: set(g.monitor.up()) == {'detection_node', 'association_node'}, 60), g.lines
    assert not g.monitor.ready  # two of four nodes are up
    stop = threading.Event()
    player = _play(g, stop)
    assert wait_until(lambda: g.monitor.frames_entered() >= 10, 30)
    g.launch(['shape_node', 'optim_node'], params)   # the usual mistake: the bag already plays
    assert g.monitor.wait_ready(120), g.lines
    player.join(timeout=30)
    assert set(g.monitor.late) == {'shape_node', 'optim_node'} and min(g.monitor.late.values()) >= 10
    assert any(line.startswith('WARNING: shape_node came up after') for line in g.lines), g.lines
    assert any(line.startswith('graph ready: 4 node(s) up and subscribed') for line in g.lines), g.lines
    # What is latched still reaches the late optimiser: the association node's current 3D boxes.
    assert wait_until(lambda: int(g.status('optim_node').get('tracks_received', '0')) >= 1, 30), g.status('optim_node')


def test_sigkill_of_a_node_while_a_bag_plays_restarts_it_and_the_others_keep_their_state(graph, params, tmp_path):
    g = graph(['detection_node', 'association_node'])
    launcher = g.launch(['detection_node', 'association_node'], params, on_failure='restart', restart_delay=0.5)
    assert g.monitor.wait_ready(60), g.lines
    stop = threading.Event()
    player = _play(g, stop, repeat_bag(BAG, tmp_path / 'long.mcap', copies=8))  # 40 s
    try:
        for victim, survivor in (('association_node', 'detection_node'), ('detection_node', 'association_node')):
            assert wait_until(lambda: int(g.status(victim).get('frames_received', '0')) >= 5, 30), g.status(victim)
            survivor_pid = launcher.pids[survivor]
            published = int(g.status(survivor).get('frames_published', '0'))
            old_pid = launcher.pids[victim]
            os.kill(old_pid, signal.SIGKILL)
            assert wait_until(lambda: launcher.pids[victim] != old_pid and victim in g.monitor.up(), 60), g.lines
            # The restarted node works again; the other one kept its process and its counters.
            assert wait_until(lambda: int(g.status(victim).get('frames_received', '0')) >= 3, 30), g.status(victim)
            assert launcher.pids[survivor] == survivor_pid
            # Its counters went on from where they were (never reset), and it works on the new frames too.
            assert int(g.status(survivor).get('frames_published', '0')) >= published
            assert wait_until(lambda: int(g.status(survivor).get('frames_published', '0')) > published, 30), \
                g.status(survivor)
            assert wait_until(lambda: any(line.startswith(f'WARNING: {victim} came up after') for line in g.lines),
                              10), (g.lines, g.monitor._up_pid, launcher.pids, {n: g.status(n).get('pid') for n in
                                                                               launcher.pids}, g.monitor.up())
    finally:
        stop.set()
        player.join(timeout=10)
    output = launcher.output.getvalue()
    for victim in ('association_node', 'detection_node'):
        assert f'{victim} was killed by SIGKILL' in output and f'restarting {victim} in' in output, output
    assert launcher.shutdown(timeout=20)
    assert [e.name for e in launcher.failures] == ['association_node', 'detection_node']
