"""Ctrl-C at the awkward ends of a node process's life.

A node whose ROS teardown stalls after Ctrl-C (in C with the GIL held, deaf to SIGINT and SIGTERM, as a
deadlocked rcl / DDS teardown is) still ends within `TEARDOWN_LIMIT_S` + 0.5 s, as stopped by Ctrl-C, with every
thread's stack in its log, so `frodo launch` stops cleanly. CI once saw a stub node stall like that after its
subscriptions were destroyed: it outlived SIGINT and SIGTERM until the launcher's SIGKILL and the launch failed.
And a Ctrl-C that comes while the node's modules are still being imported is kept, not lost."""
from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import time

import pytest

from frodo_bringup.graph import NODES
from frodo_bringup.launcher import Launcher
from frodo_bringup.session import RosSession
from frodo_bringup.testing import stub, wait_until
from frodo_common.node import TEARDOWN_LIMIT_S


@pytest.fixture
def probe():
    with RosSession('frodo_test_teardown_probe') as session:
        yield session.node


def test_a_stalled_teardown_ends_as_a_clean_ctrl_c_with_the_stacks_in_the_log(tmp_path, probe):
    params = tmp_path / 'stall.yaml'
    params.write_text('beta:\n  ros__parameters:\n    stall_teardown: 60.0\n')
    output = io.StringIO()
    launcher = Launcher([stub('alpha'), stub('beta')], [params], output=output)
    launcher.start()
    try:
        assert wait_until(lambda: {'alpha', 'beta'} <= set(probe.get_node_names()), 30), output.getvalue()
    finally:
        started = time.monotonic()
        assert launcher.shutdown(timeout=30), output.getvalue()
    elapsed = time.monotonic() - started
    log = output.getvalue()
    assert launcher.returncode == 0, log
    assert 'did not stop' not in log and elapsed < launcher.sigint_timeout, log   # no SIGTERM, no SIGKILL
    assert elapsed >= TEARDOWN_LIMIT_S, log                                       # beta did stall
    beta = [line for line in log.splitlines() if line.startswith('[beta] ')]
    assert any('Timeout (' in line for line in beta) and any('in destroy_node' in line for line in beta), log


def test_a_ctrl_c_while_the_node_modules_import_stops_the_node_process(tmp_path):
    """The process inherited SIGINT ignored (a CI background job) and the Ctrl-C comes during a seconds-long import
    (torch's; its import machinery also swallows the KeyboardInterrupt a default handler would raise there)."""
    importing = tmp_path / 'importing'
    (tmp_path / 'slow_import_stub.py').write_text(
        f'import pathlib, time\npathlib.Path({str(importing)!r}).touch()\ntime.sleep(4.0)\n'
        'from frodo_bringup.stub_node import main  # noqa: E402,F401\n')
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), os.environ.get('PYTHONPATH', '')]))
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)   # inherited by the node process
    try:
        proc = subprocess.Popen([sys.executable, '-m', 'frodo_bringup.node_process', 'slow_import_stub', '--ros-args',
                                 '-r', '__node:=slow_import'], env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True)
    finally:
        signal.signal(signal.SIGINT, previous)
    try:
        assert wait_until(importing.exists, 30)
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)   # before: ignored, the node came up and ran on
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, out


def test_the_shape_and_optimiser_nodes_stop_without_extension_leak_reports(probe):
    """run_node freezes the startup objects (frodo_common.node.freeze_startup_objects); unless it unfreezes them
    at the end, the cycles among them outlive their extensions and each stop printed ~50 'nanobind: leaked' lines."""
    output = io.StringIO()
    launcher = Launcher([node for node in NODES if node.name in ('shape_node', 'optim_node')], [], output=output)
    launcher.start()
    try:
        assert wait_until(lambda: {'shape_node', 'optim_node'} <= set(probe.get_node_names()), 120), output.getvalue()
    finally:
        assert launcher.shutdown(timeout=60), output.getvalue()
    log = output.getvalue()
    assert launcher.returncode == 0, log
    assert 'leaked' not in log, log
