"""`frodo launch` / `Launcher` in a real rclpy graph: nodes come up, Ctrl-C stops all of them with no
orphan processes, a crashing node is reported by name and stops or restarts per policy."""
from __future__ import annotations

import io
import signal
import subprocess
import sys
import time

import psutil
import pytest
from diagnostic_msgs.msg import DiagnosticArray

from frodo_bringup.graph import NODES, GraphError, select_nodes, share_file
from frodo_bringup.launcher import Launcher
from frodo_bringup.session import RosSession
from frodo_bringup.testing import stub, wait_until
from frodo_common import topics

STUB_ARGS = ['--nodes', 'alpha,beta', '--add-node', 'alpha=frodo_bringup.stub_node',
             '--add-node', 'beta=frodo_bringup.stub_node']


@pytest.fixture
def probe():
    with RosSession('frodo_test_probe') as session:
        yield session.node


def _crash_params(tmp_path, node: str, after: float = 1.0, code: int = 3):
    path = tmp_path / 'crash.yaml'
    path.write_text(f'{node}:\n  ros__parameters:\n    crash_after: {after}\n    crash_code: {code}\n')
    return path


def _alive(pids) -> list[int]:
    def running(pid: int) -> bool:
        try:
            return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
        except psutil.NoSuchProcess:
            return False
    return [pid for pid in pids if running(pid)]


def test_launcher_brings_nodes_up_and_shuts_them_down(probe):
    output = io.StringIO()
    launcher = Launcher([stub('alpha'), stub('beta')], output=output)
    launcher.start()
    try:
        assert wait_until(lambda: {'alpha', 'beta'} <= set(probe.get_node_names()), 20), output.getvalue()
    finally:
        assert launcher.shutdown(timeout=15)
    assert launcher.returncode == 0, output.getvalue()
    assert not _alive(launcher.pids.values())
    assert {e.name for e in launcher.exits} == {'alpha', 'beta'} and all(e.expected for e in launcher.exits)
    assert '[frodo] started alpha' in output.getvalue() and '[frodo] stopping alpha, beta' in output.getvalue()


def test_sigint_stops_frodo_launch_without_orphans(probe):
    proc = subprocess.Popen([sys.executable, '-m', 'frodo_bringup.cli', 'launch', *STUB_ARGS],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert wait_until(lambda: {'alpha', 'beta'} <= set(probe.get_node_names()), 20)
        children = [p.pid for p in psutil.Process(proc.pid).children(recursive=True)]
        assert len(children) >= 2
        started = time.monotonic()
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=10)
        assert time.monotonic() - started < 8
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out
    assert 'graph down' in out
    assert wait_until(lambda: not _alive(children), 2), f'orphans: {_alive(children)}'


