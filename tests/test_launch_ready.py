"""`frodo launch` says when its graph is ready (every node up and subscribed), in its log and on
/diagnostics, and `frodo play --wait-ready` starts playing only then."""
from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray

from frodo_bringup import cli
from frodo_bringup.readiness import LAUNCH_STATUS, launch_ready
from frodo_bringup.session import RosSession
from frodo_bringup.testing import write_contract_bag
from frodo_common import topics

STUB_ARGS = ['--nodes', 'alpha,beta', '--add-node', 'alpha=frodo_bringup.stub_node',
             '--add-node', 'beta=frodo_bringup.stub_node']


def test_launch_reports_ready_and_play_waits_for_it(tmp_path, capsys):
    write_contract_bag(tmp_path / 'a.mcap', frames=3)
    statuses: list[bool] = []
    with RosSession('frodo_test_ready') as probe:
        probe.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS,
                                       lambda m: statuses.append(launch_ready(m)) if launch_ready(m) is not None
                                       else None, 50)
        # Nothing launched yet: the wait times out, with a warning, and the bag plays anyway.
        assert cli.main(['play', str(tmp_path / 'a.mcap'), '--rate', '0', '--no-progress', '--wait-ready', '0.5']) == 0
        assert 'no "graph ready" from frodo launch within 0.5 s' in capsys.readouterr().err
        proc = subprocess.Popen([sys.executable, '-m', 'frodo_bringup.cli', 'launch', *STUB_ARGS],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
        reader.start()
        try:
            assert cli.main(['play', str(tmp_path / 'a.mcap'), '--rate', '0', '--no-progress',
                             '--wait-ready', '60']) == 0
            assert 'graph ready' not in capsys.readouterr().err
            # The probe's own executor may take a moment to deliver the status that `play` already saw.
            deadline = time.monotonic() + 10.0
            while not statuses and time.monotonic() < deadline:
                time.sleep(0.05)
            assert statuses and statuses[-1] is True
            assert any('graph ready: 2 node(s) up and subscribed' in line for line in lines), lines
        finally:
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=20)
            reader.join(timeout=5)
    assert proc.returncode == 0, ''.join(lines)
    assert LAUNCH_STATUS == 'frodo_launch'
