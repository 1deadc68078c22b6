"""A node whose ROS teardown stalls after Ctrl-C (in C with the GIL held, deaf to SIGINT and SIGTERM, as a
deadlocked rcl / DDS teardown is) still ends within `TEARDOWN_LIMIT_S` + 0.5 s, as stopped by Ctrl-C, with every
thread's stack in its log, so `frodo launch` stops cleanly. CI once saw a stub node stall like that after its
subscriptions were destroyed: it outlived SIGINT and SIGTERM until the launcher's SIGKILL and the launch failed."""
from __future__ import annotations

import io
import time

import pytest

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