def test_nodes_die_with_a_killed_launcher(probe):
    proc = subprocess.Popen([sys.executable, '-m', 'frodo_bringup.cli', 'launch', *STUB_ARGS],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        assert wait_until(lambda: {'alpha', 'beta'} <= set(probe.get_node_names()), 20)
        children = [p.pid for p in psutil.Process(proc.pid).children(recursive=True)]
    finally:
        proc.kill()  # SIGKILL: no chance to clean up; the kernel's parent-death signal stops the nodes
        proc.wait()
    assert wait_until(lambda: not _alive(children), 8), f'orphans: {_alive(children)}'


def test_crashing_node_is_reported_by_name_and_stops_the_graph(tmp_path):
    proc = subprocess.run([sys.executable, '-m', 'frodo_bringup.cli', 'launch', *STUB_ARGS,
                           '--params', str(_crash_params(tmp_path, 'beta'))],
                          capture_output=True, text=True, timeout=25)
    out = proc.stdout
    assert proc.returncode == 1, out
    assert 'beta exited with code 3' in out
    assert 'stub crashing on purpose' in out  # the last log lines come with the report
    assert 'stopping alpha' in out and 'FAILED: beta exited with code 3' in out


def test_restart_policy_restarts_then_gives_up(tmp_path):
    output = io.StringIO()
    launcher = Launcher([stub('alpha'), stub('beta')], [_crash_params(tmp_path, 'beta', after=0.5, code=4)],
                        on_failure='restart', max_restarts=1, restart_delay=0.1, output=output)
    launcher.start()
    assert launcher.wait(timeout=30), output.getvalue()
    crashes = [e for e in launcher.exits if e.name == 'beta' and not e.expected]
    assert [e.returncode for e in crashes] == [4, 4]
    assert 'restarting beta' in output.getvalue() and launcher.returncode == 1


def test_node_ignoring_sigint_gets_sigterm_after_the_timeout(tmp_path, probe):
    params = tmp_path / 'stubborn.yaml'
    params.write_text('alpha:\n  ros__parameters:\n    ignore_sigint: true\n')
    output = io.StringIO()
    reporters = set()
    probe.create_subscription(DiagnosticArray, topics.DIAGNOSTICS,
                              lambda msg: reporters.update(s.name for s in msg.status), 10)
    launcher = Launcher([stub('alpha')], [params], sigint_timeout=1.0, output=output)
    launcher.start()
    # The stub ignores SIGINT from the end of its constructor; diagnostics start with the first spin, after it.
    assert wait_until(lambda: 'alpha' in reporters, 20), output.getvalue()
    started = time.monotonic()
    assert launcher.shutdown(timeout=10)
    assert 1.0 <= time.monotonic() - started < 5
    assert 'alpha did not stop, sending SIGTERM' in output.getvalue()
    assert not _alive(launcher.pids.values())


def test_nodes_stop_on_sigint_even_when_started_with_sigint_ignored(tmp_path, probe):
    """Processes started in the background by a non-interactive shell (CI runners) inherit SIGINT ignored;
    a node must still stop on Ctrl-C, also when it comes while the node is being built."""
    params = tmp_path / 'slow.yaml'
    params.write_text('slow:\n  ros__parameters:\n    startup_delay: 3.0\n')
    output = io.StringIO()
    launcher = Launcher([stub('slow')], [params], sigint_timeout=15.0, output=output)
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)   # inherited by the node process
    try:
        launcher.start()
    finally:
        signal.signal(signal.SIGINT, previous)
    assert wait_until(lambda: 'slow' in probe.get_node_names(), 20)   # constructing: joined, not spinning
    started = time.monotonic()
    assert launcher.shutdown(timeout=20)
    assert time.monotonic() - started < 10, output.getvalue()        # not the SIGTERM escalation
    assert 'did not stop' not in output.getvalue() and not launcher.failures
    assert not _alive(launcher.pids.values())


def test_bad_launch_options_are_explained(tmp_path):
    with pytest.raises(GraphError, match='unknown node'):
        select_nodes(['detection_node', 'nope'])
    with pytest.raises(GraphError, match='parameter file not found'):
        Launcher(NODES, [tmp_path / 'missing.yaml'])
    with pytest.raises(GraphError, match='failure policy'):
        Launcher(NODES, on_failure='panic')


def test_real_graph_nodes_come_up_and_stop_cleanly(probe):
    """Every real node entry point starts with the shipped parameters, joins the graph, exits cleanly on SIGINT."""
    output = io.StringIO()
    launcher = Launcher(NODES, [share_file('config/frodo.yaml')], output=output, sigint_timeout=10)
    launcher.start()
    names = {n.name for n in NODES}
    try:
        up = wait_until(lambda: names <= set(probe.get_node_names()) or launcher.is_down, 90, period=0.2)
        assert up and not launcher.is_down, output.getvalue()[-3000:]
    finally:
        launcher.shutdown(timeout=30)
    assert launcher.returncode == 0, output.getvalue()[-3000:]
    assert not _alive(launcher.pids.values())

